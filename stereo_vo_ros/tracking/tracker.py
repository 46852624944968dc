"""
Stereo KLT feature tracker with the light adaptive checks of Huang et al.

Every call to ``StereoTracker.track`` takes the current stereo pair (t2) and returns the
quadruples (left t1, right t1, left t2, right t2) of the features that survive, in this order:

1. optional aperture checks (not in the paper; here and at detection): ``min_eigen_ratio``
   drops features whose KLT window is edge-like, ``min_flow_edge_ratio`` (at detection) and
   ``min_flow_edge_ratio_tracked`` (here) those whose window is edge-like along the flow the
   motion prior predicts (lane lines); then the temporal pass left(t1) -> left(t2) (initial
   flow from the motion prior when given) and the forward-backward check (eq. 4, delta1); the
   survivors are refined with an affine window model (``affine_refinement``, not in the paper:
   see ``affine_klt``);
2. stereo pass left(t2) -> right(t2) starting at the previous (or predicted) disparity; the
   disparity constraint (eq. 6, delta3) and the disparity range run BEFORE the reverse pass, so
   rejected features are not tracked back; then the left-right check (eq. 5, delta2) and the
   affine refinement (on rectified input along the row, with a plane of disparity);
3. light bi-circular check (eq. 7) between right(t2) and right(t1) with a fixed or adaptive
   (eq. 8) threshold delta_d;
4. replenishment: Shi-Tomasi corners are detected only in the buckets of the bucketing grid that
   lack features, away from the existing features (and, with a motion prior, not edge-like
   along their predicted flow), and matched (and refined) into the right image.

Before every KLT pass the second image is mapped to the brightness of the first with one gain
and offset (``photometric_compensation``, not in the paper: see ``photometric``), so
independent exposure changes of the two cameras do not break the squared-difference KLT.

A feature is deleted at its first failed check. Which checks run is set by
``TrackerConfig.variant`` (see ``klt_checks.CheckSet``). KLT runs on the images as given (raw
pixels); the correspondences handed to the estimator are undistorted to the ideal pinhole pixels
of the calibration (identical to raw pixels for rectified input).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from typing import Any, Callable

import numpy as np

from .adaptive_threshold import bicircular_threshold
from .affine_klt import refine_matches
from .detection import plan_detection
from .features import as_grey_u8, empty_correspondences, FeatureSet
from .klt_checks import (aperture_checks, bicircular_error, BICIRCULAR_MODES, CheckSet,
                         disparity_constraint, disparity_in_range, lk_pass,
                         REVERSE_PYRAMID_LEVELS, round_trip_error)
from .lucas_kanade import finite_rows, ImagePyramid
from .photometric import PhotometricMatcher
from .replenish import ExpectedFlow, NewCorners, replenish, ReplenishJob
from .stats import (CHECKS, PASSES, PendingTrack, STAGES, TrackerStats,  # noqa: F401
                    TrackResult)  # (re-exported)
from ..config import BucketingConfig, TrackerConfig
from ..errors import ConfigError, ImageError
from ..estimation.camera import StereoCalibration
from ..parallel import inline, Workers
from ..records import Correspondences

logger = logging.getLogger(__name__)

#: Clock of the per-stage timings (seconds); a benchmark may swap in ``time.thread_time``.
CLOCK = time.perf_counter
#: A searched bucket that gave no new feature is skipped for this many frames (sky, road).
BARREN_BUCKET_FRAMES = 8
#: Share of the temporally tracked features whose affine refinement the helper thread takes
#: while the caller runs the reverse pass (the caller refines the others after it): the reverse
#: pass takes about a third of the refinement's time.
HELPER_REFINE_SHARE = 0.65
#: After an early replenishment, a second one runs at once (in the caller's thread) when fewer
#: than this fraction of the features it counted on survived the later checks.
TOP_UP_FRACTION = 0.5
#: Motion prior: (prev_left_ideal (N, 2), prev_right_ideal (N, 2)) -> (cur_left_pred (N, 2),
#: cur_right_pred (N, 2)), all float64 ideal pixels.
Prior = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


class StereoTracker:
    """
    Stereo KLT tracker (Huang et al.): one call per stereo pair.

    Parameters
    ----------
    tracker_cfg : TrackerConfig
        Detector, KLT and check settings (``variant`` and ``bicircular_mode`` choose the checks).
    bucketing_cfg : BucketingConfig
        Grid used to spread new features.

    Raises
    ------
    ConfigError
        Unknown variant or bi-circular mode, or an even KLT window.

    """

    def __init__(self, tracker_cfg: TrackerConfig | None = None,
                 bucketing_cfg: BucketingConfig | None = None,
                 workers: Workers | None = None) -> None:
        self.configure(tracker_cfg or TrackerConfig(), bucketing_cfg or BucketingConfig())
        #: Where the replenishment runs (``track_async``); inline by default.
        self.workers = workers or inline()
        self._next_id = 0
        self._pending = None  # the last pair's replenishment while it may run
        self.reset()

    def configure(self, tracker_cfg: TrackerConfig, bucketing_cfg: BucketingConfig) -> None:
        """Replace the settings; the tracked features are kept (thresholds apply next frame)."""
        checks = CheckSet.for_variant(tracker_cfg.variant)
        if tracker_cfg.bicircular_mode not in BICIRCULAR_MODES:
            raise ConfigError(f'tracker.bicircular_mode must be one of {list(BICIRCULAR_MODES)}'
                              f', got {tracker_cfg.bicircular_mode!r}')
        if tracker_cfg.win_size_px % 2 == 0:
            raise ConfigError(
                f'tracker.win_size_px must be odd, got {tracker_cfg.win_size_px}')
        self.cfg = tracker_cfg
        self.bucketing_cfg = bucketing_cfg
        self._checks = (tracker_cfg.variant, checks)

    @property
    def checks(self) -> CheckSet:
        """Return the checks of ``cfg.variant`` (follows direct assignments to ``cfg``)."""
        if self._checks[0] != self.cfg.variant:
            self._checks = (self.cfg.variant, CheckSet.for_variant(self.cfg.variant))
        return self._checks[1]

    def reset(self) -> None:
        """Forget every feature and the previous images; the next pair re-initialises."""
        self._settled()  # a running replenishment ends first; its features are dropped anyway
        self._pending = None
        #: Features the checks after the temporal ones, and after the stereo ones, removed in
        #: the last pair.
        self._later_losses = (0, 0)
        #: Features an early replenishment of the pair counted on (None: none started).
        self._planned_kept: int | None = None
        self._calib: StereoCalibration | None = None
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        self._feats = FeatureSet.empty()
        self._bits = 8
        self._barren: np.ndarray | None = None  # (rows, cols) frames to skip each bucket
        self._photo = PhotometricMatcher()
        #: KLT pyramids of the images of this and the last pair (``_pyramid``).
        self._pyramids: list[ImagePyramid] = []

    @property
    def num_features(self) -> int:
        """Return the number of features alive after the last pair."""
        self._settled()
        return len(self._feats)

    # -- public API ---------------------------------------------------------------------
    def previous_left(self) -> np.ndarray | None:
        """Return the left image of the last pair as tracked ((H, W) uint8, read-only) or None."""
        return None if self._prev is None else self._prev[0]

    def last_pair(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Return the left and right images of the last pair as tracked ((H, W) uint8) or None."""
        return self._prev

    def feature_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Return ideal left and right pixels (N, 2) of the features alive after the last pair."""
        self._settled()
        f = self._feats
        return f.left_ideal.astype(np.float64), f.right_ideal.astype(np.float64)

    def as_grey(self, img: np.ndarray) -> np.ndarray:
        """Return an image as ``track`` sees it: (H, W) uint8, uint16 scaled by the bit depth."""
        return as_grey_u8(img, 'left', self._bits)[0]

    def grey_pair(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return a pair as ``track`` sees it ((H, W) uint8 each), fixing the bit depth now.

        uint16 input raises the bit depth it is scaled by (which only grows) as ``track``
        would; passing the returned images to ``track`` then tracks the same as passing
        ``left`` and ``right``. uint8 input is returned as it is (contiguous).

        Raises
        ------
        ImageError
            Images that are not grey uint8/uint16 or differ in size.

        """
        left8, self._bits = as_grey_u8(left, 'left', self._bits)
        right8, self._bits = as_grey_u8(right, 'right', self._bits)
        if left8.shape != right8.shape:
            raise ImageError(f'left and right images differ in size: {left8.shape[::-1]} vs '
                             f'{right8.shape[::-1]}')
        return left8, right8

    def track(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
              prior: Prior | None = None) -> TrackResult:
        """
        Track the features into a new stereo pair and replenish them.

        The same as ``track_async(...).result()``; see there.
        """
        return self.track_async(left, right, calib, prior).result()

    def track_async(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                    prior: Prior | None = None,
                    after_checks: Callable[[], Any] | None = None) -> 'PendingTrack':
        """
        Track the features into a new stereo pair; replenish them on a worker thread.

        Returns as soon as the quadruples are known; the detection and stereo matching of new
        corners continue on ``workers`` (inline with one thread). The tracker's feature state
        (``feature_points``, ``num_features``) is complete once ``PendingTrack.result()`` or
        ``join()`` returned; the next call joins first. The images (``last_pair``,
        ``previous_left``) are the new pair's on return.

        Parameters
        ----------
        left, right : np.ndarray
            (H, W) uint8 or uint16 grey images of the current pair (rectified or raw, as
            ``calib.kind`` says); uint16 is scaled to uint8.
        calib : StereoCalibration
            Calibration of the pair; its image size must match the images.
        prior : callable or None
            Motion prior ``(prev_left_ideal, prev_right_ideal) -> (cur_left_pred,
            cur_right_pred)``, (N, 2) float64 ideal pixels each; used as the KLT initial flow
            when ``use_motion_prior`` is set: of the temporal pass (``predicted_pyramid_levels``)
            and, through the predicted disparity, of the stereo pass (``stereo_pyramid_levels``).
        after_checks : callable or None
            Called once, without arguments, as soon as the pair's own work for the helper
            thread (``Workers.submit_local``: brightness maps, aperture checks) is queued, so
            that work it queues there runs after it (before the temporal KLT pass; at once
            on a first pair). Its return value is ``PendingTrack.after_checks``.

        Returns
        -------
        PendingTrack
            The quadruples (empty on the first frame, after ``reset`` or when the calibration
            or the image size changed) at once; ``result()`` gives the ``TrackResult`` with
            the features after replenishment and the statistics.

        Raises
        ------
        ImageError
            Images that are not grey uint8/uint16, differ in size, or do not match the
            calibration's image size.

        """
        self.join()
        t_start = CLOCK()
        left8, right8 = self.grey_pair(left, right)
        if tuple(calib.size) != (left8.shape[1], left8.shape[0]):
            raise ImageError(f'image size {left8.shape[1]}x{left8.shape[0]} does not match the '
                             f'calibration size {calib.size[0]}x{calib.size[1]}')
        # Own copies: the tracker keeps the pair and its replenishment may read it after this
        # returns, while the caller may reuse its image buffers.
        left8 = left8.copy() if np.may_share_memory(left8, left) else left8
        right8 = right8.copy() if np.may_share_memory(right8, right) else right8
        stats = TrackerStats()
        self._photo.enabled = bool(self.cfg.photometric_compensation)
        after_checks = functools.cache(after_checks or (lambda: None))  # runs once
        new = None
        if self._prev is None or self._prev[0].shape != left8.shape or \
                not calib.same_as(self._calib):
            if self._prev is not None:
                logger.info('tracker re-initialised: new calibration or image size %dx%d',
                            left8.shape[1], left8.shape[0])
            self._feats = FeatureSet.empty()
            self._barren = None
            self._later_losses = (0, 0)
            self._calib = calib
            stats.initialized = True
            corr, raw = empty_correspondences(), empty_correspondences()
            klt_right = np.zeros((0, 2))
        else:
            corr, raw, klt_right, new = self._track_existing(left8, right8, calib, prior, stats,
                                                             after_checks)
        queued = after_checks()  # (called already when the pair was tracked)
        self._prev = (left8, right8)
        # The next pair's KLT passes reuse this pair's pyramids; the others are dropped.
        self._pyramids = [p for p in self._pyramids if p.image is left8 or p.image is right8]
        if stats.initialized or self.cfg.replenish_after not in ('stereo', 'temporal'):
            new = self._replenish_survivors(left8, right8, calib, stats, prior)
        self._pending = _Finish(self, left8, right8, stats, corr, raw, new, t_start)
        return PendingTrack(corr, raw, stats, klt_right, self._pending, queued)

    def _start_replenishment(self, left: np.ndarray, right: np.ndarray,
                             calib: StereoCalibration, stats: TrackerStats,
                             prior: Prior | None, left_raw: np.ndarray, right_raw: np.ndarray,
                             disparity: np.ndarray, n_kept: int,
                             pts_left: np.ndarray | None = None,
                             pts_right: np.ndarray | None = None, first: bool = True):
        """
        Plan the replenishment and hand it to the workers; return its pending result or None.

        ``prior``: the pair's motion prior (used only if the tracking used it);
        ``left_raw``, ``right_raw`` (N, 2): the features corners keep away from and take their
        stereo start from; ``disparity`` (N,) their ideal disparities (pixels); ``n_kept`` the
        features expected to stay (corners wanted: ``max_features - n_kept``); ``pts_left``,
        ``pts_right``: the points the stereo pass maps the right image's brightness with
        (None: the whole images); ``first``: see ``_replenish_job``.
        """
        t = CLOCK()
        job = self._replenish_job(left, calib, prior if stats.used_prior else None, left_raw,
                                  right_raw, disparity, n_kept, first)
        stats.timings_ms['detection'] += (CLOCK() - t) * 1e3
        if job is None:
            return None
        right_m, _ = self._matched(left, right, pts_left, pts_right, stats)
        if self.workers.kind == 'process':
            return self.workers.submit(replenish, left, right, right_m, job)
        return self.workers.submit(replenish, left, right, right_m, job, CLOCK)

    def _replenish_survivors(self, left: np.ndarray, right: np.ndarray,
                             calib: StereoCalibration, stats: TrackerStats,
                             prior: Prior | None, first: bool = True):
        """Start a replenishment from the features that passed every check (``_feats``)."""
        f = self._feats
        return self._start_replenishment(
            left, right, calib, stats, prior, f.left_raw, f.right_raw,
            f.left_ideal[:, 0] - f.right_ideal[:, 0], len(f), first=first)

    def join(self) -> TrackResult | None:
        """
        Wait for the replenishment of the last pair; return its result (None if none).

        An error of the replenishment is raised here (and by ``PendingTrack.result``).
        """
        pending, self._pending = self._pending, None
        return None if pending is None else pending.result()

    def _settled(self) -> None:
        """Wait for a running replenishment without taking its result or its error."""
        if self._pending is not None:
            try:
                self._pending.result()
            except Exception:  # noqa: BLE001 - raised to whoever joins
                pass

    # -- stages -----------------------------------------------------------------------
    def _predict(self, prior: Prior, calib: StereoCalibration
                 ) -> tuple[np.ndarray, np.ndarray] | None:
        """Raw-pixel predictions (N, 2) of left and right positions at t2, or None."""
        f = self._feats
        pred_l, pred_r = prior(f.left_ideal.copy(), f.right_ideal.copy())
        pred_l = np.asarray(pred_l, np.float64)
        pred_r = np.asarray(pred_r, np.float64)
        if pred_l.shape != (len(f), 2) or pred_r.shape != (len(f), 2):
            logger.warning('motion prior returned shapes %s and %s for %d features; ignored',
                           pred_l.shape, pred_r.shape, len(f))
            return None
        bad = ~(finite_rows(pred_l) & finite_rows(pred_r))
        pred_l = np.where(bad[:, None], f.left_ideal, pred_l)
        pred_r = np.where(bad[:, None], f.right_ideal, pred_r)
        raw_l, raw_r = calib.distort_left(pred_l), calib.distort_right(pred_r)
        raw_l[bad] = np.nan  # lk_pass starts these at the previous position
        raw_r[bad] = np.nan
        return raw_l, raw_r

    @staticmethod
    def _aperture_passed(aperture, failed: dict[str, int]) -> np.ndarray:
        """Join ``aperture_checks``: (N,) bool of the features that pass; count the others."""
        eigen_ok, flow_ok = aperture.result()
        failed['aperture'] = int(np.count_nonzero(~eigen_ok))
        failed['flow_aperture'] = int(np.count_nonzero(eigen_ok & ~flow_ok))
        return eigen_ok & flow_ok

    def _expected_flow(self, prior: Prior | None, calib: StereoCalibration,
                       disparity: np.ndarray) -> ExpectedFlow | None:
        """
        Return the expected displacement of new corners into the next pair, or None.

        The motion prior of this pair at the median of the tracked features' ideal disparities
        ``disparity`` (``ExpectedFlow``). None without a prior, without a positive disparity or
        with the check off.
        """
        if prior is None or self.cfg.min_flow_edge_ratio <= 0:
            return None
        disparity = disparity[np.isfinite(disparity) & (disparity > 0)]
        if not len(disparity):
            return None
        return ExpectedFlow(prior, calib, float(np.median(disparity)))

    def _track_existing(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                        prior: Prior | None, stats: TrackerStats,
                        after_checks: Callable[[], Any]
                        ) -> tuple[Correspondences, Correspondences, np.ndarray, object]:
        """
        Track the features of t1 into the pair t2 through every enabled check.

        ``after_checks`` is called once the helper has the aperture checks (``track_async``).

        Returns the quadruples (ideal and raw pixels), the raw right points of their stereo
        KLT pass before the affine refinement ((N, 2) float64), and the pending replenishment
        when it started during the tracking (with a worker; else None).
        """
        cfg, checks = self.cfg, self.checks
        prev_left, prev_right = self._prev
        f = self._feats
        n_prev = len(f)
        stats.n_previous = n_prev
        win, iters = cfg.win_size_px, cfg.max_iterations
        clock = CLOCK
        ms, npts, failed = stats.timings_ms, stats.pass_points, stats.failed

        # 1. Temporal pass left(t1) -> left(t2) and forward-backward check (eq. 4).
        pred = None
        if prior is not None and cfg.use_motion_prior and n_prev:
            pred = self._predict(prior, calib)
        stats.used_prior = pred is not None
        t = clock()
        levels = cfg.predicted_pyramid_levels if pred is not None else cfg.pyramid_levels
        # Photometric compensation: every KLT pass sees its second image mapped to the
        # brightness of its first (``photometric``; the images as given when they match). With
        # the prior, the windows at the features' positions in the four images give all maps.
        t_photo = clock()
        if pred is not None:
            self._photo.observe((prev_left, left, right, prev_right),
                                (f.left_raw, pred[0], pred[1], f.right_raw))
            if self.workers.overlaps:
                # The stereo and bi-circular passes' maps are known now: the helper applies
                # them while the temporal passes run.
                later = ((left, right), (right, prev_right)) if checks.bicircular else \
                    ((left, right),)
                self._photo.prefetch(later, self.workers.submit_local)
        spent = clock() - t_photo
        ms['photometric'] += spent * 1e3
        t += spent
        # Aperture checks: on an edge-like window the flow along the edge would come from the
        # initial flow (the motion prior), not from the image; the same along the predicted
        # flow, over the window the refinement will use. With a helper thread they run next to
        # the KLT pass, which then tracks every feature (each point is tracked on its own, so
        # the kept ones come out the same). Started after the photometric fits: the helper's
        # Python would otherwise take turns with theirs on the GIL.
        flow_tracked = None
        if pred is not None and cfg.min_flow_edge_ratio_tracked > 0:
            flow_tracked = pred[0] - f.left_raw
        aperture = None
        if n_prev and (cfg.min_eigen_ratio > 0 or flow_tracked is not None):
            aperture = self.workers.submit_local(
                aperture_checks, prev_left, f.left_raw, flow_tracked, win,
                cfg.affine_win_size_px, cfg.min_eigen_ratio, cfg.min_flow_edge_ratio_tracked)
        after_checks()
        left_m, spent = self._matched(prev_left, left, None, None, stats)
        t += spent
        passed = None  # aperture: which features may be tracked (None: all)
        if aperture is not None and not self.workers.overlaps:
            passed = self._aperture_passed(aperture, failed)
        track = np.arange(n_prev) if passed is None else np.flatnonzero(passed)
        cur_l = f.left_raw.copy()
        cur_l[track], ok = lk_pass(self._pyramid(prev_left), self._pyramid(left_m),
                                   f.left_raw[track], None if pred is None else pred[0][track],
                                   levels, win, iters)
        tracked = np.zeros(n_prev, bool)
        tracked[track] = ok
        if passed is None:
            passed = np.ones(n_prev, bool) if aperture is None else \
                self._aperture_passed(aperture, failed)
        npts['temporal_fwd'] = int(np.count_nonzero(passed))
        ms['temporal_fwd'] = (clock() - t) * 1e3
        failed['temporal'] = int(np.count_nonzero(passed & ~tracked))
        alive = np.flatnonzero(passed & tracked)

        # With a helper thread the affine refinement runs next to the reverse pass, on the
        # first ``HELPER_REFINE_SHARE`` of the features the forward pass kept (each point is
        # refined on its own, so the ones the check keeps come out the same); the caller
        # refines the rest that pass the check after its reverse pass, while the helper is still
        # at its share. Not when the caller queued work of its own there (``after_checks``: the
        # road pyramids), which the refinement would wait behind.
        early, n_early = None, 0
        if self.workers.overlaps and cfg.affine_refinement and len(alive) \
                and after_checks() is None:
            n_early = int(math.ceil(HELPER_REFINE_SHARE * len(alive)))
            early = self.workers.submit_local(self._refined, prev_left, left,
                                              f.left_raw[alive[:n_early]],
                                              cur_l[alive[:n_early]])
        t = clock()
        npts['temporal_bwd'] = len(alive)
        back, ok = lk_pass(self._pyramid(left_m), self._pyramid(prev_left), cur_l[alive],
                           f.left_raw[alive], REVERSE_PYRAMID_LEVELS, win, iters)
        ok &= round_trip_error(f.left_raw[alive], back) < cfg.fb_threshold_px
        ms['temporal_bwd'] = (clock() - t) * 1e3
        failed['fb'] = int(np.count_nonzero(~ok))
        refined = None
        if early is not None:
            t = clock()
            rest = alive[n_early:][ok[n_early:]]
            refined_rest = self._refined(prev_left, left, f.left_raw[rest], cur_l[rest]) \
                if len(rest) else cur_l[rest]
            refined = np.concatenate([early.result()[ok[:n_early]], refined_rest])
            # Timed as the caller's share and wait: the helper's own time ran beside the
            # reverse pass.
            ms['affine'] += (clock() - t) * 1e3
        alive = alive[ok]
        cur_l[alive] = self._refine(prev_left, left, f.left_raw[alive], cur_l[alive], stats) \
            if refined is None else refined

        # 2. Stereo pass left(t2) -> right(t2) from the previous (or predicted) disparity; the
        #    disparity constraint (eq. 6) and range run before the reverse pass.
        t = clock()
        offset = (f.right_raw[alive] - f.left_raw[alive]).astype(np.float64)
        if pred is not None:
            predicted = pred[1][alive] - pred[0][alive]
            offset = np.where(np.isfinite(predicted), predicted, offset)
        new = None
        n_temporal = len(alive)
        if cfg.replenish_after == 'temporal':
            # The replenishment starts here (with a worker: next to the stereo pass and the
            # later checks), from the features that passed the temporal checks with the
            # disparities they were matched at in the last pair: new corners start their stereo
            # search from a measured disparity, not from the prediction the stereo pass is
            # about to check (see TrackerConfig.replenish_after).
            spent = clock()
            measured = (f.right_raw[alive] - f.left_raw[alive]).astype(np.float64)
            self._planned_kept = n_temporal - self._later_losses[0]
            new = self._start_replenishment(
                left, right, calib, stats, prior, cur_l[alive], cur_l[alive] + measured,
                f.left_ideal[alive, 0] - f.right_ideal[alive, 0], self._planned_kept,
                cur_l[alive], cur_l[alive] + offset)
            t += clock() - spent
        npts['stereo_fwd'] = len(alive)
        right_m, spent = self._matched(left, right, cur_l[alive], cur_l[alive] + offset, stats)
        t += spent
        cur_r, ok = lk_pass(self._pyramid(left), self._pyramid(right_m), cur_l[alive],
                            cur_l[alive] + offset, cfg.stereo_pyramid_levels, win, iters)
        failed['stereo'] = int(np.count_nonzero(~ok))
        alive, cur_r = alive[ok], cur_r[ok]
        ideal_l = calib.undistort_left(cur_l[alive])
        ideal_r = calib.undistort_right(cur_r)

        def range_check() -> np.ndarray:
            return disparity_in_range(calib, ideal_l, ideal_r, cfg.min_disparity_px,
                                      cfg.max_disparity_px)

        if checks.disparity_constraint:
            ok = disparity_constraint(calib, ideal_l, ideal_r, cfg.disparity_y_threshold_px)
            failed['dc'] = int(np.count_nonzero(~ok))
            rng = range_check()
            failed['disparity'] = int(np.count_nonzero(ok & ~rng))
            ok &= rng
            alive, cur_r, ideal_l, ideal_r = alive[ok], cur_r[ok], ideal_l[ok], ideal_r[ok]
        ms['stereo_fwd'] = (clock() - t) * 1e3

        # Left-right check (eq. 5); without the disparity constraint the range check follows.
        t = clock()
        npts['stereo_bwd'] = len(alive)
        back, ok = lk_pass(self._pyramid(right_m), self._pyramid(left), cur_r, cur_l[alive],
                           REVERSE_PYRAMID_LEVELS, win, iters)
        ok &= round_trip_error(cur_l[alive], back) < cfg.lr_threshold_px
        failed['lr'] = int(np.count_nonzero(~ok))
        if not checks.disparity_constraint:
            rng = range_check()
            failed['disparity'] = int(np.count_nonzero(ok & ~rng))
            ok &= rng
        alive, cur_r, ideal_l, ideal_r = alive[ok], cur_r[ok], ideal_l[ok], ideal_r[ok]
        ms['stereo_bwd'] = (clock() - t) * 1e3
        n_stereo = len(alive)
        if cfg.replenish_after == 'stereo':
            self._planned_kept = n_stereo - self._later_losses[1]
            # From here, with the stereo matches as the KLT pass found them: the worker overlaps
            # the refinement, the bi-circular check and the motion estimate.
            new = self._start_replenishment(
                left, right, calib, stats, prior, cur_l[alive], cur_r,
                ideal_l[:, 0] - ideal_r[:, 0], self._planned_kept)
        klt_r = cur_r.astype(np.float64)
        if cfg.affine_refinement and len(alive):
            cur_r = self._refine(left, right, cur_l[alive], cur_r, stats, stereo=True)
            ideal_r = calib.undistort_right(cur_r)

        ages = f.ages[alive] + 1
        stats.loss = n_prev - len(alive)
        stats.maxtrack = int(ages.max()) if len(ages) else 0
        # 3. Light bi-circular check (eq. 7) with a fixed or adaptive (eq. 8) threshold.
        if checks.bicircular and len(alive):
            t = clock()
            delta_d = bicircular_threshold(cfg, stats.loss, stats.maxtrack)
            stats.delta_d_px = delta_d
            npts['bicircular'] = len(alive)
            # Start right(t1) from right(t2) moved back by the measured left flow.
            guess = cur_r + (f.left_raw[alive] - cur_l[alive])
            prev_right_m, spent = self._matched(right, prev_right, cur_r, f.right_raw[alive],
                                                stats)
            t += spent
            back_r, ok = lk_pass(self._pyramid(right), self._pyramid(prev_right_m), cur_r, guess,
                                 cfg.predicted_pyramid_levels, win, iters)
            again = None
            if cfg.bicircular_mode == 'roundtrip':
                again = np.full_like(cur_r, np.nan)
                again[ok], ok2 = lk_pass(self._pyramid(prev_right_m), self._pyramid(right),
                                         back_r[ok], cur_r[ok], REVERSE_PYRAMID_LEVELS, win,
                                         iters)
                ok[ok] = ok2
            err = bicircular_error(cfg.bicircular_mode, cur_r, back_r, f.right_raw[alive], again)
            ok &= err < delta_d
            failed['bc'] = int(np.count_nonzero(~ok))
            alive, cur_r, ideal_l, ideal_r, ages, klt_r = (
                alive[ok], cur_r[ok], ideal_l[ok], ideal_r[ok], ages[ok], klt_r[ok])
            ms['bicircular'] = (clock() - t) * 1e3

        stats.n_tracked = len(alive)
        self._later_losses = (n_temporal - len(alive), n_stereo - len(alive))
        prev = f.take(alive)
        cur_l = cur_l[alive]
        corr = Correspondences(prev.left_ideal.copy(), prev.right_ideal.copy(), ideal_l.copy(),
                               ideal_r.copy(), prev.ids.copy(), ages.copy())
        raw = Correspondences(prev.left_raw.astype(np.float64),
                              prev.right_raw.astype(np.float64), cur_l.astype(np.float64),
                              cur_r.astype(np.float64), prev.ids.copy(), ages.copy())
        self._feats = FeatureSet(prev.ids, ages, cur_l, cur_r, ideal_l, ideal_r)
        return corr, raw, klt_r, new

    def _pyramid(self, img: np.ndarray) -> ImagePyramid:
        """
        Return the KLT pyramid of an image of this or the last pair, built once per image.

        Images are told apart by identity: the pair's images, the last pair's, and the
        brightness-mapped ones (``_matched``), which are new arrays.
        """
        for pyr in self._pyramids:
            if pyr.image is img:
                return pyr
        pyr = ImagePyramid(img)
        self._pyramids.append(pyr)
        return pyr

    def _matched(self, reference: np.ndarray, img: np.ndarray, pts_reference: np.ndarray | None,
                 pts_img: np.ndarray | None, stats: TrackerStats) -> tuple[np.ndarray, float]:
        """
        Return ``img`` mapped to the brightness of ``reference`` and the seconds it took.

        The time is added to the ``photometric`` stage; the caller moves the start of its own
        stage by it, so the stage times do not overlap.
        """
        t = CLOCK()
        out = self._photo.matched(reference, img, pts_reference, pts_img)
        spent = CLOCK() - t
        stats.timings_ms['photometric'] += spent * 1e3
        return out, spent

    def _refine(self, img_from: np.ndarray, img_to: np.ndarray, pts_from: np.ndarray,
                pts_to: np.ndarray, stats: TrackerStats, stereo: bool = False) -> np.ndarray:
        """Affine refinement of matches (raw pixels) when configured, timed as ``affine``."""
        if not self.cfg.affine_refinement or not len(pts_from):
            return pts_to
        t = CLOCK()
        out = self._refined(img_from, img_to, pts_from, pts_to, stereo)
        stats.timings_ms['affine'] = stats.timings_ms.get('affine', 0.0) + (CLOCK() - t) * 1e3
        return out

    def _refined(self, img_from: np.ndarray, img_to: np.ndarray, pts_from: np.ndarray,
                 pts_to: np.ndarray, stereo: bool = False) -> np.ndarray:
        """``_refine`` without the setting's test and the timing (also on the helper thread)."""
        rectified = self._calib is not None and self._calib.kind == 'rectified'
        out, _ = refine_matches(self.cfg, img_from, img_to, pts_from, pts_to, stereo, rectified)
        return out.astype(pts_to.dtype)

    def _replenish_job(self, left: np.ndarray, calib: StereoCalibration, prior: Prior | None,
                       left_raw: np.ndarray, right_raw: np.ndarray, disparity: np.ndarray,
                       n_kept: int, first: bool = True) -> ReplenishJob | None:
        """
        Plan a replenishment (None: no corner is needed); see ``_start_replenishment``.

        ``first``: the pair's first replenishment, which counts down the barren buckets.
        """
        cfg = self.cfg
        need = cfg.max_features - n_kept
        if need <= 0:
            return None
        bcfg = self.bucketing_cfg
        chosen = None
        if bcfg.enabled:
            if self._barren is None or self._barren.shape != (bcfg.rows, bcfg.cols):
                self._barren = np.zeros((bcfg.rows, bcfg.cols), np.int64)
            size = (left.shape[1], left.shape[0])
            chosen = plan_detection(left_raw, need, size, bcfg, self._barren > 0)
            if first:
                self._barren = np.maximum(self._barren - 1, 0)
        return ReplenishJob(cfg, bcfg, calib, np.array(left_raw, np.float32),
                            np.array(right_raw, np.float32), need, chosen,
                            self._expected_flow(prior, calib, disparity),
                            self.checks.disparity_constraint)

    def _add(self, new: NewCorners, stats: TrackerStats) -> None:
        """Add the corners of a replenishment to the features; mark its barren buckets."""
        for key, value in new.timings_ms.items():
            stats.timings_ms[key] += value
        stats.pass_points.update(new.pass_points)
        stats.n_detected = new.n_detected
        if new.barren is not None and self._barren is not None \
                and self._barren.shape == new.barren.shape:
            self._barren[new.barren] = BARREN_BUCKET_FRAMES
        # A replenishment started before the later checks may bring more than there is room for.
        n = min(len(new.left_raw), max(self.cfg.max_features - len(self._feats), 0))
        stats.n_added = n
        if not n:
            return
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        self._feats = self._feats.concat(FeatureSet(
            ids, np.zeros(n, np.int64), new.left_raw[:n], new.right_raw[:n], new.left_ideal[:n],
            new.right_ideal[:n]))

    def _top_up(self, left: np.ndarray, right: np.ndarray, stats: TrackerStats) -> None:
        """
        Replenish again, in this thread, when an early replenishment left many slots empty.

        An early replenishment (``replenish_after`` not ``all``) counts the features a later
        check may still remove; when fewer than ``TOP_UP_FRACTION`` of the features it counted
        on survived (a stereo failure over the whole image), the slots would stay empty for a
        pair.
        """
        if self._planned_kept is None or stats.initialized:
            return
        planned, self._planned_kept = self._planned_kept, None
        if stats.n_tracked >= TOP_UP_FRACTION * planned:
            return
        new = self._replenish_survivors(left, right, self._calib, stats, None, first=False)
        if new is not None:
            added = stats.n_added
            self._add(new.result(), stats)
            stats.n_added += added


