"""
Frame-to-frame egomotion from stereo correspondences (Kitt et al., section III).

:class:`MotionEstimator` holds the filter state (the velocity and its covariance) and, for each
new set of correspondences between the previous and the current stereo pair, runs

1. the constant-velocity prediction ``y_k+1 = y_k + w_k`` (``P += Q``; Q per frame, or for the
   linear velocity ``vehicle.acceleration_std`` times the time step: not in the papers),
2. bucketing of the correspondences (section III-C), leaving out the features that were clear
   outliers of the accepted motion in the last ``ransac.max_outlier_streak`` frames (not in
   the papers: they keep features on moving vehicles out),
3. RANSAC with 3-point samples (section III-D), its inliers on the ground plane of the previous
   pair counted ``ransac.ground_weight`` times (not in the papers; see
   :mod:`~stereo_vo_ros.road.ground_plane`); after a reset of the velocity (the first pair, a loss,
   a gap) eq. 14 assumes ``ransac.startup_outlier_ratio``, i.e. more samples (not in the papers),
4. the final filter update on all inliers of the best sample (section III-E), then
   ``filter.robust_rounds`` updates with Cauchy weights from the residuals (not in the
   papers: the few badly tracked inliers are not symmetric and would bias the speed),

and returns a :class:`~stereo_vo_ros.records.MotionEstimate`. It runs on correspondences from any
front end (the KLT tracker, a simulation, an .npz file) and imports no ROS.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from .camera import StereoCalibration
from .filters import make_filter
from .motion import TransferModel, transform_from_velocity
from .ransac import BatchedMeasurement, ransac, reprojection_errors
from ..config import Config, RansacConfig
from ..records import Correspondences, MotionEstimate, TrackingStatus
from ..road.ground_plane import ground_mask
from ..tracking import bucketing

LOG = logging.getLogger(__name__)
#: Coasting inflates the velocity variances up to this many times the initial ones.
COAST_VARIANCE_CAP = 1.0
#: A feature is a clear outlier when its error exceeds this many inlier thresholds.
OUTLIER_STREAK_FACTOR = 2.0


def epipolar_corrected(corr: Correspondences, calib_prev: StereoCalibration,
                       calib_cur: StereoCalibration) -> Correspondences:
    """
    Return the correspondences with both stereo pairs moved onto their epipolar geometry.

    The point-line-point transfer treats the previous pair as exact and predicts a current
    pair that satisfies the epipolar constraint, while measured matches miss it by tracking
    noise and rectification residuals (a mean vertical stereo offset of about -0.1 px on the
    KITTI and EuRoC clips). Left uncorrected, that offset is explained by a rotation: a
    camera at rest drifts. Each pair is moved to the nearest pair (sum of squared pixel
    displacements) that satisfies ``x_right^T F x_left = 0`` (Hartley-Sturm optimal
    correction, ``cv2.correctMatches``); for rectified images that is the mean of both rows.

    Parameters
    ----------
    corr : Correspondences
        Ideal pixel coordinates (N, 2) of the four views; not modified.
    calib_prev, calib_cur : StereoCalibration
        Calibration of the previous and of the current pair.

    Returns
    -------
    Correspondences
        New arrays; ids and ages shared.

    """
    def correct(calib: StereoCalibration, left: np.ndarray, right: np.ndarray):
        if len(left) == 0:
            return left.copy(), right.copy()
        if calib.kind == 'rectified':  # horizontal epipolar lines: the closed form
            a, b = left.copy(), right.copy()
            a[:, 1] = b[:, 1] = 0.5 * (left[:, 1] + right[:, 1])
            return a, b
        F = calib.fundamental()
        a, b = cv2.correctMatches(F, np.ascontiguousarray(left[None], np.float64),
                                  np.ascontiguousarray(right[None], np.float64))
        a, b = a[0], b[0]
        bad = ~(np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1))
        a[bad], b[bad] = left[bad], right[bad]
        return a, b

    prev_left, prev_right = correct(calib_prev, corr.prev_left, corr.prev_right)
    cur_left, cur_right = correct(calib_cur, corr.cur_left, corr.cur_right)
    return Correspondences(prev_left, prev_right, cur_left, cur_right, corr.ids, corr.ages)


_ONES8 = np.ones(8)
#: (4, 2): gain (n, 4) @ it = the sums of the left (u, v) and right (u, v) gains.
_PAIR_SUMS = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])

#: Median of |e| for a 2-D error e ~ N(0, s^2 I), in units of s (Rayleigh distribution).
RAYLEIGH_MEDIAN = np.sqrt(2.0 * np.log(2.0))
#: Floor of the residual sigma of the robust reweighting (pixels): exact data keeps weight ~1.
MIN_ROBUST_SIGMA_PX = 0.05


def residual_sigma(inlier_errors: np.ndarray) -> float:
    """
    Per-axis residual scale (pixels) of Euclidean 2-D errors.

    Their median over the Rayleigh median (1.177 sigma); ``inf`` without errors.
    """
    return _median(inlier_errors) / RAYLEIGH_MEDIAN if len(inlier_errors) else np.inf


def _median(values: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D array (same value, NaN with a NaN), in a third the time."""
    n = len(values)
    k = n // 2
    part = np.partition(values, [k - 1, k, -1] if n % 2 == 0 else [k, -1])
    if np.isnan(part[-1]):
        return float('nan')
    return float(part[k] if n % 2 else (part[k - 1] + part[k]) / 2.0)


