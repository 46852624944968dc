"""
Motion parameterisation (Kitt et al., eqs. 6-8) and the trifocal measurement function h(y).

State ``y = (V_X, V_Y, V_Z, w_X, w_Y, w_Z)``: linear (m/s) and angular (rad/s) velocity of the
stereo rig, expressed in the PREVIOUS LEFT camera optical frame (x right, y down, z forward).
Kitt et al. uses the previous right camera as reference; we use the previous left one, which is
where the odometry is reported. Over a time step ``dt`` (s) the motion is

* ``t = V * dt`` (eq. 7) and ``R = R_Z(w_Z dt) R_X(w_X dt) R_Y(w_Y dt)`` (eqs. 6 and 8),
* ``T_prev_cur = [[R, t], [0, 1]]``: the pose of the current left camera in the previous left
  camera frame, so a forward-driving camera has ``V_Z > 0``. (Kitt et al. writes the projection as
  ``K [R | t]``, i.e. the inverse transform; both parameterise the same motion.)

The measurement function (:class:`TransferModel`) predicts the 4N pixel coordinates
``(u_L, v_L, u_R, v_R)`` of N correspondences in the current left and right images from the
previous stereo pair through the two trifocal tensors (previous left, previous right, current
left) and (previous left, previous right, current right).
"""

from __future__ import annotations

import numpy as np

from .camera import StereoCalibration
from .trifocal import (fundamental_from_projections, perpendicular_lines, tensor_basis,
                       transfer_basis)


def rotation_zxy(theta_z: np.ndarray, phi_x: np.ndarray, psi_y: np.ndarray) -> np.ndarray:
    """Return ``R_Z(theta) R_X(phi) R_Y(psi)`` (eq. 6), broadcast over inputs, (..., 3, 3)."""
    cz, sz = np.cos(theta_z), np.sin(theta_z)
    cx, sx = np.cos(phi_x), np.sin(phi_x)
    cy, sy = np.cos(psi_y), np.sin(psi_y)
    R = np.empty(np.broadcast(cz, cx, cy).shape + (3, 3))
    R[..., 0, 0] = cz * cy - sz * sx * sy
    R[..., 0, 1] = -sz * cx
    R[..., 0, 2] = cz * sy + sz * sx * cy
    R[..., 1, 0] = sz * cy + cz * sx * sy
    R[..., 1, 1] = cz * cx
    R[..., 1, 2] = sz * sy - cz * sx * cy
    R[..., 2, 0] = -cx * sy
    R[..., 2, 1] = sx
    R[..., 2, 2] = cx * cy
    return R


def rotation_from_rates(omega: np.ndarray, dt: float | np.ndarray) -> np.ndarray:
    """Eq. 8: rotation over ``dt`` for angular rates (..., 3) = (w_X, w_Y, w_Z) in rad/s."""
    a = np.asarray(omega, np.float64) * np.asarray(dt, np.float64)[..., None]
    return rotation_zxy(a[..., 2], a[..., 0], a[..., 1])


def rates_from_rotation(R: np.ndarray, dt: float) -> np.ndarray:
    """Inverse of :func:`rotation_from_rates` for one (3, 3) rotation: (w_X, w_Y, w_Z) rad/s."""
    R = np.asarray(R, np.float64)
    phi = np.arcsin(np.clip(R[2, 1], -1.0, 1.0))
    theta = np.arctan2(-R[0, 1], R[1, 1])
    psi = np.arctan2(-R[2, 0], R[2, 2])
    return np.array([phi, psi, theta]) / dt


def transform_from_velocity(y: np.ndarray, dt: float) -> np.ndarray:
    """Return ``T_prev_cur`` (..., 4, 4) for states (..., 6) over ``dt`` seconds (eqs. 6-8)."""
    y = np.asarray(y, np.float64)
    T = np.zeros(y.shape[:-1] + (4, 4))
    T[..., :3, :3] = rotation_from_rates(y[..., 3:], dt)
    T[..., :3, 3] = y[..., :3] * dt
    T[..., 3, 3] = 1.0
    return T


def velocity_from_transform(T_prev_cur: np.ndarray, dt: float) -> np.ndarray:
    """Inverse of :func:`transform_from_velocity` for one (4, 4) transform: (6,) state."""
    T = np.asarray(T_prev_cur, np.float64)
    return np.concatenate([T[:3, 3] / dt, rates_from_rotation(T[:3, :3], dt)])


_PAIR_CACHE: dict[int, tuple[StereoCalibration, np.ndarray, np.ndarray]] = {}


