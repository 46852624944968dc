"""
What the stereo tracker returns for one stereo pair: the quadruples and its statistics.

``PendingTrack`` is the same before the pair's replenishment has finished
(``StereoTracker.track_async``).

``TrackResult`` carries the correspondences (ideal and raw pixels, x right, y down) and the
features alive after the pair; ``TrackerStats`` the counts per check, the adaptive threshold
(pixels) and the time per stage (milliseconds), keyed by ``STAGES``, ``PASSES`` and ``CHECKS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from ..records import Correspondences

#: Timed stages, keys of ``TrackerStats.timings_ms`` (plus ``total``).
STAGES = ('temporal_fwd', 'temporal_bwd', 'stereo_fwd', 'stereo_bwd', 'bicircular',
          'detection', 'affine', 'photometric')
#: KLT passes, keys of ``TrackerStats.pass_points``.
PASSES = ('temporal_fwd', 'temporal_bwd', 'stereo_fwd', 'stereo_bwd', 'bicircular',
          'new_stereo_fwd', 'new_stereo_bwd')
#: Checks, keys of ``TrackerStats.failed``: aperture (edge-like KLT window), flow_aperture
#: (edge-like along the predicted flow), KLT failure of the temporal pass, forward-backward,
#: KLT failure of the stereo pass, disparity constraint, disparity range, left-right, KLT
#: failure or threshold of the bi-circular check.
CHECKS = ('aperture', 'flow_aperture', 'temporal', 'fb', 'stereo', 'dc', 'disparity', 'lr',
          'bc')


@dataclass
class TrackerStats:
    """
    Per-frame statistics of the tracker.

    Attributes
    ----------
    initialized : bool
        True if this frame (re)started tracking (first frame, reset, new calibration or size).
    n_previous : int
        Features alive at t1.
    n_tracked : int
        Quadruples returned (features that passed every check).
    n_detected : int
        Corners detected in this frame.
    n_added : int
        Detected corners that found a stereo match and were added.
    n_features : int
        Features alive after this frame (tracked + added).
    failed : dict
        Features removed per check (keys: ``CHECKS``).
    loss : int
        Features lost before the bi-circular check (``loss`` of eq. 8).
    maxtrack : int
        Age of the oldest feature at the bi-circular check (frames, ``maxtrack`` of eq. 8).
    delta_d_px : float
        Bi-circular threshold used (pixels); NaN when the check did not run.
    used_prior : bool
        True if the motion prior gave the initial flow.
    timings_ms : dict
        Milliseconds per stage (keys: ``STAGES`` and ``total``).
    pass_points : dict
        Points entering each KLT pass of the tracked features (keys: ``STAGES`` without
        ``detection``) and of the new corners (``new_stereo_fwd``, ``new_stereo_bwd``).

    """

    initialized: bool = False
    n_previous: int = 0
    n_tracked: int = 0
    n_detected: int = 0
    n_added: int = 0
    n_features: int = 0
    failed: dict = field(default_factory=lambda: dict.fromkeys(CHECKS, 0))
    loss: int = 0
    maxtrack: int = 0
    delta_d_px: float = math.nan
    used_prior: bool = False
    timings_ms: dict = field(default_factory=lambda: dict.fromkeys(STAGES + ('total',), 0.0))
    pass_points: dict = field(default_factory=lambda: dict.fromkeys(PASSES, 0))


@dataclass
class TrackResult:
    """
    Output of one tracked stereo pair.

    Attributes
    ----------
    correspondences : Correspondences
        Quadruples in ideal (undistorted) pixels, float64, with feature ids and ages (frames
        tracked, >= 1); empty on an initialising frame.
    raw : Correspondences
        The same rows in raw pixels of the images as given (for drawing).
    features_left_raw, features_right_raw : np.ndarray
        (M, 2) float64 raw pixel positions of every feature alive after this frame in the
        current left and right image (tracked and newly detected).
    feature_ids, feature_ages : np.ndarray
        (M,) int64 ids and ages of those features (age 0: detected in this frame).
    stats : TrackerStats
        Counts, thresholds and timings of this frame.

    """

    correspondences: Correspondences
    raw: Correspondences
    features_left_raw: np.ndarray
    features_right_raw: np.ndarray
    feature_ids: np.ndarray
    feature_ages: np.ndarray
    stats: TrackerStats


@dataclass
class PendingTrack:
    """
    A tracked pair whose replenishment may still run (``StereoTracker.track_async``).

    Attributes
    ----------
    correspondences, raw : Correspondences
        The quadruples in ideal and raw pixels, final.
    stats : TrackerStats
        The pair's statistics; complete once ``result()`` returned.
    stereo_klt_right : np.ndarray
        (N, 2) float64 raw right pixels of the quadruples' current stereo matches as the 2-D
        KLT pass found them, before the affine refinement (which, on rectified input, puts the
        right point on the left point's row): their rows are measured, not copied.
    after_checks : object
        What ``track_async``'s ``after_checks`` returned (None without one).

    """

    correspondences: Correspondences
    raw: Correspondences
    stats: TrackerStats
    stereo_klt_right: np.ndarray
    _job: object
    after_checks: object = None

    def result(self) -> TrackResult:
        """Wait for the replenishment and return the whole ``TrackResult``."""
        return self._job.result()
