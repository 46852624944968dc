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
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
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
               plane: tuple[np.ndarray, float], dt: float, speeds: np.ndarray) -> RoadSpeed:
    """
    Forward speed that best maps the road of the previous left image onto the current one.

    Pixels of the previous left image whose ray meets the ground plane between
    ``ROAD_DEPTH_RANGE_M`` are moved to the current image by each hypothesis (a translation
    of ``speed * dt`` along the optical axis, no rotation), and the mean truncated grey-level
    difference is scored (both images blurred). Not in the papers: without a velocity, KLT
    starts every feature at its previous position; on a fast road the near road moves
    farther than KLT can follow (its low-contrast texture worse than most), while vehicles
    keeping pace with the camera track well. On rendered highway seed 35, only 5 of 24 road
    features of the first pair were right and the first estimate took the vehicles' 5 m/s
    for the true 27 m/s. Aligning the whole road at once finds the speed to within
    0.6 m/s on the rendered highways (seeds 0, 3, 9, 15, 35 at frames 0 and 100), and the
    speed then predicts where the features went. The sign convention: a positive speed moves
    the camera forward (+z).

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
    X = ray[on_road] * depth[on_road, None]
    blur_prev = cv2.GaussianBlur(prev_left, (0, 0), ROAD_BLUR_PX).astype(np.float32)
    blur_cur = cv2.GaussianBlur(cur_left, (0, 0), ROAD_BLUR_PX).astype(np.float32)
    ref = blur_prev[ys[on_road].astype(int), xs[on_road].astype(int)]
    score = np.full(len(speeds), np.inf)
    for k, speed in enumerate(speeds):
        z = X[:, 2] - speed * dt
        with np.errstate(divide='ignore', invalid='ignore'):
            u = (f * X[:, 0] / z + cx).astype(np.float32)
            v = (f * X[:, 1] / z + cy).astype(np.float32)
        seen = (z > ROAD_DEPTH_RANGE_M[0] / 2) & (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
        if np.count_nonzero(seen) < ROAD_MIN_PIXELS:
            continue
        moved = cv2.remap(blur_cur, u[seen][None], v[seen][None], cv2.INTER_LINEAR)[0]
        score[k] = float(np.mean(np.minimum(np.abs(moved - ref[seen]), ROAD_MAX_DIFFERENCE)))
    at_rest = int(np.argmin(np.abs(speeds)))
    best = int(np.argmin(score))
    if not np.isfinite(score[at_rest]):
        return RoadSpeed(math.nan, math.nan)
    if score[best] >= score[at_rest]:  # includes identical images (all differences 0)
        return RoadSpeed(float(speeds[at_rest]), 1.0)
    return RoadSpeed(float(speeds[best]), float(score[best] / score[at_rest]))
