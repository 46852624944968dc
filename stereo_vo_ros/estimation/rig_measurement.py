"""
The stereo rig's error model and what one pair of stereo pairs measures of it.

The state ``theta`` (``PARAMETERS``, shape (5,)) is the right camera's error against its
calibration, in its optical frame (x right, y down, z forward): roll, pitch, yaw (rad, about z,
x, y; ``R = R_z(roll) R_x(pitch) R_y(yaw)``), focal ratio (dimensionless: right focal over the
calibrated one, minus 1) and disparity offset (pixels: the right principal point x is
``cx - offset``). Pixels are ideal pixels (undistorted, rectified where the input is); points
and motion are in metres, in the left camera's optical frame. The overview (what is observable,
how the estimate is fused and applied) is in :mod:`.rig_calibration`, whose
:class:`~.rig_calibration.RigCalibrator` uses what is here:

* the error model: ``right_homography`` (calibrated right pixels -> measured right pixels),
  ``apply_homography``, its Jacobian ``rig_jacobian`` and the offsets it implies at the
  principal point (``offsets_at_centre``);
* the rows of the stereo matches: which rows the tracker pinned to the left point's row
  (``pinned_rows``), their free re-measurement (``measure_rows``), the slide along the row
  that a row error causes in the tracker's refinement (``row_coupling``) and the right points
  with those rows moved where an estimate expects them (``moved_right_points``);
* one pair's measurement (``measure_pair``): a small bundle adjustment of the four views of
  the inliers whose stereo rows measure roll, pitch and the focal ratio and whose temporal
  depth consistency measures yaw and the disparity offset, reduced to the information on
  ``theta`` (``PairMeasurement``).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numba
import numpy as np

from .camera import StereoCalibration
from ..config import RigConfig
from ..jit import (cholesky, cholesky_solve, finite, image_signatures, kernel, kernel_image,
                   readonly)
from ..records import Correspondences

#: Names of the state components, in order (rad, rad, rad, dimensionless, pixels).
PARAMETERS = ('roll_rad', 'pitch_rad', 'yaw_rad', 'focal_ratio', 'disparity_offset_px')
N_PARAMS = len(PARAMETERS)
#: A free stereo match of a pinned right point farther than this from where the current
#: estimate expects it (pixels, each coordinate) is not used to measure its row.
ROW_GATE_PX = 1.0


_F8 = numba.types.float64
_M2, _M3, _V1 = readonly(_F8, 2), readonly(_F8, 3), readonly(_F8, 1)
_W1, _W2, _W3 = (numba.types.Array(_F8, d, 'C') for d in (1, 2, 3))


# -- the error model ------------------------------------------------------------------------------
def rotation_zxy(angles: np.ndarray) -> np.ndarray:
    """``R_z(roll) R_x(pitch) R_y(yaw)`` (3, 3) of angles (roll, pitch, yaw) in rad."""
    (cz, cx, cy), (sz, sx, sy) = np.cos(angles), np.sin(angles)
    return np.array([[cz * cy - sz * sx * sy, -sz * cx, cz * sy + sz * sx * cy],
                     [sz * cy + cz * sx * sy, cz * cx, sz * sy - cz * sx * cy],
                     [-cx * sy, sx, cx * cy]])


def right_homography(K_right: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """
    Homography from calibrated (ideal) right pixels to measured right pixels.

    Parameters
    ----------
    K_right : np.ndarray
        (3, 3) calibrated right intrinsics (pixels).
    theta : np.ndarray
        (5,) rig error (``PARAMETERS``).

    Returns
    -------
    np.ndarray
        (3, 3) float64 ``K_err R^T K_right^-1``.

    """
    theta = np.asarray(theta, np.float64)
    R = rotation_zxy(theta[:3])
    K_err = np.array(K_right, np.float64)
    K_err[:2, :2] *= 1.0 + theta[3]
    K_err[0, 2] -= theta[4]
    return K_err @ R.T @ np.linalg.inv(K_right)


def apply_homography(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Map pixels (N, 2) by a (3, 3) homography; returns (N, 2) float64."""
    pts = np.asarray(pts, np.float64)
    h = pts @ H[:2, :2].T + H[:2, 2]
    w = pts @ H[2, :2] + H[2, 2]
    return h / w[:, None]


