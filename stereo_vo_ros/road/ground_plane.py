"""
Ground plane of the previous stereo pair, for RANSAC's hypothesis choice (not in the papers).

The road does not move. A vehicle ahead that keeps the camera's speed does: to a frame-pair
estimator its features look static, and when it fills much of the view (a bus or a truck
ahead on a highway) the hypothesis "the camera stands still" can gather more RANSAC inliers
than the true motion, which only the road and the far background support. Counting the
inliers on the ground plane ``ransac.ground_weight`` times breaks that tie in favour of the
road (rendered highway, 8 seeds: see the README's departures).

The same plane gives the speed to start tracking with when the velocity is unknown (at the
start, after a loss): ``road_speed`` aligns the road between two left images (see there).

The plane is fitted to the triangulated points of the previous pair with a small RANSAC over
planes (3-point samples), keeping only planes that could be a road seen by a forward-looking
camera: normal within ``ransac.ground_max_tilt_deg`` of the camera's y axis (down), at most
``ransac.ground_max_height_m`` below the camera. When no such plane has enough support, no
point is on the ground and the weights are all 1.

Frames: points in the previous left camera's optical frame (x right, y down, z forward),
metres.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import cv2
import numpy as np

from ..config import RansacConfig
from ..estimation.camera import StereoCalibration

#: Points farther than this are left out of the fit (m): their depth is too uncertain.
MAX_RANGE_M = 60.0
#: The plane lies at least this far below the optical centre (m).
MIN_HEIGHT_M = 0.1
#: Plane hypotheses (3-point samples) per frame.
PLANE_SAMPLES = 100
#: A plane needs at least this many points within the tolerance to count.
MIN_SUPPORT = 6
#: Triangulation: smallest determinant of the normal matrix relative to its scale.
MIN_RELATIVE_DET = 1e-12
#: Road alignment: the road between these depths is compared (m).
ROAD_DEPTH_RANGE_M = (2.0, 40.0)
#: Road alignment: every n-th pixel in both directions is compared.
ROAD_PIXEL_STEP = 4
#: Road alignment: Gaussian blur of both images (pixels), to widen the basin of the search.
ROAD_BLUR_PX = 1.5
#: Road alignment: grey-level differences are truncated here (occluding vehicles, glare).
ROAD_MAX_DIFFERENCE = 30.0
#: Road alignment: fewest road pixels that must be compared for a hypothesis to count.
ROAD_MIN_PIXELS = 500
#: Road speed search: the exposure change is measured on every n-th pixel of both images.
BRIGHTNESS_STEP = 2
#: ``cv2.remap`` maps are split into rows of this many points (it takes at most 32767 columns).
REMAP_COLUMNS = 1024
#: Road alignment: a pixel sees the road when its left and right grey levels, matched at the
#: plane's disparity, differ by less than this many robust scales (after a gain and offset).
ROAD_STEREO_SCALES = 3.0
#: Road alignment: smallest robust scale of those stereo differences (grey levels).
ROAD_STEREO_MIN_SCALE = 1.0


def sample_bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` (H, W[, C]) at pixels (u, v) (N,): (N,) or (N, C) float."""
    n = len(u)
    m = -(-n // REMAP_COLUMNS) * REMAP_COLUMNS
    uu = np.zeros(m, np.float32)
    vv = np.zeros(m, np.float32)
    uu[:n], vv[:n] = u, v
    out = cv2.remap(img, uu.reshape(-1, REMAP_COLUMNS), vv.reshape(-1, REMAP_COLUMNS),
                    cv2.INTER_LINEAR)
    return out.reshape((m,) + img.shape[2:])[:n]


def triangulate(calib: StereoCalibration, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """
    3-D points of stereo matches in the left camera's optical frame (metres).

    Parameters
    ----------
    calib : StereoCalibration
        Calibration of the pair.
    left, right : np.ndarray
        (N, 2) ideal (undistorted) pixels in the left and right images.

    Returns
    -------
    (N, 3) float64; NaN where the point is not in front of the camera, the rays are parallel
    or the input is not finite.

    """
    left = np.asarray(left, np.float64).reshape(-1, 2)
    right = np.asarray(right, np.float64).reshape(-1, 2)
    # Linear triangulation (DLT rows x P3 - P1, y P3 - P2 of both cameras), solved for the
    # inhomogeneous point by batched normal equations: a sixth of cv2.triangulatePoints' time.
    # Nearly parallel rays make the normal matrix singular: its determinant relative to the
    # cube of its mean eigenvalue is about (baseline / depth)^2, 1e-12 at about 500 km for a
    # KITTI rig; below that (zero disparity, parallel rays) there is no point.
    rows = []
    for P, x in ((calib.projection_left(), left), (calib.projection_right(), right)):
        rows.append(x[:, 0, None] * P[2] - P[0])
        rows.append(x[:, 1, None] * P[2] - P[1])
    A = np.stack(rows, axis=1)  # (N, 4, 4)
    M, rhs = A[:, :, :3], -A[:, :, 3]
    pts = np.full((len(left), 3), np.nan)
    with np.errstate(all='ignore'):
        AtA = np.einsum('nki,nkj->nij', M, M)
        Atb = np.einsum('nki,nk->ni', M, rhs)
        ok = np.linalg.det(AtA) > MIN_RELATIVE_DET * (np.trace(AtA, axis1=1, axis2=2) / 3) ** 3
        if ok.any():
            pts[ok] = np.linalg.solve(AtA[ok], Atb[ok][:, :, None])[:, :, 0]
    bad = ~np.all(np.isfinite(pts), axis=1) | ~(pts[:, 2] > 0)
    pts[bad] = np.nan
    return pts


def fit_ground_plane(points: np.ndarray, cfg: RansacConfig, rng: np.random.Generator
                     ) -> tuple[np.ndarray, float] | None:
    """
    Fit the road plane ``n . X = d`` to 3-D points by RANSAC.

    Parameters
    ----------
    points : np.ndarray
        (N, 3) points in the camera optical frame (m); NaN rows are ignored.
    cfg : RansacConfig
        ``ground_tolerance_m``, ``ground_max_tilt_deg`` and ``ground_max_height_m``.
    rng : np.random.Generator
        Draws the 3-point samples.

    Returns
    -------
    (normal (3,) unit with a positive y component, d in metres: the camera's height above
    the plane), or None when no admissible plane has ``MIN_SUPPORT`` points.

    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    with np.errstate(invalid='ignore'):
        use = np.flatnonzero(np.all(np.isfinite(pts), axis=1) & (pts[:, 1] > MIN_HEIGHT_M)
                             & (pts[:, 2] < MAX_RANGE_M))
    if use.size < MIN_SUPPORT:
        return None
    cand = pts[use]
    tri = cand[rng.integers(0, len(cand), (PLANE_SAMPLES, 3))]  # (H, 3, 3)
    a, b = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    # The cross product and its length written out (np.cross's and np.linalg.norm's
    # wrappers cost more than their arithmetic on 100 rows; the same operations).
    normal = np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
                       a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                       a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)
    length = np.sqrt(np.add.reduce(normal * normal, axis=1))
    ok = length > 1e-9
    normal = normal / np.where(ok, length, 1.0)[:, None]
    normal *= np.where(normal[:, 1] < 0, -1.0, 1.0)[:, None]
    d = np.einsum('hk,hk->h', normal, tri[:, 0])
    ok &= (normal[:, 1] >= np.cos(np.radians(cfg.ground_max_tilt_deg)))
    ok &= (d >= MIN_HEIGHT_M) & (d <= cfg.ground_max_height_m)
    if not ok.any():
        return None
    normal, d = normal[ok], d[ok]
    support = (np.abs(cand @ normal.T - d) < cfg.ground_tolerance_m).sum(axis=0)
    best = int(np.argmax(support))
    if support[best] < MIN_SUPPORT:
        return None
    return normal[best], float(d[best])


def ground_mask(points: np.ndarray, cfg: RansacConfig, rng: np.random.Generator) -> np.ndarray:
    """
    Which points lie on the ground plane (within ``cfg.ground_tolerance_m``).

    Parameters
    ----------
    points : np.ndarray
        (N, 3) triangulated stereo matches in the left camera's optical frame (m), NaN rows
        allowed: ``triangulate``, or the estimator's ``TransferModel.points``.
    cfg : RansacConfig
        Ground-plane settings.
    rng : np.random.Generator
        For the plane RANSAC.

    Returns
    -------
    (N,) bool; all False when no ground plane was found.

    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    plane = fit_ground_plane(pts, cfg, rng)
    if plane is None:
        return np.zeros(len(pts), bool)
    normal, d = plane
    with np.errstate(invalid='ignore'):
        return (np.abs(pts @ normal - d) < cfg.ground_tolerance_m) & (pts[:, 2] < MAX_RANGE_M)


@dataclass
class RoadSpeed:
    """
    Result of ``road_speed``.

    Attributes
    ----------
    speed : float
        Forward speed along the previous left camera's optical axis (m/s) whose road
        alignment fits best; NaN when no hypothesis could be scored.
    contrast : float
        Mean truncated grey-level difference at that speed over the one at rest (0..1, lower
        is a clearer minimum); NaN with ``speed``.

    """

    speed: float
    contrast: float


def road_speed(prev_left: np.ndarray, cur_left: np.ndarray, calib: StereoCalibration,
               plane: tuple[np.ndarray, float], dt: float, speeds: np.ndarray,
               prev_right: np.ndarray | None = None) -> RoadSpeed:
    """
    Forward speed that best maps the road of the previous left image onto the current one.

    Pixels of the previous left image whose ray meets the ground plane between
    ``ROAD_DEPTH_RANGE_M`` are moved to the current image by each hypothesis (a translation
    of ``speed * dt`` along the optical axis, no rotation), and the mean truncated grey-level
    difference is scored (both images blurred; the current image is first brought to the
    previous one's brightness, ``brightness_change``). Not in the papers: without a
    velocity, KLT starts every feature at its previous position; on a fast road the near road
    moves farther than KLT can follow (its low-contrast texture worse than most), while
    vehicles keeping pace with the camera track well. On rendered highway seed 35, only 5 of
    24 road features of the first pair were right and the first estimate took the vehicles'
    5 m/s for the true 27 m/s. Aligning the whole road at once finds the speed to within
    0.6 m/s on the rendered highways seeds 0, 3, 9, 15, 35 at frames 0 and 100; at the first
    pair of 150-frame scenes (the plane of that pair's features, ``prev_right`` given), seeds
    0-7, -1.65 to +0.53 m/s (mean -0.46, about -2 %), and photometric highways 50-57, -0.80
    to +0.28 m/s but for seed 57, whose search has no clear minimum (contrast 0.99: not
    taken). The speed then predicts where the features went. The sign convention: a positive
    speed moves the camera forward (+z).

    With ``prev_right``, only pixels that see the road are compared: those whose left and
    right grey levels agree at the plane's disparity (``road_pixels_seen``). A vehicle ahead
    covers part of the road region; its pixels match best at rest, since it keeps pace, and
    drowned the road's minimum (rendered highway seed 23: contrast 0.95 at the true 24 m/s,
    0.54 with them left out).

    Parameters
    ----------
    prev_left, cur_left : np.ndarray
        (H, W) uint8 rectified left images at t-1 and t.
    calib : StereoCalibration
        Rectified calibration (pinhole ``K_left``).
    plane : tuple
        ``(normal (3,), d)`` of ``fit_ground_plane`` in the previous left camera frame.
    dt : float
        Time between the images (s).
    speeds : np.ndarray
        (S,) forward speeds to try (m/s); must include 0.
    prev_right : np.ndarray, optional
        (H, W) uint8 rectified right image at t-1.

    Returns
    -------
    RoadSpeed

    """
    normal, d = np.asarray(plane[0], np.float64), float(plane[1])
    K = calib.K_left
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    h, w = prev_left.shape
    ys, xs = np.mgrid[0:h:ROAD_PIXEL_STEP, 0:w:ROAD_PIXEL_STEP]
    xs, ys = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    ray = np.stack([(xs - cx) / f, (ys - cy) / f, np.ones_like(xs)], axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        depth = d / (ray @ normal)
    on_road = (depth > ROAD_DEPTH_RANGE_M[0]) & (depth < ROAD_DEPTH_RANGE_M[1])
    speeds = np.asarray(speeds, np.float64)
    if np.count_nonzero(on_road) < ROAD_MIN_PIXELS or not dt > 0:
        return RoadSpeed(math.nan, math.nan)
    blur_prev = cv2.GaussianBlur(prev_left, (0, 0), ROAD_BLUR_PX).astype(np.float32)
    blur_cur = cv2.GaussianBlur(cur_left, (0, 0), ROAD_BLUR_PX).astype(np.float32)
    if prev_right is not None:
        blur_right = cv2.GaussianBlur(prev_right, (0, 0), ROAD_BLUR_PX).astype(np.float32)
        idx = np.flatnonzero(on_road)
        seen = road_pixels_seen(blur_prev, blur_right, xs[idx], ys[idx],
                                f * calib.baseline_m / depth[idx])
        on_road = np.zeros_like(on_road)
        on_road[idx[seen]] = True
        if np.count_nonzero(on_road) < ROAD_MIN_PIXELS:
            return RoadSpeed(math.nan, math.nan)
    X = ray[on_road] * depth[on_road, None]
    ref = blur_prev[ys[on_road].astype(int), xs[on_road].astype(int)]
    gain, offset = brightness_change(blur_cur, blur_prev)
    blur_cur = blur_cur * np.float32(gain) + np.float32(offset)
    score = np.full(len(speeds), np.inf)
    for k, speed in enumerate(speeds):
        z = X[:, 2] - speed * dt
        with np.errstate(divide='ignore', invalid='ignore'):
            u = (f * X[:, 0] / z + cx).astype(np.float32)
            v = (f * X[:, 1] / z + cy).astype(np.float32)
        seen = (z > ROAD_DEPTH_RANGE_M[0] / 2) & (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
        if np.count_nonzero(seen) < ROAD_MIN_PIXELS:
            continue
        moved = sample_bilinear(blur_cur, u[seen], v[seen])
        score[k] = float(np.mean(np.minimum(np.abs(moved - ref[seen]), ROAD_MAX_DIFFERENCE)))
    at_rest = int(np.argmin(np.abs(speeds)))
    best = int(np.argmin(score))
    if not np.isfinite(score[at_rest]):
        return RoadSpeed(math.nan, math.nan)
    if score[best] >= score[at_rest]:  # includes identical images (all differences 0)
        return RoadSpeed(float(speeds[at_rest]), 1.0)
    return RoadSpeed(float(speeds[best]), float(score[best] / score[at_rest]))


def brightness_change(cur: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """
    Return the gain and offset that bring image ``cur`` to the brightness of image ``ref``.

    ``ref ~ gain * cur + offset``, from the mean and standard deviation of both whole images
    ((H, W), every ``BRIGHTNESS_STEP``-th pixel). An automatic exposure changes a camera's
    gain and offset from frame to frame (by a third and by several grey levels on the
    photometric presets); unmatched, that change outweighs the road's texture in
    ``road_speed``'s differences and puts its minimum anywhere (a rendered highway whose
    exposure jumped between the first two frames scored best at -10 m/s, with a contrast of
    0.95). The exposure acts on the whole image, whose statistics a tenth of a second of
    motion hardly changes; moments of the road region alone, or of the samples of each speed
    tried, also took in the lane markings and vehicles that move through it. The map is the
    same for every speed, so it cannot favour one. (1, 0) when ``cur`` has no spread.
    """
    a = np.asarray(cur[::BRIGHTNESS_STEP, ::BRIGHTNESS_STEP], np.float64)
    b = np.asarray(ref[::BRIGHTNESS_STEP, ::BRIGHTNESS_STEP], np.float64)
    spread = float(np.std(a))
    if not spread > 0:
        return 1.0, 0.0
    gain = float(np.std(b)) / spread
    return gain, float(np.mean(b)) - gain * float(np.mean(a))


def road_pixels_seen(left: np.ndarray, right: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                     disparity: np.ndarray) -> np.ndarray:
    """
    Return which road pixels the stereo pair shows as road: (N,) bool.

    Each left pixel (xs, ys) is compared with the right image at its disparity on the ground
    plane (pixels; rectified pair, so the same row). Where something stands in front of the
    road (a vehicle, a pedestrian, a wall) the pixel shows a nearer surface, whose right image
    lies farther left, and the two grey levels differ where it has texture. The right camera's
    gain and offset are fitted first (least squares); kept are the pixels within
    ``ROAD_STEREO_SCALES`` robust scales of the differences (1.4826 times their median
    absolute value, at least ``ROAD_STEREO_MIN_SCALE``). A match outside the right image is
    not kept. Textureless pixels agree at any disparity and are kept: they weigh alike in every
    speed's score.

    Parameters
    ----------
    left, right : np.ndarray
        (H, W) float32 rectified images (blurred alike).
    xs, ys : np.ndarray
        (N,) integer-valued left pixel coordinates (x right, y down).
    disparity : np.ndarray
        (N,) disparity of the plane at those pixels (pixels, positive).

    """
    ur = np.asarray(xs - disparity, np.float32)
    inside = ur >= 0
    seen = np.zeros(len(xs), bool)
    if np.count_nonzero(inside) < 2:
        return seen
    idx = np.flatnonzero(inside)
    grey_r = sample_bilinear(right, ur[idx], ys[idx]).astype(np.float64)
    grey_l = left[ys[idx].astype(int), xs[idx].astype(int)].astype(np.float64)
    design = np.stack([grey_r, np.ones_like(grey_r)], axis=1)
    gain_offset = np.linalg.lstsq(design, grey_l, rcond=None)[0]
    diff = np.abs(design @ gain_offset - grey_l)
    scale = max(1.4826 * float(np.median(diff)), ROAD_STEREO_MIN_SCALE)
    seen[idx[diff < ROAD_STEREO_SCALES * scale]] = True
    return seen
