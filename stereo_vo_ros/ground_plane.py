"""
Ground plane of the previous stereo pair, for RANSAC's hypothesis choice (not in the papers).

The road does not move. A vehicle ahead that keeps the camera's speed does: to a frame-pair
estimator its features look static, and when it fills much of the view (a bus or a truck
ahead on a highway) the hypothesis "the camera stands still" can gather more RANSAC inliers
than the true motion, which only the road and the far background support. Counting the
inliers on the ground plane ``ransac.ground_weight`` times breaks that tie in favour of the
road (rendered highway, 8 seeds: see the README's departures).

The plane is fitted to the triangulated points of the previous pair with a small RANSAC over
planes (3-point samples), keeping only planes that could be a road seen by a forward-looking
camera: normal within ``ransac.ground_max_tilt_deg`` of the camera's y axis (down), at most
``ransac.ground_max_height_m`` below the camera. When no such plane has enough support, no
point is on the ground and the weights are all 1.

Frames: points in the previous left camera's optical frame (x right, y down, z forward),
metres.
"""

from __future__ import annotations

import numpy as np

from .camera import StereoCalibration
from .config import RansacConfig

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


def ground_mask(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                cfg: RansacConfig, rng: np.random.Generator) -> np.ndarray:
    """
    Which stereo matches lie on the ground plane (within ``cfg.ground_tolerance_m``).

    Parameters
    ----------
    calib : StereoCalibration
        Calibration of the pair.
    left, right : np.ndarray
        (N, 2) ideal pixels of the matches.
    cfg : RansacConfig
        Ground-plane settings.
    rng : np.random.Generator
        For the plane RANSAC.

    Returns
    -------
    (N,) bool; all False when no ground plane was found.

    """
    pts = triangulate(calib, left, right)
    plane = fit_ground_plane(pts, cfg, rng)
    if plane is None:
        return np.zeros(len(pts), bool)
    normal, d = plane
    with np.errstate(invalid='ignore'):
        return (np.abs(pts @ normal - d) < cfg.ground_tolerance_m) & (pts[:, 2] < MAX_RANGE_M)
