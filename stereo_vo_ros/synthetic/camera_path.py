"""
The camera's drive: a smooth path with turns, lane changes and bounce.

``Trajectory`` gives the pose of the left camera over time along a planned route (yaw rate
built up and released smoothly in turns), its height and its arc length.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import trapezoid


def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _smootherstep_slope(x: np.ndarray) -> np.ndarray:
    inside = (x > 0.0) & (x < 1.0)
    return np.where(inside, 30.0 * x * x * (1.0 - x) ** 2, 0.0)


_RAMP = 0.3  # fraction of a turn spent building up (and releasing) the yaw rate


def _turn_profile(x: np.ndarray) -> np.ndarray:
    """
    Fraction (0..1) of a turn's yaw done at fraction x of its length.

    The yaw rate ramps up along a smootherstep over the first ``_RAMP`` of the turn, stays
    constant, and ramps down symmetrically (a smooth clothoid-arc-clothoid); peak yaw rate is
    1 / (1 - _RAMP) times the mean.
    """
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    r = _RAMP

    def ramp_area(u: np.ndarray) -> np.ndarray:  # integral of smootherstep from 0 to u
        u = np.clip(u, 0.0, 1.0)
        return u ** 6 - 3.0 * u ** 5 + 2.5 * u ** 4

    area = 1.0 - r
    out = np.where(x < r, r * ramp_area(x / r), 0.5 * r + (x - r))
    out = np.where(x > 1.0 - r, area - r * ramp_area((1.0 - x) / r), out)
    return out / area


#: Displacement of a 90-degree turn along either axis, per metre of turn length.
_TURN_C = float(trapezoid(np.cos(0.5 * np.pi * _turn_profile(np.linspace(0, 1, 200001))),
                          dx=1.0 / 200000))


class Trajectory:
    """
    Smooth, vehicle-like planar path with a speed profile and a vertical bounce.

    The heading (yaw, rad, about the world y axis; 0 = +z, positive turns towards +x) is an
    analytic function of the arc length s (m): 90-degree turns follow ``_turn_profile`` (yaw
    rate continuous and smooth); lane changes add a smootherstep-derivative yaw bump.
    Positions are integrated on a 1 cm grid.
    """

    _DS = 0.01

    def __init__(self, length_m: float, turns: np.ndarray, lane_changes: np.ndarray,
                 speed_mps: float, turn_speed_mps: float, rng: np.random.Generator,
                 camera_height_m: float, bounce_m: float) -> None:
        self.turns = np.asarray(turns, np.float64).reshape(-1, 3)  # s0, length, dyaw
        self.lane_changes = np.asarray(lane_changes, np.float64).reshape(-1, 3)  # s0, L, dx
        s = np.arange(0.0, length_m + self._DS, self._DS)
        yaw = self.yaw(s)
        half = 0.5 * self._DS
        self._s = s
        self._x = np.concatenate([[0.0], np.cumsum((np.sin(yaw[1:]) + np.sin(yaw[:-1])) * half)])
        self._z = np.concatenate([[0.0], np.cumsum((np.cos(yaw[1:]) + np.cos(yaw[:-1])) * half)])
        ph = rng.uniform(0, 2 * np.pi, 4)
        v = speed_mps * (1.0 + 0.05 * np.sin(2 * np.pi * s / 170.0 + ph[0])
                         + 0.03 * np.sin(2 * np.pi * s / 61.0 + ph[1]))
        slow = np.zeros_like(s)
        ramp = 25.0
        for s0, length, _ in self.turns:
            w = np.minimum(_smootherstep((s - s0 + ramp) / ramp),
                           _smootherstep((s0 + length + ramp - s) / ramp))
            slow = np.maximum(slow, w)
        self._v = v * (1.0 - slow) + min(turn_speed_mps, speed_mps) * slow
        self._t = np.concatenate([[0.0], np.cumsum(self._DS * 0.5 * (1.0 / self._v[1:]
                                                                     + 1.0 / self._v[:-1]))])
        self.camera_height_m = camera_height_m
        self._bounce = (bounce_m, rng.uniform(1.0, 1.6), rng.uniform(1.8, 2.6), ph[2], ph[3])

    @property
    def duration_s(self) -> float:
        """Time to drive the whole path (s)."""
        return float(self._t[-1])

    def yaw(self, s: np.ndarray) -> np.ndarray:
        """Heading (rad) at arc length s (m), vectorized; turns and lane changes never overlap."""
        s = np.asarray(s, np.float64)
        yaw = np.zeros_like(s)
        if len(self.turns):
            s0, length, dyaw = self.turns.T
            done = np.searchsorted(s0 + length, s, side='right')  # completed turns
            yaw += np.concatenate([[0.0], np.cumsum(dyaw)])[done]
            k = np.minimum(done, len(s0) - 1)
            active = (done < len(s0)) & (s > s0[k])
            yaw[active] += dyaw[k[active]] * _turn_profile(
                (s[active] - s0[k[active]]) / length[k[active]])
        if len(self.lane_changes):
            s0, length, dx = self.lane_changes.T
            k = np.clip(np.searchsorted(s0, s, side='right') - 1, 0, len(s0) - 1)
            active = (s > s0[k]) & (s < s0[k] + length[k])
            kk = k[active]
            yaw[active] += dx[kk] / length[kk] * _smootherstep_slope(
                (s[active] - s0[kk]) / length[kk])
        return yaw

    def arc_length(self, t: np.ndarray) -> np.ndarray:
        """Arc length s (m) reached at time t (s) after the start."""
        return np.interp(t, self._t, self._s)

    def height(self, t: np.ndarray) -> np.ndarray:
        """Camera height above the road (m) at time t (s)."""
        a, f1, f2, p1, p2 = self._bounce
        t = np.asarray(t, np.float64)
        return self.camera_height_m + a * (0.6 * np.sin(2 * np.pi * f1 * t + p1)
                                           + 0.4 * np.sin(2 * np.pi * f2 * t + p2))

    def planar(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World x, z (m) and yaw (rad) of the left camera at times t (s)."""
        s = self.arc_length(t)
        return np.interp(s, self._s, self._x), np.interp(s, self._s, self._z), self.yaw(s)

    def poses(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) float64 ``T_world_cam`` of the left camera at times t (s)."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        x, z, yaw = self.planar(t)
        y = float(self.height(np.zeros(1))[0]) - self.height(t)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        c, s = np.cos(yaw), np.sin(yaw)
        T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, s, -s, c
        T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = x, y, z
        return T


# ---------------------------------------------------------------------------------------------
# Scene: boxes on a ground plane
# ---------------------------------------------------------------------------------------------
