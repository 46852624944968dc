"""
Online refinement of the stereo rig: the small errors of the right camera against its calibration.

A calibrated rig is never exact. What the images reveal, and this module estimates while running,
is how the right camera departs from its calibration: a residual rotation and an intrinsics
error, together the homography (ideal pixels of the calibrated right camera -> measured pixels)

    ``H(theta) = K_err R^T K_R^-1``,  ``R = R_z(roll) R_x(pitch) R_y(yaw)``

with ``K_R`` the calibrated right intrinsics (``StereoCalibration.K_right``) and ``K_err`` the
same with the focal block scaled by ``1 + focal_ratio`` and the principal point x moved by
``-disparity_offset_px``. The state ``theta`` (``PARAMETERS``, shape (5,)) is, in the right
camera's optical frame (x right, y down, z forward):

* ``roll`` (rad, about z): rows move by ``-f roll (u - cx) / f``, zero at the principal point,
  growing towards the left and right borders;
* ``pitch`` (rad, about x): rows of the right image move down by about ``f pitch``; a row offset
  of the right principal point is the same to 7 % at KITTI's field of view, so it is not a
  separate parameter;
* ``yaw`` (rad, about y): columns move left by ``f yaw (1 + ((u - cx) / f)^2)``, i.e. every
  disparity grows by about ``f yaw``, more towards the borders;
* ``focal_ratio``: the right focal over the calibrated one, minus 1 (rows and disparities off by
  an amount that grows towards the borders);
* ``disparity_offset_px``: the right principal point x is ``cx - offset``: every disparity grows
  by ``offset`` (pixels). Only the border terms of yaw tell the two apart (weakly).

The same sign conventions as ``synthetic.SequenceSpec.right_homography``. NOT observable from
images alone, hence not estimated: the absolute baseline and the focal length common to both
cameras (together the metric scale: a rig whose baseline is 0.3 % longer than calibrated sees
the world 0.3 % smaller, with every image identical), and the left camera's own intrinsics.

Per stereo pair with a motion estimate (:func:`measure_pair`) a small bundle adjustment over
the RANSAC inliers measures the error that remains after the correction: unknowns are each
point (inverse depth anchored on its previous left ray), the 6-DoF motion and ``theta``; the
residuals are the PIXEL residuals of the four views, Huber-weighted, with the residual scale
from the data. The rows of every stereo match measure roll, pitch and the focal ratio; the
temporal consistency of depth under the motion measures yaw and the disparity offset (a
disparity offset makes far points move inconsistently with near ones). Points and motion are
eliminated (Schur complements) and the information on ``theta`` is fused into a slow Kalman
filter (:class:`RigCalibrator`) with a first-order Gauss-Markov process noise (time constant
``rig.time_constant_s``), gated, and frozen while the data cannot inform it (standing still,
too few inliers). The correction is applied to the right-image measurements of the
correspondences (ideal pixels) before the estimator sees them (:meth:`RigCalibrator.corrected`),
each part (rows: roll, pitch, focal ratio; disparities: yaw, offset) once it differs from zero
significantly (``rig.apply_probability``).

On rectified input the tracker's affine stereo refinement puts the right point on the left
point's row (``pinned_rows``): such rows carry no information, so the rows of the inliers are
measured again (:func:`measure_rows`), and the slide along the row that the row error caused is
undone (:func:`row_coupling`). A tracker that refined along the rig's epipolar line (the rows
this estimate expects) and kept its free row would make both unnecessary.
"""

from __future__ import annotations

import dataclasses
import functools
import logging

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import gammaincinv

from .camera import StereoCalibration
from ..config import RigConfig
from ..records import Correspondences, RigEstimate

LOG = logging.getLogger(__name__)

#: Names of the state components, in order (rad, rad, rad, dimensionless, pixels).
PARAMETERS = ('roll_rad', 'pitch_rad', 'yaw_rad', 'focal_ratio', 'disparity_offset_px')
N_PARAMS = len(PARAMETERS)
#: Blocks of the state tested for significance before they are applied: what the rows measure
#: (roll, pitch, focal ratio) and what the disparities measure (yaw, disparity offset).
BLOCKS = (np.array([0, 1, 3]), np.array([2, 4]))
#: Consecutive gated-out pairs after which the estimate's covariance is widened by a tenth of
#: the prior (the rig may have changed, or the estimate went wrong). Many: a vehicle that
#: moves almost as the camera does can stay among the motion's inliers for seconds, and its
#: pairs are gated out as long as the estimate holds.
MAX_REJECTIONS = 100
#: Chi-square 99.9 % points for 1..5 degrees of freedom (gate of the per-pair measurement).
CHI2_999 = (10.83, 13.82, 16.27, 18.47, 20.52)


