"""
Simulated stereo sequences of Kitt et al. (sections IV-A to IV-C) and their evaluation.

The paper evaluates its filters on simulated sequences: 2000 frames at a mean speed of 10 m/s
(2000 m), 40 scene points per frame, Gaussian pixel noise of 0.7 px, and for the outlier study
20 % outliers. It gives the image size (1344 x 391 px) and the baseline (0.7 m) of its real rig
but not the focal length, the frame rate, the trajectory or the scene. Our choices:

Rig (:class:`SimulationSpec` fields ``width``, ``height``, ``focal_px``, ``baseline``)
    Rectified pair, 1344 x 391 px, principal point at the image centre, fx = fy = 645 px (the
    focal length of the group's 1344 x 391 Karlsruhe sequences), baseline 0.7 m.
Time
    ``rate`` = 10 Hz, so ``frames`` = 2000 frame-to-frame motions at 10 m/s cover 2000 m.
    ``frames`` counts motions; the sequence has ``frames + 1`` stereo frames.
Trajectory (:func:`simulate_velocities`)
    The true motion of every step is given in the estimator's own parameterisation (velocity
    of the previous left camera, :func:`~stereo_vo_ros.estimation.motion.transform_from_velocity`),
    which can express any rigid motion. Each component is a smooth random signal: a sum of three
    sinusoids with random periods and phases. Forward speed ``speed`` +/- ``speed_amplitude``
    (periods 20-120 s, clipped to at least 20 % of ``speed``), yaw rate (about the camera's
    y axis) +/- ``yaw_rate_deg`` (periods 15-90 s: gentle turns both ways), pitch and roll
    rates +/- ``pitch_roll_rate_deg`` (periods 1-5 s: body oscillation), lateral and vertical
    velocity +/- ``side_velocity`` (periods 2-10 s).
Scene (:func:`simulate_sequence`)
    Every frame pair sees ``points`` fresh static points (no tracks): a pixel drawn uniformly
    in the previous left image and a depth drawn uniformly in [``min_depth``, ``max_depth``]
    (5-60 m), kept only if it projects into all four images at least ``border_px`` (15 px)
    from the border (so bucketing keeps it) with a depth of at least 1 m; rejected candidates
    are redrawn. The scene is a random point cloud, not a road model.
Noise
    Independent Gaussian noise with standard deviation ``noise_px`` on both coordinates of all
    four observations.
Outliers (``outlier_ratio``, ``outlier_model``)
    ``round(outlier_ratio * points)`` of the points of every frame pair are outliers, drawn
    like the others but then corrupted: ``moving`` -- the point lies on an independently
    moving object that moves 2-15 m/s in a random direction in the camera's x-z plane between
    the two frames (both stereo pairs stay consistent, only the static-world assumption is
    violated); ``mismatch`` -- a gross temporal mismatch: the current left and right
    observations are shifted by the same random offset of 5-50 px (the current pair stays on
    one image row); ``mixed`` (default) -- half of the outliers (rounded down) are moving
    points, the others mismatches.

:func:`run_simulation` runs the :class:`~stereo_vo_ros.estimation.estimator.MotionEstimator` on
such a sequence through :func:`~stereo_vo_ros.io.correspondences.iter_estimates` (the very
code path of ``stereo_vo estimate``), integrates ``T_world_cur = T_world_prev @ T_prev_cur`` and
returns JSON-ready figures. Use :func:`paper_config` to build the matching configuration: the
filter's measurement noise must equal the simulated pixel noise for the paper's experiments.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
import logging
import math

import numpy as np

from ..config import Config
from ..errors import ConfigError
from ..estimation.camera import StereoCalibration
from ..estimation.motion import transform_from_velocity
from ..io.correspondences import CorrespondenceData, iter_estimates
from ..records import TrackingStatus

LOG = logging.getLogger(__name__)

OUTLIER_MODELS = ('mixed', 'moving', 'mismatch')
MIN_FILTER_NOISE_PX = 0.01  #: filter noise used by :func:`paper_config` for noiseless data
MIN_VISIBLE_DEPTH_M = 1.0  #: smallest depth of a simulated point in any camera (m)
IMAGE_KEYS = ('prev_left', 'prev_right', 'cur_left', 'cur_right')
_MAX_REDRAWS = 200


@dataclass(frozen=True)
class SimulationSpec:
    """
    Parameters of one simulated sequence (defaults: Kitt et al., section IV-A).

    Attributes
    ----------
    frames : int
        Frame-to-frame motions M (the sequence has M + 1 stereo frames).
    points : int
        Correspondences per frame pair N.
    noise_px : float
        Standard deviation of the Gaussian pixel noise on every coordinate (pixels), >= 0.
    outlier_ratio : float
        Fraction of the N correspondences that are outliers, in [0, 0.9].
    seed : int
        Seed of the sequence (trajectory, scene, noise, outliers).
    speed : float
        Mean forward speed (m/s).
    rate : float
        Frame rate (Hz).
    outlier_model : str
        ``mixed``, ``moving`` or ``mismatch`` (module docstring).
    speed_amplitude : float
        Amplitude of the forward speed variation (m/s).
    yaw_rate_deg : float
        Amplitude of the yaw rate (deg/s).
    pitch_roll_rate_deg : float
        Amplitude of the pitch and roll rates (deg/s).
    side_velocity : float
        Amplitude of the lateral and vertical velocity (m/s).
    min_depth, max_depth : float
        Depth range of the scene points in the previous left camera (m).
    width, height : int
        Image size (pixels).
    focal_px : float
        Focal length fx = fy (pixels).
    baseline : float
        Stereo baseline (m).
    border_px : float
        Every observation lies at least this far inside the image (pixels).

    """

    frames: int = 2000
    points: int = 40
    noise_px: float = 0.7
    outlier_ratio: float = 0.0
    seed: int = 1
    speed: float = 10.0
    rate: float = 10.0
    outlier_model: str = 'mixed'
    speed_amplitude: float = 3.0
    yaw_rate_deg: float = 5.0
    pitch_roll_rate_deg: float = 0.5
    side_velocity: float = 0.1
    min_depth: float = 5.0
    max_depth: float = 60.0
    width: int = 1344
    height: int = 391
    focal_px: float = 645.0
    baseline: float = 0.7
    border_px: float = 15.0

    def __post_init__(self) -> None:
        checks = [
            ('frames', self.frames >= 1), ('points', self.points >= 1),
            ('noise_px', self.noise_px >= 0), ('outlier_ratio', 0 <= self.outlier_ratio <= 0.9),
            ('seed', self.seed >= 0), ('speed', self.speed > 0), ('rate', self.rate > 0),
            ('speed_amplitude', self.speed_amplitude >= 0),
            ('yaw_rate_deg', self.yaw_rate_deg >= 0),
            ('pitch_roll_rate_deg', self.pitch_roll_rate_deg >= 0),
            ('side_velocity', self.side_velocity >= 0),
            ('min_depth', self.min_depth >= MIN_VISIBLE_DEPTH_M),
            ('max_depth', self.max_depth > self.min_depth),
            ('width', self.width > 2 * self.border_px),
            ('height', self.height > 2 * self.border_px),
            ('focal_px', self.focal_px > 0), ('baseline', self.baseline > 0),
            ('border_px', self.border_px >= 0)]
        for name, ok in checks:
            value = getattr(self, name)
            if not ok or (isinstance(value, float) and not math.isfinite(value)):
                raise ConfigError(f'simulation {name} out of range: {value!r}')
        if self.outlier_model not in OUTLIER_MODELS:
            raise ConfigError(f'simulation outlier_model must be one of {list(OUTLIER_MODELS)}, '
                              f'got {self.outlier_model!r}')

    @property
    def dt(self) -> float:
        """Time between stereo frames (s)."""
        return 1.0 / self.rate

    def projections(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the rectified (P0, P1), each (3, 4) float64 pixels; P1[0, 3] = -f * b."""
        K = np.array([[self.focal_px, 0.0, self.width / 2.0],
                      [0.0, self.focal_px, self.height / 2.0], [0.0, 0.0, 1.0]])
        P0 = np.hstack([K, np.zeros((3, 1))])
        P1 = P0.copy()
        P1[0, 3] = -self.focal_px * self.baseline
        return P0, P1

    def calibration(self) -> StereoCalibration:
        """Return the StereoCalibration of the simulated rig."""
        P0, P1 = self.projections()
        return StereoCalibration.from_projections(P0, P1, self.width, self.height)


