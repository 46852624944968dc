"""
The images-to-odometry pipeline: one object, one call per stereo pair.

``StereoOdometry(config).process(frame) -> OdometryResult`` runs

    tracker (Huang et al.) -> rig correction -> bucketing -> RANSAC + ISPKF (Kitt et al.) -> rig
    refinement -> rolling-vehicle prior (fused) -> road alignment (fused) -> pose integration

What the pose of a pair does not need comes after it: ``process`` returns the pose, and the
rest (the rig refinement's update, waiting for the tracker's new corners) runs at the start of
the next call or when the caller asks for it (``settle``, which the ROS node calls after
publishing). Results do not depend on which.

It handles the first frame, lost tracking (re-detection, constant-velocity coasting with an
inflated covariance for at most ``pipeline.max_lost_time_s``), calibration that changes between
frames, gaps (the time step comes from the stamps) and stamps that do not increase. It imports
no ROS; the node and the offline tools both drive it.

Frames: ``world`` is the optical frame of the first left camera (x right, y down, z forward);
``T_world_cam`` is the pose of the current left camera in it.
"""

from __future__ import annotations

import functools
import logging
import time

import numpy as np

from .allocator import keep_freed_memory
from .config import Config
from .errors import ImageError
from .estimation.camera import StereoCalibration
from .estimation.estimator import MotionEstimator
from .estimation.motion import rotation_from_rates, TransferModel, transform_from_velocity
from .estimation.rig_calibration import apply_homography, RigCalibrator
from .parallel import auto_threads, Workers
from .records import Correspondences, OdometryResult, StereoFrame, TrackingStatus
from .road.ground_plane import fit_ground_plane, road_speed, triangulate
from .road.road_alignment import RoadAligner, RoadImages, RoadPlane
from .road.vehicle_motion import lateral_constraint
from .tracking.tracker import PendingTrack, StereoTracker

LOG = logging.getLogger(__name__)
#: What a worker process does as it starts: import the replenishment it runs and the modules of
#: what it is sent (the motion prior is this module's), and share equal calibrations.
WORKER_MODULES = ('stereo_vo_ros.tracking.replenish', __name__,
                  'stereo_vo_ros.estimation.camera:share_unpickled_calibrations')

#: A stamp this far (s) before the previous one means the input restarted (e.g. a looping bag).
RESTART_JUMP_S = 1.0
#: Position / angle variance (m^2, rad^2) added per second while LOST.
LOST_VARIANCE_RATE = (1.0, np.deg2rad(10.0) ** 2)
#: Road speed search: slower than this (m/s) counts as at rest, and tracking keeps no prior.
ROAD_MIN_SPEED = 1.0
#: Road speed search: the best speed's road difference over the one at rest must be below
#: this (a clear minimum; about 0.2-0.5 on the rendered highways, 1 at rest).
ROAD_MAX_CONTRAST = 0.8