# -- the error model ----------------------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def chi2_quantile(probability: float, dof: int) -> float:
    """Quantile of the chi-square distribution (``scipy.stats.chi2.ppf``, without its import)."""
    return 2.0 * float(gammaincinv(0.5 * dof, probability))


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
        (N, 2) float64 right pixels, NaN where KLT failed or moved more than a pixel.

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
    ok = (status.ravel() == 1) & np.all(np.abs(found - start.reshape(-1, 2)) < 1.0, axis=1)
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
    if len(pts) == 0:
        return np.zeros(0)
    half = int(win_size_px) // 2
    r = np.arange(-half - 1, half + 2)
    H, W = img.shape
    cx = np.clip(np.rint(pts[:, 0]).astype(np.intp), half + 1, W - half - 2)
    cy = np.clip(np.rint(pts[:, 1]).astype(np.intp), half + 1, H - half - 2)
    patch = np.asarray(img)[cy[:, None, None] + r[None, :, None],
                            cx[:, None, None] + r[None, None, :]].astype(np.float32)
    st = max(int(step_px), 1)
    gx = (0.5 * (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2]))[:, ::st, ::st]
    gy = (0.5 * (patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1]))[:, ::st, ::st]
    x = r[1:-1][::st].astype(np.float32)
    n, k = len(pts), gx.shape[1] * gx.shape[2]
    sd = np.stack([gx * x[None, None, :], gx * x[None, :, None], gx], 1).reshape(n, 3, k)
    sd = sd - sd.mean(axis=2, keepdims=True)
    gy = gy.reshape(n, k)
    gy = gy - gy.mean(axis=1, keepdims=True)
    hess = (sd @ np.swapaxes(sd, 1, 2)).astype(np.float64)
    hess += np.eye(3) * (1e-4 * np.trace(hess, axis1=1, axis2=2)[:, None, None] + 1e-6)
    rhs = (sd @ gy[:, :, None])[:, :, 0].astype(np.float64)
    out = np.linalg.solve(hess, rhs[:, :, None])[:, 2, 0]
    return np.where(np.isfinite(out), out, 0.0)


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


