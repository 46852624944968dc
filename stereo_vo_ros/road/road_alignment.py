"""
Direct alignment of the road plane (not in the papers): a dense measurement of the motion.

The tracker hands the estimator a few dozen road features per pair, and on a fast road their
temporal matches are the weak part of the odometry: the near road moves 50-160 px a pair and
deforms within the KLT window. Every road pixel carries the same information, and the plane
predicts where each one goes:

1. :meth:`RoadAligner.refine_plane` refines the road plane ``n . X = d`` of a rectified stereo
   pair by aligning the left image's road pixels with the right image. The disparity of a
   plane is linear in ``p = n / d``: Gauss-Newton on p and the right camera's gain and offset,
   Cauchy-weighted, coarse to fine. It starts from the previous pair's plane moved by the
   motion (or from the plane of the features, ``ground_plane.fit_ground_plane``) and keeps the
   pixels whose left and right images agree with the plane: a vehicle standing on the road
   does not. The right image is sampled through the rig error that the online rig refinement
   estimates, as the features' right points are corrected by it.
2. :meth:`RoadAligner.align` aligns those pixels of the previous left image with the current
   left image (plane-induced warp), starting from the estimator's motion: Gauss-Newton with the
   ESM gradient (Benhimane and Malis 2004), the exposure's gain and offset, Cauchy weights and
   occluders truncated, coarse to fine. By default it refines and measures the longitudinal
   motion only (forward and vertical translation, pitch): the lateral translation and the yaw,
   which the road alone hardly tells apart, stay the features'.

The pipeline fuses the measurement with the filter's estimate (:meth:`MotionEstimator.fuse`)
after a Mahalanobis gate. Only rectified input is aligned; without an admissible road plane
(no road in view, a wall ahead), or when either step does not converge, nothing is measured
and the pair is estimated as the papers describe.

Pixels compared: every ``road.pixel_step``-th of each pyramid level (a lattice fixed to the
level's full image), on the plane between
``road.min_depth_m`` and ``road.max_depth_m`` ahead and within ``road.max_lateral_m`` of the
optical axis. Frames: the previous / current left camera optical frames (x right, y down,
z forward), metres; ``T_prev_cur`` is the pose of the current left camera in the previous one.

The per-pixel work (choosing the road pixels, sampling the images, the stereo and temporal
residuals, the ESM gradients, the Cauchy weights, the normal equations) runs in compiled
kernels (:mod:`~stereo_vo_ros.jit`), which release the GIL: the pipeline refines the plane on
its helper thread next to the tracking. The images are sampled with exact bilinear weights
(``cv2.remap`` quantises them to 1/32 px in some versions and channel counts), from one plane
per quantity (value, d/du, d/dv) that the OpenCV filters write in place. Points are stored one
row per coordinate ((3, N)), the motion's iterations of a level run in one kernel (its small
solves with them; the plane's go through OpenCV), the lattice is computed once per level
geometry, and a pixel that leaves the view is dropped for the rest of the level.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import cv2
import numba
import numpy as np

from ..config import RansacConfig, RoadConfig
from ..estimation.camera import StereoCalibration
from ..estimation.motion import velocity_from_transform
from ..jit import finite, kernel, readonly

#: The plane lies at least this far below the optical centre (m).
MIN_HEIGHT_M = 0.1
#: Grey-level differences above this are occluders (a vehicle, a barrier) and weigh nothing.
MAX_DIFFERENCE = 30.0
#: The blur's kernel reaches this many sigmas either side (OpenCV's default for float
#: images, four, costs a third more for weights below 0.1 % of the kernel's).
BLUR_SIGMAS = 3.0
#: Scale of the Cauchy weights in robust residual scales.
CAUCHY_SCALES = 2.0
#: The residual scale is the median of every n-th residual.
SCALE_SUBSAMPLE = 4
#: Floor of the residual scale (grey levels).
MIN_SCALE = 0.5
#: A road pixel agrees with the plane when its stereo residual is within this many robust
#: scales (grey levels).
STEREO_INLIER_SCALES = 3.0
#: Rows prepared above the farthest road compared (input pixels): blur, and the road moving up
#: in the image between two pairs (pitch, bounce).
FIRST_ROW_MARGIN_PX = 24
#: Finite-difference step of the motion-to-velocity Jacobian (m and rad).
JACOBIAN_STEP = 1e-6
#: Per ``road.motion``: the state components (V_X, V_Y, V_Z, w_X, w_Y, w_Z) the alignment
#: refines, and those of them it reports as measured (the pipeline fuses those).
MOTION_COMPONENTS = {'forward': ([1, 2, 3], [2]), 'longitudinal': ([1, 2, 3], [1, 2, 3]),
                     'full': ([0, 1, 2, 3, 4, 5], [0, 1, 2, 3, 4, 5])}
#: The alignment converged when its last step moved the road pixels by less than this (RMS, px).
CONVERGED_PX = 0.05
#: The plane, refined again at every pair from the last one, converged when its last step
#: moved the disparities by less than this (RMS, pixels).
PLANE_CONVERGED_PX = 0.25


@dataclass(frozen=True)
class RoadPlane:
    """
    The road ``normal . X = d`` in a left camera optical frame.

    Attributes
    ----------
    normal : np.ndarray
        (3,) unit normal pointing down (positive y component).
    d : float
        Height of the optical centre above the plane (m).
    pixels : tuple or None
        Per pyramid level of the pair it was refined on (``RoadAligner.refine_plane``), the
        grid pixels u, v (N,) of that level, their points (3, N) on the plane and the left
        image's (value, d/du, d/dv) (N, 3) there, those whose left and right images agree with
        the plane (a vehicle on the road does not); None for a plane from elsewhere.

    """

    normal: np.ndarray
    d: float
    pixels: tuple | None = None

    def in_frame(self, T_a_b: np.ndarray) -> 'RoadPlane':
        """Return the plane in frame b, given the pose ``T_a_b`` (4, 4) of b in this frame a."""
        R, t = T_a_b[:3, :3], T_a_b[:3, 3]
        return RoadPlane(R.T @ self.normal, float(self.d - self.normal @ t))

    def admissible(self, ransac: RansacConfig) -> bool:
        """Whether a forward-looking camera could stand on it (``ransac.ground_*`` bounds)."""
        return bool(np.all(np.isfinite(self.normal)) and math.isfinite(self.d)
                    and self.normal[1] >= math.cos(math.radians(ransac.ground_max_tilt_deg))
                    and MIN_HEIGHT_M <= self.d <= ransac.ground_max_height_m)


@dataclass
class RoadLevel:
    """
    One pyramid level of a rectified stereo pair prepared for the alignment.

    Attributes
    ----------
    left : (H, W) float32 the blurred left image (grey levels; ``left_grad[0]``).
    left_grad : (3, H, W) float32 the blurred left image and its x and y gradients (grey
        levels, grey levels per pixel), one plane each.
    right_grad : (2, H, W) float32 the blurred right image and its x gradient.
    scale : float pixels of this level per pixel of the input (1, 1/2, 1/4, ...).
    row0 : int the arrays start at this row of the level (the rows above see no road).

    """

    left: np.ndarray
    left_grad: np.ndarray
    right_grad: np.ndarray
    scale: float
    row0: int = 0

    def intrinsics(self, calib: StereoCalibration) -> tuple[float, float, float]:
        """Focal length and principal point (f, cx, cy) of the left camera at this level."""
        K, s = calib.K_left, self.scale  # cv2.pyrDown: pixel j of a level is pixel 2j below
        return K[0, 0] * s, K[0, 2] * s, K[1, 2] * s


@dataclass
class RoadImages:
    """A rectified stereo pair prepared for the alignment: levels[0] is the finest."""

    levels: list[RoadLevel]


@dataclass
class RoadMotion:
    """
    Result of :meth:`RoadAligner.align`.

    Attributes
    ----------
    T_prev_cur : (4, 4) float64 pose of the current left camera in the previous one (m).
    velocity : (6,) float64 the same motion as a state of the estimator (m/s, rad/s, previous
        left frame; see :mod:`~stereo_vo_ros.estimation.motion`).
    covariance : (6, 6) float64 covariance of ``velocity`` (inflated by
        ``road.covariance_inflation``); meaningful in the rows and columns of ``components``.
    components : list of int the state components measured (``MOTION_COMPONENTS``): only
        those of ``velocity`` and ``covariance`` are meant to be fused.
    pixels : int road pixels compared in the last iteration.
    scale : float robust residual scale (grey levels).

    """

    T_prev_cur: np.ndarray
    velocity: np.ndarray
    covariance: np.ndarray
    components: list
    pixels: int
    scale: float


_F8, _I8 = numba.types.float64, numba.types.int64
_M2, _V1 = readonly(_F8, 2), readonly(_F8, 1)
_W1, _W2 = numba.types.Array(_F8, 1, 'C'), numba.types.Array(_F8, 2, 'C')
_B1 = numba.types.Array(numba.types.boolean, 1, 'C')
_IDX, _I1 = numba.types.Array(_I8, 1, 'C'), readonly(_I8, 1)
_IMG = readonly(numba.types.float32, 3)  # (planes, H, W)


@kernel(_F8(_V1))
def _scale(r):
    """
    Return the robust scale of residuals r (N,) (grey levels).

    1.4826 times the median (the upper one) absolute residual below ``MAX_DIFFERENCE``, of
    every ``SCALE_SUBSAMPLE``-th residual (the median of all was a tenth of the alignment's
    time), at least ``MIN_SCALE``.
    """
    step = SCALE_SUBSAMPLE if len(r) >= 400 * SCALE_SUBSAMPLE else 1
    a = np.empty((len(r) + step - 1) // step)
    n = 0
    for i in range(0, len(r), step):
        if abs(r[i]) < MAX_DIFFERENCE:
            a[n] = abs(r[i])
            n += 1
    if n == 0:
        return MAX_DIFFERENCE
    return max(1.4826 * np.partition(a[:n], n // 2)[n // 2], MIN_SCALE)


@kernel()
def _inside(x, y, w, h):
    """Whether array pixel (x, y) of a (h, w) array can be sampled (not NaN, 2 x 2 inside)."""
    return x > 0.0 and x < w - 1.0 and y > 0.0 and y < h - 1.0


@kernel()
def _bilinear(img, c, ix, iy, a, b):
    """
    Bilinear sample of plane ``c`` of ``img`` (C, H, W) at array pixel (ix + a, iy + b).

    ``ix, iy`` the integer part of a pixel that ``_inside`` accepts, ``a, b`` the fractions.
    """
    p00, p01 = np.float64(img[c, iy, ix]), np.float64(img[c, iy, ix + 1])
    p10, p11 = np.float64(img[c, iy + 1, ix]), np.float64(img[c, iy + 1, ix + 1])
    top = p00 + a * (p01 - p00)
    return top + b * (p10 + a * (p11 - p10) - top)


@kernel(numba.types.void(_IMG, _V1, _V1, _F8, _W2))
def _sample(img, u, v, row0, out):
    """
    Write bilinear samples (N, 3) of a level's left planes ``img`` (3, H, W) at pixels (u, v).

    The planes start at the level's row ``row0``. A pixel that cannot be sampled (``_inside``)
    gets zeros.
    """
    h, w = img.shape[1], img.shape[2]
    for i in range(len(u)):
        x, y = u[i], v[i] - row0
        if not _inside(x, y, w, h):
            out[i, 0] = out[i, 1] = out[i, 2] = 0.0
            continue
        ix, iy = int(x), int(y)  # positive: truncation is the floor
        for c in range(3):
            out[i, c] = _bilinear(img, c, ix, iy, x - ix, y - iy)


@kernel(_I8(_V1, _V1, _V1, _V1, _V1, _F8, _F8, _F8, _F8, _W1, _W1, _W2))
def _road_rays(us, vs, xr, yr, n, d, min_depth, max_depth, max_lateral, us_out, vs_out, ray):
    """
    Write the pixels (us, vs) whose rays (xr, yr, 1) meet the road, and those rays; count them.

    The road: the plane ``n . X = d`` between the depths ``min_depth`` and ``max_depth`` and
    within ``max_lateral`` of the optical axis (m). ``ray`` is (3, N), its last row ones.
    """
    count = 0
    for i in range(len(us)):
        depth = d / (n[0] * xr[i] + n[1] * yr[i] + n[2])
        if depth > min_depth and depth < max_depth and abs(xr[i] * depth) < max_lateral:
            us_out[count], vs_out[count] = us[i], vs[i]
            ray[0, count], ray[1, count], ray[2, count] = xr[i], yr[i], 1.0
            count += 1
    return count


@kernel(_I8(_IMG, _F8, _M2, _V1, _V1, _M2, _M2, _V1, _F8, _F8, _F8, _W1, _W2, _IDX))
def _stereo_residuals(right, row0, H, us, vs, ray, tmpl, p, fb, gain, offset, r, sampled, idx):
    """
    Write the stereo residuals ``g I_R + o - I_L`` (grey levels) of left pixels on plane p.

    The disparity of the left pixel (us, vs) on ray ``ray`` (3, N; z = 1) is ``fb p . r``;
    ``H`` (3, 3) moves the calibrated right pixel to where the right level's planes ``right``
    (2, H, W: value, d/du; starting at row ``row0``) show it; ``tmpl`` (N, 3) are the left
    samples (value first), g and o the right camera's gain and offset. Only the pixels whose
    match can be sampled: their residuals to ``r``, the right samples to ``sampled`` (N, 2)
    and their indices to ``idx``, in order; returns how many.
    """
    h, w = right.shape[1], right.shape[2]
    n = 0
    for i in range(len(us)):
        ur = us[i] - fb * (p[0] * ray[0, i] + p[1] * ray[1, i] + p[2] * ray[2, i])
        iw = 1.0 / (H[2, 0] * ur + H[2, 1] * vs[i] + H[2, 2])
        x = (H[0, 0] * ur + H[0, 1] * vs[i] + H[0, 2]) * iw
        y = (H[1, 0] * ur + H[1, 1] * vs[i] + H[1, 2]) * iw - row0
        if not _inside(x, y, w, h):
            continue
        ix, iy = int(x), int(y)
        for c in range(2):
            sampled[n, c] = _bilinear(right, c, ix, iy, x - ix, y - iy)
        r[n] = gain * sampled[n, 0] + offset - tmpl[i, 0]
        idx[n] = i
        n += 1
    return n


@kernel()
def _motion_row(ga, gb, xn, yn, iz, free, row):
    """
    Write the derivatives of an image value by the motion components ``free`` into ``row``.

    The point ``X' = (xn, yn, 1) / iz`` (current camera frame) is perturbed as
    ``X' -> X' + dv + dw x X'``; ``ga, gb`` are the image gradient times the focal length.
    With ``(ga, gb) = (f, 0)`` (``(0, f)``) the row is the derivative of the pixel's u (v).
    """
    c = ga * xn + gb * yn
    every = (ga * iz, gb * iz, -c * iz, -(c * yn + gb), c * xn + ga, gb * xn - ga * yn)
    for j in range(len(free)):
        row[j] = every[free[j]]


@kernel()
def _accumulate(row, ri, c2, max_r2, A, b):
    """
    Add a residual ``ri`` with Jacobian ``row`` to the lower triangle of ``A`` and to ``b``.

    Cauchy weight ``c2 / (c2 + ri^2)``; nothing from ``max_r2`` on (an occluder).
    """
    r2 = ri * ri
    if r2 >= max_r2:
        return
    w = c2 / (c2 + r2)
    for a in range(len(row)):
        wa = w * row[a]
        b[a] -= wa * ri
        for col in range(a + 1):
            A[a, col] += wa * row[col]


@kernel()
def _mirror(A):
    """Copy the lower triangle of the square ``A`` to its upper triangle."""
    for a in range(A.shape[0]):
        for col in range(a):
            A[col, a] = A[a, col]


@kernel(_I8(_M2, _M2, _F8, _F8, _F8, _F8, _IMG, _F8, _M2, _F8, _F8, _W2, _B1, _W2, _W1, _W1))
def _warp_road(X, T, f, cx, cy, min_z, img, row0, tmpl, gain, offset, proj, alive, cur_s, r,
               r_alive):
    """
    Move the road points into the current image and compare; return how many stay alive.

    ``X`` (3, N) points (m), ``T`` (4, 4) the transform into the current frame; writes
    ``proj`` (5, N): u, v (pixels of the level), x / z, y / z and 1 / z. A point stays
    ``alive`` (N,) while it is farther than ``min_z`` and the current left planes ``img``
    (3, H, W; from the level's row ``row0``) can be sampled there (``_inside``). For those:
    the samples (value, d/du, d/dv) to ``cur_s`` (N, 3) and the residuals
    ``g I_cur + o - I_prev`` (grey levels; ``tmpl`` (N, 3) the template) to ``r`` (N,) and,
    in order, to ``r_alive``. The others get u = v = -1 and zeros.
    """
    h, w = img.shape[1], img.shape[2]
    count = 0
    for i in range(X.shape[1]):
        if alive[i]:
            x, y, z = X[0, i], X[1, i], X[2, i]
            xc = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            yc = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            zc = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            iz = 1.0 / zc
            xn, yn = xc * iz, yc * iz
            u, v = f * xn + cx, f * yn + cy
            alive[i] = zc > min_z and _inside(u, v - row0, w, h)
        if not alive[i]:
            proj[0, i] = proj[1, i] = -1.0
            cur_s[i, 0] = cur_s[i, 1] = cur_s[i, 2] = r[i] = 0.0
            continue
        proj[0, i], proj[1, i], proj[2, i], proj[3, i], proj[4, i] = u, v, xn, yn, iz
        ix, iy = int(u), int(v - row0)  # positive: truncation is the floor
        for c in range(3):
            cur_s[i, c] = _bilinear(img, c, ix, iy, u - ix, v - row0 - iy)
        r[i] = gain * cur_s[i, 0] + offset - tmpl[i, 0]
        r_alive[count] = r[i]
        count += 1
    return count


@kernel(numba.types.boolean(_M2, _M2, _V1, _V1, _M2, _V1, readonly(numba.types.boolean, 1),
                            _M2, _F8, _F8, _F8, _F8, readonly(numba.types.int64, 1), _W2, _W1))
def _motion_system(cur_s, tmpl, us, vs, proj, r, alive, G, gain, f, c2, max_r2, free, A, b):
    """
    Write the normal equations ``A x = b`` of a Gauss-Newton step of the motion (``align``).

    ``cur_s`` (N, 3) the current image's value and gradients at the projected pixels, ``tmpl``
    (N, 3) the template's, ``us, vs`` (N,) the template pixels, ``proj`` (5, N) from
    ``_warp_road``, ``r`` (N,) the residuals, ``alive`` (N,) the pixels compared, ``G``
    the inverse plane warp (current -> previous pixels), ``c2`` the squared Cauchy scale,
    ``max_r2`` the squared occluder limit, ``free`` the state components refined. Rows of J:
    the components of ``free`` (``_motion_row``), then gain and offset; weights as
    ``_accumulate`` gives them. False when a gradient is not finite.
    """
    k = len(free)
    A[:, :] = 0.0
    b[:] = 0.0
    row = np.empty(k + 2)
    for i in range(len(r)):
        if not alive[i]:
            continue
        u, v, xn, yn, iz = proj[0, i], proj[1, i], proj[2, i], proj[3, i], proj[4, i]
        # ESM: the mean of the current gradient and the template's carried by G.
        s = 0.5 / (G[2, 0] * u + G[2, 1] * v + G[2, 2])
        tu, tv = tmpl[i, 1] * s, tmpl[i, 2] * s
        gx = 0.5 * gain * cur_s[i, 1] + tu * (G[0, 0] - us[i] * G[2, 0]) \
            + tv * (G[1, 0] - vs[i] * G[2, 0])
        gy = 0.5 * gain * cur_s[i, 2] + tu * (G[0, 1] - us[i] * G[2, 1]) \
            + tv * (G[1, 1] - vs[i] * G[2, 1])
        if not (finite(gx) and finite(gy)):
            return False
        _motion_row(f * gx, f * gy, xn, yn, iz, free, row)
        row[k] = cur_s[i, 0]
        row[k + 1] = 1.0
        _accumulate(row, r[i], c2, max_r2, A, b)
    _mirror(A)
    return True


@kernel(numba.types.void(_M2, _M2, _I1, _V1, _F8, _F8, _F8, _W2, _W1))
def _plane_system(sampled, ray, idx, r, fb_gain, c2, max_r2, A, b):
    """
    Write the normal equations ``A x = b`` of a Gauss-Newton step of the plane.

    ``sampled`` (M, 2) the right image's value and x gradient at the matches, ``ray`` (3, N)
    the left rays (z = 1), ``idx`` (M,) the matches' rays, ``r`` (M,) the stereo residuals,
    ``fb_gain`` focal length times baseline times the right camera's gain, ``c2`` the squared
    Cauchy scale, ``max_r2`` the squared occluder limit. Rows of J: the plane's p = n / d,
    then gain and offset; weights as ``_accumulate`` gives them.
    """
    A[:, :] = 0.0
    b[:] = 0.0
    row = np.empty(5)
    for m in range(len(r)):
        i = idx[m]
        g = -fb_gain * sampled[m, 1]
        row[0], row[1], row[2] = g * ray[0, i], g * ray[1, i], g * ray[2, i]
        row[3], row[4] = sampled[m, 0], 1.0
        _accumulate(row, r[m], c2, max_r2, A, b)
    _mirror(A)


@kernel(_F8(_M2, _I1, _V1, _F8))
def _disparity_rms(ray, idx, dp, fb):
    """RMS change ``fb dp . r`` of the disparities of the rays ``ray[:, idx]`` (3, N; pixels)."""
    total = 0.0
    for i in idx:
        d = fb * (dp[0] * ray[0, i] + dp[1] * ray[1, i] + dp[2] * ray[2, i])
        total += d * d
    return math.sqrt(total / len(idx)) if len(idx) else math.nan


@kernel(_I8(_V1, _V1, _M2, _M2, _I1, _V1, _F8, _V1, _W1, _W1, _W2, _W2))
def _plane_pixels(us, vs, ray, tmpl, idx, r, limit, p, us_out, vs_out, X, tmpl_out):
    """
    Write the pixels ``idx`` (M,) whose residual r (M,) is below ``limit`` in magnitude.

    Their coordinates from ``us, vs`` (N,), their points ``X = ray / p . ray`` (3, N) on the
    plane p = n / d, and their template rows from ``tmpl`` (N, 3); returns how many.
    """
    count = 0
    for m in range(len(idx)):
        if not abs(r[m]) < limit:
            continue
        i = idx[m]
        depth = 1.0 / (p[0] * ray[0, i] + p[1] * ray[1, i] + p[2] * ray[2, i])
        us_out[count], vs_out[count] = us[i], vs[i]
        for c in range(3):
            X[c, count] = ray[c, i] * depth
            tmpl_out[count, c] = tmpl[i, c]
        count += 1
    return count


@kernel(_F8(_M2, readonly(numba.types.boolean, 1), _F8, readonly(numba.types.int64, 1), _V1))
def _moved_rms(proj, alive, f, free, step):
    """RMS image motion (pixels of the level) of the alive pixels by a step of ``free``."""
    row = np.empty(len(free))
    total, n = 0.0, 0
    for i in range(proj.shape[1]):
        if not alive[i]:
            continue
        for axis in range(2):
            _motion_row(f if axis == 0 else 0.0, f if axis == 1 else 0.0, proj[2, i],
                        proj[3, i], proj[4, i], free, row)
            d = 0.0
            for j in range(len(free)):
                d += step[j] * row[j]
            total += d * d
        n += 1
    return math.sqrt(total / n) if n else math.nan


#: Smallest pivot magnitude of ``_solve_lu`` (that of ``cv2.solve``'s LU decomposition).
_LU_MIN_PIVOT = 100 * np.finfo(np.float64).eps


@kernel()
def _solve_lu(A, b, x):
    """
    Solve ``A x = b`` ((k, k), (k,)) into ``x`` by LU with partial pivoting (as ``cv2.solve``).

    False, ``x`` unset, when a pivot is below ``_LU_MIN_PIVOT`` in magnitude or not a number
    (singular). On a numerically singular system (condition number about 1e16) the verdict can
    differ from ``cv2.solve``'s, whose elimination runs in another order.
    """
    k = A.shape[0]
    M, y = A.copy(), b.copy()
    for c in range(k):
        p = c
        for row in range(c + 1, k):
            if abs(M[row, c]) > abs(M[p, c]):
                p = row
        if not abs(M[p, c]) >= _LU_MIN_PIVOT:
            return False
        for j in range(k):
            M[c, j], M[p, j] = M[p, j], M[c, j]
        y[c], y[p] = y[p], y[c]
        for row in range(c + 1, k):
            g = M[row, c] / M[c, c]
            for j in range(c, k):
                M[row, j] -= g * M[c, j]
            y[row] -= g * y[c]
    for c in range(k - 1, -1, -1):
        s = y[c]
        for j in range(c + 1, k):
            s -= M[c, j] * x[j]
        x[c] = s / M[c, c]
    return True


@kernel()
def _exp_se3_times(delta, T):
    """``T`` (4, 4) <- ``_exp_se3(delta) @ T``, in place (Rodrigues' formula)."""
    wx, wy, wz = delta[3], delta[4], delta[5]
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    E = np.eye(3)
    if not theta < np.finfo(np.float64).eps:  # (NaN propagates, as in cv2.Rodrigues)
        c, s = math.cos(theta), math.sin(theta)
        c1 = 1.0 - c
        rx, ry, rz = wx / theta, wy / theta, wz / theta
        E[0, 0], E[0, 1], E[0, 2] = c + c1 * rx * rx, c1 * rx * ry - s * rz, c1 * rx * rz + s * ry
        E[1, 0], E[1, 1], E[1, 2] = c1 * ry * rx + s * rz, c + c1 * ry * ry, c1 * ry * rz - s * rx
        E[2, 0], E[2, 1], E[2, 2] = c1 * rz * rx - s * ry, c1 * rz * ry + s * rx, c + c1 * rz * rz
    out = np.empty((3, 4))
    for a in range(3):
        for col in range(4):
            out[a, col] = E[a, 0] * T[0, col] + E[a, 1] * T[1, col] + E[a, 2] * T[2, col]
        out[a, 3] += delta[a]
    T[:3, :] = out


@kernel(exact=True)
def _plane_warp(T, normal, d, f, cx, cy, G):
    """
    Write ``G`` (3, 3), pixels of the current level to the previous one's, through the plane.

    ``K (R + t n^T / d)^-1 K^-1`` with ``T`` = (R, t) (previous -> current frame), the plane
    ``n . X = d`` (previous frame, m) and ``K`` of focal length ``f`` and centre (cx, cy).
    Exact arithmetic: a singular matrix (the camera on the plane) has a zero determinant and
    gives zeros, as ``cv2.invert`` does, not the inverse of rounding noise.
    """
    m = np.empty((3, 3))
    for a in range(3):
        for col in range(3):
            m[a, col] = T[a, col] + T[a, 3] * normal[col] / d
    a00, a01, a02 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1], m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2], \
        m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
    a10, a11, a12 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2], m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0], \
        m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
    a20, a21, a22 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0], m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1], \
        m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    det = m[0, 0] * a00 + m[0, 1] * a10 + m[0, 2] * a20
    inv = 1.0 / det if det != 0.0 else 0.0  # (cv2.invert gives zeros then)
    mi = np.empty((3, 3))
    mi[0, 0], mi[0, 1], mi[0, 2] = a00 * inv, a01 * inv, a02 * inv
    mi[1, 0], mi[1, 1], mi[1, 2] = a10 * inv, a11 * inv, a12 * inv
    mi[2, 0], mi[2, 1], mi[2, 2] = a20 * inv, a21 * inv, a22 * inv
    for col in range(3):  # K mi
        G[0, col] = f * mi[0, col] + cx * mi[2, col]
        G[1, col] = f * mi[1, col] + cy * mi[2, col]
        G[2, col] = mi[2, col]
    for a in range(3):  # times K^-1 = [[1/f, 0, -cx/f], [0, 1/f, -cy/f], [0, 0, 1]]
        g0, g1, g2 = G[a, 0], G[a, 1], G[a, 2]
        G[a, 0], G[a, 1], G[a, 2] = g0 / f, g1 / f, g2 - (cx * g0 + cy * g1) / f


