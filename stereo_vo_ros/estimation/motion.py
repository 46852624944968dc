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

import math

import numba
import numpy as np

from .camera import StereoCalibration
from .trifocal import (fundamental_from_projections, perpendicular_lines_t, tensor_basis,
                       transfer_basis_t)
from ..jit import kernel, readonly


def rotation_zxy(theta_z: np.ndarray, phi_x: np.ndarray, psi_y: np.ndarray) -> np.ndarray:
    """Return ``R_Z(theta) R_X(phi) R_Y(psi)`` (eq. 6), broadcast over inputs, (..., 3, 3)."""
    cz, sz = np.cos(theta_z), np.sin(theta_z)
    cx, sx = np.cos(phi_x), np.sin(phi_x)
    cy, sy = np.cos(psi_y), np.sin(psi_y)
    R = np.empty(np.broadcast(cz, cx, cy).shape + (3, 3))
    for k, value in enumerate(_rotation_entries(cz, sz, cx, sx, cy, sy)):
        R[..., k // 3, k % 3] = value
    return R


def _rotation_entries(cz: np.ndarray, sz: np.ndarray, cx: np.ndarray, sx: np.ndarray,
                      cy: np.ndarray, sy: np.ndarray) -> tuple:
    """Return the nine entries of eq. 6, row by row, from the cosines and sines of the angles."""
    szsx, czsx = sz * sx, cz * sx
    return (cz * cy - szsx * sy, -sz * cx, cz * sy + szsx * cy,
            sz * cy + czsx * sy, cz * cx, sz * sy - czsx * cy,
            -cx * sy, sx, cx * cy)


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


STATE_DIM = 6
_PAIR_CACHE: dict[int, tuple] = {}


def _pair_geometry(calib: StereoCalibration
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Tensor basis G (3, 3, 4), fundamental matrix F and the camera stack W (6, 3), o (6,).

    G and F of the pair as the previous one, W and o as the current one (see TransferModel).
    All depend on the calibration only, so they are computed once per calibration object.
    """
    hit = _PAIR_CACHE.get(id(calib))
    if hit is not None and hit[0] is calib:
        return hit[1]
    P_A, P_B = calib.projection_left(), calib.projection_right()
    W = np.vstack([calib.K_left, calib.K_right @ calib.R_right_left])
    o = np.concatenate([np.zeros(3), calib.K_right @ calib.t_right_left])
    out = (tensor_basis(P_A, P_B), fundamental_from_projections(P_A, P_B), W, o)
    if len(_PAIR_CACHE) > 8:
        _PAIR_CACHE.clear()
    _PAIR_CACHE[id(calib)] = (calib, out)
    return out


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
        self.G, self.F, _, _ = _pair_geometry(calib)
        #: Both current cameras at once: ``P(y) = [W R^T | o - W R^T t]`` with
        #: ``W = [K_L; K_R R_rl]`` (6, 3) and ``o = [0; K_R t_rl]`` (6,) (pixels).
        _, _, self.W, self.o = _pair_geometry(cur)
        self.prev_left = np.asarray(prev_left, np.float64)
        self.prev_right = np.asarray(prev_right, np.float64)
        left_t, right_t = self.prev_left.T, self.prev_right.T
        lines = perpendicular_lines_t(self.F, left_t, right_t)
        self.X = transfer_basis_t(self.G, left_t, lines).T  # (N, 4), a transposed view

    def __len__(self) -> int:
        return len(self.X)

    def points(self) -> np.ndarray:
        """
        Return the previous pair's 3-D matches as an (N, 3) array, left camera frame (metres).

        Where the ray of ``prev_left`` meets the plane back-projected from the line through
        ``prev_right`` (the transfer's own triangulation: depth from the disparity along the
        epipolar line). NaN rows where the point is not in front of the camera, not finite,
        or at infinity up to rounding (zero disparity: ``X`` has unit norm, so a homogeneous
        part below ``1e-9`` is a point beyond about 1e9 m).
        """
        X = self.X
        with np.errstate(all='ignore'):
            pts = X[:, :3] / X[:, 3:]
            bad = ~(np.isfinite(pts.sum(axis=1)) & (pts[:, 2] > 0) & (X[:, 3] > 1e-9))
        pts[bad] = np.nan
        return pts

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
        n = len(self.X)
        # The four perturbed copies of the previous pair (u_L, v_L, u_R, v_R moved in turn),
        # transferred in one pass.
        left, right = np.empty((2, 4, n)), np.empty((2, 4, n))
        left[:] = self.prev_left.T[:, None]
        right[:] = self.prev_right.T[:, None]
        left[0, 0] += step_px
        left[1, 1] += step_px
        right[0, 2] += step_px
        right[1, 3] += step_px
        left, right = left.reshape(2, 4 * n), right.reshape(2, 4 * n)
        # Unnormalised: only ratios of the projections are used.
        X = transfer_basis_t(self.G, left, perpendicular_lines_t(self.F, left, right),
                             normalize=False)
        pred = self.predict_planes(np.asarray(y, np.float64).reshape(STATE_DIM, 1),
                                   np.concatenate([self.X.T, X], axis=1).T)
        pred = pred.reshape(4, 5, n)  # coordinate, (unperturbed, 4 perturbations), point
        diff = (pred[:, 1:] - pred[:, :1]) / step_px
        diff *= diff
        gain = diff.sum(axis=1).T
        if not np.isfinite(gain.sum()):
            gain = np.where(np.isfinite(gain), gain, 1e6)
        return gain

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
        y = np.asarray(y, np.float64)
        uv = self.predict_stacked(np.moveaxis(y, -1, 0), X)  # (..., 4, N)
        return uv.swapaxes(-1, -2)

    def predict_stacked(self, yT: np.ndarray, X: np.ndarray | None = None) -> np.ndarray:
        """
        Predict current pixels of states given component by component.

        Parameters
        ----------
        yT : np.ndarray
            (6, ...) states, component first: (6, K), or (6, B, K) with a batched X.
        X : np.ndarray, optional
            (N, 4) transfer vectors (default: all of this frame's), or (B, N, 4): problem b's
            states see its own points.

        Returns
        -------
        (..., 4, N) float64: the ``u_L, v_L, u_R, v_R`` rows of every state's predictions
        (a view of :meth:`predict_planes`); non-finite where a point maps to infinity.

        """
        uv = self.predict_planes(yT, X)
        return np.moveaxis(uv, 0, -2)

    def predict_planes(self, yT: np.ndarray, X: np.ndarray | None = None) -> np.ndarray:
        """
        :meth:`predict_stacked` with the coordinate first: (4, ..., N), each plane contiguous.

        The layout the filters and RANSAC use: every division and difference runs over one
        contiguous block.
        """
        X = self.X if X is None else X
        lead = yT.shape[1:]
        if X.ndim == 3 and (len(lead) != 2 or lead[0] != X.shape[0]):
            raise ValueError(f'states {yT.shape} do not pair with batched X {X.shape}: expected '
                             f'(6, {X.shape[0]}, K)')
        states = np.ascontiguousarray(yT, np.float64).reshape(STATE_DIM, -1)
        XT = X.swapaxes(-1, -2)
        XT = np.ascontiguousarray(XT if X.ndim == 3 else XT[None])  # (B, 4, N)
        uv = np.empty((4, states.shape[1], X.shape[-2]))
        _project(states, self.dt, self.W, self.o, XT, uv)
        return uv.reshape((4,) + lead + (X.shape[-2],))


@kernel(numba.types.void(readonly(numba.types.float64, 2), numba.types.float64,
                         readonly(numba.types.float64, 2), readonly(numba.types.float64, 1),
                         readonly(numba.types.float64, 3),
                         numba.types.Array(numba.types.float64, 3, 'C')))
def _project(states, dt, W, o, XT, out):
    """
    ``TransferModel.predict_planes`` of states (6, S) and transposed transfer vectors (B, 4, N).

    State s sees the points ``XT[s // (S // B)]``. For each state the cameras
    ``P = [W R^T | o - W R^T t]`` (eqs. 6-8), then the six rows of ``P X`` over the points and
    the four pixel coordinates ``(u_L, v_L, u_R, v_R)`` into ``out`` (4, S, N); non-finite
    where a point maps to infinity.
    """
    n_states, n = states.shape[1], XT.shape[2]
    per = max(n_states // max(XT.shape[0], 1), 1)
    P = np.empty((6, 4))
    h = np.empty((6, n))
    for s in range(n_states):
        phi, psi, theta = states[3, s] * dt, states[4, s] * dt, states[5, s] * dt
        cz, sz = math.cos(theta), math.sin(theta)
        cx, sx = math.cos(phi), math.sin(phi)
        cy, sy = math.cos(psi), math.sin(psi)
        szsx, czsx = sz * sx, cz * sx
        # R row by row (eq. 6, as _rotation_entries); (W R^T)[r, c] = sum_j W[r, j] R[c, j].
        r00, r01, r02 = cz * cy - szsx * sy, -sz * cx, cz * sy + szsx * cy
        r10, r11, r12 = sz * cy + czsx * sy, cz * cx, sz * sy - czsx * cy
        r20, r21, r22 = -cx * sy, sx, cx * cy
        tx, ty, tz = states[0, s] * dt, states[1, s] * dt, states[2, s] * dt
        for r in range(6):
            w0, w1, w2 = W[r, 0], W[r, 1], W[r, 2]
            P[r, 0] = w0 * r00 + w1 * r01 + w2 * r02
            P[r, 1] = w0 * r10 + w1 * r11 + w2 * r12
            P[r, 2] = w0 * r20 + w1 * r21 + w2 * r22
            P[r, 3] = o[r] - (P[r, 0] * tx + P[r, 1] * ty + P[r, 2] * tz)
        b = min(s // per, XT.shape[0] - 1)
        for r in range(6):
            p0, p1, p2, p3 = P[r, 0], P[r, 1], P[r, 2], P[r, 3]
            for k in range(n):
                h[r, k] = p0 * XT[b, 0, k] + p1 * XT[b, 1, k] + p2 * XT[b, 2, k] + p3 * XT[b, 3, k]
        for k in range(n):
            out[0, s, k] = h[0, k] / h[2, k]
            out[1, s, k] = h[1, k] / h[2, k]
            out[2, s, k] = h[3, k] / h[5, k]
            out[3, s, k] = h[4, k] / h[5, k]


def project_current(model: TransferModel, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return predicted current (left (N, 2), right (N, 2)) pixels for one state (6,)."""
    pred = model.predict(np.asarray(y, np.float64))
    return pred[:, :2], pred[:, 2:]
