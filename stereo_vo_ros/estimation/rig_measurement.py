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
  (``pinned_rows``), their free re-measurement (``measure_rows``) and the slide along the row
  that a row error causes in the tracker's refinement (``row_coupling``);
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
from scipy.spatial.transform import Rotation

from .camera import StereoCalibration
from ..config import RigConfig
from ..jit import cholesky, cholesky_solve, image_signatures, kernel, kernel_image, readonly
from ..records import Correspondences

#: Names of the state components, in order (rad, rad, rad, dimensionless, pixels).
PARAMETERS = ('roll_rad', 'pitch_rad', 'yaw_rad', 'focal_ratio', 'disparity_offset_px')
N_PARAMS = len(PARAMETERS)
#: A free stereo match of a pinned right point farther than this from where the current
#: estimate expects it (pixels, each coordinate) is not used to measure its row.
ROW_GATE_PX = 1.0


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
    pts = np.asarray(pts, np.float64)
    A, c = K_right[:2, :2], K_right[:2, 2]
    n = (pts - c) @ np.linalg.inv(A).T  # normalised coordinates (u, v)
    u, v = n[:, 0], n[:, 1]
    dn = np.empty((len(pts), 2, N_PARAMS))
    dn[:, 0, 0], dn[:, 1, 0] = v, -u  # roll
    dn[:, 0, 1], dn[:, 1, 1] = u * v, 1.0 + v * v  # pitch
    dn[:, 0, 2], dn[:, 1, 2] = -(1.0 + u * u), -u * v  # yaw
    dn[:, 0, 3], dn[:, 1, 3] = u, v  # focal ratio (A n = p - c)
    J = np.einsum('ij,njk->nik', A, dn[:, :, :4])
    offset = np.zeros((len(pts), 2, 1))
    offset[:, 0, 0] = -1.0
    return np.concatenate([J, offset], axis=2)


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
        out[i] = sol[2] if math.isfinite(sol[2]) else 0.0


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
    ray_l = np.hstack([prev_left, np.ones((len(prev_left), 1))]) @ np.linalg.inv(calib.K_left).T
    ray_l /= ray_l[:, 2:3]
    R_lr = calib.R_right_left.T
    ray_r = np.hstack([prev_right, np.ones((len(prev_right), 1))]) @ \
        (R_lr @ np.linalg.inv(calib.K_right)).T  # in the left frame
    centre = -R_lr @ calib.t_right_left  # right optical centre in the left frame (m)
    ll = np.sum(ray_l * ray_l, 1)
    rr = np.sum(ray_r * ray_r, 1)
    lr = np.sum(ray_l * ray_r, 1)
    lc, rc = ray_l @ centre, ray_r @ centre
    # Depth lambda = (lc rr - lr rc) / (ll rr - lr^2); its inverse stays finite at infinity.
    with np.errstate(divide='ignore', invalid='ignore'):
        rho = (ll * rr - lr * lr) / (lc * rr - lr * rc)
    return np.column_stack([ray_l[:, 0], ray_l[:, 1], rho])