class _Finish:
    """
    The end of one ``track_async``: waits for the replenishment, applies it, gives the result.

    Runs once, in the thread that asks first (``result``); later calls return the same result
    or raise the same error.
    """

    def __init__(self, tracker: StereoTracker, left8: np.ndarray, right8: np.ndarray,
                 stats: TrackerStats, corr: Correspondences, raw: Correspondences,
                 new, t_start: float) -> None:
        self._args = (tracker, left8, right8, stats, corr, raw, new, t_start)
        self._value: TrackResult | None = None
        self._error: Exception | None = None

    def result(self) -> TrackResult:
        if self._args is not None:
            args, self._args = self._args, None
            try:
                self._value = self._finish(*args)
            except Exception as exc:  # raised to every caller, as a Future does
                self._error = exc
            except BaseException:  # interrupted (Ctrl-C): the next call finishes
                self._args = args
                raise
        if self._error is not None:
            raise self._error
        return self._value

    @staticmethod
    def _finish(tracker: StereoTracker, left8: np.ndarray, right8: np.ndarray,
                stats: TrackerStats, corr: Correspondences, raw: Correspondences, new,
                t_start: float) -> TrackResult:
        if new is not None:
            tracker._add(new.result(), stats)
        tracker._top_up(left8, right8, stats)
        tracker._photo.carry(((left8, tracker._prev[0]), (right8, tracker._prev[1])))
        stats.n_features = len(tracker._feats)
        stats.timings_ms['total'] = (CLOCK() - t_start) * 1e3
        f = tracker._feats
        return TrackResult(corr, raw, f.left_raw.astype(np.float64),
                           f.right_raw.astype(np.float64), f.ids.copy(), f.ages.copy(), stats)