def skew(v: np.ndarray) -> np.ndarray:
    """Return the (3, 3) cross-product matrix of a 3-vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint (6, 6) of an SE(3) transform for twists ordered (translation, rotation)."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[:3, 3:] = skew(t) @ R
    return A


def validate_images(left: np.ndarray, right: np.ndarray, calib: StereoCalibration) -> None:
    """Raise ImageError unless both images are 2-D, non-empty, equal and match the calibration."""
    for img, name in ((left, 'left'), (right, 'right')):
        if not isinstance(img, np.ndarray) or img.ndim != 2 or img.size == 0:
            shape = getattr(img, 'shape', None)
            raise ImageError(f'{name} image must be a non-empty 2-D grey array, got shape {shape}')
        if img.dtype not in (np.uint8, np.uint16):
            raise ImageError(f'{name} image must be uint8 or uint16, got {img.dtype}')
    if left.shape != right.shape:
        raise ImageError(f'left and right images differ in size: {left.shape[::-1]} vs '
                         f'{right.shape[::-1]} (width, height)')
    if (left.shape[1], left.shape[0]) != calib.size:
        raise ImageError(f'image size {left.shape[1]}x{left.shape[0]} does not match the '
                         f'calibration {calib.size[0]}x{calib.size[1]}')


def _uniform_images(frame: StereoFrame) -> str:
    """Name the images of the pair that have no texture at all (one grey level), or ''."""
    notes = []
    for img, name in ((frame.left, 'left'), (frame.right, 'right')):
        lo, hi = int(img.min()), int(img.max())
        if lo == hi:
            notes.append(f'{name} image is uniform (every pixel {lo})')
    return ', '.join(notes)


class StereoOdometry:
    """
    Stereo visual odometry: feed stereo pairs, get poses.

    Parameters
    ----------
    config : Config
        The whole configuration (tracker, bucketing, filter, ransac, pipeline sections).

    """

    def __init__(self, config: Config | None = None) -> None:
        self.config = config or Config()
        keep_freed_memory(self.config.pipeline.keep_freed_memory_mb)
        #: Where the replenishment runs (``pipeline.threads``, ``pipeline.worker``).
        self.workers = self._workers(self.config)
        self.tracker = StereoTracker(self.config.tracker, self.config.bucketing, self.workers)
        self.estimator = MotionEstimator(self.config)
        self.road = RoadAligner(self.config.road, self.config.ransac)
        #: Online estimate of the rig's error (``rig``); kept by ``reset()``: it belongs to the
        #: cameras, not to the trajectory. A new calibration starts it over.
        self.rig = RigCalibrator(self.config.rig)
        #: The last pair's work that its pose did not need (``settle``): that pair's result and
        #: its rig update (None without one), or None.
        self._unsettled: tuple | None = None
        #: The previous pair's road plane to refine (``_road_step``), handed over by
        #: ``settle`` (``_settle_road``), while it is refined on the helper (the job), or None.
        self._road_pending: tuple | None = None
        self._road_plane_work: tuple | None = None
        self._road_plane_job = None
        self.reset()

    # -- control -----------------------------------------------------------------------
    def reset(self) -> None:
        """Start over: identity pose, zero velocity, no features (the rig estimate stays)."""
        self._settle_quietly('reset')
        self.T_world_cam = np.eye(4)
        self.pose_cov = np.zeros((6, 6))
        self._prev_stamp: float | None = None
        self._prev_calib: StereoCalibration | None = None
        self._lost_time = 0.0
        self._last_dt = 0.1
        self._status = TrackingStatus.INITIALIZING
        self._road_rng = np.random.default_rng(0)
        #: The previous pair prepared for the road alignment, and its road plane.
        self._road_images: RoadImages | None = None
        self._road_plane: RoadPlane | None = None
        #: The time refining ``_road_plane`` took (ms; counted in the next pair's ``road``).
        self._road_plane_ms = 0.0
        self._road_pending = self._road_plane_work = None
        #: The previous pair's left image as tracked (the rig's row coupling of its matches).
        self._rig_prev_left: np.ndarray | None = None
        self.tracker.reset()
        self.estimator.reset()

    def set_pose(self, T_world_cam: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """Set the current pose (4, 4) in ``world`` and optionally its covariance (6, 6)."""
        T = np.asarray(T_world_cam, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f'pose must be a finite 4x4 matrix, got shape {T.shape}')
        self.T_world_cam = T.copy()
        self.pose_cov = np.zeros((6, 6)) if covariance is None else \
            np.asarray(covariance, np.float64).reshape(6, 6).copy()

    def update_config(self, config: Config) -> None:
        """Apply a new configuration (run-time changes of thresholds) without a reset."""
        self._settle_quietly('configuration change')
        old, self.config = self.config, config
        self.tracker.cfg = config.tracker
        self.tracker.bucketing_cfg = config.bucketing
        self.estimator.config = config
        self.road.cfg, self.road.ransac = config.road, config.ransac
        self.rig.cfg = config.rig
        pipe = config.pipeline
        keep_changed = pipe.keep_freed_memory_mb != old.pipeline.keep_freed_memory_mb
        if keep_changed:
            keep_freed_memory(pipe.keep_freed_memory_mb)
        if auto_threads(pipe.threads) != self.workers.threads or \
                (self.workers.threads > 1 and (pipe.worker != self.workers.requested
                                               or keep_changed)):
            self.workers.close()
            self.workers = self.tracker.workers = self._workers(config)

    @staticmethod
    def _workers(config: Config) -> Workers:
        """Return the workers of ``pipeline.threads`` and ``pipeline.worker``."""
        keep = config.pipeline.keep_freed_memory_mb
        allocator = (f'{keep_freed_memory.__module__}:keep_freed_memory={keep}',) if keep > 0 \
            else ()
        return Workers(config.pipeline.threads, kind=config.pipeline.worker,
                       preload=WORKER_MODULES + allocator)

    def close(self) -> None:
        """Finish the last pair's work, stop the worker (later calls run in this thread)."""
        try:
            self._settle_quietly('close')
        finally:
            self.workers.close()

    def _settle_quietly(self, why: str) -> None:
        """``settle`` where its error must not stop the caller: logged instead."""
        try:
            self.settle()
            self._take_road_plane()  # left by a pair that stopped before its road step
        except Exception as exc:  # noqa: BLE001 - the caller goes on (reset, close, ...)
            LOG.error("the last pair's work after its pose failed before the %s: %s: %s", why,
                      type(exc).__name__, exc)
            self._road_plane_work = self._road_plane_job = None

    def settle(self) -> float:
        """
        Run the last pair's work that its pose did not need; return its time (ms).

        That is the rig refinement's update from the pair (``rig``), which moves the estimate
        the next pair's correction and motion prior use, the wait for the tracker's
        replenishment (new corners for the next pair, found on the worker), and the refinement
        of the pair's road plane (``road``), the next pair's start. ``process`` returns the
        pose before them; a caller with time between pairs (the ROS node, once the odometry is
        published) calls this to take them out of the time to the next pose. Otherwise the
        next ``process`` runs them first thing, the road plane on the helper thread next to its
        tracking (``_settle_road``). Once they ran, the pair's result is complete: its ``rig``
        is the estimate after its update, its ``timings_ms`` has the tracker's stage times
        (``track.*``), ``rig`` includes the update, ``road`` the plane (when it ran here) and
        ``after_pose`` is the time of all (0.0 until then). Nothing to do: returns 0.0. An
        error of any is raised here, once (``reset``, ``update_config`` and ``close`` log it
        and go on).
        """
        return self._settle(road_now=True)

    def _settle(self, road_now: bool) -> float:
        """``settle``; the road plane is refined before this returns only with ``road_now``."""
        work, self._unsettled = self._unsettled, None
        if work is None:
            return 0.0
        res, rig_update = work
        road, self._road_pending = self._road_pending, None
        timings = res.timings_ms
        t0 = time.perf_counter()
        try:
            if rig_update is not None:  # first: the worker may still be finding corners
                update, args = rig_update
                update(*args)
                timings['rig'] = timings.get('rig', 0.0) + (time.perf_counter() - t0) * 1e3
                res.rig = self.rig_estimate()
        finally:
            self._join_tracker(timings)
            self._settle_road(road)
            if road is not None and road_now:
                self._take_road_plane()
                timings['road'] = timings.get('road', 0.0) + self._road_plane_ms
                self._road_plane_ms = 0.0
            ms = (time.perf_counter() - t0) * 1e3
            timings['after_pose'] = ms
        return ms

    def rig_estimate(self):
        """Return the rig refinement's estimate (``RigEstimate``); None if off or before a pair."""
        if not self.config.rig.enabled or self._prev_calib is None:
            return None
        return self.rig.estimate(self._prev_calib)

    @property
    def status(self) -> TrackingStatus:
        """Status of the latest processed frame."""
        return self._status

    # -- per frame ---------------------------------------------------------------------
    def process(self, frame: StereoFrame) -> OdometryResult:
        """
        Process one stereo pair and return the integrated pose.

        Runs the previous pair's work after its pose first, if nobody called ``settle``.

        Raises
        ------
        ImageError
            The images cannot be used with the frame's calibration (nothing changes then,
            apart from the previous pair's work after its pose).
        Exception
            What that work raised (see ``settle``); the frame is not processed.

        """
        t_start = time.perf_counter()
        self._settle(road_now=False)
        calib = frame.calibration
        validate_images(frame.left, frame.right, calib)
        stamp = float(frame.stamp_s)
        if not np.isfinite(stamp):
            raise ImageError(f'stamp must be finite, got {stamp!r}')
        prev_stamp, prev_calib = self._prev_stamp, self._prev_calib
        if prev_stamp is not None and stamp < prev_stamp - RESTART_JUMP_S:
            LOG.warning('stamp jumped back %.3f s: restarting odometry', prev_stamp - stamp)
            self.reset()
            prev_stamp = prev_calib = None
        if prev_stamp is not None and stamp <= prev_stamp:
            return self._result(stamp, self._status, t_start, {}, accepted=False,
                                message=f'stamp {stamp:.9f} s not after {prev_stamp:.9f} s; '
                                'frame ignored')
        timings: dict[str, float] = {}
        if prev_stamp is None:
            self._track(frame.left, frame.right, calib, None, timings)
            self._road_step(frame, 0.0, False, timings)
            self._rig_prev_left = self.tracker.previous_left()
            self._commit(stamp, calib, TrackingStatus.INITIALIZING)
            return self._after_pose(self._result(stamp, TrackingStatus.INITIALIZING, t_start,
                                                 timings,
                                                 message='first frame: features detected'))
        dt = stamp - prev_stamp
        if dt > self.config.pipeline.max_gap_s:
            LOG.warning('gap of %.3f s: velocity re-initialised', dt)
            self.estimator.reset()
        calib_changed = not calib.same_as(prev_calib)
        if calib_changed:
            LOG.info('calibration changed: features re-detected, rig refinement restarted')
            self.tracker.reset()
            self.rig.reset()
        prior = None if calib_changed else self._prior(prev_calib, calib, dt)
        if prior is None and not calib_changed:
            t0 = time.perf_counter()
            prior = self._road_prior(frame, calib, dt)
            timings['road_search'] = (time.perf_counter() - t0) * 1e3
        left, right, road_start = frame.left, frame.right, None
        if self.workers.overlaps and self._aligns_road(calib):
            # The road pyramids are built on the helper next to the tracking, once the tracker
            # handed it the checks its KLT pass waits for: the replenishment takes the other
            # core from the middle of the tracking to the end of the motion estimate. In one
            # thread the road step builds them.
            left, right = self.tracker.grey_pair(left, right)
            road_start = functools.partial(self._start_road_images, calib, left, right)
        track = self._track(left, right, calib, prior, timings, road_start)
        corr = track.correspondences
        t0 = time.perf_counter()
        if corr is None or len(corr) == 0:
            est = None
            self.estimator.coast(dt=dt)
        else:
            tcfg = self.config.tracker
            coupling = self.rig.couplings(corr, prev_calib, calib, self._rig_prev_left,
                                          self.tracker.previous_left(),
                                          tcfg.affine_stereo_win_size_px, tcfg.affine_step_px)
            corr_rig = self.rig.corrected(corr, prev_calib, calib, coupling)
            rig_ms = (time.perf_counter() - t0) * 1e3
            t0 = time.perf_counter()
            est = self.estimator.estimate(corr_rig, prev_calib, dt,
                                          calib_cur=calib if calib_changed else None)
        self._check_velocity_state()
        timings['estimate'] = (time.perf_counter() - t0) * 1e3
        if est is not None and self.config.rig.enabled:
            timings['rig'] = rig_ms
        ok = est is not None and est.status is TrackingStatus.OK
        rig_update = None
        if ok and not calib_changed and self.config.rig.enabled:
            # After the pose (see ``settle``): nothing of this pair depends on it.
            rig_update = (self.rig.update, (
                corr, est.inliers, est.T_prev_cur, dt, prev_calib, calib,
                self.tracker.last_pair(), self.config.tracker.win_size_px, coupling,
                track.stereo_klt_right[:, 1]))
        if ok:
            self._lost_time = 0.0
            status = TrackingStatus.OK
            message = ''
        else:
            self._lost_time += dt
            status = est.status if est is not None else TrackingStatus.DEGENERATE
            message = est.message if est is not None else 'no correspondences'
            blank = _uniform_images(frame)
            if blank:
                message = f'{blank}; {message}'
            if calib_changed and est is None:
                status, message = TrackingStatus.INITIALIZING, 'calibration changed'
            if self._lost_time > self.config.pipeline.max_lost_time_s:
                self.estimator.reset()
                status = TrackingStatus.LOST
                message = f'no motion estimate for {self._lost_time:.2f} s ({message})'
        vehicle_fused = ok and self._vehicle_step(dt)
        road_fused = self._road_step(frame, dt, ok and not calib_changed, timings,
                                     track.after_checks)
        self._integrate(dt, lost=status is TrackingStatus.LOST)
        self._rig_prev_left = self.tracker.previous_left()
        self._commit(stamp, calib, status)
        return self._after_pose(self._result(
            stamp, status, t_start, timings, corr=corr,
            inliers=est.inliers if est is not None else None,
            iterations=est.iterations if est is not None else 0, message=message,
            road_fused=road_fused, vehicle_fused=vehicle_fused), rig_update)

    # -- steps -------------------------------------------------------------------------
    def _after_pose(self, res: OdometryResult, rig_update: tuple | None = None
                    ) -> OdometryResult:
        """Leave the pair's remaining work (see ``settle``) for later; return ``res``."""
        res.timings_ms['after_pose'] = 0.0
        self._unsettled = (res, rig_update)
        return res

    def _check_velocity_state(self) -> None:
        """Re-initialise the velocity if its mean or covariance became unusable."""
        mean, cov = self.estimator.mean, self.estimator.cov
        if np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)):
            w = np.linalg.eigvalsh(0.5 * (cov + cov.T))
            if w[0] >= -1e-9 * max(1.0, float(np.abs(w).max())):
                return
            why = f'smallest covariance eigenvalue {w[0]:.3g}'
        else:
            why = 'non-finite values'
        LOG.warning('velocity state is not a valid Gaussian (%s): velocity re-initialised', why)
        self.estimator.reset()

    def _features_plane(self, calib: StereoCalibration,
                        points: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, float] | None:
        """Ground plane (``fit_ground_plane``) of features' ideal (left, right) pixels, or None."""
        return fit_ground_plane(triangulate(calib, *points), self.config.ransac, self._road_rng)

    def _vehicle_step(self, dt: float) -> bool:
        """
        Fuse the rolling-vehicle prior (``vehicle``, :mod:`~stereo_vo_ros.road.vehicle_motion`).

        A Kalman update with the pseudo-measurement ``0 = c(y)``, linearised at the features'
        estimate, standard deviation ``vehicle.lateral_speed_std``. Returns whether it was fused.
        """
        vcfg = self.config.vehicle
        if not vcfg.nonholonomic or not dt > 0:
            return False
        value, row = lateral_constraint(self.estimator.mean, dt, vcfg.lever_arm_m)
        return self.estimator.fuse_linear(row[None], np.array([-value]),
                                          np.array([[vcfg.lateral_speed_std ** 2]]),
                                          vcfg.gate_chi2)

    def _aligns_road(self, calib: StereoCalibration) -> bool:
        """Return whether the road is aligned on pairs of ``calib`` (on, rectified input)."""
        return self.config.road.enabled and calib.kind == 'rectified'

    def _start_road_images(self, calib: StereoCalibration, left: np.ndarray,
                           right: np.ndarray):
        """
        Start the road pyramids of a pair ((H, W) uint8 images, as the tracker sees them).

        ``RoadAligner.prepare``: with a helper thread they are built there, next to the
        caller (OpenCV filters, which release the GIL), after the previous pair's road plane
        (``_queue_road_plane``), which sets their first row; the same images either way. The
        images must not change until the result is taken. Returns the pending result
        (``.result()``: the images and the time building them took, ms), or None when the road
        is not aligned.
        """
        if not self._aligns_road(calib):
            return None
        self._queue_road_plane()
        return self.workers.submit_local(self._prepare_road, calib, left, right,
                                         self._road_plane_job, self._road_plane)

    def _prepare_road(self, calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                      plane_job, plane: RoadPlane | None):
        """``_start_road_images``' work: the plane is ``plane_job``'s when there is one."""
        if plane_job is not None:  # done: queued before this on the same helper thread
            plane = plane_job.result()[0]
        t0 = time.perf_counter()
        images = self.road.prepare(left, right, self.road.first_row(calib, plane))
        return images, (time.perf_counter() - t0) * 1e3

    def _road_step(self, frame: StereoFrame, dt: float, measure: bool,
                   timings: dict[str, float], images=None) -> bool:
        """
        Road alignment (``road``, :mod:`~stereo_vo_ros.road.road_alignment`; not in the papers).

        ``images``: the pending pyramids of ``_start_road_images`` (built here when None).

        With ``measure`` (the features gave an estimate, same calibration) the road of the
        previous left image is aligned with the current one, starting from the filter's motion,
        and fused with it (``MotionEstimator.fuse``). The current pair's road plane, for the
        next pair, is refined after the pose (``_settle_road``), starting from the previous
        plane moved by the motion. Rectified input only. Returns whether the road motion was
        fused.
        """
        calib = frame.calibration
        self._take_road_plane()  # (its own time is ``_road_plane_ms``)
        t0 = time.perf_counter()
        if not self._aligns_road(calib):
            self._road_images = self._road_plane = None
            return False
        if images is None:
            images = self._start_road_images(calib, *self.tracker.last_pair())
        prev_images, plane = self._road_images, self._road_plane
        images, prepare_ms = images.result()  # this pair, as the tracker converted it
        T_prev_cur = transform_from_velocity(self.estimator.mean, dt) if dt > 0 else None
        fused = False
        if measure and prev_images is not None and plane is not None:
            motion = self.road.align(prev_images, images, calib, plane, T_prev_cur, dt)
            if motion is not None:
                fused = self.estimator.fuse(motion.velocity, motion.covariance,
                                            self.config.road.gate_chi2, motion.components)
                if fused:
                    T_prev_cur = transform_from_velocity(self.estimator.mean, dt)
        start = plane.in_frame(T_prev_cur) if plane is not None and measure else None
        self._road_images, self._road_plane = images, None
        # The pyramids' time counts wherever they were built, and so does the previous plane's.
        timings['road'] = (time.perf_counter() - t0) * 1e3 + prepare_ms + self._road_plane_ms
        self._road_plane_ms = 0.0
        # The rig correction this pair's features were estimated with, for its plane.
        right_map = self.rig.homography(calib) if self.rig.active() else None
        self._road_pending = (start, images, calib, right_map)
        return fused

    def _settle_road(self, pending: tuple | None) -> None:
        """
        Keep the last pair's road plane work (``pending``: ``_road_step``'s) for the next pair.

        With the tracker's features after their replenishment (``settle`` has joined it): the
        plane falls back on theirs. Unless ``settle`` runs it at once, the next pair hands the
        work to the helper thread with its road pyramids (``_queue_road_plane``), where it runs
        next to the KLT passes (which release the GIL), not next to the Python of the rig
        update and the motion estimate.
        """
        if pending is not None:
            self._road_plane_work = (*pending, self.tracker.feature_points())

    def _queue_road_plane(self) -> None:
        """Hand the road plane work kept by ``_settle_road`` to the helper thread, if any."""
        work, self._road_plane_work = self._road_plane_work, None
        if work is not None:
            self._road_plane_job = self.workers.submit_local(self._refine_road_plane, *work)

    def _refine_road_plane(self, start: RoadPlane | None, images: RoadImages,
                           calib: StereoCalibration, right_map: np.ndarray | None,
                           points: tuple[np.ndarray, np.ndarray]):
        """
        Refine the road plane of a pair; return it (or None) and the time it took (ms).

        From ``start``, the previous plane moved by the motion (``RoadAligner.refine_plane``,
        through the rig correction ``right_map`` that the pair's features had); without one,
        or when it is lost, from the plane of the features' ideal (left, right) pixels
        ``points``.
        """
        t0 = time.perf_counter()
        plane = self.road.refine_plane(images, calib, start, right_map) \
            if start is not None else None
        if plane is None:  # no previous plane, or it was lost: the features' plane
            found = self._features_plane(calib, points)
            if found is not None:
                plane = self.road.refine_plane(images, calib, RoadPlane(*found), right_map)
        return plane, (time.perf_counter() - t0) * 1e3

    def _take_road_plane(self) -> None:
        """Wait for the previous pair's road plane (``_queue_road_plane``): ``_road_plane``."""
        self._queue_road_plane()
        job, self._road_plane_job = self._road_plane_job, None
        if job is not None:
            self._road_plane, self._road_plane_ms = job.result()

    def _prior(self, prev_calib: StereoCalibration, calib: StereoCalibration, dt: float):
        """
        Constant-velocity prediction of the current pixels for the tracker (initial flow).

        None while the velocity is unknown (linear std above
        ``pipeline.prior_max_velocity_std``): the tracker then searches with its full pyramid.
        """
        if self.estimator.velocity_unknown():
            return None
        return self._predictor(prev_calib, calib, dt, self.estimator.mean.copy(), self.rig)

    def _road_prior(self, frame: StereoFrame, calib: StereoCalibration, dt: float):
        """
        Return a forward-motion prior from the road (``ground_plane.road_speed``), or None.

        Used while the velocity is unknown (``pipeline.road_speed_search``): the ground plane
        of the previous pair's features, then the forward speed from -10 m/s to
        ``pipeline.max_speed`` that aligns the road best. None when off (or the tracker uses
        no prior), without a plane, on raw input, at rest (below ``ROAD_MIN_SPEED``) or
        without a clear minimum (``ROAD_MAX_CONTRAST``).
        """
        pcfg = self.config.pipeline
        prev = self.tracker.previous_left()
        if not (pcfg.road_speed_search and self.config.tracker.use_motion_prior) or \
                prev is None or calib.kind != 'rectified':
            return None  # (the tracker would ignore a prior without use_motion_prior)
        self._take_road_plane()  # its random draws come first
        plane = self._features_plane(calib, self.tracker.feature_points())
        if plane is None:
            return None
        speeds = np.arange(-10.0, pcfg.max_speed + 0.5, 1.0)
        found = road_speed(prev, self.tracker.as_grey(frame.left), calib, plane, dt, speeds,
                           self.tracker.last_pair()[1])
        if not (abs(found.speed) >= ROAD_MIN_SPEED and found.contrast <= ROAD_MAX_CONTRAST):
            return None
        LOG.info('velocity unknown: tracking with %.0f m/s forward from the road', found.speed)
        return self._predictor(calib, calib, dt,
                               np.array([0.0, 0.0, found.speed, 0.0, 0.0, 0.0]), self.rig)

    @staticmethod
    def _predictor(prev_calib: StereoCalibration, calib: StereoCalibration, dt: float,
                   velocity: np.ndarray, rig: RigCalibrator | None = None
                   ) -> 'ConstantVelocityPrior':
        """
        Return the constant-velocity prior of one velocity (6,) (m/s, rad/s).

        With ``rig`` the right points are corrected before the transfer and the predicted ones
        moved to where the real right camera sees them.
        """
        H_prev = H_cur = None
        if rig is not None and rig.active():
            H_prev = rig.homography_inverse(prev_calib)
            H_cur = np.linalg.inv(rig.homography_inverse(calib))
        return ConstantVelocityPrior(prev_calib, calib, dt, velocity, H_prev, H_cur)

    def _track(self, left: np.ndarray, right: np.ndarray, calib: StereoCalibration, prior,
               timings: dict[str, float], after_checks=None) -> PendingTrack:
        """Track the pair; its replenishment runs on while the caller estimates the motion."""
        t0 = time.perf_counter()
        track = self.tracker.track_async(left, right, calib, prior=prior,
                                         after_checks=after_checks)
        timings['track'] = (time.perf_counter() - t0) * 1e3
        return track

    def _join_tracker(self, timings: dict[str, float]) -> None:
        """Wait for the tracker's replenishment; record its stage times."""
        t0 = time.perf_counter()
        track = self.tracker.join()
        if track is None:
            return
        # ``track``: the caller's time in the tracker (tracking plus any wait for the
        # replenishment); ``track.*``: the tracker's stages, ``track.total`` its whole time.
        timings['track'] = timings.get('track', 0.0) + (time.perf_counter() - t0) * 1e3
        for key, value in track.stats.timings_ms.items():
            timings[f'track.{key}'] = float(value)

    def _integrate(self, dt: float, lost: bool) -> None:
        """Move the pose by the filter's velocity and propagate the covariance."""
        velocity, cov_v = self.estimator.mean, self.estimator.cov
        T_prev_cur = transform_from_velocity(velocity, dt)
        # Increment as a left perturbation in the previous camera frame: (t, rot) ~ dt * y.
        cov_inc = cov_v * dt * dt
        if lost:
            cov_inc = cov_inc + np.diag([LOST_VARIANCE_RATE[0] * dt] * 3 +
                                        [LOST_VARIANCE_RATE[1] * dt] * 3)
        A = adjoint(self.T_world_cam)
        self.pose_cov = self.pose_cov + A @ cov_inc @ A.T
        self.pose_cov = 0.5 * (self.pose_cov + self.pose_cov.T)
        self.T_world_cam = self.T_world_cam @ T_prev_cur
        self._last_dt = dt

    def _commit(self, stamp: float, calib: StereoCalibration, status: TrackingStatus) -> None:
        self._prev_stamp = stamp
        self._prev_calib = calib
        self._status = status

    def _result(self, stamp: float, status: TrackingStatus, t_start: float,
                timings: dict[str, float], corr: Correspondences | None = None,
                inliers: np.ndarray | None = None, iterations: int = 0, message: str = '',
                accepted: bool = True, road_fused: bool = False,
                vehicle_fused: bool = False) -> OdometryResult:
        # Velocity in the CURRENT camera frame: rotate by the frame-to-frame rotation.
        v = self.estimator.mean
        R = rotation_from_rates(v[3:], self._last_dt)
        Rb = np.zeros((6, 6))
        Rb[:3, :3] = Rb[3:, 3:] = R.T
        timings = dict(timings)
        timings['total'] = (time.perf_counter() - t_start) * 1e3
        n_tracked = len(corr) if corr is not None else 0
        n_inl = int(np.count_nonzero(inliers)) if inliers is not None else 0
        res = OdometryResult(
            stamp_s=stamp, T_world_cam=self.T_world_cam.copy(),
            pose_covariance=self.pose_cov.copy(),
            velocity=Rb @ v, velocity_covariance=Rb @ self.estimator.cov @ Rb.T, status=status,
            n_tracked=n_tracked, n_inliers=n_inl, iterations=iterations, timings_ms=timings,
            message=message, features=corr, inliers=inliers, accepted=accepted,
            road_fused=road_fused, vehicle_fused=vehicle_fused,
            rig=self.rig_estimate())
        return res


