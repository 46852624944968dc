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
taken from the tracker's 2-D stereo KLT match before that refinement (or, without it, measured
again: :func:`measure_rows`), and the slide along the row that the row error caused is undone
(:func:`row_coupling`). A tracker that refined along the rig's epipolar line (the rows this
estimate expects) would make the slide correction unnecessary.

The error model and the per-pair measurements are in :mod:`.rig_measurement`, the refined
calibration's CameraInfo fields and YAML in :mod:`.rig_camera_info`; their public names are
re-exported here.
"""

from __future__ import annotations

import functools
import logging

import numpy as np
from scipy.special import gammaincinv

from .camera import StereoCalibration
from .rig_camera_info import camera_info_yaml, refined_camera_infos
from .rig_measurement import (apply_homography, initial_points, measure_pair, measure_rows,
                              moved_right_points, N_PARAMS, offsets_at_centre, PairMeasurement,
                              PARAMETERS, pinned_rows, rig_jacobian, right_homography,
                              rotation_zxy, row_coupling, ROW_GATE_PX)
from ..config import RigConfig
from ..records import Correspondences, RigEstimate

__all__ = ['BLOCKS', 'CHI2_999', 'MAX_REJECTIONS', 'N_PARAMS', 'PARAMETERS', 'PairMeasurement',
           'RigCalibrator', 'apply_homography', 'camera_info_yaml', 'chi2_quantile',
           'initial_points', 'measure_pair', 'measure_rows', 'offsets_at_centre', 'pinned_rows',
           'refined_camera_infos', 'right_homography', 'rig_jacobian', 'rotation_zxy',
           'row_coupling']

LOG = logging.getLogger(__name__)

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


# -- the significance test of the correction ------------------------------------------------------
@functools.lru_cache(maxsize=32)
def chi2_quantile(probability: float, dof: int) -> float:
    """Quantile of the chi-square distribution (``scipy.stats.chi2.ppf``, without its import)."""
    return 2.0 * float(gammaincinv(0.5 * dof, probability))


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
        #: Focal length (pixels) of the right camera the prior is built for (None: none seen yet;
        #: kept by ``reset``, taken again when another calibration is seen).
        self._focal_px: float | None = None
        self.reset()

    def prior_covariance(self) -> np.ndarray:
        """
        Covariance (5, 5) of the rig error before any data (from the config).

        Roll, pitch and the focal ratio are independent. Yaw and the disparity offset are
        not: a yaw shifts every disparity by f yaw and those near the left and right borders by
        a further f yaw ((u - cx) / f)^2 (f the focal length, pixels), and the prior takes that
        border term and the disparity at the principal point (f yaw plus the offset) as
        independent, with the stds ``rig.prior_yaw_std_deg`` (times f) and
        ``rig.prior_disparity_offset_std_px``. A rectified rig's border term comes from what
        its rectification left (on both KITTI clips the refinement ends at 0.18-0.24 deg), its
        disparity at the centre from its principal points and baseline: with yaw and offset
        independent instead, a border term of that size came with a prior disparity error of
        the same size at the centre, and the estimate crept towards the border term over
        hundreds of pairs. Until a calibration was seen (its focal length) yaw and offset are
        independent.
        """
        c = self.cfg
        a = np.deg2rad(c.prior_angle_std_deg) ** 2
        yaw = np.deg2rad(c.prior_yaw_std_deg)
        P = np.diag([a, a, yaw ** 2, c.prior_focal_ratio_std ** 2,
                     c.prior_disparity_offset_std_px ** 2])
        if self._focal_px is not None:
            border = self._focal_px * yaw  # pixels
            P[4, 4] += border ** 2  # offset = centre disparity - f yaw
            P[2, 4] = P[4, 2] = -border * yaw
        return P

    def _see_calibration(self, calib: StereoCalibration) -> None:
        """Take the focal length of the prior from ``calib`` (its covariance, before any data)."""
        f = float(calib.K_right[0, 0])
        if f != self._focal_px:
            self._focal_px = f
            if self.updates == 0 and self.rejected == 0:
                self.cov = self.prior_covariance()

    def reset(self) -> None:
        """Forget the estimate: zero error with the prior covariance."""
        self.theta = np.zeros(N_PARAMS)
        self.cov = self.prior_covariance()
        self.updates = 0
        self.rejected = 0
        self._applied = [False] * len(BLOCKS)
        #: The state ``applied`` last tested and its result (``applied``).
        self._applied_cache: tuple | None = None
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
        #: The correction a measurement is linearised at instead of ``applied`` (None: that).
        self._linearised_at: np.ndarray | None = None

    # -- correction ----------------------------------------------------------------------------
    def homography(self, calib: StereoCalibration) -> np.ndarray:
        """(3, 3) map from calibrated to measured right pixels of ``calib`` (the estimate)."""
        return self._homographies(calib)[0]

    def homography_inverse(self, calib: StereoCalibration) -> np.ndarray:
        """(3, 3) map from measured to corrected (calibrated) right pixels of ``calib``."""
        return self._homographies(calib)[1]

    def _homographies(self, calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
        theta = self._correction()[0]
        key = (id(calib), theta.tobytes())
        if self._H_cache is None or self._H_cache[0] != key:
            H = right_homography(calib.K_right, theta)
            self._H_cache = (key, H, np.linalg.inv(H))
        return self._H_cache[1], self._H_cache[2]

    def active(self) -> bool:
        """Whether the correction is applied (enabled and away from zero)."""
        return self.cfg.enabled and self._correction()[1]

    def applied(self) -> np.ndarray:
        """
        Return the correction in use (5,): the blocks of the estimate that differ from zero.

        Each block of ``BLOCKS`` is applied once its squared Mahalanobis distance from zero
        exceeds the ``rig.apply_probability`` quantile of chi-square, and stays applied; until
        then it is zero. On an exact rig the estimate wanders within its uncertainty (about
        0.01-0.02 px of disparity after 150 pairs), which already costs 0.05-0.1 % of t_rel on
        a city render.

        The test (which latches) runs once per state of the estimate: again only when
        ``theta``, ``cov``, the grid of ``rig.apply_min_px`` or the thresholds changed since
        the last call (on an unchanged state it would repeat the last result).
        """
        return self._correction()[0].copy()

    def _correction(self) -> tuple[np.ndarray, bool]:
        """Return ``applied`` (not a copy: not to be changed) and whether it differs from zero."""
        if self._linearised_at is not None:
            return self._linearised_at, bool(np.any(self._linearised_at != 0.0))
        key = (np.asarray(self.theta).tobytes(), np.asarray(self.cov).tobytes(),
               self._grid_jacobian is None, self.cfg.apply_probability, self.cfg.apply_min_px)
        if self._applied_cache is None or self._applied_cache[0] != key:
            out = self._test_blocks()
            self._applied_cache = (key, out, bool(np.any(out != 0.0)))
        return self._applied_cache[1], self._applied_cache[2]

    def _test_blocks(self) -> np.ndarray:
        """Latch the blocks that differ from zero significantly; the correction (5,)."""
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
        if not self.active():
            return right
        return moved_right_points(self.homography(calib), None, left, right,
                                  calib.kind == 'rectified', coupling)

    def _correct(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration,
                 coupling: np.ndarray | None = None) -> np.ndarray:
        H, H_inv = self._homographies(calib)
        return moved_right_points(H, H_inv, left, right, calib.kind == 'rectified', coupling)

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
               coupling: tuple[np.ndarray, np.ndarray] | None = None,
               stereo_rows: np.ndarray | None = None) -> str:
        """
        Measure the rig error on one pair's inliers and fuse it.

        The pair is measured at the correction in use; with ``rig.update_iterations`` above 1
        it is measured again at the correction the estimate then applies and fused again from
        the same prior (an iterated update: the measurement's robust weights depend on where
        it is linearised, and taken at the correction in use they pass over the matches a large
        error moves most).

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
        stereo_rows : np.ndarray, optional
            (N,) rows (pixels) of the current right points as a free 2-D stereo match found
            them (the tracker's stereo KLT pass, before its refinement pinned the rows; NaN
            where unknown). Given, they replace ``measure_rows`` for the pinned inliers.

        Returns
        -------
        str: ``updated``, ``rejected`` (gated out), ``frozen`` (standing still, too few
        inliers, no usable measurement), ``skipped`` (``rig.measure_every``) or ``off``.

        """
        cfg = self.cfg
        if not cfg.enabled:
            self.last = 'off'
            return self.last
        self._see_calibration(calib_cur)
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
        if stereo_rows is not None:
            stereo_rows = np.asarray(stereo_rows, np.float64)[inliers]
        args = (raw, calib_prev, calib_cur, T_prev_cur, images, win_size_px, coupling,
                stereo_rows)
        meas = self._measure(*args)
        if meas is None:
            self.last = 'frozen'
            return self.last
        prior, at = (self.theta.copy(), self.cov.copy()), self.applied()
        self.last = 'updated' if self._fuse(meas) else 'rejected'
        for _ in range(cfg.update_iterations - 1 if self.last == 'updated' else 0):
            # Iterated: measured again at the correction the estimate applies (``applied``),
            # fused again from the same prior; not while that correction stays where it was.
            posterior, last_at, at = (self.theta, self.cov), at, self.applied()
            if np.array_equal(at, last_at):
                break
            (self.theta, self.cov), self._linearised_at = prior, at
            try:
                again = self._measure(*args)
            finally:
                self._linearised_at = None
            if again is None:
                self.theta, self.cov = posterior
                break
            self._fused(again.information, again.gradient, self.cov)  # (the first was gated)
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

    def _measure(self, raw: Correspondences, calib_prev: StereoCalibration,
                 calib_cur: StereoCalibration, T_prev_cur: np.ndarray,
                 images: tuple[np.ndarray, np.ndarray] | None, win_size_px: int,
                 coupling: tuple[np.ndarray, np.ndarray] | None,
                 stereo_rows: np.ndarray | None) -> PairMeasurement | None:
        """
        Measure the rig error on a pair's inliers ``raw``, linearised at the correction in use.

        ``update``'s arguments, cut to the inliers. Returns the measurement with its gradient
        referred to the estimate ``theta``, or None when it is unusable.
        """
        cfg = self.cfg
        sub = self.corrected(raw, calib_prev, calib_cur, coupling)
        used = np.ones((len(raw), 8), bool)
        used[:, 3] = ~pinned_rows(calib_prev, raw.prev_left, raw.prev_right)
        pinned = np.flatnonzero(pinned_rows(calib_cur, raw.cur_left, raw.cur_right))
        used[pinned, 7] = False
        rows = None
        if pinned.size and (stereo_rows is not None or images is not None):
            start = self._unpinned(raw.cur_left[pinned], raw.cur_right[pinned], calib_cur)
            if stereo_rows is not None:
                rows = stereo_rows[pinned]
                with np.errstate(invalid='ignore'):
                    rows[~(np.abs(rows - start[:, 1]) < ROW_GATE_PX)] = np.nan
            else:
                rows = measure_rows(images[0], images[1], raw.cur_left[pinned], start,
                                    win_size_px)[:, 1]
        if rows is not None:
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
            return None
        # The pair measured the error left after the correction in use; refer it to the estimate.
        meas.gradient = meas.gradient - meas.information @ (self.theta - self.applied())
        return meas

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
        return self._fused(I, g, P)

    def _fused(self, info: np.ndarray, g: np.ndarray, P: np.ndarray) -> bool:
        """Fuse information ``info`` and gradient ``g`` (no gate) into an estimate of cov ``P``."""
        info_post = np.linalg.inv(P) + info
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