@dataclass
class SimulatedSequence:
    """
    A simulated sequence with its ground truth.

    Attributes
    ----------
    spec : SimulationSpec
    data : CorrespondenceData
        Noisy correspondences (M, N, 2) per image, calibration, rate and ``gt_poses``.
    velocities : np.ndarray
        (M, 6) float64 true state (m/s, rad/s) of every motion, previous left camera frame.
    T_prev_cur : np.ndarray
        (M, 4, 4) float64 true motion of every step (current left in previous left frame).
    poses : np.ndarray
        (M + 1, 4, 4) float64 true ``T_world_cam`` of the left camera (first left frame).
    outliers : np.ndarray
        (M, N) bool, True for the corrupted correspondences.
    clean : dict
        Noise-free, outlier-free observations: key (``prev_left``, ...) -> (M, N, 2) pixels.

    """

    spec: SimulationSpec
    data: CorrespondenceData
    velocities: np.ndarray
    T_prev_cur: np.ndarray
    poses: np.ndarray
    outliers: np.ndarray
    clean: dict

    @property
    def distance_m(self) -> float:
        """Length of the true path (m)."""
        return float(np.linalg.norm(self.T_prev_cur[:, :3, 3], axis=1).sum())


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, amplitude: float,
                   periods_s: tuple[float, float], terms: int = 3) -> np.ndarray:
    """Return a zero-mean sum of ``terms`` sinusoids with peak amplitude <= ``amplitude``."""
    periods = rng.uniform(*periods_s, size=terms)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=terms)
    weights = rng.uniform(0.5, 1.0, size=terms)
    weights *= amplitude / weights.sum()
    return (weights * np.sin(2.0 * np.pi * t[:, None] / periods + phases)).sum(axis=1)