@kernel(_F8(_M2, _W2, _F8, _F8, _F8, _F8, _IMG, _F8, _M2, _V1, _V1, _V1, _F8, _F8, _I8,
            readonly(numba.types.int64, 1), _W1, _W2, _B1, _W2, _W1, _W1, _W2, _W1, _W1, _F8))
def _align_level(X, T, f, cx, cy, min_z, img, row0, tmpl, us, vs, normal, d, need, iterations,
                 free, bright, proj, alive, cur_s, r, r_alive, A, b, step, scale):
    """
    ``align``'s Gauss-Newton iterations on one level; return the residual scale, -1 on failure.

    ``X`` (3, N) the road points (m, previous frame), ``T`` (4, 4) previous -> current frame and
    ``bright`` (2,) gain and offset, both updated in place; ``proj``, ``alive``, ``cur_s``,
    ``r``, ``r_alive`` as ``_warp_road`` writes them, ``A``, ``b`` the last normal equations and
    ``step`` (k + 2,) the last step. Fails when fewer than ``need`` pixels stay in view, a
    gradient is not finite or the system is singular. ``scale`` is returned without iterations.
    """
    k = free.shape[0]
    G = np.empty((3, 3))
    delta = np.zeros(6)
    for _ in range(iterations):
        # The exposure may change between the pairs: r = g I_cur + o - I_prev.
        n_ok = _warp_road(X, T, f, cx, cy, min_z, img, row0, tmpl, bright[0], bright[1], proj,
                          alive, cur_s, r, r_alive)
        if n_ok < need:
            return -1.0
        # ESM (Benhimane & Malis): the mean of the current image's gradient and the template's,
        # carried into current pixels by the Jacobian of the inverse plane warp G (current ->
        # previous pixels). The current image alone (forward additive) converged at a third of
        # the rate: near the camera it shows the road larger and sharper than the template.
        _plane_warp(T, normal, d, f, cx, cy, G)
        scale = _scale(r_alive[:n_ok])
        if not _motion_system(cur_s, tmpl, us, vs, proj, r, alive, G, bright[0], f,
                              (CAUCHY_SCALES * scale) ** 2, MAX_DIFFERENCE ** 2, free, A, b):
            return -1.0
        if not _solve_lu(A, b, step):
            return -1.0
        for j in range(k):
            delta[free[j]] = step[j]
        _exp_se3_times(delta, T)
        bright[0] += step[k]
        bright[1] += step[k + 1]
    return scale


