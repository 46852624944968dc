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

import logging
import time
from typing import Callable

import numpy as np

from .adaptive_threshold import bicircular_threshold
from .affine_klt import refine_affine
from .detection import bucket_ids, detect_corners, plan_detection
from .features import as_grey_u8, empty_correspondences, FeatureSet
from .klt_checks import (bicircular_error, BICIRCULAR_MODES, CheckSet, disparity_constraint,
                         disparity_in_range, eigen_ratio, flow_edge_ratio, lk_pass,
                         round_trip_error)
from .photometric import PhotometricMatcher
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
#: Pyramid levels of the reverse passes (forward-backward, left-right, bi-circular return);
#: they start at the point they should return to, so the base image suffices.
REVERSE_PYRAMID_LEVELS = 0
#: A new corner closer than this to a tracked feature starts its stereo search at that
#: feature's disparity with ``predicted_pyramid_levels`` (pixels).
NEIGHBOUR_RADIUS_PX = 80.0
#: A searched bucket that gave no new feature is skipped for this many frames (sky, road).
BARREN_BUCKET_FRAMES = 8
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
        self._calib: StereoCalibration | None = None
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        self._floats: list[tuple[np.ndarray, np.ndarray]] = []
        self._feats = FeatureSet.empty()
        self._bits = 8
        self._barren: np.ndarray | None = None  # (rows, cols) frames to skip each bucket
        self._photo = PhotometricMatcher()

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

    def track(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
              prior: Prior | None = None) -> TrackResult:
        """
        Track the features into a new stereo pair and replenish them.

        The same as ``track_async(...).result()``; see there.
        """
        return self.track_async(left, right, calib, prior).result()

    def track_async(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                    prior: Prior | None = None) -> 'PendingTrack':
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
            with ``predicted_pyramid_levels`` when ``use_motion_prior`` is set.

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
        # float32 images of the refinement: only the previous pair's (owned by the tracker, never
        # written) carry over; the caller may reuse its buffers for the next pair.
        self._floats = [(src, conv) for src, conv in self._floats
                        if self._prev is not None and any(src is p for p in self._prev)]
        left8, self._bits = as_grey_u8(left, 'left', self._bits)
        right8, self._bits = as_grey_u8(right, 'right', self._bits)
        if left8.shape != right8.shape:
            raise ImageError(f'left and right images differ in size: {left8.shape[::-1]} vs '
                             f'{right8.shape[::-1]}')
        if tuple(calib.size) != (left8.shape[1], left8.shape[0]):
            raise ImageError(f'image size {left8.shape[1]}x{left8.shape[0]} does not match the '
                             f'calibration size {calib.size[0]}x{calib.size[1]}')
        stats = TrackerStats()
        self._photo.enabled = bool(self.cfg.photometric_compensation)
        if self._prev is None or self._prev[0].shape != left8.shape or \
                not calib.same_as(self._calib):
            if self._prev is not None:
                logger.info('tracker re-initialised: new calibration or image size %dx%d',
                            left8.shape[1], left8.shape[0])
            self._feats = FeatureSet.empty()
            self._barren = None
            self._calib = calib
            stats.initialized = True
            corr, raw = empty_correspondences(), empty_correspondences()
            klt_right = np.zeros((0, 2))
        else:
            corr, raw, klt_right = self._track_existing(left8, right8, calib, prior, stats)
        # Own copies: the caller may reuse its image buffers.
        self._prev = (left8.copy() if np.may_share_memory(left8, left) else left8,
                      right8.copy() if np.may_share_memory(right8, right) else right8)
        # Replenishment needs nothing the caller computes from the quadruples: it runs on a
        # worker thread (inline with one thread) while the caller estimates the motion.
        self._pending = self.workers.submit(
            self._replenish_and_finish, left8, right8, calib, stats,
            prior if stats.used_prior else None, corr, raw, t_start)
        return PendingTrack(corr, raw, stats, klt_right, self._pending)

    def _replenish_and_finish(self, left8: np.ndarray, right8: np.ndarray,
                              calib: StereoCalibration, stats: TrackerStats,
                              prior: Prior | None, corr: Correspondences, raw: Correspondences,
                              t_start: float) -> TrackResult:
        """Replenish the features of the pair just tracked and return the whole result."""
        self._replenish(left8, right8, calib, stats, prior)
        self._photo.carry(((left8, self._prev[0]), (right8, self._prev[1])))
        stats.n_features = len(self._feats)
        stats.timings_ms['total'] = (CLOCK() - t_start) * 1e3
        f = self._feats
        return TrackResult(corr, raw, f.left_raw.astype(np.float64),
                           f.right_raw.astype(np.float64), f.ids.copy(), f.ages.copy(), stats)

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
        bad = ~(np.all(np.isfinite(pred_l), axis=1) & np.all(np.isfinite(pred_r), axis=1))
        pred_l = np.where(bad[:, None], f.left_ideal, pred_l)
        pred_r = np.where(bad[:, None], f.right_ideal, pred_r)
        raw_l, raw_r = calib.distort_left(pred_l), calib.distort_right(pred_r)
        raw_l[bad] = np.nan  # lk_pass starts these at the previous position
        raw_r[bad] = np.nan
        return raw_l, raw_r

    def _expected_flow(self, prior: Prior | None, calib: StereoCalibration
                       ) -> Callable[[np.ndarray], np.ndarray] | None:
        """
        Return the expected displacement of new corners into the next pair, or None.

        The motion prior of this pair, applied again from here (constant velocity), to each
        corner at the median disparity of the tracked features: the direction of the flow is
        what the detection check needs, and it hardly depends on the depth. None without a
        prior, without tracked features or with the check off.
        """
        f = self._feats
        if prior is None or not len(f) or self.cfg.min_flow_edge_ratio <= 0:
            return None
        disparity = f.left_ideal[:, 0] - f.right_ideal[:, 0]
        disparity = disparity[np.isfinite(disparity) & (disparity > 0)]
        if not len(disparity):
            return None
        offset = np.array([float(np.median(disparity)), 0.0])

        def flow(raw: np.ndarray) -> np.ndarray:
            ideal = calib.undistort_left(raw)
            pred = np.asarray(prior(ideal, ideal - offset)[0], np.float64).reshape(-1, 2)
            if pred.shape != raw.shape:
                return np.full(raw.shape, np.nan)
            return calib.distort_left(pred) - raw
        return flow

    def _track_existing(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                        prior: Prior | None, stats: TrackerStats
                        ) -> tuple[Correspondences, Correspondences, np.ndarray]:
        """
        Track the features of t1 into the pair t2 through every enabled check.

        Returns the quadruples (ideal and raw pixels) and the raw right points of their stereo
        KLT pass before the affine refinement ((N, 2) float64).
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
        alive = np.arange(n_prev)
        if cfg.min_eigen_ratio > 0 and n_prev:
            # Aperture check: on an edge-like window the flow along the edge would come from
            # the initial flow (the motion prior), not from the image.
            ok = eigen_ratio(prev_left, f.left_raw, win) >= cfg.min_eigen_ratio
            failed['aperture'] = int(np.count_nonzero(~ok))
            alive = alive[ok]
        if pred is not None and cfg.min_flow_edge_ratio_tracked > 0 and len(alive):
            # The same along the predicted flow, over the window the refinement will use.
            ok = flow_edge_ratio(prev_left, f.left_raw[alive],
                                 pred[0][alive] - f.left_raw[alive],
                                 cfg.affine_win_size_px) >= cfg.min_flow_edge_ratio_tracked
            failed['flow_aperture'] = int(np.count_nonzero(~ok))
            alive = alive[ok]
        npts['temporal_fwd'] = len(alive)
        # Photometric compensation: every KLT pass sees its second image mapped to the
        # brightness of its first (``photometric``; the images as given when they match). With
        # the prior, the windows at the features' positions in the four images give all maps.
        t_photo = clock()
        if pred is not None:
            self._photo.observe((prev_left, left, right, prev_right),
                                (f.left_raw[alive], pred[0][alive], pred[1][alive],
                                 f.right_raw[alive]))
        spent = clock() - t_photo
        ms['photometric'] += spent * 1e3
        t += spent
        left_m, spent = self._matched(prev_left, left, None, None, stats)
        t += spent
        cur_l = f.left_raw.copy()
        cur_l[alive], ok = lk_pass(prev_left, left_m, f.left_raw[alive],
                                   None if pred is None else pred[0][alive], levels, win, iters)
        ms['temporal_fwd'] = (clock() - t) * 1e3
        failed['temporal'] = int(np.count_nonzero(~ok))
        alive = alive[ok]

        t = clock()
        npts['temporal_bwd'] = len(alive)
        back, ok = lk_pass(left_m, prev_left, cur_l[alive], f.left_raw[alive],
                           REVERSE_PYRAMID_LEVELS, win, iters)
        ok &= round_trip_error(f.left_raw[alive], back) < cfg.fb_threshold_px
        ms['temporal_bwd'] = (clock() - t) * 1e3
        failed['fb'] = int(np.count_nonzero(~ok))
        alive = alive[ok]
        cur_l[alive] = self._refine(prev_left, left, f.left_raw[alive], cur_l[alive], stats)

        # 2. Stereo pass left(t2) -> right(t2) from the previous (or predicted) disparity; the
        #    disparity constraint (eq. 6) and range run before the reverse pass.
        t = clock()
        offset = (f.right_raw[alive] - f.left_raw[alive]).astype(np.float64)
        if pred is not None:
            predicted = pred[1][alive] - pred[0][alive]
            offset = np.where(np.isfinite(predicted), predicted, offset)
        npts['stereo_fwd'] = len(alive)
        right_m, spent = self._matched(left, right, cur_l[alive], cur_l[alive] + offset, stats)
        t += spent
        cur_r, ok = lk_pass(left, right_m, cur_l[alive], cur_l[alive] + offset,
                            cfg.predicted_pyramid_levels, win, iters)
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
        back, ok = lk_pass(right_m, left, cur_r, cur_l[alive], REVERSE_PYRAMID_LEVELS, win,
                           iters)
        ok &= round_trip_error(cur_l[alive], back) < cfg.lr_threshold_px
        failed['lr'] = int(np.count_nonzero(~ok))
        if not checks.disparity_constraint:
            rng = range_check()
            failed['disparity'] = int(np.count_nonzero(ok & ~rng))
            ok &= rng
        alive, cur_r, ideal_l, ideal_r = alive[ok], cur_r[ok], ideal_l[ok], ideal_r[ok]
        ms['stereo_bwd'] = (clock() - t) * 1e3
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
            back_r, ok = lk_pass(right, prev_right_m, cur_r, guess,
                                 cfg.predicted_pyramid_levels, win, iters)
            again = None
            if cfg.bicircular_mode == 'roundtrip':
                again = np.full_like(cur_r, np.nan)
                again[ok], ok2 = lk_pass(prev_right_m, right, back_r[ok], cur_r[ok],
                                         REVERSE_PYRAMID_LEVELS, win, iters)
                ok[ok] = ok2
            err = bicircular_error(cfg.bicircular_mode, cur_r, back_r, f.right_raw[alive], again)
            ok &= err < delta_d
            failed['bc'] = int(np.count_nonzero(~ok))
            alive, cur_r, ideal_l, ideal_r, ages, klt_r = (
                alive[ok], cur_r[ok], ideal_l[ok], ideal_r[ok], ages[ok], klt_r[ok])
            ms['bicircular'] = (clock() - t) * 1e3

        stats.n_tracked = len(alive)
        prev = f.take(alive)
        cur_l = cur_l[alive]
        corr = Correspondences(prev.left_ideal.copy(), prev.right_ideal.copy(), ideal_l.copy(),
                               ideal_r.copy(), prev.ids.copy(), ages.copy())
        raw = Correspondences(prev.left_raw.astype(np.float64),
                              prev.right_raw.astype(np.float64), cur_l.astype(np.float64),
                              cur_r.astype(np.float64), prev.ids.copy(), ages.copy())
        self._feats = FeatureSet(prev.ids, ages, cur_l, cur_r, ideal_l, ideal_r)
        return corr, raw, klt_r

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

    def _float(self, img: np.ndarray) -> np.ndarray:
        """float32 copy of a uint8 image, converted once per frame (the refinement samples it)."""
        for src, converted in self._floats:
            if src is img:
                return converted
        converted = img.astype(np.float32)
        self._floats = (self._floats + [(img, converted)])[-3:]
        return converted

    def _refine(self, img_from: np.ndarray, img_to: np.ndarray, pts_from: np.ndarray,
                pts_to: np.ndarray, stats: TrackerStats, stereo: bool = False) -> np.ndarray:
        """Affine refinement of matches (raw pixels) when configured, timed as ``affine``."""
        cfg = self.cfg
        if not cfg.affine_refinement or not len(pts_from):
            return pts_to
        t = CLOCK()
        horizontal = stereo and self._calib is not None and self._calib.kind == 'rectified'
        win = cfg.affine_stereo_win_size_px if stereo else cfg.affine_win_size_px
        out, _ = refine_affine(self._float(img_from), self._float(img_to), pts_from, pts_to,
                               win, cfg.affine_iterations, horizontal=horizontal,
                               step_px=cfg.affine_step_px)
        stats.timings_ms['affine'] = stats.timings_ms.get('affine', 0.0) + (CLOCK() - t) * 1e3
        return out.astype(pts_to.dtype)

    def _replenish(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                   stats: TrackerStats, prior: Prior | None = None) -> None:
        """Detect corners where features are missing and match them into the right image."""
        cfg, f = self.cfg, self._feats
        need = cfg.max_features - len(f)
        if need <= 0:
            return
        win, iters = cfg.win_size_px, cfg.max_iterations
        bcfg = self.bucketing_cfg
        size = (left.shape[1], left.shape[0])
        t = CLOCK()
        chosen = None
        if bcfg.enabled:
            if self._barren is None or self._barren.shape != (bcfg.rows, bcfg.cols):
                self._barren = np.zeros((bcfg.rows, bcfg.cols), np.int64)
            chosen = plan_detection(f.left_raw, need, size, bcfg, self._barren > 0)
            self._barren = np.maximum(self._barren - 1, 0)
        pts, found = detect_corners(left, f.left_raw, need, cfg, bcfg, chosen,
                                    self._expected_flow(prior, calib))
        stats.timings_ms['detection'] = (CLOCK() - t) * 1e3
        stats.n_detected = len(pts)
        if chosen is not None and len(pts):
            # Buckets searched without a corner are skipped for a while (not when the whole
            # image gave nothing: a black or covered frame says nothing about the scene).
            self._barren[chosen & (found.reshape(chosen.shape) == 0)] = BARREN_BUCKET_FRAMES
        if not len(pts):
            return
        submitted = pts
        if cfg.min_eigen_ratio > 0:
            pts = pts[eigen_ratio(left, pts, win) >= cfg.min_eigen_ratio]
            if not len(pts):
                return
        t = CLOCK()
        # Corners near a tracked feature start at its disparity (raw pixel offset) and need
        # few pyramid levels; the others are searched with the full pyramid.
        guided = np.zeros(len(pts), bool)
        guess = pts.copy()
        if len(f):
            d2 = ((pts[:, None, :] - f.left_raw[None, :, :]) ** 2).sum(axis=2)
            nearest = np.argmin(d2, axis=1)
            guided = d2[np.arange(len(pts)), nearest] <= NEIGHBOUR_RADIUS_PX ** 2
            guess = pts + (f.right_raw[nearest] - f.left_raw[nearest])
        pr = np.empty_like(pts)
        ok = np.zeros(len(pts), bool)
        stats.pass_points['new_stereo_fwd'] = len(pts)
        right_m, spent = self._matched(left, right, None, None, stats)
        t += spent
        for sel, levels in ((guided, cfg.predicted_pyramid_levels),
                            (~guided, cfg.pyramid_levels)):
            if sel.any():
                pr[sel], ok[sel] = lk_pass(left, right_m, pts[sel], guess[sel], levels, win,
                                           iters)
        pts, pr = pts[ok], pr[ok]
        il, ir = calib.undistort_left(pts), calib.undistort_right(pr)
        ok = disparity_in_range(calib, il, ir, cfg.min_disparity_px, cfg.max_disparity_px)
        if self.checks.disparity_constraint:
            ok &= disparity_constraint(calib, il, ir, cfg.disparity_y_threshold_px)
        pts, pr, il, ir = pts[ok], pr[ok], il[ok], ir[ok]
        stats.timings_ms['stereo_fwd'] += (CLOCK() - t) * 1e3
        t = CLOCK()
        stats.pass_points['new_stereo_bwd'] = len(pts)
        back, ok = lk_pass(right_m, left, pr, pts, REVERSE_PYRAMID_LEVELS, win, iters)
        ok &= round_trip_error(pts, back) < cfg.lr_threshold_px
        stats.timings_ms['stereo_bwd'] += (CLOCK() - t) * 1e3
        if cfg.affine_refinement and ok.any():
            pr[ok] = self._refine(left, right, pts[ok], pr[ok], stats, stereo=True)
            ir[ok] = calib.undistort_right(pr[ok])
        n = int(np.count_nonzero(ok))
        stats.n_added = n
        if chosen is not None and n:
            # Buckets whose corners all failed the stereo match are skipped for a while.
            tried = np.bincount(bucket_ids(submitted, size, bcfg), minlength=chosen.size)
            kept = np.bincount(bucket_ids(pts[ok], size, bcfg), minlength=chosen.size)
            self._barren[((tried > 0) & (kept == 0)).reshape(chosen.shape)] = \
                BARREN_BUCKET_FRAMES
        if not n:
            return
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        new = FeatureSet(ids, np.zeros(n, np.int64), pts[ok].astype(np.float32),
                         pr[ok].astype(np.float32), il[ok], ir[ok])
        self._feats = f.concat(new)