def simulate_velocities(spec: SimulationSpec, rng: np.random.Generator) -> np.ndarray:
    """
    Return the true states (frames, 6) = (V_X, V_Y, V_Z, w_X, w_Y, w_Z) in m/s and rad/s.

    Velocities of the previous left camera (x right, y down, z forward), one per motion; see
    the module docstring for the signals.
    """
    t = np.arange(spec.frames) * spec.dt
    y = np.zeros((spec.frames, 6))
    y[:, 0] = _smooth_signal(rng, t, spec.side_velocity, (2.0, 10.0))
    y[:, 1] = _smooth_signal(rng, t, spec.side_velocity, (2.0, 10.0))
    y[:, 2] = np.maximum(spec.speed + _smooth_signal(rng, t, spec.speed_amplitude, (20.0, 120.0)),
                         0.2 * spec.speed)
    pr = np.deg2rad(spec.pitch_roll_rate_deg)
    y[:, 3] = _smooth_signal(rng, t, pr, (1.0, 5.0))
    y[:, 4] = _smooth_signal(rng, t, np.deg2rad(spec.yaw_rate_deg), (15.0, 90.0))
    y[:, 5] = _smooth_signal(rng, t, pr, (1.0, 5.0))
    return y


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) of camera-frame points X (..., 3) through intrinsics K (3, 3)."""
    h = X @ K.T
    with np.errstate(divide='ignore', invalid='ignore'):
        return h[..., :2] / h[..., 2:3]


def _views(calib: StereoCalibration, T_prev_cur: np.ndarray, X_prev: np.ndarray,
           X_cur_prev: np.ndarray) -> tuple[dict, np.ndarray]:
    """
    Project points into the four cameras.

    ``X_prev`` (F, K, 3) are points at the time of the previous pair and ``X_cur_prev`` the
    same points at the time of the current pair, both in the previous left frame (they differ
    for moving objects). Returns the pixels per image (F, K, 2) and the (F, K) smallest depth.
    """
    R, t = T_prev_cur[:, None, :3, :3], T_prev_cur[:, None, :3, 3]
    X_cur = np.einsum('fkji,fkj->fki', R, X_cur_prev - t)  # R^T (X - t)
    R_rl, t_rl = calib.R_right_left, calib.t_right_left
    X_pr = X_prev @ R_rl.T + t_rl
    X_cr = X_cur @ R_rl.T + t_rl
    views = {'prev_left': _project(calib.K_left, X_prev),
             'prev_right': _project(calib.K_right, X_pr),
             'cur_left': _project(calib.K_left, X_cur),
             'cur_right': _project(calib.K_right, X_cr)}
    depth = np.minimum.reduce([X_prev[..., 2], X_pr[..., 2], X_cur[..., 2], X_cr[..., 2]])
    return views, depth


def _draw_points(spec: SimulationSpec, calib: StereoCalibration, T_prev_cur: np.ndarray,
                 count: int, kind: str, rng: np.random.Generator) -> tuple[dict, dict]:
    """
    Draw ``count`` points per frame pair visible in all four images.

    Parameters
    ----------
    spec : SimulationSpec
        Rig, depth range and border.
    calib : StereoCalibration
        Calibration of the rig.
    T_prev_cur : np.ndarray
        (F, 4, 4) float64 true motions (current left in previous left frame).
    count : int
        Points per frame pair.
    kind : str
        ``static`` (inliers), ``moving`` or ``mismatch`` (outliers, module docstring).
    rng : np.random.Generator
        Source of randomness.

    Returns
    -------
    (observed, clean): dicts image name -> (F, count, 2) float64 pixels. ``observed`` carries
    the outlier corruption (no noise), ``clean`` the static-world projections of the same
    points.

    """
    F = len(T_prev_cur)
    w, h, b = spec.width, spec.height, spec.border_px
    observed = {k: np.empty((F, count, 2)) for k in IMAGE_KEYS}
    clean = {k: np.empty((F, count, 2)) for k in IMAGE_KEYS}
    if count == 0:
        return observed, clean
    todo = np.arange(F)
    K_inv = np.linalg.inv(calib.K_left)
    cand = 3 * count + 8
    for _ in range(_MAX_REDRAWS):
        n = len(todo)
        T = T_prev_cur[todo]
        uv = np.stack([rng.uniform(b, w - b, (n, cand)), rng.uniform(b, h - b, (n, cand))], -1)
        depth = rng.uniform(spec.min_depth, spec.max_depth, (n, cand))
        X_prev = (np.concatenate([uv, np.ones((n, cand, 1))], -1) @ K_inv.T) * depth[..., None]
        views_clean, depth_clean = _views(calib, T, X_prev, X_prev)
        views, dep = views_clean, depth_clean
        if kind == 'moving':
            speed = rng.uniform(2.0, 15.0, (n, cand)) * spec.dt
            heading = rng.uniform(0.0, 2.0 * np.pi, (n, cand))
            move = np.stack([np.cos(heading), np.zeros_like(heading), np.sin(heading)], -1)
            views, dep = _views(calib, T, X_prev, X_prev + move * speed[..., None])
        elif kind == 'mismatch':
            mag = rng.uniform(5.0, 50.0, (n, cand))
            ang = rng.uniform(0.0, 2.0 * np.pi, (n, cand))
            shift = np.stack([mag * np.cos(ang), mag * np.sin(ang)], -1)
            views = dict(views_clean, cur_left=views_clean['cur_left'] + shift,
                         cur_right=views_clean['cur_right'] + shift)
        ok = (dep >= MIN_VISIBLE_DEPTH_M) & (depth_clean >= MIN_VISIBLE_DEPTH_M)
        for p in views.values():
            ok &= (p[..., 0] >= b) & (p[..., 0] <= w - b) & (p[..., 1] >= b) & (p[..., 1] <= h - b)
        done = ok.sum(axis=1) >= count
        pick = np.argsort(~ok[done], axis=1, kind='stable')[:, :count, None]  # visible first
        rows = todo[done]
        for key in IMAGE_KEYS:
            observed[key][rows] = np.take_along_axis(views[key][done], pick, axis=1)
            clean[key][rows] = np.take_along_axis(views_clean[key][done], pick, axis=1)
        todo = todo[~done]
        if todo.size == 0:
            return observed, clean
    raise ConfigError(f'simulation cannot place {count} visible points per frame; check the '
                      f'depth range {spec.min_depth}-{spec.max_depth} m and the image size')


def simulate_sequence(spec: SimulationSpec) -> SimulatedSequence:
    """
    Simulate one sequence of stereo correspondences with its ground truth.

    Parameters
    ----------
    spec : SimulationSpec
        The sequence to simulate.

    Returns
    -------
    SimulatedSequence
        Deterministic for a given ``spec`` (all randomness comes from ``spec.seed``).

    """
    rng = np.random.default_rng(spec.seed)
    calib = spec.calibration()
    y = simulate_velocities(spec, rng)
    T = transform_from_velocity(y, spec.dt)
    poses = np.empty((spec.frames + 1, 4, 4))
    poses[0] = np.eye(4)
    for k in range(spec.frames):
        poses[k + 1] = poses[k] @ T[k]
    M, N = spec.frames, spec.points
    n_out = int(round(spec.outlier_ratio * N))
    if spec.outlier_model == 'mixed':
        n_moving = n_out // 2
    else:
        n_moving = n_out if spec.outlier_model == 'moving' else 0
    parts = [_draw_points(spec, calib, T, n_moving, 'moving', rng),
             _draw_points(spec, calib, T, n_out - n_moving, 'mismatch', rng),
             _draw_points(spec, calib, T, N - n_out, 'static', rng)]
    # Scatter the outliers to random rows so that row order says nothing.
    order = np.argsort(rng.random((M, N)), axis=1)
    outliers = np.zeros((M, N), bool)
    np.put_along_axis(outliers, order[:, :n_out], True, axis=1)
    observed, clean = {}, {}
    for key in IMAGE_KEYS:
        for dst, which in ((observed, 0), (clean, 1)):
            both = np.concatenate([part[which][key] for part in parts], axis=1)  # outliers first
            arr = np.empty_like(both)
            np.put_along_axis(arr, order[..., None], both, axis=1)
            dst[key] = arr
    noisy = {k: v + rng.normal(0.0, spec.noise_px, v.shape) if spec.noise_px > 0 else v.copy()
             for k, v in observed.items()}
    P0, P1 = spec.projections()
    data = CorrespondenceData(**noisy, P0=P0, P1=P1, rate=spec.rate, width=spec.width,
                              height=spec.height, gt_poses=poses)
    return SimulatedSequence(spec=spec, data=data, velocities=y, T_prev_cur=T, poses=poses,
                             outliers=outliers, clean=clean)


def paper_config(filter_type: str = 'ispkf', ransac: bool = True, threshold: float = 1e-3,
                 noise_px: float = 0.7, max_iterations: int | None = None,
                 base: Config | None = None) -> Config:
    """
    Return the estimator configuration of the paper's simulation experiments.

    Kitt et al.'s estimator as published: the additions for moving vehicles (ground-plane weights,
    outlier streaks, more RANSAC samples after a reset) and the robust reweighting of the final
    update are switched off.

    Parameters
    ----------
    filter_type : str
        ``ispkf``, ``iekf``, ``ukf`` or ``ekf``.
    ransac : bool
        RANSAC outlier rejection on or off.
    threshold : float
        Termination threshold of the iterated filters, both in m/s and in deg/s (Kitt et al.,
        footnote 2).
    noise_px : float
        Simulated pixel noise; the filter's ``pixel_noise_px`` is set to it (at least
        :data:`MIN_FILTER_NOISE_PX` for noiseless data).
    max_iterations : int, optional
        Iteration cap of the iterated filters (default: the base configuration's).
    base : Config, optional
        Configuration to start from (default ``Config()``).

    Returns
    -------
    Config

    """
    base = base or Config()
    overrides = {'filter.type': filter_type, 'ransac.enabled': bool(ransac),
                 'filter.threshold_velocity': float(threshold),
                 'filter.threshold_angular_deg': float(threshold),
                 'filter.pixel_noise_px': max(float(noise_px), MIN_FILTER_NOISE_PX),
                 'ransac.ground_weight': 1.0, 'ransac.max_outlier_streak': 0,
                 'ransac.startup_outlier_ratio': 0.0, 'filter.robust_loss': 'none'}
    if max_iterations is not None:
        overrides['filter.max_iterations'] = int(max_iterations)
    return base.replace(**overrides)


@dataclass
class SimulationRun:
    """
    A simulated sequence and the estimator's output on it.

    Attributes
    ----------
    sequence : SimulatedSequence
    poses : np.ndarray
        (M + 1, 4, 4) float64 estimated ``T_world_cam`` (first left camera frame).
    velocities : np.ndarray
        (M, 6) float64 estimated state of every frame pair (m/s, rad/s).
    iterations : np.ndarray
        (M,) int64 filter iterations of the final update.
    hypotheses : np.ndarray
        (M,) int64 RANSAC samples.
    inliers : np.ndarray
        (M, N) bool correspondences used in the final update.
    statuses : list of TrackingStatus
        Status of every frame pair.
    elapsed_ms : np.ndarray
        (M,) float64 wall time of ``MotionEstimator.estimate`` (milliseconds).
    config : Config

    """

    sequence: SimulatedSequence
    poses: np.ndarray
    velocities: np.ndarray
    iterations: np.ndarray
    hypotheses: np.ndarray
    inliers: np.ndarray
    statuses: list
    elapsed_ms: np.ndarray
    config: Config


def simulate_and_estimate(spec: SimulationSpec, config: Config | None = None,
                          sequence: SimulatedSequence | None = None) -> SimulationRun:
    """
    Simulate a sequence (unless given) and run the estimator over it.

    Parameters
    ----------
    spec : SimulationSpec
        The sequence to simulate.
    config : Config, optional
        Estimator configuration; default :func:`paper_config` with ``spec.noise_px``.
    sequence : SimulatedSequence, optional
        A sequence already simulated from ``spec`` (reused across filter configurations).

    Returns
    -------
    SimulationRun

    """
    config = config or paper_config(noise_px=spec.noise_px)
    seq = sequence or simulate_sequence(spec)
    M, N = len(seq.data), seq.data.num_points
    poses = np.empty((M + 1, 4, 4))
    poses[0] = np.eye(4)
    vel = np.empty((M, 6))
    iters = np.zeros(M, np.int64)
    hyps = np.zeros(M, np.int64)
    inl = np.zeros((M, N), bool)
    ms = np.empty(M)
    statuses = []
    for fe in iter_estimates(seq.data, config):
        k, est = fe.index, fe.estimate
        poses[k + 1] = fe.T_world_cam
        vel[k] = est.velocity
        iters[k] = est.iterations
        hyps[k] = est.hypotheses
        inl[k] = est.inliers
        ms[k] = fe.elapsed_ms
        statuses.append(est.status)
    return SimulationRun(seq, poses, vel, iters, hyps, inl, statuses, ms, config)


def summarize(run: SimulationRun) -> dict:
    """
    Return JSON-ready figures of a simulation run.

    Keys: ``filter``, ``ransac``, ``threshold_velocity`` (m/s), ``threshold_angular_deg``,
    ``max_iterations``, ``spec`` (the SimulationSpec fields), ``frames``, ``distance_m``,
    ``final_position_error_m``, ``final_error_percent`` (of the distance),
    ``final_rotation_error_deg``, ``mean_iterations`` (final update, OK frames),
    ``capped_frames`` (frames whose iterated filter stopped at ``max_iterations``),
    ``mean_hypotheses``, ``ms_per_frame_mean``, ``ms_per_frame_median``, ``ms_per_frame_p95``
    (estimator wall time), ``statuses`` (count per TrackingStatus value),
    ``outliers_accepted_percent`` (outliers used in the final update, % of all outliers; None
    without outliers), ``inliers_rejected_percent`` (true inliers left out, %).
    """
    seq, cfg = run.sequence, run.config
    gt, est = seq.poses, run.poses
    dist = seq.distance_m
    err = float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))
    dR = gt[-1, :3, :3].T @ est[-1, :3, :3]
    rot = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    ok = np.array([s is TrackingStatus.OK for s in run.statuses])
    counts = {s.value: 0 for s in TrackingStatus}
    for s in run.statuses:
        counts[s.value] += 1
    iterated = cfg.filter.type in ('ispkf', 'iekf')
    out_mask = seq.outliers
    n_out = int(out_mask.sum())
    return {
        'filter': cfg.filter.type,
        'ransac': bool(cfg.ransac.enabled),
        'threshold_velocity': cfg.filter.threshold_velocity,
        'threshold_angular_deg': cfg.filter.threshold_angular_deg,
        'max_iterations': cfg.filter.max_iterations,
        'spec': asdict(seq.spec),
        'frames': len(run.statuses),
        'distance_m': dist,
        'final_position_error_m': err,
        'final_error_percent': 100.0 * err / dist if dist > 0 else None,
        'final_rotation_error_deg': rot,
        'mean_iterations': float(run.iterations[ok].mean()) if ok.any() else None,
        'capped_frames': int(np.sum(run.iterations[ok] >= cfg.filter.max_iterations))
        if iterated else 0,
        'mean_hypotheses': float(run.hypotheses.mean()),
        'ms_per_frame_mean': float(run.elapsed_ms.mean()),
        'ms_per_frame_median': float(np.median(run.elapsed_ms)),
        'ms_per_frame_p95': float(np.percentile(run.elapsed_ms, 95)),
        'statuses': counts,
        'outliers_accepted_percent':
            100.0 * float((run.inliers & out_mask).sum()) / n_out if n_out else None,
        'inliers_rejected_percent':
            100.0 * float((~run.inliers & ~out_mask).sum()) / max(int((~out_mask).sum()), 1),
    }


def run_simulation(spec: SimulationSpec, config: Config | None = None) -> dict:
    """
    Simulate a sequence, estimate its trajectory and return the figures of :func:`summarize`.

    Parameters
    ----------
    spec : SimulationSpec
        The sequence (``frames``, ``points``, ``noise_px``, ``outlier_ratio``, ``seed``, ...).
    config : Config, optional
        Estimator configuration; default :func:`paper_config` with ``spec.noise_px``.

    Returns
    -------
    dict
        JSON-ready results (see :func:`summarize`).

    """
    return summarize(simulate_and_estimate(spec, config))