def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """Solve the small system ``A x = b`` ((k, k), (k,)): x (k,), or None when A is singular."""
    solved, x = cv2.solve(A, b.reshape(-1, 1), flags=cv2.DECOMP_LU)
    return x.ravel() if solved else None


def _exp_se3(delta: np.ndarray) -> np.ndarray:
    """(4, 4) transform of a left perturbation ``(dv (3), dw (3))``: ``X -> R(dw) X + dv``."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(delta[3:], np.float64).reshape(3, 1))[0]
    T[:3, 3] = delta[:3]
    return T


#: No rig correction (``RoadAligner._stereo``).
_IDENTITY = np.eye(3)


def _into(plane: np.ndarray, out: np.ndarray) -> None:
    """Make sure an OpenCV result asked into ``plane`` (``dst=``) is there (a copy if not)."""
    if not np.shares_memory(plane, out):
        plane[...] = out


def _at_level(H: np.ndarray | None, scale: float) -> np.ndarray | None:
    """Return a homography of input pixels (3, 3) acting on the pixels of a level (or None)."""
    if H is None:
        return None
    S = np.diag([scale, scale, 1.0])
    return S @ np.asarray(H, np.float64) @ np.diag([1.0 / scale, 1.0 / scale, 1.0])


class RoadAligner:
    """
    Dense road alignment of stereo pairs and of consecutive left images.

    Parameters
    ----------
    cfg : RoadConfig
        The ``road`` section of the configuration.
    ransac : RansacConfig
        Its ``ground_*`` bounds decide which planes are admissible.

    """

    def __init__(self, cfg: RoadConfig, ransac: RansacConfig) -> None:
        self.cfg = cfg
        self.ransac = ransac
        #: Per level geometry, the pixels of the level's full image ``_grid`` compares.
        self._grids: dict = {}

    def first_row(self, calib: StereoCalibration, plane: RoadPlane | None) -> int:
        """
        First image row that can see the plane nearer than ``road.max_depth_m``, less a margin.

        0 without a plane. Pass it to :meth:`prepare` to leave the sky and the far scene out.
        """
        if plane is None:
            return 0
        K = calib.K_left
        f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
        n = plane.normal
        u = np.array([0.0, calib.size[0] - 1.0])
        v = cy + f * (plane.d / self.cfg.max_depth_m - n[2] - (u - cx) / f * n[0]) / n[1]
        return int(max(0.0, np.floor(np.min(v)) - FIRST_ROW_MARGIN_PX))

    def prepare(self, left: np.ndarray, right: np.ndarray, first_row: int = 0) -> RoadImages:
        """
        Build ``road.levels`` pyramid levels of a rectified pair ((H, W) uint8 each).

        The finest is the input reduced ``road.first_level`` times (``cv2.pyrDown``). Each
        level is blurred by ``road.blur_px`` (its own pixels) and carries its gradients. Only
        the rows from ``first_row`` on are prepared (rounded down to the coarsest level).
        """
        sigma = self.cfg.blur_px
        ksize = 2 * math.ceil(BLUR_SIGMAS * sigma) + 1
        levels = []
        first = self.cfg.first_level
        q = 2 ** (self.cfg.levels - 1 + first)
        r0 = (min(max(int(first_row), 0), left.shape[0] - 16 * q) // q) * q
        r0 = max(r0, 0)
        lo, ro = left[r0:], right[r0:]
        for _ in range(first):
            lo, ro = cv2.pyrDown(lo), cv2.pyrDown(ro)
        lo, ro = lo.astype(np.float32), ro.astype(np.float32)
        for k in range(first, first + self.cfg.levels):
            if k > first:
                lo, ro = cv2.pyrDown(lo), cv2.pyrDown(ro)
            # Written in place into the planes the kernels sample (no interleaving copy).
            lp, rp = np.empty((3, *lo.shape), np.float32), np.empty((2, *ro.shape), np.float32)
            for src, planes in ((lo, lp), (ro, rp)):
                if sigma > 0:
                    _into(planes[0], cv2.GaussianBlur(src, (ksize, ksize), sigma,
                                                      dst=planes[0]))
                else:
                    planes[0] = src
                for c in range(1, len(planes)):
                    _into(planes[c], cv2.Sobel(planes[0], cv2.CV_32F, int(c == 1), int(c == 2),
                                               dst=planes[c], ksize=3, scale=0.125))
            levels.append(RoadLevel(lp[0], lp, rp, 0.5 ** k, r0 // 2 ** k))
        return RoadImages(levels)

    def _grid(self, level: RoadLevel, calib: StereoCalibration
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """
        Return the pixels of a level compared when they see the road, and their rays.

        Every ``road.pixel_step``-th pixel of every ``road.pixel_step``-th row of the level's
        full image, counted from pixel (1, 1), inside the level's arrays with one pixel to spare:
        u, v (N,) (pixels of the level) and the rays' x / z and y / z (N,). The full grid of a
        level is computed once per calibration and image size (kept in ``_grids``).
        """
        f, cx, cy = level.intrinsics(calib)
        step = self.cfg.pixel_step
        h, w = level.left.shape
        key = (f, cx, cy, step, w, level.row0 + h)
        grid = self._grids.get(key)
        if grid is None:
            if len(self._grids) > 8:  # the calibration or the image size changed
                self._grids.clear()
            vs, us = np.mgrid[1:level.row0 + h - 1:step, 1:w - 1:step]
            us, vs = us.ravel().astype(np.float64), vs.ravel().astype(np.float64)
            grid = self._grids[key] = (us, vs, (us - cx) / f, (vs - cy) / f)
        row_len = len(range(1, w - 1, step))
        first = -(-level.row0 // step)  # first lattice row > row0: 1 + step * first
        last = (level.row0 + h - 3) // step  # last one < row0 + h - 1
        return tuple(a[first * row_len:(last + 1) * row_len] for a in grid)

    def _road_pixels(self, level: RoadLevel, calib: StereoCalibration, plane: RoadPlane
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Return the grid pixels of a level's left image that see the road.

        The road is the plane between the depth bounds and within ``road.max_lateral_m`` of
        the optical axis.

        Returns their coordinates u, v (N,) (pixels of the level) and rays (3, N) (z = 1),
        one coordinate per row.
        """
        us, vs, xr, yr = self._grid(level, calib)
        n = len(us)
        us_on, vs_on, ray = np.empty(n), np.empty(n), np.empty((3, n))
        count = _road_rays(us, vs, xr, yr, np.asarray(plane.normal, np.float64),
                           float(plane.d), self.cfg.min_depth_m, self.cfg.max_depth_m,
                           self.cfg.max_lateral_m, us_on, vs_on, ray)
        return us_on[:count], vs_on[:count], np.ascontiguousarray(ray[:, :count])

    def refine_plane(self, images: RoadImages, calib: StereoCalibration, plane: RoadPlane,
                     right_map: np.ndarray | None = None) -> RoadPlane | None:
        """
        Refine the road plane of a rectified pair by aligning its left and right images.

        The disparity of the left pixel on ray ``r`` (z = 1) is ``f b p . r`` with
        ``p = n / d``: Gauss-Newton on p, coarse level first. The plane's distance and tilt set
        the scale of the road motion (``align``), so the right image is sampled where the real
        right camera sees the match: ``right_map`` is the stereo rig's error as the online
        rig refinement estimates it (``RigCalibrator.homography``). Without it, a rig whose
        disparities are off by a pixel at the image borders, where the near road is, puts the
        plane a few percent too far away and the road motion that much too fast.

        Parameters
        ----------
        images : RoadImages
            The pair (``prepare``).
        calib : StereoCalibration
            Rectified calibration (``K_left``, ``baseline_m``).
        plane : RoadPlane
            Starting plane (left camera frame), within a few pixels of disparity.
        right_map : np.ndarray or None
            (3, 3) homography from the calibrated right camera's pixels to the measured ones
            (input pixels); None: the calibration is exact.

        Returns
        -------
        RoadPlane, or None when too few road pixels are seen, the last step still moved the
        disparities by ``PLANE_CONVERGED_PX`` or more (RMS), or the result is not an admissible
        road.

        """
        p = plane.normal / plane.d
        gain, offset = 1.0, 0.0
        moved = np.inf
        grids = []
        for level in reversed(images.levels):
            fb = level.intrinsics(calib)[0] * calib.baseline_m
            H = _at_level(right_map, level.scale)
            norm = float(np.linalg.norm(p))
            us, vs, ray = self._road_pixels(level, calib, RoadPlane(p / norm, 1.0 / norm))
            if len(us) < self.cfg.min_pixels * level.scale ** 2:
                return None
            tmpl = np.empty((len(us), 3))  # the left image's value, d/du, d/dv
            _sample(level.left_grad, us, vs, float(level.row0), tmpl)
            grids.insert(0, (level, fb, H, us, vs, ray, tmpl))
            for _ in range(self.cfg.stereo_iterations):
                r, idx, sampled = self._stereo(level, fb, H, us, vs, ray, tmpl, p, gain, offset)
                if len(r) < self.cfg.min_pixels * level.scale ** 2:
                    return None
                A, b = np.empty((5, 5)), np.empty(5)
                _plane_system(sampled, ray, idx, r, fb * float(gain),
                              (CAUCHY_SCALES * _scale(r)) ** 2, MAX_DIFFERENCE ** 2, A, b)
                step = _solve(A, b)
                if step is None:
                    return None
                p = p + step[:3]
                gain, offset = gain + step[3], offset + step[4]
                moved = _disparity_rms(ray, idx, step[:3], fb) / level.scale
        norm = float(np.linalg.norm(p))
        if not (np.isfinite(norm) and norm > 0 and moved < PLANE_CONVERGED_PX):
            return None
        out = RoadPlane(p / norm, 1.0 / norm)
        if not out.admissible(self.ransac):
            return None
        # Per level, the pixels whose left and right images agree with the plane (residual
        # within STEREO_INLIER_SCALES robust scales): a vehicle standing on the road does not.
        pixels = []
        for level, fb, H, us, vs, ray, tmpl in grids:
            r, idx, _ = self._stereo(level, fb, H, us, vs, ray, tmpl, p, gain, offset)
            n = len(r)
            us_in, vs_in, X, tmpl_in = np.empty(n), np.empty(n), np.empty((3, n)), np.empty((n, 3))
            m = _plane_pixels(us, vs, ray, tmpl, idx, r, STEREO_INLIER_SCALES * _scale(r), p,
                              us_in, vs_in, X, tmpl_in)
            pixels.append((us_in[:m], vs_in[:m], np.ascontiguousarray(X[:, :m]), tmpl_in[:m]))
        return RoadPlane(out.normal, out.d, tuple(pixels))

    @staticmethod
    def _stereo(level: RoadLevel, fb: float, H: np.ndarray | None, us: np.ndarray,
                vs: np.ndarray, ray: np.ndarray, tmpl: np.ndarray, p: np.ndarray, gain: float,
                offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Stereo residuals ``g I_R + o - I_L`` (grey levels) of left pixels (us, vs) on plane p.

        The disparity of the pixel on ray r (z = 1) is ``fb p . r``; the right camera's gain g
        and offset o may differ from the left one's. ``H`` (3, 3; pixels of the level) moves
        the calibrated right pixel to where the right image shows it (None: identity). ``ray``
        is (3, N), ``tmpl`` (N, 3) the left samples. Returns the residuals (M,) of the pixels
        whose match lies inside the right image, their indices (M,) and the right image's
        samples (value, d/du) (M, 2) there. The Gauss-Newton step takes d/du as the
        residual's derivative by the calibrated column: H differs from the identity by a small
        rotation and offsets, which change that derivative by parts in a thousand.
        """
        n = len(us)
        r, idx, sampled = np.empty(n), np.empty(n, np.int64), np.empty((n, 2))
        m = _stereo_residuals(level.right_grad, float(level.row0), _IDENTITY if H is None else H,
                              us, vs, ray, tmpl, np.asarray(p, np.float64), fb, float(gain),
                              float(offset), r, sampled, idx)
        return r[:m], idx[:m], sampled[:m]

    def align(self, prev: RoadImages, cur: RoadImages, calib: StereoCalibration,
              plane: RoadPlane, T_prev_cur: np.ndarray, dt: float) -> RoadMotion | None:
        """
        Refine the motion between two left images by aligning the road.

        Unless ``road.motion`` is ``full`` only the forward and vertical translation and the
        pitch are refined (the others stay at the starting motion): on the rendered highway the
        lateral translation and the yaw, which the road alone hardly tells apart, drifted
        together and dragged the forward translation along. With ``forward`` (the default) only
        the forward speed is reported as measured: the road's pitch and vertical speed made the
        rendered city scenes worse than the features' (r_rel 0.08 -> 0.11 deg/100 m).

        Parameters
        ----------
        prev, cur : RoadImages
            The previous and the current pair (only their left images are used).
        calib : StereoCalibration
            Rectified calibration (``K_left``).
        plane : RoadPlane
            The road in the previous left camera frame.
        T_prev_cur : np.ndarray
            (4, 4) starting motion (the estimator's), within a few pixels on the road.
        dt : float
            Time between the pairs (s), > 0.

        Returns
        -------
        RoadMotion, or None when too few road pixels stay in view, the solve is singular or
        the last step still moved the road pixels by ``CONVERGED_PX`` or more (RMS).

        """
        free, measured = MOTION_COMPONENTS[self.cfg.motion]
        k = len(free)
        free_idx = np.asarray(free, np.int64)
        # Maps previous-frame points into the current frame.
        T_cp = np.ascontiguousarray(np.linalg.inv(np.asarray(T_prev_cur, np.float64)))
        bright = np.array([1.0, 0.0])  # gain, offset
        normal, scale = np.ascontiguousarray(plane.normal, np.float64), 1.0
        for index in reversed(range(len(prev.levels))):
            lp, lc = prev.levels[index], cur.levels[index]
            f, cx, cy = lp.intrinsics(calib)
            if plane.pixels is not None:
                us, vs, X, tmpl = plane.pixels[index]
            else:
                us, vs, ray = self._road_pixels(lp, calib, plane)
                X = ray * (plane.d / (plane.normal @ ray))
                tmpl = None
            need = self.cfg.min_pixels * lp.scale ** 2
            if len(us) < need or not dt > 0:
                return None
            if tmpl is None:
                tmpl = np.empty((len(us), 3))  # value, d/du, d/dv
                _sample(lp.left_grad, us, vs, float(lp.row0), tmpl)
            iterations = self.cfg.motion_iterations if index == 0 else self.cfg.coarse_iterations
            X = np.ascontiguousarray(X, np.float64)
            # A pixel that leaves the view is dropped for the rest of the level.
            n = len(us)
            alive, proj, r, r_alive = np.ones(n, bool), np.empty((5, n)), np.empty(n), \
                np.empty(n)
            cur_s = np.empty((n, 3))
            A, b, step = (np.full(shape, np.nan) for shape in ((k + 2, k + 2), k + 2, k + 2))
            scale = _align_level(X, T_cp, f, cx, cy, self.cfg.min_depth_m / 2, lc.left_grad,
                                 float(lc.row0), tmpl, np.ascontiguousarray(us, np.float64),
                                 np.ascontiguousarray(vs, np.float64), normal, float(plane.d),
                                 float(need), iterations, free_idx, bright, proj, alive, cur_s,
                                 r, r_alive, A, b, step, scale)
            if not scale > 0.0:
                return None
        n_ok = int(np.count_nonzero(alive))
        # RMS image motion of the road pixels in the last step (input pixels).
        moved = _moved_rms(proj, alive, f, free_idx, step[:k]) / lp.scale
        if not moved < CONVERGED_PX or not np.all(np.isfinite(T_cp)):
            return None
        try:
            # The brightness parameters are marginalised: the motion block of the inverse.
            cov_free = np.linalg.inv(A)[:k, :k] * scale ** 2 * self.cfg.covariance_inflation
        except np.linalg.LinAlgError:
            return None
        T = np.linalg.inv(T_cp)
        y = velocity_from_transform(T, dt)
        Jy = np.empty((6, k))
        for j, i in enumerate(free):
            e = np.zeros(6)
            e[i] = JACOBIAN_STEP
            Jy[:, j] = (velocity_from_transform(np.linalg.inv(_exp_se3(e) @ T_cp), dt) - y) \
                / JACOBIAN_STEP
        # Only the rows and columns of ``measured`` are meant to be fused.
        cov = Jy @ cov_free @ Jy.T
        return RoadMotion(T, y, 0.5 * (cov + cov.T), measured, n_ok, scale)