def _pair_geometry(calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
    """
    Tensor basis G (3, 3, 4) and fundamental matrix F of the (previous) stereo pair.

    Both depend on the calibration only, so they are computed once per calibration object.
    """
    hit = _PAIR_CACHE.get(id(calib))
    if hit is not None and hit[0] is calib:
        return hit[1], hit[2]
    P_A, P_B = calib.projection_left(), calib.projection_right()
    G, F = tensor_basis(P_A, P_B), fundamental_from_projections(P_A, P_B)
    if len(_PAIR_CACHE) > 8:
        _PAIR_CACHE.clear()
    _PAIR_CACHE[id(calib)] = (calib, G, F)
    return G, F


class TransferModel:
    """
    Measurement function h(y) of Kitt et al. for one frame pair.

    Parameters
    ----------
    calib : StereoCalibration
        Calibration of the previous pair (measurements are ideal, undistorted pixels).
    prev_left, prev_right : (N, 2) float64
        Correspondences in the previous left and right images (pixels).
    dt : float
        Time between the previous and the current pair (s), > 0.
    calib_cur : StereoCalibration, optional
        Calibration of the current pair if it changed (Kitt et al. allows a varying calibration).

    Notes
    -----
    The previous pair (cameras A = previous left, B = previous right) is fixed, so the tensor
    basis of eq. 4 and the transfer lines through ``prev_right`` are computed once here; each
    state then maps to the two current cameras C (left) and D (right):
    ``P_C = K_L [R^T | -R^T t]`` and ``P_D = K_R [R_RL R^T | t_RL - R_RL R^T t]``.

    """

    def __init__(self, calib: StereoCalibration, prev_left: np.ndarray, prev_right: np.ndarray,
                 dt: float, calib_cur: StereoCalibration | None = None) -> None:
        self.dt = float(dt)
        cur = calib_cur or calib
        self.K_left = cur.K_left
        self.K_right = cur.K_right
        self.R_rl = cur.R_right_left
        self.t_rl = cur.t_right_left
        self.G, self.F = _pair_geometry(calib)
        self.prev_left = np.asarray(prev_left, np.float64)
        self.prev_right = np.asarray(prev_right, np.float64)
        lines = perpendicular_lines(self.F, prev_left, prev_right)
        self.X = transfer_basis(self.G, prev_left, lines)  # (N, 4)

    def __len__(self) -> int:
        return len(self.X)

    def previous_noise_gain(self, y: np.ndarray, step_px: float = 0.5) -> np.ndarray:
        """
        Sensitivity of the predictions to the previous observations.

        The transfer treats the previous pair as exact; its pixel noise reaches the predicted
        current pixels through the transfer. This returns, for each predicted coordinate, the
        sum of squared derivatives with respect to the four previous coordinates (u_L, v_L,
        u_R, v_R), by finite differences of ``step_px`` at state ``y``: with isotropic pixel
        noise ``sigma`` the variance of a residual is ``sigma^2 (1 + gain)``.

        Parameters
        ----------
        y : np.ndarray
            (6,) state at which to linearise (m/s, rad/s).
        step_px : float
            Finite-difference step (pixels).

        Returns
        -------
        (N, 4) float64 gains (dimensionless), finite (non-finite entries become 1e6).

        """
        base = self.predict(np.asarray(y, np.float64))  # (N, 4)
        gain = np.zeros_like(base)
        for side, col in ((0, 0), (0, 1), (1, 0), (1, 1)):
            pl, pr = self.prev_left.copy(), self.prev_right.copy()
            (pl if side == 0 else pr)[:, col] += step_px
            lines = perpendicular_lines(self.F, pl, pr)
            pert = self.predict(y, transfer_basis(self.G, pl, lines))
            gain += ((pert - base) / step_px) ** 2
        return np.where(np.isfinite(gain), gain, 1e6)

    def cameras(self, y: np.ndarray) -> np.ndarray:
        """
        Return the stacked current left and right projections (..., 6, 4) for states y.

        Rows 0-2 are ``P_C`` (current left), rows 3-5 ``P_D`` (current right), both mapping
        points of the previous left camera frame to pixels.
        """
        y = np.asarray(y, np.float64)
        R = rotation_from_rates(y[..., 3:], self.dt)
        Rt = np.swapaxes(R, -1, -2)
        M = np.empty(y.shape[:-1] + (6, 4))
        M[..., :3, :3] = Rt
        M[..., :3, 3] = -(Rt @ (y[..., :3, None] * self.dt))[..., 0]
        M[..., 3:, :] = self.R_rl @ M[..., :3, :]
        M[..., 3:, 3] += self.t_rl
        M[..., :3, :] = self.K_left @ M[..., :3, :]
        M[..., 3:, :] = self.K_right @ M[..., 3:, :]
        return M

    def predict(self, y: np.ndarray, X: np.ndarray | None = None) -> np.ndarray:
        """
        Predict current pixels for states ``y``.

        Parameters
        ----------
        y : np.ndarray
            (..., 6) states (m/s, rad/s).
        X : np.ndarray, optional
            (N, 4) or (B, N, 4) transfer vectors (default: all of this frame's); a batched X
            pairs with states of shape (B, S, 6).

        Returns
        -------
        (..., N, 4) float64 ``(u_L, v_L, u_R, v_R)`` pixels; non-finite where a point maps to
        infinity.

        """
        X = self.X if X is None else X
        P = self.cameras(y)  # (..., 6, 4)
        if X.ndim == 2:
            h = P @ X.T  # (..., 6, N)
        else:  # (B, N, 4) with states (B, S, 6)
            h = P @ np.swapaxes(X, 1, 2)[:, None]
        with np.errstate(divide='ignore', invalid='ignore'):
            uv = np.concatenate([h[..., 0:2, :] / h[..., 2:3, :], h[..., 3:5, :] / h[..., 5:6, :]],
                                axis=-2)  # (..., 4, N)
        return np.swapaxes(uv, -1, -2)


def project_current(model: TransferModel, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return predicted current (left (N, 2), right (N, 2)) pixels for one state (6,)."""
    pred = model.predict(np.asarray(y, np.float64))
    return pred[:, :2], pred[:, 2:]