def _project(K: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of directions q (N, 3) and d pixel / d q (N, 2, 3)."""
    p = q @ K.T
    inv_z = 1.0 / p[:, 2]
    pix = p[:, :2] * inv_z[:, None]
    D = np.empty((len(q), 2, 3))
    D[:, 0, 0] = inv_z
    D[:, 0, 1] = 0.0
    D[:, 1, 0] = 0.0
    D[:, 1, 1] = inv_z
    D[:, :, 2] = -pix * inv_z[:, None]
    return pix, D @ K


def _cross_rows(D: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rows of ``D @ [q]x``: each row (N, 2, 3) crossed with its point's q (N, 3)."""
    out = np.empty_like(D)
    q0, q1, q2 = q[:, None, 0], q[:, None, 1], q[:, None, 2]
    out[:, :, 0] = D[:, :, 1] * q2 - D[:, :, 2] * q1
    out[:, :, 1] = D[:, :, 2] * q0 - D[:, :, 0] * q2
    out[:, :, 2] = D[:, :, 0] * q1 - D[:, :, 1] * q0
    return out


def _inv3(M: np.ndarray) -> np.ndarray:
    """Inverses (N, 3, 3) of symmetric positive definite 3x3 matrices (adjugate over det)."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    det = a * A + b * B + c * C
    if not np.all(np.abs(det) > 0):
        raise np.linalg.LinAlgError('singular point block')
    out = np.empty_like(M)
    out[:, 0, 0] = A
    out[:, 0, 1] = out[:, 1, 0] = B
    out[:, 0, 2] = out[:, 2, 0] = C
    out[:, 1, 1] = a * f - c * c
    out[:, 1, 2] = out[:, 2, 1] = b * c - a * e
    out[:, 2, 2] = a * d - b * b
    return out / det[:, None, None]


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

    Notes
    -----
    Residuals (pixels, 8 per point): previous left, previous right, current left, current
    right. Each point is ``(a, b, rho)`` (its previous left normalised ray and inverse depth,
    metres^-1); the motion increment ``xi = (v, w)`` perturbs the current camera,
    ``X_cur <- X_cur - w x X_cur - v`` (m, rad); the rig error adds ``rig_jacobian`` to both
    right views. Gauss-Newton on points and motion with ``theta`` held at 0 (``cfg.iterations``
    steps, Huber weights after the first), then the information on ``theta`` with points and
    motion eliminated (Schur complements). Pixel residuals keep the errors-in-variables bias of
    far points out: every observation, previous or current, has its own residual.

    """
    if len(corr) < cfg.min_points:
        return None
    K_L0, K_R0 = calib_prev.K_left, calib_prev.K_right
    K_L1, K_R1 = calib_cur.K_left, calib_cur.K_right
    R_rl0, t_rl0 = calib_prev.R_right_left, calib_prev.t_right_left
    R_rl1, t_rl1 = calib_cur.R_right_left, calib_cur.t_right_left
    z = np.concatenate([corr.prev_left, corr.prev_right, corr.cur_left, corr.cur_right], 1)
    pts = initial_points(calib_prev, corr.prev_left, corr.prev_right)
    ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(z), axis=1)
    n = int(np.count_nonzero(ok))
    if n < cfg.min_points:
        return None
    pts, z = pts[ok], z[ok]
    mask = np.ones((n, 8)) if used is None else np.asarray(used, np.float64)[ok]
    R = np.asarray(T_prev_cur, np.float64)[:3, :3].copy()
    t = np.asarray(T_prev_cur, np.float64)[:3, 3].copy()
    n_glob = 6 + N_PARAMS
    # Full Jacobian per point: 8 residuals x (3 point + 6 motion + 5 rig) parameters.
    J = np.zeros((n, 8, 3 + n_glob))
    J[:, 2:4, 3 + 6:] = rig_jacobian(K_R0, corr.prev_right[ok])
    J[:, 6:8, 3 + 6:] = rig_jacobian(K_R1, corr.cur_right[ok])
    weights = mask
    sigma = np.nan
    for it in range(cfg.iterations + 1):
        a, b, rho = pts[:, 0], pts[:, 1], pts[:, 2]
        ray = np.column_stack([a, b, np.ones(n)])
        q1l = (ray - rho[:, None] * t) @ R  # R^T (ray - rho t), row-wise
        pix0l = ray[:, :2] @ K_L0[:2, :2].T + K_L0[:2, 2]
        pix0r, D0r = _project(K_R0, ray @ R_rl0.T + rho[:, None] * t_rl0)
        pix1l, D1l = _project(K_L1, q1l)
        pix1r, D1r = _project(K_R1, q1l @ R_rl1.T + rho[:, None] * t_rl1)
        res = (z - np.concatenate([pix0l, pix0r, pix1l, pix1r], 1)) * (mask > 0)  # (n, 8)
        # d pixel / d (a, b, rho): previous left, previous right, current left, current right.
        J[:, 0:2, 0:2] = K_L0[:2, :2]
        D0r_R = D0r @ R_rl0
        J[:, 2:4, 0:2] = D0r_R[:, :, :2]
        J[:, 2:4, 2] = D0r @ t_rl0
        dq1l_ab = R.T[:, :2]  # (3, 2)
        dq1l_rho = -(R.T @ t)
        J[:, 4:6, 0:2] = D1l @ dq1l_ab
        J[:, 4:6, 2] = D1l @ dq1l_rho
        D1r_R = D1r @ R_rl1
        J[:, 6:8, 0:2] = D1r_R @ dq1l_ab
        J[:, 6:8, 2] = D1r_R @ dq1l_rho + D1r @ t_rl1
        # d pixel / d xi of the current views: dq / dv = -rho I, dq / dw = [q]x.
        J[:, 4:6, 3:6] = -rho[:, None, None] * D1l
        J[:, 4:6, 6:9] = _cross_rows(D1l, q1l)
        J[:, 6:8, 3:6] = -rho[:, None, None] * D1r_R
        J[:, 6:8, 6:9] = _cross_rows(D1r_R, q1l)
        # Robust scale and weights (Huber); the first pass uses unit weights.
        absr = np.abs(res)
        if it == 0:  # the previous pair fixed the points: the current views carry the errors
            sigma = max(1.4826 * float(np.median(absr[:, 4:][mask[:, 4:] > 0])),
                        cfg.min_sigma_px)
        else:
            n_res = int(np.count_nonzero(mask))
            dof = max(n_res - 3 * n - n_glob, 1)
            sigma = max(1.4826 * float(np.median(absr[mask > 0])) * np.sqrt(n_res / dof),
                        cfg.min_sigma_px)
        if it > 0 or cfg.iterations == 0:
            keep = np.max(absr, axis=1) < cfg.outlier_sigmas * sigma
            if not np.all(keep):
                pts, z, res, absr, J = pts[keep], z[keep], res[keep], absr[keep], J[keep]
                mask = mask[keep]
                n = len(pts)
                if n < cfg.min_points:
                    return None
            k = cfg.huber_sigmas * sigma
            weights = mask * np.minimum(1.0, k / np.maximum(absr, 1e-12))
        WJ = J * weights[:, :, None]
        WJpt = np.swapaxes(WJ[:, :, :3], 1, 2)  # (n, 3, 8)
        Hp = WJpt @ J  # (n, 3, 14): point rows of the normal equations
        bp = (WJpt @ res[:, :, None])[:, :, 0]  # (n, 3)
        Jg = J[:, :, 3:].reshape(-1, n_glob)
        WJg = WJ[:, :, 3:].reshape(-1, n_glob)
        Hpp_inv = _inv3(Hp[:, :, :3])
        Hpg = Hp[:, :, 3:]  # (n, 3, 11)
        G = np.swapaxes(Hpg, 1, 2) @ Hpp_inv  # (n, 11, 3)
        G_flat = np.swapaxes(G, 0, 1).reshape(n_glob, -1)  # (11, 3n)
        S = WJg.T @ Jg - G_flat @ Hpg.reshape(-1, n_glob)
        s = WJg.T @ res.reshape(-1) - G_flat @ bp.reshape(-1)
        if it == cfg.iterations:
            break
        # Gauss-Newton step of points and motion; theta held (its columns left out).
        d_xi = np.linalg.solve(S[:6, :6], s[:6])
        d_pts = (Hpp_inv @ (bp - Hpg[:, :, :6] @ d_xi)[:, :, None])[:, :, 0]
        pts = pts + d_pts
        t = t + R @ d_xi[:3]  # T <- T exp(xi)
        R = R @ Rotation.from_rotvec(d_xi[3:]).as_matrix()
    # Eliminate the motion: information and gradient of theta alone, scaled by the noise.
    S_mm_inv = np.linalg.inv(S[:6, :6])
    info = S[6:, 6:] - S[6:, :6] @ S_mm_inv @ S[:6, 6:]
    grad = s[6:] - S[6:, :6] @ S_mm_inv @ s[:6]
    scale = 1.0 / (sigma * sigma * cfg.measurement_inflation)
    info = 0.5 * (info + info.T) * scale
    return PairMeasurement(information=info, gradient=grad * scale, n_points=int(n),
                           sigma_px=float(sigma))