def rig_jacobian(K_right: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """
    Differentiate the measured right pixels by the rig error at ``theta = 0``.

    Parameters
    ----------
    K_right : np.ndarray
        (3, 3) calibrated right intrinsics (pixels; an affine upper block is allowed).
    pts : np.ndarray
        (N, 2) ideal right pixels.

    Returns
    -------
    np.ndarray
        (N, 2, 5) float64 pixels per unit of each ``PARAMETERS`` component.

    """
    pts = np.ascontiguousarray(pts, np.float64).reshape(-1, 2)
    A = np.ascontiguousarray(K_right[:2, :2], np.float64)
    out = np.empty((len(pts), 2, N_PARAMS))
    _rig_jacobian(A, np.linalg.inv(A), np.ascontiguousarray(K_right[:2, 2], np.float64), pts,
                  out)
    return out


@kernel(numba.types.void(_M2, _M2, _V1, _M2, _W3))
def _rig_jacobian(A, A_inv, c, pts, out):
    """``rig_jacobian`` into ``out`` (N, 2, 5): ``A`` (2, 2) and ``c`` (2,) of the intrinsics."""
    dn = np.empty((2, 4))
    for i in range(pts.shape[0]):
        x, y = pts[i, 0] - c[0], pts[i, 1] - c[1]
        u = A_inv[0, 0] * x + A_inv[0, 1] * y  # normalised coordinates
        v = A_inv[1, 0] * x + A_inv[1, 1] * y
        dn[0, 0], dn[1, 0] = v, -u  # roll
        dn[0, 1], dn[1, 1] = u * v, 1.0 + v * v  # pitch
        dn[0, 2], dn[1, 2] = -(1.0 + u * u), -u * v  # yaw
        dn[0, 3], dn[1, 3] = u, v  # focal ratio (A n = p - c)
        for r in range(2):
            for k in range(4):
                out[i, r, k] = A[r, 0] * dn[0, k] + A[r, 1] * dn[1, k]
        out[i, 0, 4], out[i, 1, 4] = -1.0, 0.0  # disparity offset


def offsets_at_centre(K_right: np.ndarray) -> np.ndarray:
    """
    Rows mapping ``theta`` to (row offset, disparity offset) at the right principal point.

    Returns (2, 5): row offset ``v_R - v_L`` (pixels, positive: right rows lower) and disparity
    offset (pixels, measured minus true disparity).
    """
    J = rig_jacobian(K_right, K_right[:2, 2][None])[0]
    return np.stack([J[1], -J[0]])


# -- the rows of the stereo matches ---------------------------------------------------------------
def pinned_rows(calib: StereoCalibration, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """
    (N,) bool: right points whose row the tracker copied from the left point.

    On rectified input the tracker's affine stereo refinement searches along the row of the
    left point only, so its matches carry no row information (and sit on the nominal row,
    not on the real rig's). Exactly equal rows mark them.
    """
    if calib.kind != 'rectified' or len(left) == 0:
        return np.zeros(len(left), bool)
    return np.asarray(right)[:, 1] == np.asarray(left)[:, 1]


def moved_right_points(H_row: np.ndarray, H_out: np.ndarray | None, left: np.ndarray,
                       right: np.ndarray, rectified: bool,
                       coupling: np.ndarray | None = None) -> np.ndarray:
    """
    Right points with pinned rows moved to the rows ``H_row`` gives them, then mapped by ``H_out``.

    Parameters
    ----------
    H_row : np.ndarray
        (3, 3) homography whose image of a pinned right point gives its row.
    H_out : np.ndarray or None
        (3, 3) homography every point is then mapped by (None: not mapped).
    left, right : np.ndarray
        (N, 2) matched ideal pixels.
    rectified : bool
        Whether the calibration is rectified (only then are rows pinned, ``pinned_rows``).
    coupling : np.ndarray, optional
        (N,) ``row_coupling`` of the matches: a pinned point also slides back along its row by
        its coupling times the row's move.

    Returns
    -------
    np.ndarray
        (N, 2) float64 (a new array).

    Raises
    ------
    ValueError
        ``left`` or ``coupling`` does not have N rows.

    """
    right = np.ascontiguousarray(right, np.float64).reshape(-1, 2)
    left = np.ascontiguousarray(left, np.float64).reshape(-1, 2)
    if len(left) != len(right) or (coupling is not None and np.shape(coupling) != (len(right),)):
        raise ValueError(f'{len(right)} right points need as many left points and couplings')
    out = np.empty_like(right)
    _moved_right_points(np.ascontiguousarray(H_row, np.float64),
                        np.ascontiguousarray(np.eye(3) if H_out is None else H_out, np.float64),
                        H_out is not None, left, right, bool(rectified),
                        np.zeros(len(right)) if coupling is None else
                        np.ascontiguousarray(coupling, np.float64), out)
    return out


@kernel(numba.types.void(_M2, _M2, numba.types.boolean, _M2, _M2, numba.types.boolean, _V1,
                         _W2))
def _moved_right_points(H_row, H_out, map_out, left, right, rectified, coupling, out):
    """``moved_right_points`` into ``out`` (N, 2)."""
    for i in range(right.shape[0]):
        x, y = right[i, 0], right[i, 1]
        if rectified and y == left[i, 1]:
            row = (H_row[1, 0] * x + H_row[1, 1] * y + H_row[1, 2]) / \
                (H_row[2, 0] * x + H_row[2, 1] * y + H_row[2, 2])
            x -= (row - y) * coupling[i]
            y = row
        if map_out:
            w = H_out[2, 0] * x + H_out[2, 1] * y + H_out[2, 2]
            x, y = (H_out[0, 0] * x + H_out[0, 1] * y + H_out[0, 2]) / w, \
                (H_out[1, 0] * x + H_out[1, 1] * y + H_out[1, 2]) / w
        out[i, 0], out[i, 1] = x, y


def measure_rows(left_img: np.ndarray, right_img: np.ndarray, left: np.ndarray,
                 right: np.ndarray, win_size_px: int) -> np.ndarray:
    """
    Stereo matches measured freely (2-D KLT, one level, from the given match).

    Parameters
    ----------
    left_img, right_img : np.ndarray
        (H, W) uint8 images of the pair (rectified).
    left, right : np.ndarray
        (N, 2) matched pixels; ``right`` is the starting point.
    win_size_px : int
        KLT window side (pixels).

    Returns
    -------
    np.ndarray
        (N, 2) float64 right pixels, NaN where KLT failed or moved ``ROW_GATE_PX`` or more.

    """
    if len(left) == 0:
        return np.zeros(0)
    start = np.ascontiguousarray(right, np.float32).reshape(-1, 1, 2)
    found, status, _ = cv2.calcOpticalFlowPyrLK(
        left_img, right_img, np.ascontiguousarray(left, np.float32).reshape(-1, 1, 2),
        start.copy(), winSize=(win_size_px, win_size_px), maxLevel=0,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.005),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    found = found.reshape(-1, 2).astype(np.float64)
    ok = (status.ravel() == 1) & np.all(np.abs(found - start.reshape(-1, 2)) < ROW_GATE_PX,
                                        axis=1)
    return np.where(ok[:, None], found, np.nan)


def row_coupling(img: np.ndarray, pts: np.ndarray, win_size_px: int, step_px: int = 1
                 ) -> np.ndarray:
    """
    How far a row-pinned stereo match slides along its row per pixel of row error.

    The tracker's horizontal affine refinement (``affine_klt.refine_affine(horizontal=True)``:
    shift, x-scale and x-shear of the window, on the left point's row) finds the right point
    at ``x_true + coupling * (y_true - y_left)`` when the real match lies off that row: an
    oblique edge shifted down looks shifted sideways. This is its least-squares model, from
    the gradients of the left window (the template) with the same centring.

    Parameters
    ----------
    img : np.ndarray
        (H, W) left image (uint8 or float).
    pts : np.ndarray
        (N, 2) left pixels (window centres).
    win_size_px, step_px : int
        The refinement's window side and pixel step (``tracker.affine_stereo_win_size_px``,
        ``tracker.affine_step_px``).

    Returns
    -------
    np.ndarray
        (N,) float64 coupling (pixels of x per pixel of row error); 0 where undefined.

    """
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    out = np.zeros(len(pts))
    if len(pts) == 0:
        return out
    half = int(win_size_px) // 2
    H, W = img.shape
    cx = np.clip(np.rint(pts[:, 0]).astype(np.intp), half + 1, W - half - 2)
    cy = np.clip(np.rint(pts[:, 1]).astype(np.intp), half + 1, H - half - 2)
    _row_couplings(kernel_image(img), cx, cy, half, max(int(step_px), 1), out)
    return out


@kernel(image_signatures(lambda img: numba.types.void(
    img, readonly(numba.types.intp, 1), readonly(numba.types.intp, 1), numba.types.int64,
    numba.types.int64, numba.types.Array(numba.types.float64, 1, 'C'))))
def _row_couplings(img, cx, cy, half, step, out):
    """
    ``row_coupling`` at integer centres inside the image by a window and a pixel, into ``out``.

    Steepest-descent images of the horizontal refinement (x-scale, x-shear, shift: the x
    gradient times x, y and 1), centred over the window, and the centred y gradient; the
    coupling is the shift's coefficient of the least-squares fit of the latter by the former.
    """
    sd = np.empty((3, (2 * half + 1 + step - 1) // step * ((2 * half + 1 + step - 1) // step)))
    gy = np.empty(sd.shape[1])
    hess = np.empty((3, 3))
    chol = np.zeros((3, 3))
    rhs, tmp, sol = np.empty(3), np.empty(3), np.empty(3)
    k_n = sd.shape[1]
    for i in range(len(cx)):
        k = 0
        for dy in range(-half, half + 1, step):
            y = cy[i] + dy
            for dx in range(-half, half + 1, step):
                x = cx[i] + dx
                gx = 0.5 * (float(img[y, x + 1]) - float(img[y, x - 1]))
                gy[k] = 0.5 * (float(img[y + 1, x]) - float(img[y - 1, x]))
                sd[0, k], sd[1, k], sd[2, k] = gx * dx, gx * dy, gx
                k += 1
        for a in range(3):
            m = 0.0
            for k in range(k_n):
                m += sd[a, k]
            m /= k_n
            for k in range(k_n):
                sd[a, k] -= m
        m = 0.0
        for k in range(k_n):
            m += gy[k]
        m /= k_n
        trace = 0.0
        for a in range(3):
            s = 0.0
            for k in range(k_n):
                s += sd[a, k] * (gy[k] - m)
            rhs[a] = s
            for b in range(a + 1):
                s = 0.0
                for k in range(k_n):
                    s += sd[a, k] * sd[b, k]
                hess[a, b] = s
            trace += hess[a, a]
        for a in range(3):
            hess[a, a] += 1e-4 * trace + 1e-6
        cholesky(hess, 3, chol)
        cholesky_solve(chol, 3, rhs, tmp, sol)
        out[i] = sol[2] if finite(sol[2]) else 0.0


# -- one pair's measurement -----------------------------------------------------------------------
@dataclasses.dataclass
class PairMeasurement:
    """
    What one stereo pair says about the remaining rig error (a linearised likelihood).

    Attributes
    ----------
    information : np.ndarray
        (5, 5) information matrix of ``theta`` (motion and points eliminated), inflated.
    gradient : np.ndarray
        (5,) ``J^T W r`` reduced the same way: the best increment is ``information^-1 gradient``.
    n_points : int
        Points used.
    sigma_px : float
        Residual scale (pixels) the weights were computed with.

    """

    information: np.ndarray
    gradient: np.ndarray
    n_points: int
    sigma_px: float


def initial_points(calib: StereoCalibration, prev_left: np.ndarray, prev_right: np.ndarray
                   ) -> np.ndarray:
    """
    Points (N, 3) as (a, b, rho) from the previous pair: left normalised ray, inverse depth.

    ``(a, b, 1) / rho`` is the point in the previous left camera frame (m); rho (1/m) is the
    inverse depth of the closest point of the left ray to the right ray, slightly negative for
    far points whose noisy rays diverge.
    """
    R_lr = calib.R_right_left.T
    out = np.empty((len(prev_left), 3))
    _ray_points(np.ascontiguousarray(prev_left, np.float64),
                np.ascontiguousarray(prev_right, np.float64), np.linalg.inv(calib.K_left),
                R_lr @ np.linalg.inv(calib.K_right), -R_lr @ calib.t_right_left, out)
    return out


@kernel(numba.types.void(_M2, _M2, _M2, _M2, _V1, _W2), exact=True)
def _ray_points(left, right, K_left_inv, right_to_left, centre, out):
    """
    ``initial_points`` into ``out``: rays of the left and right pixels, their closest points.

    ``right_to_left`` (3, 3) maps right pixels to rays in the left frame; ``centre`` (3,) is
    the right optical centre in the left frame (m). Exact arithmetic: parallel rays (zero
    disparity) give 0 / 0, NaN, as they must, not the rounding noise of fused multiply-adds.
    """
    ray_r = np.empty(3)
    for i in range(left.shape[0]):
        u, v = left[i, 0], left[i, 1]
        w = K_left_inv[2, 0] * u + K_left_inv[2, 1] * v + K_left_inv[2, 2]
        a = (K_left_inv[0, 0] * u + K_left_inv[0, 1] * v + K_left_inv[0, 2]) / w
        b = (K_left_inv[1, 0] * u + K_left_inv[1, 1] * v + K_left_inv[1, 2]) / w
        one = w / w
        for c in range(3):
            ray_r[c] = right_to_left[c, 0] * right[i, 0] + right_to_left[c, 1] * right[i, 1] + \
                right_to_left[c, 2]
        ll = a * a + b * b + one * one
        rr = ray_r[0] * ray_r[0] + ray_r[1] * ray_r[1] + ray_r[2] * ray_r[2]
        lr = a * ray_r[0] + b * ray_r[1] + one * ray_r[2]
        lc = a * centre[0] + b * centre[1] + one * centre[2]
        rc = ray_r[0] * centre[0] + ray_r[1] * centre[1] + ray_r[2] * centre[2]
        # Depth lambda = (lc rr - lr rc) / (ll rr - lr^2); its inverse stays finite at infinity.
        out[i, 0], out[i, 1] = a, b
        out[i, 2] = (ll * rr - lr * lr) / (lc * rr - lr * rc)


@kernel()
def _project(K, q, pix, D):
    """Pixels (2,) of a direction q (3,) into ``pix`` and d pixel / d q (2, 3) into ``D``."""
    p0 = K[0, 0] * q[0] + K[0, 1] * q[1] + K[0, 2] * q[2]
    p1 = K[1, 0] * q[0] + K[1, 1] * q[1] + K[1, 2] * q[2]
    inv_z = 1.0 / (K[2, 0] * q[0] + K[2, 1] * q[1] + K[2, 2] * q[2])
    pix[0], pix[1] = p0 * inv_z, p1 * inv_z
    for r in range(2):
        for c in range(3):
            D[r, c] = (K[r, c] - pix[r] * K[2, c]) * inv_z


@kernel()
def _motion_columns(D, q, rho, J, row):
    """Write ``d pixel / d xi`` of rows ``row:row+2`` of ``J``: ``-rho D`` and ``D [q]x``."""
    for r in range(2):
        J[row + r, 3], J[row + r, 4], J[row + r, 5] = -rho * D[r, 0], -rho * D[r, 1], \
            -rho * D[r, 2]
        J[row + r, 6] = D[r, 1] * q[2] - D[r, 2] * q[1]
        J[row + r, 7] = D[r, 2] * q[0] - D[r, 0] * q[2]
        J[row + r, 8] = D[r, 0] * q[1] - D[r, 1] * q[0]


@kernel(numba.types.void(numba.types.int64, _M2, _M2, _M2, _M2, _V1, _M2, _M2, _V1, _M2, _M2,
                         _M2, _V1, _M2, _W2, _W3))
def _residuals_jacobian(n, pts, z, mask, R, t, K_L0, K_R0, t_rl0, R_rl0, K_L1, K_R1, t_rl1,
                        R_rl1, res, J):
    """
    Residuals (n, 8) and Jacobian (n, 8, 14) of the four views of the first n points (a, b, rho).

    Columns: the point (a, b, rho), the motion increment xi = (v, w), the rig error; the rig
    columns (right views) are constant and left as they are. ``R``, ``t``: the motion (pose of
    the current left camera in the previous one); ``K_*``, ``R_rl*``, ``t_rl*``: the previous
    (0) and current (1) calibrations. Residuals where ``mask`` is 0 are 0.
    """
    q0 = np.empty(3)
    q = np.empty(3)
    qr = np.empty(3)
    pix = np.empty(2)
    D = np.empty((2, 3))
    DR = np.empty((2, 3))
    Rt_t = np.empty(3)  # R^T t
    for c in range(3):
        Rt_t[c] = R[0, c] * t[0] + R[1, c] * t[1] + R[2, c] * t[2]
    for i in range(n):
        a, b, rho = pts[i, 0], pts[i, 1], pts[i, 2]
        Ji = J[i]
        # Previous left: K (a, b, 1).
        pix[0] = K_L0[0, 0] * a + K_L0[0, 1] * b + K_L0[0, 2]
        pix[1] = K_L0[1, 0] * a + K_L0[1, 1] * b + K_L0[1, 2]
        for r in range(2):
            res[i, r] = z[i, r] - pix[r]
            Ji[r, 0], Ji[r, 1], Ji[r, 2] = K_L0[r, 0], K_L0[r, 1], 0.0
        # Previous right: R_rl (a, b, 1) + rho t_rl.
        for c in range(3):
            q0[c] = R_rl0[c, 0] * a + R_rl0[c, 1] * b + R_rl0[c, 2] + rho * t_rl0[c]
        _project(K_R0, q0, pix, D)
        for r in range(2):
            res[i, 2 + r] = z[i, 2 + r] - pix[r]
            for c in range(2):
                Ji[2 + r, c] = D[r, 0] * R_rl0[0, c] + D[r, 1] * R_rl0[1, c] + \
                    D[r, 2] * R_rl0[2, c]
            Ji[2 + r, 2] = D[r, 0] * t_rl0[0] + D[r, 1] * t_rl0[1] + D[r, 2] * t_rl0[2]
        # Current left: q = R^T ((a, b, 1) - rho t); d q / d (a, b) = R^T[:, :2],
        # d q / d rho = -R^T t.
        for c in range(3):
            q[c] = R[0, c] * a + R[1, c] * b + R[2, c] - rho * Rt_t[c]
        _project(K_L1, q, pix, D)
        for r in range(2):
            res[i, 4 + r] = z[i, 4 + r] - pix[r]
            for c in range(2):
                Ji[4 + r, c] = D[r, 0] * R[c, 0] + D[r, 1] * R[c, 1] + D[r, 2] * R[c, 2]
            Ji[4 + r, 2] = -(D[r, 0] * Rt_t[0] + D[r, 1] * Rt_t[1] + D[r, 2] * Rt_t[2])
        _motion_columns(D, q, rho, Ji, 4)
        # Current right: R_rl q + rho t_rl.
        for c in range(3):
            qr[c] = R_rl1[c, 0] * q[0] + R_rl1[c, 1] * q[1] + R_rl1[c, 2] * q[2] + \
                rho * t_rl1[c]
        _project(K_R1, qr, pix, D)
        for r in range(2):
            res[i, 6 + r] = z[i, 6 + r] - pix[r]
            for c in range(3):
                DR[r, c] = D[r, 0] * R_rl1[0, c] + D[r, 1] * R_rl1[1, c] + D[r, 2] * R_rl1[2, c]
            for c in range(2):
                Ji[6 + r, c] = DR[r, 0] * R[c, 0] + DR[r, 1] * R[c, 1] + DR[r, 2] * R[c, 2]
            Ji[6 + r, 2] = -(DR[r, 0] * Rt_t[0] + DR[r, 1] * Rt_t[1] + DR[r, 2] * Rt_t[2]) + \
                D[r, 0] * t_rl1[0] + D[r, 1] * t_rl1[1] + D[r, 2] * t_rl1[2]
        _motion_columns(DR, q, rho, Ji, 6)
        for k in range(8):
            if not mask[i, k] > 0:
                res[i, k] = 0.0


#: Per residual row of a point (previous left, previous right, current left, current right, two
#: rows each), the first and last + 1 global column (motion 0-5, rig 6-10) its Jacobian can fill:
#: the previous views do not move with the motion, the left views not with the rig.
_GLOBAL_FROM = np.array([0, 0, 6, 6, 0, 0, 0, 0])
_GLOBAL_TO = np.array([0, 0, 11, 11, 6, 6, 11, 11])


@kernel(numba.types.boolean(numba.types.int64, _M3, _M2, _M2, _W2, _W1, _W3, _W3, _W2))
def _reduced_normal_equations(n, J, res, weights, S, s, Hpp_inv, Hpg, bp):
    """
    Write the normal equations of the global parameters (motion, rig), points eliminated.

    The first n points of ``J`` (N, 8, 3 + 11) as ``_residuals_jacobian`` writes it, ``res``
    and ``weights`` (N, 8); writes ``S`` (11, 11) and ``s`` (11,) (Schur complements), and per
    point ``Hpp_inv`` (N, 3, 3), ``Hpg`` (N, 3, 11) and ``bp`` (N, 3). Sums skip the Jacobian's
    zero blocks (``_GLOBAL_FROM``, ``_GLOBAL_TO``). False when a point's 3x3 block is singular.
    """
    m, cols = J.shape[1], J.shape[2]
    g = cols - 3
    S[:, :] = 0.0
    s[:] = 0.0
    H = np.empty((3, 3))
    G = np.empty((g, 3))
    wj = np.empty(cols)
    for i in range(n):
        Ji, wi, ri = J[i], weights[i], res[i]
        H[:, :] = 0.0
        bp[i, :] = 0.0
        Hpg[i, :, :] = 0.0
        for r in range(m):  # the direct terms
            lo, hi = _GLOBAL_FROM[r], _GLOBAL_TO[r]
            w = wi[r]
            for c in range(3):
                wj[c] = w * Ji[r, c]
            for c in range(3 + lo, 3 + hi):
                wj[c] = w * Ji[r, c]
            for a in range(3):
                for b in range(a + 1):
                    H[a, b] += wj[a] * Ji[r, b]
                bp[i, a] += wj[a] * ri[r]
                for c in range(lo, hi):
                    Hpg[i, a, c] += wj[a] * Ji[r, 3 + c]
            for c in range(lo, hi):
                s[c] += wj[3 + c] * ri[r]
                for c2 in range(lo, c + 1):
                    S[c, c2] += wj[3 + c] * Ji[r, 3 + c2]
        # Inverse of the symmetric point block (adjugate over determinant).
        p, q, u = H[0, 0], H[1, 0], H[2, 0]
        d, e, f = H[1, 1], H[2, 1], H[2, 2]
        A, B, C = d * f - e * e, u * e - q * f, q * e - u * d
        det = p * A + q * B + u * C
        if not abs(det) > 0.0:
            return False
        Hi = Hpp_inv[i]
        Hi[0, 0], Hi[0, 1], Hi[0, 2] = A / det, B / det, C / det
        Hi[1, 0], Hi[1, 1], Hi[1, 2] = B / det, (p * f - u * u) / det, (q * u - p * e) / det
        Hi[2, 0], Hi[2, 1], Hi[2, 2] = C / det, Hi[1, 2], (p * d - q * q) / det
        Hg = Hpg[i]
        for c in range(g):  # the point eliminated
            for a in range(3):
                G[c, a] = Hg[0, c] * Hi[0, a] + Hg[1, c] * Hi[1, a] + Hg[2, c] * Hi[2, a]
            s[c] -= G[c, 0] * bp[i, 0] + G[c, 1] * bp[i, 1] + G[c, 2] * bp[i, 2]
            for c2 in range(c + 1):
                S[c, c2] -= G[c, 0] * Hg[0, c2] + G[c, 1] * Hg[1, c2] + G[c, 2] * Hg[2, c2]
    for c in range(g):
        for c2 in range(c):
            S[c2, c] = S[c, c2]
    return True


@kernel()
def _median_abs(n, res, mask, first, buf):
    """
    Median of ``|res[:n, first:]|`` where ``mask`` > 0 (NaN if any is NaN or none is), and count.

    ``buf`` (at least ``res.size``) is scratch space.
    """
    m, no_nan = 0, True
    for i in range(n):
        for k in range(first, res.shape[1]):
            if mask[i, k] > 0:
                buf[m] = abs(res[i, k])
                no_nan = no_nan and not np.isnan(buf[m])
                m += 1
    if m == 0 or not no_nan:
        return np.nan, m
    k = m // 2
    upper = _select(buf, m, k)
    if m % 2:
        return upper, m
    lower = buf[0]
    for i in range(1, k):
        lower = max(lower, buf[i])
    return 0.5 * (lower + upper), m


@kernel()
def _select(a, n, k):
    """Return the ``k``-th smallest of ``a[:n]`` (no NaN), reordering it: ``a[:k]`` below."""
    lo, hi = 0, n - 1
    while lo < hi:  # Hoare's selection
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@kernel()
def _rotate_by(R, v, at):
    """``R`` (3, 3) times the rotation of rotation vector ``v[at:at + 3]`` (rad), in place."""
    w = (v[at], v[at + 1], v[at + 2])
    th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    th = math.sqrt(th2)
    if th < 1e-8:
        a, b = 1.0, 0.5
    else:  # sin(th) / th, (1 - cos(th)) / th^2 without the cancellation
        h = math.sin(0.5 * th)
        a, b = math.sin(th) / th, 2.0 * h * h / th2
    E = np.empty((3, 3))
    for r in range(3):  # E = I + a [w]x + b [w]x^2, [w]x^2 = w w^T - |w|^2 I
        for c in range(3):
            E[r, c] = b * w[r] * w[c] + (1.0 - b * th2 if r == c else 0.0)
    E[0, 1] -= a * w[2]
    E[0, 2] += a * w[1]
    E[1, 0] += a * w[2]
    E[1, 2] -= a * w[0]
    E[2, 0] -= a * w[1]
    E[2, 1] += a * w[0]
    row = np.empty(3)
    for r in range(3):
        for c in range(3):
            row[c] = R[r, 0] * E[0, c] + R[r, 1] * E[1, c] + R[r, 2] * E[2, c]
        for c in range(3):
            R[r, c] = row[c]


@kernel()
def _move_point(pts, z, mask, J, i, to):
    """Copy point ``i``'s rows of ``pts``, ``z``, ``mask`` and ``J`` to row ``to``."""
    for k in range(pts.shape[1]):
        pts[to, k] = pts[i, k]
    for k in range(z.shape[1]):
        z[to, k], mask[to, k] = z[i, k], mask[i, k]
        for c in range(J.shape[2]):
            J[to, k, c] = J[i, k, c]


@kernel(numba.types.int64(_W2, _W2, _W2, _W2, _W1, _M2, _M2, _V1, _M2, _M2, _M2, _V1, _M2, _W3,
                          numba.types.int64, numba.types.int64, _F8, _F8, _F8, _W2, _W1, _W1))
def _adjust(pts, z, mask, R, t, K_L0, K_R0, t_rl0, R_rl0, K_L1, K_R1, t_rl1, R_rl1, J,
            iterations, min_points, min_sigma, outlier_sigmas, huber_sigmas, info, grad,
            sigma_out):
    """
    ``measure_pair``'s bundle adjustment; returns the points kept, -1 for a singular block.

    A block is singular when a point's 3x3 block has no inverse or the motion's 6x6 block (points
    eliminated) is not positive definite.

    ``pts`` (N, 3), ``z`` and ``mask`` (N, 8), the motion ``R``, ``t`` and ``J`` (N, 8, 14)
    with its rig columns filled are changed in place (the kept points first). Writes the
    information ``info`` (5, 5) and gradient ``grad`` (5,) on the rig error (points and motion
    eliminated, not yet scaled by the noise) and the residual scale ``sigma_out[0]`` (pixels).
    Fewer than ``min_points`` kept: nothing written.
    """
    n_glob = J.shape[2] - 3
    n = 0
    for i in range(pts.shape[0]):  # points and views that are finite
        good = True
        for k in range(3):
            good = good and finite(pts[i, k])
        for k in range(8):
            good = good and finite(z[i, k])
        if good:
            _move_point(pts, z, mask, J, i, n)
            n += 1
    if n < min_points:
        return n
    res, weights, buf = np.empty((n, 8)), np.empty((n, 8)), np.empty(8 * n)
    S, s = np.empty((n_glob, n_glob)), np.empty(n_glob)
    Hpp_inv, Hpg, bp = np.empty((n, 3, 3)), np.empty((n, 3, n_glob)), np.empty((n, 3))
    chol, tmp, d_xi, e = np.zeros((6, 6)), np.empty(6), np.empty(6), np.empty(3)
    sigma = np.nan
    for it in range(iterations + 1):
        _residuals_jacobian(n, pts, z, mask, R, t, K_L0, K_R0, t_rl0, R_rl0, K_L1, K_R1, t_rl1,
                            R_rl1, res, J)
        # Robust scale and weights (Huber); the first pass uses unit weights.
        if it == 0:  # the previous pair fixed the points: the current views carry the errors
            med, _ = _median_abs(n, res, mask, 4, buf)
            sigma = 1.4826 * med
        else:
            med, n_res = _median_abs(n, res, mask, 0, buf)
            dof = max(n_res - 3 * n - n_glob, 1)
            sigma = 1.4826 * med * math.sqrt(n_res / dof)
        sigma = min_sigma if min_sigma > sigma else sigma  # (NaN stays NaN)
        if it > 0 or iterations == 0:
            kept = 0
            for i in range(n):
                big, no_nan = 0.0, True
                for k in range(8):
                    no_nan = no_nan and not np.isnan(res[i, k])
                    big = max(big, abs(res[i, k]))
                if no_nan and big < outlier_sigmas * sigma:
                    _move_point(pts, z, mask, J, i, kept)
                    for k in range(8):
                        res[kept, k] = res[i, k]
                    kept += 1
            n = kept
            if n < min_points:
                return n
            k_huber = huber_sigmas * sigma
            for i in range(n):
                for k in range(8):
                    weights[i, k] = mask[i, k] * min(1.0, k_huber / max(abs(res[i, k]), 1e-12))
        else:
            for i in range(n):
                for k in range(8):
                    weights[i, k] = mask[i, k]
        if not _reduced_normal_equations(n, J, res, weights, S, s, Hpp_inv, Hpg, bp):
            return -1
        cholesky(S, 6, chol)
        if not chol[5, 5] > 0.0:  # the motion block is singular (NaN from the failed pivot on)
            return -1
        if it == iterations:
            break
        # Gauss-Newton step of points and motion; theta held (its columns left out).
        cholesky_solve(chol, 6, s, tmp, d_xi)
        for i in range(n):
            for a in range(3):
                acc = bp[i, a]
                for c in range(6):
                    acc -= Hpg[i, a, c] * d_xi[c]
                e[a] = acc
            for a in range(3):
                pts[i, a] += Hpp_inv[i, a, 0] * e[0] + Hpp_inv[i, a, 1] * e[1] + \
                    Hpp_inv[i, a, 2] * e[2]
        for r in range(3):  # T <- T exp(xi)
            t[r] += R[r, 0] * d_xi[0] + R[r, 1] * d_xi[1] + R[r, 2] * d_xi[2]
        _rotate_by(R, d_xi, 3)
    # Eliminate the motion: information and gradient of theta alone.
    col, x = np.empty(6), np.empty((n_glob - 6, 6))  # x[b] = S_mm^-1 S_m,6+b
    for b in range(n_glob - 6):
        for c in range(6):
            col[c] = S[c, 6 + b]
        cholesky_solve(chol, 6, col, tmp, x[b])
    cholesky_solve(chol, 6, s, tmp, d_xi)
    for a in range(n_glob - 6):
        acc = s[6 + a]
        for c in range(6):
            acc -= S[6 + a, c] * d_xi[c]
        grad[a] = acc
        for b in range(n_glob - 6):
            acc = S[6 + a, 6 + b]
            for c in range(6):
                acc -= S[6 + a, c] * x[b, c]
            info[a, b] = acc
    sigma_out[0] = sigma
    return n


def measure_pair(corr: Correspondences, calib_prev: StereoCalibration,
                 calib_cur: StereoCalibration, T_prev_cur: np.ndarray, cfg: RigConfig,
                 used: np.ndarray | None = None) -> PairMeasurement | None:
    """
    Bundle-adjust one pair of stereo pairs and return its information on the rig error.

    Parameters
    ----------
    corr : Correspondences
        The inliers (N rows), right points already corrected by the current rig estimate
        (ideal pixels of the four views).
    calib_prev, calib_cur : StereoCalibration
        Calibration of the previous and the current pair.
    T_prev_cur : np.ndarray
        (4, 4) motion estimate: pose of the current left camera in the previous left frame (m).
    cfg : RigConfig
        Iterations, Huber constant, outlier gate, inflation.
    used : np.ndarray, optional
        (N, 8) bool: which of the 8 residuals of each point are measurements (default all),
        e.g. False for a right row that the tracker copied from the left one.

    Returns
    -------
    PairMeasurement or None when too few points remain.

    Raises
    ------
    numpy.linalg.LinAlgError
        A point's block or the motion's block of the normal equations is singular.
    ValueError
        ``used`` is not (N, 8).

    Notes
    -----
    Residuals (pixels, 8 per point): previous left, previous right, current left, current
    right. Each point is ``(a, b, rho)`` (its previous left normalised ray and inverse depth,
    metres^-1); the motion increment ``xi = (v, w)`` perturbs the current camera,
    ``X_cur <- X_cur - w x X_cur - v`` (m, rad); the rig error adds ``rig_jacobian`` to both
    right views. Gauss-Newton on points and motion with ``theta`` held at 0 (``cfg.iterations``
    steps, Huber weights after the first), then the information on ``theta`` with points and
    motion eliminated (Schur complements). Pixel residuals keep the errors-in-variables bias of
    far points out: every observation, previous or current, has its own residual. The steps
    run in one compiled kernel (``_adjust``).

    """
    if used is not None and np.shape(used) != (len(corr), 8):
        raise ValueError(f'used must be ({len(corr)}, 8), got {np.shape(used)}')
    if len(corr) < cfg.min_points:
        return None
    z = np.concatenate([corr.prev_left, corr.prev_right, corr.cur_left, corr.cur_right], 1
                       ).astype(np.float64)
    pts = initial_points(calib_prev, corr.prev_left, corr.prev_right)
    mask = np.ones((len(z), 8)) if used is None else np.array(used, np.float64)
    T = np.asarray(T_prev_cur, np.float64)
    R, t = T[:3, :3].copy(), T[:3, 3].copy()
    # Full Jacobian per point: 8 residuals x (3 point + 6 motion + 5 rig) parameters.
    J = np.zeros((len(z), 8, 3 + 6 + N_PARAMS))
    J[:, 2:4, 3 + 6:] = rig_jacobian(calib_prev.K_right, z[:, 2:4])
    J[:, 6:8, 3 + 6:] = rig_jacobian(calib_cur.K_right, z[:, 6:8])
    cams = [np.ascontiguousarray(a, np.float64) for a in (
        calib_prev.K_left, calib_prev.K_right, calib_prev.t_right_left,
        calib_prev.R_right_left, calib_cur.K_left, calib_cur.K_right, calib_cur.t_right_left,
        calib_cur.R_right_left)]
    info, grad, sigma = np.empty((N_PARAMS, N_PARAMS)), np.empty(N_PARAMS), np.empty(1)
    n = _adjust(pts, z, mask, R, t, *cams, J, cfg.iterations, cfg.min_points,
                cfg.min_sigma_px, cfg.outlier_sigmas, cfg.huber_sigmas, info, grad, sigma)
    if n < 0:
        raise np.linalg.LinAlgError('singular point or motion block')
    if n < cfg.min_points:
        return None
    # Scaled by the noise.
    scale = 1.0 / (sigma[0] * sigma[0] * cfg.measurement_inflation)
    return PairMeasurement(information=0.5 * (info + info.T) * scale, gradient=grad * scale,
                           n_points=int(n), sigma_px=float(sigma[0]))