class ConstantVelocityPrior:
    """
    The tracker's motion prior: current pixels predicted from previous ones at one velocity.

    A plain object (picklable: the tracker's replenishment may use it in a worker process).
    ``velocity`` (6,) is (m/s, rad/s) in the previous left camera frame; ``H_prev`` and
    ``H_cur`` (3, 3) or None are the rig refinement's right-image corrections of the previous
    and current pair.
    """

    def __init__(self, prev_calib: StereoCalibration, calib: StereoCalibration, dt: float,
                 velocity: np.ndarray, H_prev: np.ndarray | None = None,
                 H_cur: np.ndarray | None = None) -> None:
        self.prev_calib, self.calib, self.dt = prev_calib, calib, dt
        self.velocity = velocity
        self.H_prev, self.H_cur = H_prev, H_cur

    def __call__(self, prev_left: np.ndarray, prev_right: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Return the predicted (N, 2) left and right ideal pixels of (N, 2) previous ones."""
        if len(prev_left) == 0:
            return prev_left.copy(), prev_right.copy()
        right = prev_right if self.H_prev is None else apply_homography(self.H_prev, prev_right)
        pred = TransferModel(self.prev_calib, prev_left, right, self.dt,
                             self.calib).predict(self.velocity)
        if self.H_cur is not None:
            pred[:, 2:] = apply_homography(self.H_cur, pred[:, 2:])
        bad = ~np.all(np.isfinite(pred), axis=1)
        pred[bad, :2] = prev_left[bad]
        pred[bad, 2:] = prev_right[bad]
        return pred[:, :2], pred[:, 2:]