# -- the slow filter ------------------------------------------------------------------------------
class RigCalibrator:
    """
    Slowly varying rig error with its uncertainty: correct, measure, fuse.

    Parameters
    ----------
    cfg : RigConfig
        The ``rig`` configuration section.

    Attributes
    ----------
    theta : (5,) float64 estimate (``PARAMETERS``) relative to the calibration in use.
    cov : (5, 5) float64 its covariance.

    """

    def __init__(self, cfg: RigConfig) -> None:
        self.cfg = cfg
        self.reset()

    def prior_covariance(self) -> np.ndarray:
        """Covariance (5, 5) of the rig error before any data (diagonal, from the config)."""
        c = self.cfg
        a = np.deg2rad(c.prior_angle_std_deg) ** 2
        return np.diag([a, a, np.deg2rad(c.prior_yaw_std_deg) ** 2, c.prior_focal_ratio_std ** 2,
                        c.prior_disparity_offset_std_px ** 2])

    def reset(self) -> None:
        """Forget the estimate: zero error with the prior covariance."""
        self.theta = np.zeros(N_PARAMS)
        self.cov = self.prior_covariance()
        self.updates = 0
        self.rejected = 0
        self._applied = [False] * len(BLOCKS)
        self._centre: tuple | None = None
        #: (9, 2, 5) rig Jacobian at the corners, edge middles and centre (``apply_min_px``).
        self._grid_jacobian: np.ndarray | None = None
        #: Feature ids (sorted) and row couplings of the last current pair (``couplings``).
        self._coupling_ids: tuple[np.ndarray, np.ndarray] | None = None
        self._streak = 0
        self._pairs = 0
        self.settled = False
        self.last = 'none'
        self._H_cache: tuple | None = None

    # -- correction ----------------------------------------------------------------------------
    def homography(self, calib: StereoCalibration) -> np.ndarray:
        """(3, 3) map from calibrated to measured right pixels of ``calib`` (the estimate)."""
        return self._homographies(calib)[0]

    def homography_inverse(self, calib: StereoCalibration) -> np.ndarray:
        """(3, 3) map from measured to corrected (calibrated) right pixels of ``calib``."""
        return self._homographies(calib)[1]

    def _homographies(self, calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
        theta = self.applied()
        key = (id(calib), theta.tobytes())
        if self._H_cache is None or self._H_cache[0] != key:
            H = right_homography(calib.K_right, theta)
            self._H_cache = (key, H, np.linalg.inv(H))
        return self._H_cache[1], self._H_cache[2]

    def active(self) -> bool:
        """Whether the correction is applied (enabled and away from zero)."""
        return self.cfg.enabled and bool(np.any(self.applied() != 0.0))

    def applied(self) -> np.ndarray:
        """
        Return the correction in use (5,): the blocks of the estimate that differ from zero.

        Each block of ``BLOCKS`` is applied once its squared Mahalanobis distance from zero
        exceeds the ``rig.apply_probability`` quantile of chi-square, and stays applied; until
        then it is zero. On an exact rig the estimate wanders within its uncertainty (about
        0.01-0.02 px of disparity after 150 pairs), which already costs 0.05-0.1 % of t_rel on
        a city render.
        """
        out = np.zeros(N_PARAMS)
        for k, idx in enumerate(BLOCKS):
            if not self._applied[k]:
                P = self.cov[np.ix_(idx, idx)]
                m2 = float(self.theta[idx] @ np.linalg.solve(P, self.theta[idx]))
                big = self._grid_jacobian is None or float(np.abs(
                    self._grid_jacobian[:, :, idx] @ self.theta[idx]).max()) > \
                    self.cfg.apply_min_px
                self._applied[k] = big and m2 > chi2_quantile(self.cfg.apply_probability,
                                                              len(idx))
            if self._applied[k]:
                out[idx] = self.theta[idx]
        return out

    def corrected(self, corr: Correspondences, calib_prev: StereoCalibration,
                  calib_cur: StereoCalibration,
                  coupling: tuple[np.ndarray, np.ndarray] | None = None) -> Correspondences:
        """
        Return the correspondences with both right points mapped by the inverse rig error.

        Ideal pixels in, ideal pixels of the calibrated right camera out (new arrays; ids and
        ages shared); the input itself when off or at zero. A right point that the tracker put
        on the row of its left point (``pinned_rows``) is first moved to the row the rig
        estimate expects and, with ``coupling`` (``row_coupling`` of its left window, (N,)
        for the previous and the current pair), back along its row by the slide that the row
        error caused.
        """
        if not self.active() or len(corr) == 0:
            return corr
        c_prev, c_cur = (None, None) if coupling is None else coupling
        return Correspondences(
            corr.prev_left, self._correct(corr.prev_left, corr.prev_right, calib_prev, c_prev),
            corr.cur_left, self._correct(corr.cur_left, corr.cur_right, calib_cur, c_cur),
            corr.ids, corr.ages)

    def couplings(self, corr: Correspondences, calib_prev: StereoCalibration,
                  calib_cur: StereoCalibration, prev_img: np.ndarray | None,
                  cur_img: np.ndarray | None, win_size_px: int, step_px: int
                  ) -> tuple[np.ndarray, np.ndarray] | None:
        """
        ``row_coupling`` of the pinned matches of both pairs ((N,) each, 0 elsewhere).

        None while no row correction is applied (nothing to undo; also with ``rig.enabled``
        off, when ``corrected`` returns its input) or without the images.
        """
        if prev_img is None or cur_img is None or not self.cfg.enabled or \
                not np.any(self.applied()[BLOCKS[0]]):
            self._coupling_ids = None
            return None
        ids = corr.ids if corr.ids.size == len(corr) else None
        out = []
        for k, (calib, img, left, right) in enumerate((
                (calib_prev, prev_img, corr.prev_left, corr.prev_right),
                (calib_cur, cur_img, corr.cur_left, corr.cur_right))):
            c = np.zeros(len(left))
            todo = pinned_rows(calib, left, right)
            if k == 0 and ids is not None and self._coupling_ids is not None:
                # The previous pair's windows were measured as the current ones last time.
                known, cached = self._coupling_ids
                pos = np.searchsorted(known, ids)
                hit = (pos < len(known)) & (known[np.minimum(pos, len(known) - 1)] == ids)
                c[hit] = cached[pos[hit]]
                todo &= ~hit
            if np.any(todo):
                c[todo] = row_coupling(img, left[todo], win_size_px, step_px)
            out.append(c)
        if ids is not None:
            order = np.argsort(ids)
            self._coupling_ids = (ids[order], out[1][order])
        return out[0], out[1]

    def _unpinned(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                  coupling: np.ndarray | None = None) -> np.ndarray:
        """Right points (N, 2) with pinned rows moved to the rows the estimate expects."""
        pinned = pinned_rows(calib, left, right)
        if not np.any(pinned) or not self.active():
            return right
        right = np.array(right, np.float64)
        row = apply_homography(self.homography(calib), right[pinned])[:, 1]
        if coupling is not None:
            right[pinned, 0] -= (row - right[pinned, 1]) * coupling[pinned]
        right[pinned, 1] = row
        return right

    def _correct(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                 coupling: np.ndarray | None = None) -> np.ndarray:
        return apply_homography(self.homography_inverse(calib),
                                self._unpinned(left, right, calib, coupling))

    def distorted(self, pts: np.ndarray, calib: StereoCalibration) -> np.ndarray:
        """Map calibrated right pixels (N, 2) to where the real right camera sees them."""
        if not self.active() or len(pts) == 0:
            return pts
        return apply_homography(self.homography(calib), pts)

    # -- update --------------------------------------------------------------------------------
    def predict(self, dt: float) -> None:
        """Gauss-Markov step over ``dt`` seconds: mean decays, covariance towards the prior."""
        if not dt > 0:
            return
        decay = np.exp(-dt / self.cfg.time_constant_s)
        self.theta = self.theta * decay
        self.cov = self.cov * decay * decay + self.prior_covariance() * (1.0 - decay * decay)

    def update(self, corr: Correspondences, inliers: np.ndarray, T_prev_cur: np.ndarray,
               dt: float, calib_prev: StereoCalibration, calib_cur: StereoCalibration,
               images: tuple[np.ndarray, np.ndarray] | None = None,
               win_size_px: int = 13,
               coupling: tuple[np.ndarray, np.ndarray] | None = None) -> str:
        """
        Measure the rig error on one pair's inliers and fuse it.

        Parameters
        ----------
        corr : Correspondences
            The pair's correspondences as tracked (ideal pixels, NOT corrected).
        inliers : np.ndarray
            (N,) bool inliers of the motion estimate.
        T_prev_cur : np.ndarray
            (4, 4) motion estimate (pose of the current left camera in the previous one, m).
        dt : float
            Time between the pairs (s).
        calib_prev, calib_cur : StereoCalibration
            Calibrations of the two pairs.
        images : tuple of np.ndarray, optional
            The current pair's (H, W) uint8 left and right images: the rows of the inliers
            whose rows the tracker pinned are measured in them (``measure_rows``). Without
            them those rows are left out (the error is then seen through the columns only).
        win_size_px : int
            KLT window of that row measurement (pixels).
        coupling : tuple of np.ndarray, optional
            ``couplings`` of the pair (as for ``corrected``).

        Returns
        -------
        str: ``updated``, ``rejected`` (gated out), ``frozen`` (standing still, too few
        inliers, no usable measurement), ``skipped`` (``rig.measure_every``) or ``off``.

        """
        cfg = self.cfg
        if not cfg.enabled:
            self.last = 'off'
            return self.last
        self.predict(dt)
        self._pairs += 1
        if self._pairs % cfg.measure_every:
            self.last = 'skipped'
            return self.last
        inliers = np.asarray(inliers, bool)
        moved = float(np.linalg.norm(np.asarray(T_prev_cur)[:3, 3]))
        if moved < cfg.min_translation_m or np.count_nonzero(inliers) < cfg.min_points:
            self.last = 'frozen'
            return self.last
        raw = corr.subset(inliers)
        if coupling is not None:
            coupling = (coupling[0][inliers], coupling[1][inliers])
        sub = self.corrected(raw, calib_prev, calib_cur, coupling)
        used = np.ones((len(raw), 8), bool)
        used[:, 3] = ~pinned_rows(calib_prev, raw.prev_left, raw.prev_right)
        pinned = np.flatnonzero(pinned_rows(calib_cur, raw.cur_left, raw.cur_right))
        used[pinned, 7] = False
        if pinned.size and images is not None:
            start = self._unpinned(raw.cur_left[pinned], raw.cur_right[pinned], calib_cur)
            rows = measure_rows(images[0], images[1], raw.cur_left[pinned], start, win_size_px)
            rows = rows[:, 1]
            good = np.isfinite(rows)
            free = raw.cur_right[pinned[good]].astype(np.float64)
            free[:, 1] = rows[good]
            cur_right = np.array(sub.cur_right, np.float64)
            cur_right[pinned[good]] = apply_homography(self.homography_inverse(calib_cur), free)
            sub = Correspondences(sub.prev_left, sub.prev_right, sub.cur_left, cur_right,
                                  sub.ids, sub.ages)
            used[pinned[good], 7] = True
        try:
            with np.errstate(divide='ignore', invalid='ignore'):
                meas = measure_pair(sub, calib_prev, calib_cur, T_prev_cur, cfg, used)
        except np.linalg.LinAlgError:
            meas = None
        if meas is None or not (np.all(np.isfinite(meas.information)) and
                                np.all(np.isfinite(meas.gradient))):
            self.last = 'frozen'
            return self.last
        # The pair measured the error left after the correction in use; refer it to the estimate.
        meas.gradient = meas.gradient - meas.information @ (self.theta - self.applied())
        self.last = 'updated' if self._fuse(meas) else 'rejected'
        if self.last == 'updated':
            self.updates += 1
            self._streak = 0
        else:
            self.rejected += 1
            self._streak += 1
            if self._streak >= MAX_REJECTIONS:
                LOG.warning('stereo rig: %d pairs in a row disagree with the estimate; its '
                            'uncertainty is widened', self._streak)
                self.cov = self.cov + 0.1 * self.prior_covariance()
                self._streak = 0
        self._check_settled(calib_cur)
        return self.last

    def _fuse(self, meas: PairMeasurement) -> bool:
        """Information-form Kalman update with a 99.9 % gate; returns whether it was fused."""
        I, g, P = meas.information, meas.gradient, self.cov
        # Gate: the measurement z = I^-1 g has covariance I^-1 + P; in information form the
        # squared distance is g^T (I + I P I)^+ g (works where I is singular).
        M = I + I @ P @ I
        w, V = np.linalg.eigh(0.5 * (M + M.T))
        good = w > 1e-9 * max(float(w.max()), 1e-300)
        dof = int(np.count_nonzero(good))
        if dof == 0:
            return False
        proj = V[:, good].T @ g
        m2 = float(np.sum(proj * proj / w[good]))
        if not (np.isfinite(m2) and m2 < CHI2_999[dof - 1]):
            return False
        info_post = np.linalg.inv(P) + I
        cov = np.linalg.inv(0.5 * (info_post + info_post.T))
        self.theta = self.theta + cov @ g
        self.cov = 0.5 * (cov + cov.T)
        self._H_cache = None
        return True

    def _check_settled(self, calib: StereoCalibration) -> None:
        """Log once when the offsets at the principal point are known to ``settled_std_px``."""
        est = self.estimate(calib)
        settled = max(est.row_offset_std_px, est.disparity_offset_std_px) < \
            self.cfg.settled_std_px
        if self._grid_jacobian is None:  # corners, edge middles and centre of the image
            w, h = calib.size
            grid = np.stack(np.meshgrid([0.0, w / 2.0, w - 1.0], [0.0, h / 2.0, h - 1.0]),
                            -1).reshape(-1, 2)
            self._grid_jacobian = rig_jacobian(calib.K_right, grid)
        if settled and not self.settled:
            LOG.info('stereo rig refined after %d pairs: row offset %+.3f +- %.3f px, disparity '
                     'offset %+.3f +- %.3f px (roll %+.4f, pitch %+.4f, yaw %+.4f deg, right '
                     'focal %+.4f %%, principal point x %+.3f px)', self.updates,
                     est.row_offset_px, est.row_offset_std_px, est.disparity_offset_px,
                     est.disparity_offset_std_px, *np.rad2deg(self.theta[:3]),
                     100.0 * self.theta[3], -self.theta[4])
        self.settled = self.settled or settled

    # -- output --------------------------------------------------------------------------------
    def estimate(self, calib: StereoCalibration | None) -> RigEstimate:
        """Return the current estimate as a record (offsets at ``calib``'s principal point)."""
        theta, cov = self.theta.copy(), self.cov.copy()
        row = disp = row_std = disp_std = float('nan')
        if calib is not None:
            if self._centre is None or self._centre[0] is not calib:
                self._centre = (calib, offsets_at_centre(calib.K_right))
            C = self._centre[1]
            off, off_cov = C @ theta, C @ cov @ C.T
            row, disp = float(off[0]), float(off[1])
            row_std, disp_std = (float(np.sqrt(max(v, 0.0))) for v in np.diag(off_cov))
        return RigEstimate(theta=theta, covariance=cov, row_offset_px=row,
                           row_offset_std_px=row_std, disparity_offset_px=disp,
                           disparity_offset_std_px=disp_std, updates=self.updates,
                           rejected=self.rejected, settled=self.settled,
                           enabled=self.cfg.enabled, last=self.last, applied=self.applied())


# -- the refined calibration ----------------------------------------------------------------------
def refined_camera_infos(calib: StereoCalibration, theta: np.ndarray) -> tuple[dict, dict]:
    """
    Return the CameraInfo fields of both cameras with the rig error folded in.

    The right camera gets intrinsics ``K_err`` (focal ratio, principal point x) and its
    rectification rotation turned by the residual rotation, exactly; the projection matrices
    stay the calibrated ones. Such a pair describes the images as they are, but as
    ``raw`` input (``pipeline.input_kind: raw``; no distortion when the input was rectified):
    a rectified CameraInfo (P only) cannot hold a rotated right camera. The metric scale
    (baseline, common focal length) is the calibration's: the images do not tell it.

    Parameters
    ----------
    calib : StereoCalibration
        The calibration the estimate refers to.
    theta : np.ndarray
        (5,) rig error (``PARAMETERS``).

    Returns
    -------
    tuple of dict
        ``k`` (9), ``d``, ``r`` (9), ``p`` (12), ``width``, ``height``, ``distortion_model``
        for the left and the right camera (lists of floats, row-major).

    """
    theta = np.asarray(theta, np.float64)
    R = rotation_zxy(theta[:3])
    out = []
    for cam, K, rot in ((calib.left, calib.K_left, np.eye(3)),
                        (calib.right, calib.K_right, R)):
        K = np.array(K, np.float64)
        if cam is calib.right:
            K[:2, :2] *= 1.0 + theta[3]
            K[0, 2] -= theta[4]
        R_rect = np.eye(3) if calib.kind == 'rectified' else cam.R
        D = np.zeros(5) if calib.kind == 'rectified' else cam.D
        model = 'plumb_bob' if calib.kind == 'rectified' else cam.distortion_model
        out.append({'width': int(cam.width), 'height': int(cam.height),
                    'distortion_model': model, 'd': [float(v) for v in D],
                    'k': [float(v) for v in K.ravel()],
                    'r': [float(v) for v in (R_rect @ rot).ravel()],
                    'p': [float(v) for v in cam.P.ravel()]})
    return out[0], out[1]


def camera_info_yaml(left: dict, right: dict) -> str:
    """Return both cameras in the camera_calibration_parsers YAML layout, under left/right."""
    def block(name: str, info: dict) -> list[str]:
        def matrix(key: str, rows: int, cols: int, data: list) -> list[str]:
            values = ', '.join(repr(float(v)) for v in data)
            return [f'  {key}:', f'    rows: {rows}', f'    cols: {cols}',
                    f'    data: [{values}]']
        return ([f'{name}:', f'  image_width: {info["width"]}',
                 f'  image_height: {info["height"]}', f'  camera_name: {name}']
                + matrix('camera_matrix', 3, 3, info['k'])
                + [f'  distortion_model: {info["distortion_model"]}']
                + matrix('distortion_coefficients', 1, len(info['d']), info['d'])
                + matrix('rectification_matrix', 3, 3, info['r'])
                + matrix('projection_matrix', 3, 4, info['p']))
    lines = ['# Stereo calibration refined online by stereo_vo_ros (rig_calibration.py): the',
             "# right camera's residual rotation (rectification_matrix), focal ratio and",
             '# principal point folded in. Describes the images as raw input (input_kind: raw).']
    return '\n'.join(lines + block('left', left) + block('right', right)) + '\n'
