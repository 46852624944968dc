"""
Motion prior of a wheeled vehicle (not in the papers): it rolls along its heading.

A car, or any robot on wheels that do not slide, moves in the direction it points. The point it
turns about (for a car, the middle of the rear axle) then travels along an arc whose chord, over
a pair, leaves the old heading at half the heading change. A camera that looks forward along the
vehicle, ``lever_arm_m`` ahead of that point, sees its own lateral motion fixed by its yaw rate.
Frame and state as in :mod:`~stereo_vo_ros.estimation.motion`: the previous left camera's optical
frame (x right, y down, z forward, m) and ``y = (V_X, V_Y, V_Z, w_X, w_Y, w_Z)`` (m/s, rad/s), so
the pair's translation is ``V dt`` and its heading change ``psi = w_Y dt`` (about the camera's y
axis, down; positive turns the view to the right).

With ``l`` the lever arm, ``t = V dt`` and the turning point's forward travel
``s = t_Z - l (cos psi - 1)``, the camera's displacement is the chord ``(s tan(psi / 2), 0, s)``
plus the lever arm turned, ``l (sin psi, 0, cos psi - 1)``. The prior is that its lateral
component is what that gives::

    c(y) = V_X - (s tan(psi / 2) + l sin psi) / dt = 0       (m/s; to first order in psi,
                                                                V_X = (V_Z dt / 2 + l) w_Y)

The pitch and the vertical speed are left alone (a road is not flat over a pair; the road
alignment measures them). The features hardly tell a small yaw from a small lateral motion
when most of them are far: on the rendered highway the yaw error of single pairs came out with
a spread of 11.5 mdeg, and 5.3 mdeg with this prior (seed 0, road alignment on; one-off
script).
"""

from __future__ import annotations

import math

import numpy as np


def lateral_constraint(state: np.ndarray, dt: float, lever_arm_m: float = 0.0
                       ) -> tuple[float, np.ndarray]:
    """
    Value and gradient of the rolling constraint ``c(y)`` at ``state``.

    Parameters
    ----------
    state : np.ndarray
        (6,) velocity state (m/s, rad/s), previous left camera frame.
    dt : float
        Time between the pairs (s), > 0.
    lever_arm_m : float
        How far the camera sits ahead of the point the vehicle turns about (m).

    Returns
    -------
    value : float
        ``c(state)`` (m/s): 0 for a vehicle that rolls along its heading.
    gradient : np.ndarray
        (6,) ``dc / dy`` at ``state``: the row of a linearised measurement ``0 = c(y)``.

    """
    y = np.asarray(state, np.float64)
    dt = float(dt)
    lever = float(lever_arm_m)
    psi = y[4] * dt
    half_tan = math.tan(0.5 * psi)
    travel = y[2] * dt - lever * (math.cos(psi) - 1.0)  # the turning point's forward travel
    value = y[0] - (travel * half_tan + lever * math.sin(psi)) / dt
    gradient = np.zeros(6)
    gradient[0] = 1.0
    gradient[2] = -half_tan
    # d/dpsi of the lateral displacement, times dpsi / dw_Y = dt, over dt.
    gradient[4] = -(lever * math.sin(psi) * half_tan + 0.5 * travel / math.cos(0.5 * psi) ** 2
                    + lever * math.cos(psi))
    return float(value), gradient
