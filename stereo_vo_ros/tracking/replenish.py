"""
Replenishment: new corners where features are missing, matched into the right image.

Step 4 of the tracker (``tracker``), written as a function of its inputs alone so that it can
run anywhere: inline, on a thread, or in a worker process (``parallel.Workers``) while the
caller estimates the motion. ``ReplenishJob`` is what it reads besides the images (picklable:
settings, calibration, the tracked features, the buckets to search and the expected flow of
new corners); ``NewCorners`` what it returns. The tracker keeps every piece of state (feature
ids, barren buckets) and applies the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Callable

import numpy as np

from .affine_klt import refine_matches
from .detection import bucket_ids, detect_corners, squared_distances
from .klt_checks import (disparity_constraint, disparity_in_range, eigen_ratio, lk_pass,
                         REVERSE_PYRAMID_LEVELS, round_trip_error)
from .lucas_kanade import ImagePyramid
from ..config import BucketingConfig, TrackerConfig
from ..estimation.camera import StereoCalibration

#: A new corner closer than this to a tracked feature starts its stereo search at that
#: feature's disparity with ``stereo_pyramid_levels`` (pixels).
NEIGHBOUR_RADIUS_PX = 80.0


class ExpectedFlow:
    """
    Expected displacement (pixels) of new corners into the next pair (picklable).

    The motion prior of this pair applied again from here (constant velocity) to each corner at
    one disparity (the median of the tracked features): the direction of the flow is what the
    detection check needs, and it hardly depends on the depth.

    Parameters
    ----------
    prior : callable
        Motion prior ``(prev_left_ideal, prev_right_ideal) -> (cur_left_pred,
        cur_right_pred)``, (N, 2) float64 ideal pixels.
    calib : StereoCalibration
        Calibration of the pair the corners are detected in.
    disparity_px : float
        Disparity (ideal pixels) the corners are placed at.

    """

    def __init__(self, prior: Callable, calib: StereoCalibration, disparity_px: float) -> None:
        self.prior = prior
        self.calib = calib
        self.offset = np.array([float(disparity_px), 0.0])

    def __call__(self, raw: np.ndarray) -> np.ndarray:
        """Return the (M, 2) displacement of (M, 2) raw left pixels (NaN if unknown)."""
        ideal = self.calib.undistort_left(raw)
        pred = np.asarray(self.prior(ideal, ideal - self.offset)[0], np.float64).reshape(-1, 2)
        if pred.shape != raw.shape:
            return np.full(raw.shape, np.nan)
        return self.calib.distort_left(pred) - raw


@dataclass
class ReplenishJob:
    """
    What the replenishment of one pair reads besides its images.

    Attributes
    ----------
    cfg, bcfg : TrackerConfig, BucketingConfig
        Detector, KLT and bucketing settings.
    calib : StereoCalibration
        Calibration of the pair.
    left_raw, right_raw : np.ndarray
        (N, 2) float32 raw pixels of the features tracked into the pair (left and right).
    need : int
        Corners wanted (``max_features`` minus the tracked features).
    chosen : np.ndarray or None
        (rows, cols) bool buckets to search (None with bucketing off).
    flow : ExpectedFlow or None
        Expected flow of new corners (the detection's flow-aperture check), or None.
    disparity_constraint : bool
        Apply the disparity constraint (eq. 6) to the new stereo matches.

    """

    cfg: TrackerConfig
    bcfg: BucketingConfig
    calib: StereoCalibration
    left_raw: np.ndarray
    right_raw: np.ndarray
    need: int
    chosen: np.ndarray | None
    flow: ExpectedFlow | None
    disparity_constraint: bool


@dataclass
class NewCorners:
    """
    The corners one replenishment adds, and what it measured.

    Attributes
    ----------
    left_raw, right_raw : np.ndarray
        (M, 2) float32 raw pixels of the accepted corners and their stereo matches.
    left_ideal, right_ideal : np.ndarray
        (M, 2) float64 ideal pixels of the same.
    barren : np.ndarray or None
        (rows, cols) bool buckets to skip for a while: searched without a corner, or whose
        corners all failed the stereo match (None with bucketing off).
    n_detected : int
        Corners detected.
    pass_points : dict
        Points entering the new corners' stereo passes (``new_stereo_fwd``, ``new_stereo_bwd``).
    timings_ms : dict
        Milliseconds per stage (``detection``, ``stereo_fwd``, ``stereo_bwd``, ``affine``).

    """

    left_raw: np.ndarray
    right_raw: np.ndarray
    left_ideal: np.ndarray
    right_ideal: np.ndarray
    barren: np.ndarray | None = None
    n_detected: int = 0
    pass_points: dict = field(default_factory=dict)
    timings_ms: dict = field(default_factory=dict)

    @classmethod
    def none(cls, **kwargs) -> 'NewCorners':
        z32, z64 = np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float64)
        return cls(z32, z32.copy(), z64, z64.copy(), **kwargs)


def replenish(left: np.ndarray, right: np.ndarray, right_matched: np.ndarray,
              job: ReplenishJob, clock: Callable[[], float] = time.perf_counter) -> NewCorners:
    """
    Detect corners where features are missing and match them into the right image.

    Parameters
    ----------
    left, right : np.ndarray
        (H, W) uint8 images of the pair.
    right_matched : np.ndarray
        ``right`` mapped to the brightness of ``left`` (``photometric``; ``right`` itself when
        they match): the KLT passes run on it, the affine refinement on ``right``.
    job : ReplenishJob
        Settings, calibration, tracked features and buckets to search.
    clock : callable
        Clock of the stage timings (seconds).

    Returns
    -------
    NewCorners
        The accepted corners (best first) and the buckets to skip.

    """
    cfg, bcfg, calib = job.cfg, job.bcfg, job.calib
    win, iters = cfg.win_size_px, cfg.max_iterations
    size = (left.shape[1], left.shape[0])
    chosen = job.chosen
    timings = dict.fromkeys(('detection', 'stereo_fwd', 'stereo_bwd', 'affine'), 0.0)
    points = dict.fromkeys(('new_stereo_fwd', 'new_stereo_bwd'), 0)
    barren = None if chosen is None else np.zeros(chosen.shape, bool)

    def outcome(n_detected: int, *arrays) -> NewCorners:
        kwargs = {'barren': barren, 'n_detected': n_detected, 'pass_points': points,
                  'timings_ms': timings}
        return NewCorners(*arrays, **kwargs) if arrays else NewCorners.none(**kwargs)

    t = clock()
    pts, found = detect_corners(left, job.left_raw, job.need, cfg, bcfg, chosen, job.flow)
    timings['detection'] = (clock() - t) * 1e3
    if chosen is not None and len(pts):
        # Buckets searched without a corner are skipped for a while (not when the whole
        # image gave nothing: a black or covered frame says nothing about the scene).
        barren |= chosen & (found.reshape(chosen.shape) == 0)
    if not len(pts):
        return outcome(0)
    n_detected, submitted = len(pts), pts
    if cfg.min_eigen_ratio > 0:
        pts = pts[eigen_ratio(left, pts, win) >= cfg.min_eigen_ratio]
        if not len(pts):
            return outcome(n_detected)
    t = clock()
    # Corners near a tracked feature start at its disparity (raw pixel offset) and need
    # few pyramid levels; the others are searched with the full pyramid.
    guided = np.zeros(len(pts), bool)
    guess = pts.copy()
    if len(job.left_raw):
        d2 = squared_distances(pts, job.left_raw)
        nearest = np.argmin(d2, axis=1)
        guided = d2[np.arange(len(pts)), nearest] <= NEIGHBOUR_RADIUS_PX ** 2
        guess = pts + (job.right_raw[nearest] - job.left_raw[nearest])
    pr = np.empty_like(pts)
    ok = np.zeros(len(pts), bool)
    points['new_stereo_fwd'] = len(pts)
    # Both passes, and both groups of the forward pass, use one pyramid of each image.
    pyr_left, pyr_right = ImagePyramid(left), ImagePyramid(right_matched)
    for sel, levels in ((guided, cfg.stereo_pyramid_levels),
                        (~guided, cfg.pyramid_levels)):
        if sel.any():
            pr[sel], ok[sel] = lk_pass(pyr_left, pyr_right, pts[sel], guess[sel], levels, win,
                                       iters)
    pts, pr = pts[ok], pr[ok]
    il, ir = calib.undistort_left(pts), calib.undistort_right(pr)
    ok = disparity_in_range(calib, il, ir, cfg.min_disparity_px, cfg.max_disparity_px)
    if job.disparity_constraint:
        ok &= disparity_constraint(calib, il, ir, cfg.disparity_y_threshold_px)
    pts, pr, il, ir = pts[ok], pr[ok], il[ok], ir[ok]
    timings['stereo_fwd'] = (clock() - t) * 1e3
    t = clock()
    points['new_stereo_bwd'] = len(pts)
    back, ok = lk_pass(pyr_right, pyr_left, pr, pts, REVERSE_PYRAMID_LEVELS, win, iters)
    ok &= round_trip_error(pts, back) < cfg.lr_threshold_px
    timings['stereo_bwd'] = (clock() - t) * 1e3
    if cfg.affine_refinement and ok.any():
        t = clock()
        refined, _ = refine_matches(cfg, left, right, pts[ok], pr[ok], stereo=True,
                                    rectified=calib.kind == 'rectified')
        pr[ok] = refined.astype(pr.dtype)
        ir[ok] = calib.undistort_right(pr[ok])
        timings['affine'] = (clock() - t) * 1e3
    n = int(np.count_nonzero(ok))
    if chosen is not None and n:
        # Buckets whose corners all failed the stereo match are skipped for a while.
        tried = np.bincount(bucket_ids(submitted, size, bcfg), minlength=chosen.size)
        kept = np.bincount(bucket_ids(pts[ok], size, bcfg), minlength=chosen.size)
        barren |= ((tried > 0) & (kept == 0)).reshape(chosen.shape)
    if not n:
        return outcome(n_detected)
    return outcome(n_detected, pts[ok].astype(np.float32), pr[ok].astype(np.float32), il[ok],
                   ir[ok])