def adaptive_gate(inlier_errors: np.ndarray, cfg: RansacConfig) -> float:
    """
    Inlier threshold from the residual scale of a hypothesis (pixels).

    The threshold is ``cfg.adaptive_sigmas`` times :func:`residual_sigma` clipped to
    [``cfg.min_inlier_threshold_px``, ``cfg.inlier_threshold_px``].
    """
    sigma = residual_sigma(inlier_errors)
    gate = cfg.adaptive_sigmas * sigma
    if gate != gate:  # NaN stays NaN, as with np.clip
        return gate
    return float(min(max(gate, cfg.min_inlier_threshold_px), cfg.inlier_threshold_px))


class MotionEstimator:
    """
    Egomotion filter: the state and its update from correspondences.

    Parameters
    ----------
    config : Config
        Uses the ``filter``, ``ransac``, ``bucketing`` and ``pipeline`` sections.

    Attributes
    ----------
    mean : (6,) float64 current velocity estimate (m/s, rad/s) in the previous left frame.
    cov : (6, 6) float64 its covariance.

    """

    def __init__(self, config: Config) -> None:
        self.config = config
        self.filter = make_filter(config.filter)
        self.rng = np.random.default_rng(config.ransac.seed)
        self.ground_rng = np.random.default_rng([config.ransac.seed, 1])
        #: Feature id -> consecutive frames as a clear outlier of the accepted motion.
        self.outlier_streak: dict[int, int] = {}
        self._process_noise: tuple = (None, None)
        self.reset()

    # -- state -------------------------------------------------------------------------
    def initial_covariance(self) -> np.ndarray:
        """Prior covariance at start and after loss (6, 6)."""
        f = self.config.filter
        return np.diag([f.initial_velocity_std ** 2] * 3 +
                       [np.deg2rad(f.initial_angular_std_deg) ** 2] * 3)

    def process_noise(self, dt: float | None = None) -> np.ndarray:
        """
        Q (6, 6): the random walk of the velocities from one pair to the next.

        Per frame (``filter.velocity_process_noise``, ``filter.angular_process_noise_deg``);
        with ``vehicle.acceleration_std`` set and the time step ``dt`` (s) given, the linear
        velocities' std is that acceleration times ``dt`` instead.
        """
        f = self.config.filter
        accel = self.config.vehicle.acceleration_std
        v_std = accel * dt if accel > 0 and dt is not None and dt > 0 else \
            f.velocity_process_noise
        key = (v_std, f.angular_process_noise_deg)
        if self._process_noise[0] != key:  # the parameters can change at run time
            self._process_noise = (key, np.diag([v_std ** 2] * 3 +
                                                [np.deg2rad(f.angular_process_noise_deg) ** 2] *
                                                3))
        return self._process_noise[1].copy()

    def reset(self, velocity: np.ndarray | None = None) -> None:
        """Forget the motion: zero (or given) velocity with the initial covariance."""
        self.mean = np.zeros(6) if velocity is None else np.asarray(velocity, np.float64).copy()
        self.cov = self.initial_covariance()
        self.outlier_streak = {}
        #: No estimate since the reset: RANSAC draws more samples (``startup_outlier_ratio``).
        self.fresh = True

    def velocity_unknown(self) -> bool:
        """
        Whether the linear velocity is unknown: its largest std above a bound.

        The bound is ``pipeline.prior_max_velocity_std`` (m/s); the velocity is unknown at the
        start, after a long loss or gap, and after two coasted pairs (one keeps it known at the
        defaults). The pipeline then tracks without the motion prior.
        """
        std = np.sqrt(max(float(np.max(np.diag(self.cov)[:3])), 0.0))
        return bool(std > self.config.pipeline.prior_max_velocity_std)

    def predict(self, dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the constant-velocity prediction (mean (6,), cov (6, 6)); no state change.

        ``dt``: the time to the next pair (s), for ``vehicle.acceleration_std``.
        """
        cov = self.cov + self.process_noise(dt)
        return self.mean.copy(), cov

    def coast(self, inflation: float | None = None, dt: float | None = None) -> None:
        """
        Keep the predicted velocity and inflate its covariance (no usable measurements).

        The covariance is multiplied by ``inflation`` (default
        ``pipeline.lost_covariance_inflation``); with ``vehicle.acceleration_std`` set only
        the angular part is, and the linear velocity widens by the vehicle's acceleration over
        ``dt``, the time since the last pair (s), as in :meth:`predict`.
        """
        mean, cov = self.predict(dt)
        factor = self.config.pipeline.lost_covariance_inflation if inflation is None \
            else inflation
        self.mean = mean
        if factor > 1:
            if self.config.vehicle.acceleration_std > 0:
                # A vehicle's speed cannot change faster than it accelerates: a pair without
                # an estimate widens the linear velocity by the process noise only.
                s = np.sqrt(np.array([1.0] * 3 + [factor] * 3))
                cov = cov * np.outer(s, s)
            else:
                cov = cov * factor
            # Cap every standard deviation at the initial one (after a loss the velocity is
            # no better known than at the start; a wider prior stops RANSAC hypotheses from
            # converging) with a congruence D C D (D diagonal, <= 1): unlike an element-wise
            # minimum it keeps C positive definite.
            cap = np.diag(self.initial_covariance()) * COAST_VARIANCE_CAP
            d = np.sqrt(np.minimum(1.0, cap / np.maximum(np.diag(cov), 1e-300)))
            cov = cov * np.outer(d, d)
        self.cov = 0.5 * (cov + cov.T)

    # -- update ------------------------------------------------------------------------
    def estimate(self, corr: Correspondences, calib: StereoCalibration, dt: float,
                 calib_cur: StereoCalibration | None = None,
                 image_size: tuple[int, int] | None = None) -> MotionEstimate:
        """
        Estimate the motion between the previous and the current pair.

        Parameters
        ----------
        corr : Correspondences
            Ideal pixels previous left/right -> current left/right.
        calib : StereoCalibration
            Calibration of the previous pair.
        dt : float
            Time between the pairs (s), > 0.
        calib_cur : StereoCalibration, optional
            Calibration of the current pair when it changed.
        image_size : tuple of int, optional
            (width, height) for bucketing; default the calibration's.

        Returns
        -------
        MotionEstimate. On OK the filter state is updated; otherwise the state coasts (the
        prediction is kept with an inflated covariance) and the estimate carries it. A
        numerically singular solve re-initialises the velocity and reports DEGENERATE.

        """
        try:
            return self._estimate(corr, calib, dt, calib_cur, image_size)
        except np.linalg.LinAlgError as exc:  # numerically degenerate geometry or state
            why = f'motion estimate failed (LinAlgError: {exc}); velocity re-initialised'
            LOG.warning(why)
            self.reset()
            return self._fail(TrackingStatus.DEGENERATE, dt, np.zeros(len(corr), bool), 0, 0,
                              why)

    def _estimate(self, corr: Correspondences, calib: StereoCalibration, dt: float,
                  calib_cur: StereoCalibration | None = None,
                  image_size: tuple[int, int] | None = None) -> MotionEstimate:
        """Body of :meth:`estimate` (which turns a singular solve into DEGENERATE)."""
        cfg = self.config
        prior_mean, prior_cov = self.predict(dt)
        n_all = len(corr)
        used = np.zeros(n_all, bool)
        # A row is finite when its sum is (NaN and inf propagate): one product, not 8 columns.
        finite = np.isfinite(np.hstack([corr.prev_left, corr.prev_right, corr.cur_left,
                                        corr.cur_right]) @ _ONES8) if n_all else used
        candidates = watched = np.flatnonzero(finite)
        streak = cfg.ransac.max_outlier_streak
        if streak > 0 and cfg.ransac.enabled and corr.ids.size and self.outlier_streak:
            out_ids = [i for i, n in self.outlier_streak.items() if n >= streak]
            if out_ids:
                left_out = np.isin(corr.ids[candidates], out_ids)
                if np.count_nonzero(~left_out) >= max(cfg.pipeline.min_features, 4):
                    candidates = candidates[~left_out]  # else too few would be left: keep all
        if candidates.size and cfg.bucketing.enabled:
            size = image_size or calib.size
            prio = corr.ages[candidates] if corr.ages.size else None
            keep = bucketing.select(corr.cur_left[candidates], size, cfg.bucketing, prio)
            candidates = candidates[keep]
        if candidates.size < max(cfg.pipeline.min_features, 4) or not dt > 0:
            return self._fail(TrackingStatus.DEGENERATE, dt, used, 0, 0,
                              f'{candidates.size} usable correspondences (need '
                              f'{cfg.pipeline.min_features})' if dt > 0 else f'dt = {dt!r} s')
        sub = corr.subset(candidates)
        if cfg.filter.epipolar_correction:
            sub = epipolar_corrected(sub, calib, calib_cur or calib)
        model = TransferModel(calib, sub.prev_left, sub.prev_right, dt, calib_cur)
        z = np.hstack([sub.cur_left, sub.cur_right])  # (n, 4)
        sigma2 = cfg.filter.pixel_noise_px ** 2
        if cfg.filter.propagate_previous_noise:
            # The previous observations are noisy too: their noise reaches each prediction
            # through the transfer (errors in variables). R stays diagonal.
            gain = model.previous_noise_gain(prior_mean)
        else:
            gain = np.zeros_like(z)
        noise_var = sigma2 * (1.0 + gain)  # (n, 4)
        scale = np.sqrt(1.0 + 0.5 * (gain @ _PAIR_SUMS))  # (n, 2): left and right image
        hypotheses = 0
        inl = np.ones(len(candidates), bool)
        gate = cfg.ransac.inlier_threshold_px
        if cfg.ransac.enabled:
            weights = None
            if cfg.ransac.ground_weight != 1.0:
                on_ground = ground_mask(model.points(), cfg.ransac, self.ground_rng)
                weights = np.where(on_ground, cfg.ransac.ground_weight, 1.0)
            rcfg = cfg.ransac
            if self.fresh:
                rcfg = dataclasses.replace(rcfg, outlier_ratio=max(
                    rcfg.outlier_ratio, rcfg.startup_outlier_ratio))
            res = ransac(model, z, prior_mean, prior_cov, self.filter, noise_var, rcfg,
                         self.rng, scale, weights)
            inl, hypotheses = res.inliers, res.hypotheses
            if cfg.ransac.adaptive_threshold and inl.sum() >= cfg.pipeline.min_inliers:
                gate = adaptive_gate(res.errors[inl], cfg.ransac)
                inl = res.errors < gate
        if inl.sum() < cfg.pipeline.min_inliers:
            return self._fail(TrackingStatus.TOO_FEW_INLIERS, dt, used, hypotheses, 0,
                              f'{int(inl.sum())} inliers of {len(candidates)} (need '
                              f'{cfg.pipeline.min_inliers})')
        mean, cov, iters = self._final_update(prior_mean, prior_cov, model, z, noise_var, scale,
                                              inl)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            return self._fail(TrackingStatus.DEGENERATE, dt, used, hypotheses, iters,
                              'non-finite filter update')
        speed = float(np.linalg.norm(mean[:3]))
        if speed > cfg.pipeline.max_speed:
            return self._fail(TrackingStatus.DEGENERATE, dt, used, hypotheses, iters,
                              f'implausible speed {speed:.1f} m/s')
        if cfg.ransac.enabled:
            # Report the inliers of the final estimate (what the motion explains).
            err = reprojection_errors(model, mean[None], z, scale)[0]
            inl = err < gate
        used[candidates[inl]] = True
        self.mean, self.cov = mean, cov
        self.fresh = False
        self._count_outliers(corr, watched, calib, dt, calib_cur, gate)
        return MotionEstimate(velocity=mean.copy(), covariance=cov.copy(),
                              T_prev_cur=transform_from_velocity(mean, dt), inliers=used,
                              iterations=iters, status=TrackingStatus.OK, hypotheses=hypotheses)

    def fuse(self, velocity: np.ndarray, covariance: np.ndarray, gate_chi2: float,
             components: np.ndarray | None = None) -> bool:
        """
        Fuse an independent measurement of (some components of) the velocity state.

        A Kalman update with ``H`` the rows ``components`` of the identity.

        Parameters
        ----------
        velocity : np.ndarray
            (6,) measured state (m/s, rad/s, previous left frame), e.g. the road alignment's.
        covariance : np.ndarray
            (6, 6) its covariance.
        gate_chi2 : float
            The measurement is rejected (state unchanged) when its squared Mahalanobis distance
            to the current estimate, over both covariances, is not below this.
        components : np.ndarray, optional
            Indices (k,) of the state components measured (default all six).

        Returns
        -------
        bool: whether it was fused.

        """
        idx = np.arange(6) if components is None else np.asarray(components, int)
        return self.fuse_linear(np.eye(6)[idx],
                                np.asarray(velocity, np.float64)[idx] - self.mean[idx],
                                np.asarray(covariance)[np.ix_(idx, idx)], gate_chi2)

    def fuse_linear(self, H: np.ndarray, innovation: np.ndarray, R: np.ndarray,
                    gate_chi2: float) -> bool:
        """
        Kalman update of the velocity state with a linear(ised) measurement.

        Parameters
        ----------
        H : np.ndarray
            (k, 6) measurement rows.
        innovation : np.ndarray
            (k,) measured minus predicted values (``z - h(mean)``).
        R : np.ndarray
            (k, k) measurement covariance.
        gate_chi2 : float
            The measurement is rejected (state unchanged) when its squared Mahalanobis distance
            ``innovation^T S^-1 innovation`` is not below this.

        Returns
        -------
        bool: whether it was fused.

        """
        H = np.asarray(H, np.float64).reshape(-1, 6)
        innovation = np.asarray(innovation, np.float64).reshape(-1)
        R = np.asarray(R, np.float64).reshape(len(innovation), len(innovation))
        PHt = self.cov @ H.T  # (6, k)
        S = H @ PHt + R
        try:
            m2 = float(innovation @ np.linalg.solve(S, innovation))
            gain = np.linalg.solve(S, PHt.T).T  # P H^T S^-1 (S symmetric)
        except np.linalg.LinAlgError:
            return False
        if not (np.isfinite(m2) and m2 < gate_chi2 and np.all(np.isfinite(gain))):
            return False
        self.mean = self.mean + gain @ innovation
        I_KH = np.eye(6) - gain @ H
        cov = I_KH @ self.cov @ I_KH.T + gain @ R @ gain.T  # Joseph form
        self.cov = 0.5 * (cov + cov.T)
        return True

    def _final_update(self, prior_mean: np.ndarray, prior_cov: np.ndarray,
                      model: TransferModel, z: np.ndarray, noise_var: np.ndarray,
                      scale: np.ndarray, inl: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """
        Filter update on the inliers, robustly reweighted (``filter.robust_loss``).

        The first update is Kitt et al.'s (section III-E). With the Cauchy loss, each further round
        computes every inlier's reprojection error ``e`` (pixels, scaled as RANSAC's) under the
        latest estimate, ``sigma`` from them (:func:`residual_sigma`, as the adaptive gate), and
        updates again from the prior with each inlier's variances divided by its weight
        ``1 / (1 + (e / (robust_scale_sigmas * sigma))^2)``. A round's first step reuses the
        last linearisation of the round before (same prior, same measurements: only the weights
        differ), and an iterated filter goes on from there until it converges, rather than
        linearising at the prior again. Returns the mean (6,), covariance (6, 6) and iterations
        of the last update.
        """
        fcfg = self.config.filter
        idx = np.flatnonzero(inl)
        h = BatchedMeasurement(model, index=idx[None])
        z_in, var = z[idx].reshape(1, -1), noise_var[idx]
        out = self.filter.update(prior_mean[None], prior_cov, h, z_in, var.reshape(1, -1))
        rounds = fcfg.robust_rounds if fcfg.robust_loss == 'cauchy' else 0
        for _ in range(rounds):
            if not np.all(np.isfinite(out.mean[0])):
                break  # the caller reports the non-finite update
            err = reprojection_errors(model, out.mean, z, scale, idx)[0]
            sigma = max(residual_sigma(err), MIN_ROBUST_SIGMA_PX)
            weight = 1.0 / (1.0 + (err / (fcfg.robust_scale_sigmas * sigma)) ** 2)
            out = self.filter.update(prior_mean[None], prior_cov, h, z_in,
                                     (var / weight[:, None]).reshape(1, -1),
                                     start=out.linearization)
        return out.mean[0], out.cov[0], int(out.iterations[0])

    def _count_outliers(self, corr: Correspondences, watched: np.ndarray,
                        calib: StereoCalibration, dt: float,
                        calib_cur: StereoCalibration | None, gate: float) -> None:
        """
        Update each feature's streak of frames as a clear outlier of the accepted motion.

        Every finite correspondence (indices ``watched`` into ``corr``) counts, also those
        bucketing or an earlier streak left out: a feature whose error (pixels) is above
        ``OUTLIER_STREAK_FACTOR * gate`` extends its streak, one below ``gate`` ends it, one in
        between keeps it. Features no longer tracked are forgotten. The errors are not scaled
        by the previous pair's noise as RANSAC's are: a near vehicle's large scale kept its
        features in (rendered highway seed 3 locked onto it, 39 % t_rel), and the scale costs
        0.5 ms.
        """
        cfg = self.config.ransac
        if cfg.max_outlier_streak <= 0 or not cfg.enabled or not corr.ids.size or \
                not watched.size:
            self.outlier_streak = {}
            return
        corr = corr.subset(watched)
        model = TransferModel(calib, corr.prev_left, corr.prev_right, dt, calib_cur)
        err = reprojection_errors(model, self.mean[None],
                                  np.hstack([corr.cur_left, corr.cur_right]))[0]
        old = self.outlier_streak
        streak = {}
        clear = ~(err < gate * OUTLIER_STREAK_FACTOR)  # NaN and inf count as outliers
        kept = clear | (err >= gate)  # the others end their streak
        for fid, is_clear in zip(corr.ids[kept].tolist(), clear[kept].tolist()):
            streak[fid] = old.get(fid, 0) + is_clear
        self.outlier_streak = streak

    def _fail(self, status: TrackingStatus, dt: float, used: np.ndarray, hypotheses: int,
              iters: int, why: str) -> MotionEstimate:
        LOG.debug('motion estimate failed: %s (%s)', status.value, why)
        self.coast(dt=dt)
        T = transform_from_velocity(self.mean, dt) if dt > 0 else np.eye(4)
        return MotionEstimate(velocity=self.mean.copy(), covariance=self.cov.copy(),
                              T_prev_cur=T, inliers=used, iterations=iters, status=status,
                              hypotheses=hypotheses, message=why)
