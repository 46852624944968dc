"""
Accuracy and speed of the whole pipeline: real clips, rendered sequences, degradations, ablation.

Prints six tables (``StereoOdometry(config).process`` frame by frame, default configuration
unless stated):

1. real KITTI clips of the data folder: end-point drift (% of the ground-truth path) next to
   libviso2 (VISO2-S) measured on this machine, ATE, RPE (RMSE over frame pairs), lost frames;
   frame-to-frame errors (translation in m and in % of the true step, rotation in deg) with
   the worst frame; and a breakdown of the end error (scale, heading, along / across / up).
   Then the static EuRoC clip: the estimated displacement (m) over the clip, which should be 0;
2. time per frame at KITTI size with 200 features and one thread (``pipeline.threads: 1``,
   OMP / OpenBLAS / MKL threads set to 1 before NumPy loads): median and p95 of every key of
   ``timings_ms`` (wall clock), and the thread CPU time (``time.thread_time``) around
   ``process()``, which a busy machine disturbs less; target: total median <= half of
   libviso2's time (``LIBVISO2_MS``, about 9 ms);
3. rendered sequences at 1241x376 (presets urban, highway, exposure): the KITTI devkit metric
   (t_rel %, r_rel deg/100 m), ATE, end drift, scale error, the share of inliers on moving
   vehicles and of inliers inconsistent with the true motion (> 3 px); target on the clean
   scenes (urban, highway): <= 0.3 % and <= 0.3 deg/100 m (libviso2 on a comparable render:
   0.15 %, 0.21 deg/100 m);
4. degradations of the urban preset, rendered with the renderer's own options: Gaussian blur
   (sigma 1.5 px instead of 0.5), sensor noise (sigma 5 grey levels instead of 1), automatic
   exposure changes (the exposure preset's gain changes and left/right gain mismatch), and a
   wrong calibration handed to the pipeline (focal length +0.5 %, baseline +1 %, principal
   point +2 px) while the images are rendered with the true one; a good real rig's residual
   calibration error (``synthetic.RIG_ERROR``: the right camera's rows off by 0.25 px, its
   disparity by 0.15 px, its focal by 0.03 %, true baseline +0.3 % and focal -0.2 %; the
   pipeline gets the nominal calibration), independent per-camera exposure jumps and
   vignetting (``synthetic.PHOTOMETRIC``: gain x U[0.7, 1.3], offset U[-5, 5] grey levels per
   camera and frame, 30 % vignetting), and both; each row also gives t_rel after one scale
   factor fitted to the whole trajectory (``metrics.kitti_odometry_error_scale_aligned``);
5. Huang et al.'s ablation (Tables I / II style) on the urban render and the KITTI clips: per
tracker
   variant (and bi-circular mode for ``full``) the accuracy, features and inliers per frame and
   the tracking milliseconds;
6. diagnostics of where the errors come from: the share of RANSAC inliers on moving vehicles
   (from the renderer's static masks), the highway render without moving vehicles and with a
   1 px RANSAC gate, the spread of the clean-scene figures over other seeds (the scene layout
   depends on the seed and on the number of frames), and a zero-motion test (the first pair
   of each real clip fed repeatedly) with the stereo offsets v_R - v_L of the tracked points.

Rendered sequences are rendered once and kept in memory while needed; runs with the same
sequence and configuration are shared between the tables.

Usage::

    python benchmarks/bench_accuracy.py [--data ../shared/data] [--frames N] [--repeat 3]
        [--seed 0] [--quick] [--json results.json] [--set road.enabled=true ...]

``--frames`` shortens every rendered sequence (default: the preset's count, 300 or 200); the
renderer lays the scene out from the duration, so a shorter sequence is another scene, not a
prefix. ``--quick`` renders 150 frames, times one repeat and sweeps one extra seed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import sys
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.config import Config, overrides_from_items  # noqa: E402
from stereo_vo_ros.errors import ConfigError  # noqa: E402
from stereo_vo_ros.estimation.camera import StereoCalibration  # noqa: E402
from stereo_vo_ros.estimation.motion import TransferModel, velocity_from_transform  # noqa: E402
from stereo_vo_ros.evaluation import metrics  # noqa: E402
from stereo_vo_ros.io import open_sequence  # noqa: E402
from stereo_vo_ros.pipeline import StereoOdometry  # noqa: E402
from stereo_vo_ros.records import StereoFrame, TrackingStatus  # noqa: E402
from stereo_vo_ros.synthetic import (PHOTOMETRIC, RIG_ERROR, SequenceSpec,  # noqa: E402
                                     StereoRenderer)

#: Overrides (``--set``) applied to every configuration of the run.
BASE_OVERRIDES: dict = {}


def base_config() -> Config:
    """Return the default configuration, one thread, with the ``--set`` overrides of this run."""
    return Config().replace(**{'pipeline.threads': 1, **BASE_OVERRIDES})


KITTI_CLIPS = ('kitti06_f0000-0050', 'kitti01_f0000-0050')
STATIC_CLIP = 'euroc_v101_static'
#: libviso2 (VISO2-S) end-point drift (%) measured on this machine.
LIBVISO2_DRIFT_PCT = {'kitti06_f0000-0050': 1.06, 'kitti01_f0000-0050': 6.7}
#: libviso2 on a comparable render: t_rel (%) and r_rel (deg/100 m).
LIBVISO2_RENDER = (0.15, 0.21)
#: libviso2 (VISO2-S, its process() only), median ms per pair on kitti06, one run on this machine.
LIBVISO2_MS = 18.3
TARGET_T_REL_PCT, TARGET_R_REL_DEG, TARGET_TOTAL_MS = 0.3, 0.3, 0.5 * LIBVISO2_MS
CLEAN_PRESETS = ('urban', 'highway')
#: Degradations of the urban preset: label -> (SequenceSpec overrides, calibration error).
DEGRADATIONS = {
    'clean': ({}, False),
    'blur 1.5px': ({'blur_sigma_px': 1.5}, False),
    'noise 5gl': ({'noise_std': 5.0}, False),
    'exposure': ({'exposure_change': 0.35, 'stereo_gain_mismatch': 0.05}, False),
    'wrong calib': ({}, True),
    'rig error': (RIG_ERROR, False),
    'photometric': (PHOTOMETRIC, False),
    'rig + photo': ({**RIG_ERROR, **PHOTOMETRIC}, False),
}
#: Calibration error of the ``wrong calib`` row: focal factor, baseline factor, pp shift (px).
CALIB_ERROR = (1.005, 1.01, 2.0)
#: Ablation rows: (variant, bicircular_mode or None for the default, departures switched off).
#: The last three rows switch off this package's two departures from Huang et al.'s tracker (the
#: affine refinement of every match and the aperture check); "neither" is the paper's tracker.
NO_AFFINE = {'tracker.affine_refinement': False}
NO_APERTURE = {'tracker.min_eigen_ratio': 0.0, 'tracker.min_flow_edge_ratio': 0.0,
               'tracker.min_flow_edge_ratio_tracked': 0.0}
ABLATION = (('baseline', None, {}), ('dc', None, {}), ('bc', None, {}), ('db', None, {}),
            ('full', 'closure', {}), ('full', 'roundtrip', {}),
            ('full', 'closure', NO_AFFINE), ('full', 'closure', NO_APERTURE),
            ('full', 'closure', {**NO_AFFINE, **NO_APERTURE}))
GOOD = (TrackingStatus.OK, TrackingStatus.INITIALIZING)
#: An inlier whose current left pixel is this far (px) from its true-motion transfer is bad.
BAD_INLIER_PX = 3.0


def departures_off(extra: dict) -> str:
    """Label of the departures an ablation row switches off."""
    if not extra:
        return '-'
    names = [name for name, part in (('affine', NO_AFFINE), ('aperture', NO_APERTURE))
             if all(extra.get(k) == v for k, v in part.items())]
    return 'neither' if len(names) == 2 else f'no {names[0]}'


# -- sequences ------------------------------------------------------------------------------
class Clip:
    """
    A sequence held in memory.

    Attributes: ``frames`` (list of StereoFrame), ``gt`` ((N, 4, 4) ground-truth T_world_cam,
    metres), ``static`` (rendered clips: list of (H, W) bool left masks, False on moving
    vehicles; None for real clips), ``info`` (how it was made), ``size`` (width, height).
    """

    def __init__(self, name: str, frames: list, gt: np.ndarray, info: str = '',
                 static: list | None = None) -> None:
        self.name = name
        self.frames = frames
        self.gt = gt
        self.info = info
        self.static = static
        self.size = frames[0].calibration.size

    def with_calibration(self, calib: StereoCalibration, name: str) -> 'Clip':
        """Return the same images and ground truth with another calibration."""
        frames = [StereoFrame(f.left, f.right, f.stamp_s, calib) for f in self.frames]
        return Clip(name, frames, self.gt, self.info, self.static)


#: The read-only clips next to the repository (``../shared/data``), as CI lays them out.
SHARED_DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'
#: Pairs of the rendered urban scenes the timing benchmarks add with ``--render WxH``.
RENDER_PAIRS = 60


def load_real(folder: Path) -> Clip:
    """Load a KITTI-layout folder into memory (images are read once)."""
    seq = open_sequence(folder)
    return Clip(folder.name, list(seq), seq.ground_truth)


def render(spec: SequenceSpec, name: str) -> Clip:
    """Render every pair of a spec (and its left static mask) into memory."""
    t0 = time.perf_counter()
    renderer = StereoRenderer(spec)
    frames, static = [], []
    for i in range(len(renderer)):
        pair = renderer.render(i, depth=True)
        frames.append(pair.stereo_frame(renderer.calibration))
        static.append(pair.static_left)
    info = f'rendered {len(frames)} pairs in {time.perf_counter() - t0:.0f} s'
    return Clip(name, frames, renderer.poses.copy(), info, static)


def image_size(text: str) -> tuple[int, int] | None:
    """Return (width, height) of ``'WxH'`` (pixels; ``x`` in either case), or None."""
    try:
        width, height = (int(v) for v in text.lower().split('x'))
    except ValueError:
        return None
    return width, height


def render_urban(width: int, height: int, name: str) -> Clip:
    """Render the urban preset at ``width`` x ``height`` pixels (``RENDER_PAIRS`` pairs)."""
    return render(SequenceSpec.preset('urban', n_frames=RENDER_PAIRS, width=width,
                                      height=height), name)


def wrong_calibration(calib: StereoCalibration) -> StereoCalibration:
    """Return the calibration with focal, baseline and principal point off by CALIB_ERROR."""
    focal, base, shift = CALIB_ERROR
    P0 = calib.projection_left().copy()
    P0[0, 0] *= focal
    P0[1, 1] *= focal
    P0[:2, 2] += shift
    P1 = P0.copy()
    P1[0, 3] = -P0[0, 0] * calib.baseline_m * base
    return StereoCalibration.from_projections(P0, P1, *calib.size)


# -- running --------------------------------------------------------------------------------
def run_clip(clip: Clip, config: Config) -> dict:
    """
    Run the pipeline over a clip and return poses and per-frame records.

    Keys: ``poses`` (N, 4, 4), ``status`` (N,) TrackingStatus, ``tracked`` / ``inliers``
    (N,) int, ``mover_inliers`` (N,) int inliers seen on moving vehicles (rendered clips,
    else 0), ``bad_inliers`` (N,) int inliers farther than BAD_INLIER_PX from where the
    ground-truth motion transfers them, ``timings`` (list of dicts, ms), ``cpu_ms`` (N,)
    thread CPU time of ``process()`` (ms), ``all_cpu_ms`` (N,) CPU time of every thread and the
    worker process during ``process()`` (ms; the worker's in ticks of 10 ms, meaningful summed
    over many pairs), ``worker_cpu_ms`` (N,) the worker process's share of it, ``rig_measured``
    (N,) bool whether the pair's work after its pose measured the rig (its rig record, completed
    then, says ``updated`` or ``rejected``), ``first_dy`` stereo offsets v_R - v_L (px) of the
    previous points of the second frame.
    """
    vo = StereoOdometry(config)
    vo.workers.wait_ready()  # a worker process's start-up is not timed
    poses, status, tracked, inliers, movers, bad, timings, cpu = [], [], [], [], [], [], [], []
    all_cpu, worker_cpu, results = [], [], []
    first_dy = np.zeros(0)
    for i, frame in enumerate(clip.frames):
        c0, p0, w0 = time.thread_time(), time.process_time(), vo.workers.worker_cpu_seconds()
        res = vo.process(frame)
        cpu.append((time.thread_time() - c0) * 1e3)
        p1 = time.process_time()
        worker_cpu.append((vo.workers.worker_cpu_seconds() - w0) * 1e3)
        all_cpu.append((p1 - p0) * 1e3 + worker_cpu[-1])
        if not res.accepted:
            raise RuntimeError(f'{clip.name}: frame at {frame.stamp_s} s was not accepted')
        results.append(res)
        poses.append(res.T_world_cam)
        status.append(res.status)
        tracked.append(res.n_tracked)
        inliers.append(res.n_inliers)
        timings.append(res.timings_ms)
        on_movers = off_truth = 0
        corr = res.features
        if corr is not None and len(corr) and res.inliers is not None:
            if i == 1:
                first_dy = corr.prev_right[:, 1] - corr.prev_left[:, 1]
            dt = frame.stamp_s - clip.frames[i - 1].stamp_s
            sub = corr.subset(res.inliers)
            model = TransferModel(clip.frames[i - 1].calibration, sub.prev_left, sub.prev_right,
                                  dt)
            T_prev_cur = inv_se3(clip.gt[i - 1]) @ clip.gt[i]
            pred = model.predict(velocity_from_transform(T_prev_cur, dt))
            with np.errstate(invalid='ignore'):
                off_truth = int(np.count_nonzero(
                    ~(np.linalg.norm(pred[:, :2] - sub.cur_left, axis=1) <= BAD_INLIER_PX)))
            if clip.static is not None:
                mask = clip.static[i]
                px = np.round(corr.cur_left[res.inliers]).astype(int)
                px[:, 0] = np.clip(px[:, 0], 0, mask.shape[1] - 1)
                px[:, 1] = np.clip(px[:, 1], 0, mask.shape[0] - 1)
                on_movers = int(np.count_nonzero(~mask[px[:, 1], px[:, 0]]))
        movers.append(on_movers)
        bad.append(off_truth)
    vo.close()
    measured = np.array([r.rig is not None and r.rig.last in ('updated', 'rejected')
                         for r in results], bool)
    return {'poses': np.asarray(poses), 'status': status, 'tracked': np.asarray(tracked),
            'inliers': np.asarray(inliers), 'mover_inliers': np.asarray(movers),
            'bad_inliers': np.asarray(bad),
            'timings': timings, 'cpu_ms': np.asarray(cpu), 'all_cpu_ms': np.asarray(all_cpu),
            'worker_cpu_ms': np.asarray(worker_cpu), 'rig_measured': measured,
            'first_dy': first_dy}


class Runner:
    """Run (clip, config overrides) pairs once and remember the outputs."""

    def __init__(self) -> None:
        self._memo: dict = {}

    def __call__(self, clip: Clip, **overrides: object) -> dict:
        """Return the run of ``clip`` with ``base_config().replace(**overrides)``."""
        config = base_config().replace(**overrides)
        key = (clip.name, repr(config.as_dict()))
        if key not in self._memo:
            self._memo[key] = run_clip(clip, config)
        return self._memo[key]


# -- figures --------------------------------------------------------------------------------
def inv_se3(T: np.ndarray) -> np.ndarray:
    """Invert (..., 4, 4) rigid transforms."""
    out = np.zeros_like(T)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum('...ij,...j->...i', rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def frame_errors(gt: np.ndarray, est: np.ndarray) -> dict:
    """Frame-to-frame errors: (N-1,) translation (m, % of the true step), rotation (deg)."""
    dg = inv_se3(gt[:-1]) @ gt[1:]
    de = inv_se3(est[:-1]) @ est[1:]
    err = inv_se3(dg) @ de
    t_m = np.linalg.norm(err[:, :3, 3], axis=1)
    step = np.linalg.norm(dg[:, :3, 3], axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        t_pct = np.where(step > 1e-3, 100.0 * t_m / step, np.nan)
    return {'t_m': t_m, 't_pct': t_pct,
            'r_deg': np.degrees(metrics.rotation_angle(err[:, :3, :3]))}


def nanstat(values: np.ndarray, func) -> float:
    """Apply a NumPy reduction to the finite values; NaN when there are none."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(func(v)) if v.size else math.nan


def speed_ratio(gt: np.ndarray, est: np.ndarray) -> np.ndarray:
    """(N-1,) estimated / true distance per frame (NaN where the true step is < 1 mm)."""
    true = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    step = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(true > 1e-3, step / true, np.nan)


def yaw_deg(T: np.ndarray) -> np.ndarray:
    """Heading (deg) of camera poses about the world y axis (optical frame, y down)."""
    return np.degrees(np.arctan2(T[..., 0, 2], T[..., 2, 2]))


def breakdown(gt: np.ndarray, est: np.ndarray) -> dict:
    """
    Split the end error into scale, heading and components in the last true camera frame.

    ``scale_pct``: estimated / true path length - 1 (%); ``heading_deg``: end rotation error
    angle; ``along_m`` / ``across_m`` / ``up_m``: end position error along the last true
    camera's z, x and -y axes (m).
    """
    len_gt = metrics.path_distances(gt)[-1]
    len_est = metrics.path_distances(est)[-1]
    d = gt[-1, :3, :3].T @ (est[-1, :3, 3] - gt[-1, :3, 3])
    rot = gt[-1, :3, :3].T @ est[-1, :3, :3]
    return {'scale_pct': 100.0 * (len_est / len_gt - 1.0) if len_gt > 0 else math.nan,
            'heading_deg': float(np.degrees(metrics.rotation_angle(rot))),
            'along_m': float(d[2]), 'across_m': float(d[0]), 'up_m': float(-d[1])}


def summary(clip: Clip, run: dict) -> dict:
    """Metrics of one run: metrics.evaluate plus errors, breakdown, counts and timings."""
    out = metrics.evaluate(clip.gt, run['poses'])
    fe = frame_errors(clip.gt, run['poses'])
    out.update(breakdown(clip.gt, run['poses']))
    worst = int(np.argmax(fe['t_m']))
    ratio = speed_ratio(clip.gt, run['poses'])
    slow = np.flatnonzero(ratio < 0.5)
    out.update({
        'f2f_t_m_mean': float(np.mean(fe['t_m'])), 'f2f_t_m_median': float(np.median(fe['t_m'])),
        'f2f_t_m_max': float(fe['t_m'][worst]),
        'f2f_t_pct_mean': nanstat(fe['t_pct'], np.mean),
        'f2f_t_pct_median': nanstat(fe['t_pct'], np.median),
        'f2f_r_deg_mean': float(np.mean(fe['r_deg'])),
        'f2f_r_deg_median': float(np.median(fe['r_deg'])),
        'f2f_r_deg_max': float(np.max(fe['r_deg'])),
        'worst_frame': worst + 1, 'worst_frame_tracked': int(run['tracked'][worst + 1]),
        'worst_frame_inliers': int(run['inliers'][worst + 1]),
        'lost_frames': int(sum(s not in GOOD for s in run['status'])),
        'features_per_frame': float(np.mean(run['tracked'][1:])),
        'inliers_per_frame': float(np.mean(run['inliers'][1:])),
        'mover_inlier_pct': (100.0 * run['mover_inliers'].sum() / max(run['inliers'].sum(), 1)
                             if clip.static is not None else math.nan),
        'bad_inlier_pct': 100.0 * run['bad_inliers'].sum() / max(run['inliers'].sum(), 1),
        'slow_frames': int(slow.size), 'first_slow_frame': int(slow[0]) + 1 if slow.size else -1,
        'track_ms_median': float(np.median([t['track'] for t in run['timings'][1:]])),
        'total_ms_median': float(np.median([t['total'] for t in run['timings'][1:]])),
        'cpu_ms_median': float(np.median(run['cpu_ms'][1:])),
        'turn_deg': float(np.sum(np.abs(np.diff(np.unwrap(np.radians(yaw_deg(clip.gt))))))
                          * 180.0 / np.pi),
    })
    return out


def fmt(value: float, width: int, prec: int) -> str:
    """Right-aligned number, '-' for NaN."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return f'{"-":>{width}s}'
    return f'{value:{width}.{prec}f}'


def verdict(ok: bool) -> str:
    """Return MET or MISSED."""
    return 'MET' if ok else 'MISSED'


# -- tables ---------------------------------------------------------------------------------
def table_real(clips: dict, static: Clip | None, runner: Runner) -> dict:
    """Table 1: KITTI clips and the static EuRoC clip with the default configuration."""
    results = {}
    print('\n== 1. Real KITTI clips (default configuration: variant full, closure) ==')
    if not clips:
        print('  (no KITTI clip found: skipped)')
    else:
        print(f'{"clip":20s} {"size":>9s} {"frames":>6s} {"path m":>7s} {"drift %":>8s} '
              f'{"libviso2 %":>10s} {"ATE m":>7s} {"RPE t m":>8s} {"RPE r deg":>9s} '
              f'{"lost":>5s}')
        for name, clip in clips.items():
            s = summary(clip, runner(clip))
            results[name] = s
            ref = LIBVISO2_DRIFT_PCT.get(name, math.nan)
            print(f'{name:20s} {clip.size[0]:>4d}x{clip.size[1]:<4d} {s["frames"]:6d} '
                  f'{fmt(s["path_length_m"], 7, 1)} {fmt(s["end_drift_pct"], 8, 2)} '
                  f'{fmt(ref, 10, 2)} {fmt(s["ate_rmse_m"], 7, 3)} '
                  f'{fmt(s["rpe_trans_rmse_m"], 8, 4)} {fmt(s["rpe_rot_rmse_deg"], 9, 4)} '
                  f'{s["lost_frames"]:5d}')
        print('\nFrame-to-frame errors (E = inv(dGT) dEST per consecutive pair; % of the true '
              'step; worst: frame with the largest translation error)')
        print(f'{"clip":20s} {"t m mean/med/max":>22s} {"t % mean/med":>13s} '
              f'{"r deg mean/med/max":>22s} {"worst":>6s} {"tracked":>7s} {"inl":>4s}')
        for name, s in results.items():
            print(f'{name:20s} {s["f2f_t_m_mean"]:6.4f}/{s["f2f_t_m_median"]:6.4f}/'
                  f'{s["f2f_t_m_max"]:6.4f}   {s["f2f_t_pct_mean"]:5.2f}/'
                  f'{s["f2f_t_pct_median"]:5.2f}  {s["f2f_r_deg_mean"]:6.4f}/'
                  f'{s["f2f_r_deg_median"]:6.4f}/{s["f2f_r_deg_max"]:6.4f} '
                  f'{s["worst_frame"]:6d} {s["worst_frame_tracked"]:7d} '
                  f'{s["worst_frame_inliers"]:4d}')
        print('\nEnd error breakdown (scale: estimated/true path length - 1; heading: end '
              'rotation error; along/across/up: end position error in the last true camera '
              f'frame; bad%: inliers > {BAD_INLIER_PX:.0f} px from their transfer under the '
              'ground-truth motion)')
        print(f'{"clip":20s} {"scale %":>8s} {"heading deg":>11s} {"along m":>8s} '
              f'{"across m":>8s} {"up m":>7s} {"inl/frame":>9s} {"feat/frame":>10s} '
              f'{"bad%":>5s}')
        for name, s in results.items():
            print(f'{name:20s} {s["scale_pct"]:8.2f} {s["heading_deg"]:11.3f} '
                  f'{s["along_m"]:8.3f} {s["across_m"]:8.3f} {s["up_m"]:7.3f} '
                  f'{s["inliers_per_frame"]:9.1f} {s["features_per_frame"]:10.1f} '
                  f'{s["bad_inlier_pct"]:5.1f}')
    print('\nStatic EuRoC clip (MAV at rest: the estimate should not move)')
    if static is None:
        print('  (no euroc_v101_static folder: skipped)')
        return results
    run = runner(static)
    p = run['poses'][:, :3, 3]
    disp = np.linalg.norm(p - p[0], axis=1)
    gt_disp = np.linalg.norm(static.gt[-1, :3, 3] - static.gt[0, :3, 3])
    rot = float(np.degrees(metrics.rotation_angle(run['poses'][-1, :3, :3])))
    est_len = float(metrics.path_distances(run['poses'])[-1])
    lost = int(sum(s not in GOOD for s in run['status']))
    duration = static.frames[-1].stamp_s - static.frames[0].stamp_s
    results[STATIC_CLIP] = {'end_displacement_m': float(disp[-1]),
                            'max_displacement_m': float(disp.max()),
                            'end_rotation_deg': rot, 'est_path_m': est_len,
                            'gt_end_displacement_m': float(gt_disp), 'lost_frames': lost,
                            'frames': len(static.frames), 'duration_s': duration}
    print(f'{"clip":20s} {"frames":>6s} {"dur s":>6s} {"end m":>7s} {"max m":>7s} '
          f'{"path m":>7s} {"end rot deg":>11s} {"GT end m":>8s} {"lost":>5s}')
    print(f'{STATIC_CLIP:20s} {len(static.frames):6d} {duration:6.2f} {disp[-1]:7.4f} '
          f'{disp.max():7.4f} {est_len:7.4f} {rot:11.4f} {gt_disp:8.4f} {lost:5d}')
    return results


def timing_rows(clip: Clip, repeat: int) -> dict:
    """Per-stage ms of ``repeat`` runs (first frame of each left out), pooled over runs."""
    stages: dict[str, list] = {}
    cpu: list = []
    for _ in range(repeat):
        run = run_clip(clip, base_config())
        for t in run['timings'][1:]:
            for key, value in t.items():
                stages.setdefault(key, []).append(value)
        cpu.extend(run['cpu_ms'][1:])
    stages['total (thread CPU)'] = cpu
    return {k: (float(np.median(v)), float(np.percentile(v, 95))) for k, v in stages.items()}


def table_timing(clips: list, repeat: int) -> dict:
    """Table 2: milliseconds per frame and stage, wall and thread CPU clocks."""
    cfg = base_config()
    print(f'\n== 2. Time per frame (ms, median / p95 over frames of {repeat} run(s), first '
          f'frame left out), {cfg.tracker.max_features} features, cv2 threads '
          f'{cv2.getNumThreads()}, OMP/OpenBLAS threads {os.environ["OMP_NUM_THREADS"]}, '
          f'load average before {os.getloadavg()[0]:.2f} ==')
    results = {c.name: timing_rows(c, repeat) for c in clips}
    keys = sorted({k for r in results.values() for k in r},
                  key=lambda k: (k.startswith('total'), not k.startswith('track'),
                                 k != 'track', k == 'track.total', k))
    print(f'{"stage":20s} ' + ' '.join(f'{f"{c.name} {c.size[0]}x{c.size[1]}":>30s}'
                                       for c in clips))
    for key in keys:
        cells = []
        for c in clips:
            med, p95 = results[c.name].get(key, (math.nan, math.nan))
            cells.append(f'{fmt(med, 21, 2)} /{fmt(p95, 7, 2)}')
        print(f'{key:20s} ' + ' '.join(cells))
    for c in clips:
        med = results[c.name]['total'][0]
        cpu = results[c.name]['total (thread CPU)'][0]
        print(f'target total median <= {TARGET_TOTAL_MS:.1f} ms on {c.name}: wall {med:.2f} ms '
              f'{verdict(med <= TARGET_TOTAL_MS)}, thread CPU {cpu:.2f} ms '
              f'{verdict(cpu <= TARGET_TOTAL_MS)}')
    print(f'(load average after: {os.getloadavg()[0]:.2f}; the machine has {os.cpu_count()} '
          'cores)')
    return {name: {k: {'median': v[0], 'p95': v[1]} for k, v in r.items()}
            for name, r in results.items()}


SYN_HEADER = (f'{"sequence":14s} {"frames":>6s} {"path m":>7s} {"turn deg":>8s} '
              f'{"t_rel %":>8s} {"r_rel":>6s} {"seg":>4s} {"ATE m":>7s} {"drift %":>8s} '
              f'{"scale %":>8s} {"RPE t m":>8s} {"RPE r deg":>9s} {"feat":>5s} {"inl":>5s} '
              f'{"mov%":>5s} {"bad%":>5s} {"lost":>4s}')


def syn_row(label: str, s: dict) -> str:
    """One line of the rendered-sequence tables."""
    return (f'{label:14s} {s["frames"]:6d} {fmt(s["path_length_m"], 7, 1)} '
            f'{fmt(s["turn_deg"], 8, 0)} {fmt(s["t_rel_pct"], 8, 3)} '
            f'{fmt(s["r_rel_deg_per_100m"], 6, 3)} {s["segments"]:4d} '
            f'{fmt(s["ate_rmse_m"], 7, 3)} {fmt(s["end_drift_pct"], 8, 3)} '
            f'{fmt(s["scale_pct"], 8, 3)} {fmt(s["rpe_trans_rmse_m"], 8, 4)} '
            f'{fmt(s["rpe_rot_rmse_deg"], 9, 4)} {s["features_per_frame"]:5.0f} '
            f'{s["inliers_per_frame"]:5.0f} {fmt(s["mover_inlier_pct"], 5, 1)} '
            f'{s["bad_inlier_pct"]:5.1f} {s["lost_frames"]:4d}')


def table_rendered(specs: dict, cache: dict, runner: Runner) -> dict:
    """Table 3: rendered presets with the default configuration."""
    print('\n== 3. Rendered sequences at 1241x376 (KITTI devkit metric: t_rel %, r_rel '
          'deg/100 m; turn: total heading change; scale: estimated/true path length - 1; '
          'feat/inl: per frame; mov%: share of the inliers seen on moving vehicles; bad%: share '
          f'of the inliers > {BAD_INLIER_PX:.0f} px from their true-motion transfer) ==')
    print(SYN_HEADER)
    results = {}
    for name, spec in specs.items():
        if name not in cache:
            cache[name] = render(spec, name)
        clip = cache[name]
        s = summary(clip, runner(clip))
        s['moving_objects'] = spec.moving_objects
        results[name] = s
        print(syn_row(name, s) + f'   ({clip.info}, {spec.moving_objects} movers)')
    print(f'libviso2 on a comparable render: {LIBVISO2_RENDER[0]:.2f} %, '
          f'{LIBVISO2_RENDER[1]:.2f} deg/100 m')
    for name in CLEAN_PRESETS:
        if name in results:
            s = results[name]
            print(f'target on clean {name}: t_rel {fmt(s["t_rel_pct"], 0, 3)} % <= '
                  f'{TARGET_T_REL_PCT} {verdict(s["t_rel_pct"] <= TARGET_T_REL_PCT)}, r_rel '
                  f'{fmt(s["r_rel_deg_per_100m"], 0, 3)} deg/100 m <= {TARGET_R_REL_DEG} '
                  f'{verdict(s["r_rel_deg_per_100m"] <= TARGET_R_REL_DEG)}')
    return results


def table_degradations(base: SequenceSpec, cache: dict, runner: Runner) -> dict:
    """Table 4: the urban preset under blur, noise, exposure changes and a wrong calibration."""
    focal, base_f, shift = CALIB_ERROR
    print(f'\n== 4. Degradations of the urban preset (renderer default: blur '
          f'{base.blur_sigma_px} px, noise {base.noise_std} grey levels; wrong calib: focal '
          f'x{focal}, baseline x{base_f}, principal point +{shift} px given to the pipeline) ==')
    print(SYN_HEADER)
    results = {}
    for label, (overrides, bad_calib) in DEGRADATIONS.items():
        if overrides:
            clip = render(base.replace(**overrides), f'urban {label}')
        else:
            clip = cache['urban']
        if bad_calib:
            clip = clip.with_calibration(wrong_calibration(clip.frames[0].calibration),
                                         f'urban {label}')
        run = runner(clip)
        s = summary(clip, run)
        t_s, r_s, _, scale = metrics.kitti_odometry_error_scale_aligned(clip.gt, run['poses'])
        s.update({'t_rel_scaled_pct': t_s, 'r_rel_scaled_deg_per_100m': r_s,
                  'fitted_scale': scale})
        results[label] = s
        print(syn_row(label, s) + f'   scale-aligned t_rel {fmt(t_s, 0, 3)} %, r_rel '
              f'{fmt(r_s, 0, 3)} (x{scale:.4f})')
        del clip
    return results


def table_ablation(clips: list, runner: Runner) -> dict:
    """Table 5: Huang et al.'s ablation per tracker variant on the urban render and KITTI clips."""
    print('\n== 5. Tracker ablation (Huang et al., Tables I/II style): default configuration but '
          'tracker.variant (and bicircular_mode; off: the departures from the paper switched '
          "off, affine refinement and aperture check; neither = Huang et al.'s tracker); "
          'feat/inl: per frame; inl %: inliers / '
          f'features; bad%: inliers > {BAD_INLIER_PX:.0f} px from their true-motion transfer; '
          'track ms: median wall time of the tracker; cpu ms: median thread CPU time of the '
          'whole process() ==')
    print(f'{"sequence":20s} {"variant":9s} {"bc mode":9s} {"off":11s} {"t_rel %":>8s} '
          f'{"r_rel":>6s} '
          f'{"drift %":>8s} {"ATE m":>7s} {"feat":>6s} {"inl":>6s} {"inl %":>6s} '
          f'{"bad%":>5s} {"lost":>4s} {"track ms":>8s} {"cpu ms":>6s}')
    results = {}
    for clip in clips:
        results[clip.name] = {}
        for variant, mode, extra in ABLATION:
            overrides = {'tracker.variant': variant, **extra}
            if mode is not None:
                overrides['tracker.bicircular_mode'] = mode
            off = departures_off(extra)
            s = summary(clip, runner(clip, **overrides))
            shown = mode or (base_config().tracker.bicircular_mode
                             if variant in ('bc', 'db') else '-')
            results[clip.name][f'{variant}/{shown}' + ('' if off == '-' else f'/{off}')] = s
            ratio = 100.0 * s['inliers_per_frame'] / max(s['features_per_frame'], 1e-9)
            print(f'{clip.name:20s} {variant:9s} {shown:9s} {off:11s} {fmt(s["t_rel_pct"], 8, 3)} '
                  f'{fmt(s["r_rel_deg_per_100m"], 6, 3)} {fmt(s["end_drift_pct"], 8, 3)} '
                  f'{fmt(s["ate_rmse_m"], 7, 3)} {s["features_per_frame"]:6.1f} '
                  f'{s["inliers_per_frame"]:6.1f} {ratio:6.1f} {s["bad_inlier_pct"]:5.1f} '
                  f'{s["lost_frames"]:4d} {s["track_ms_median"]:8.2f} '
                  f'{s["cpu_ms_median"]:6.2f}')
    return results


def identical_pairs(clip: Clip, frames: int) -> dict:
    """Feed the first pair of a clip ``frames`` times: the estimate must stay at identity."""
    f0 = clip.frames[0]
    dt = clip.frames[1].stamp_s - f0.stamp_s
    same = Clip(f'{clip.name} first pair x{frames}',
                [StereoFrame(f0.left, f0.right, f0.stamp_s + i * dt, f0.calibration)
                 for i in range(frames)], np.tile(np.eye(4), (frames, 1, 1)))
    run = run_clip(same, base_config())
    end = run['poses'][-1]
    dy = run['first_dy']
    return {'frames': frames, 'dt_s': dt, 'end_m': float(np.linalg.norm(end[:3, 3])),
            'end_rot_deg': float(np.degrees(metrics.rotation_angle(end[:3, :3]))),
            'rotvec_deg': np.degrees(cv2.Rodrigues(end[:3, :3])[0].ravel()).tolist(),
            'dy_mean_px': nanstat(dy, np.mean), 'dy_rms_px': nanstat(dy ** 2, np.mean) ** 0.5}


def table_diagnostics(cache: dict, specs: dict, real: dict, static: Clip | None,
                      runner: Runner, seeds: list) -> dict:
    """Table 6: where the errors come from (moving vehicles, RANSAC gate, stereo offsets)."""
    results: dict = {'gate': {}, 'identical': {}}
    print('\n== 6. Diagnostics ==')
    print('a) Moving vehicles and the RANSAC gate (slow: frames whose estimated step is below '
          'half the true one; first: the first of them)')
    print(f'{"sequence":16s} {"setting":22s} {"t_rel %":>8s} {"r_rel":>6s} {"drift %":>8s} '
          f'{"scale %":>8s} {"inl":>5s} {"mov%":>5s} {"bad%":>5s} {"slow":>5s} {"first":>5s}')
    rows = []
    if 'highway' in cache:
        rows.append((cache['highway'], 'default', {}))
        rows.append((cache['highway'], 'ransac gate 1 px', {'ransac.inlier_threshold_px': 1.0}))
        rows.append((render(specs['highway'].replace(moving_objects=0), 'highway static'),
                     'no moving vehicles', {}))
    rows.append((cache['urban'], 'default', {}))
    rows.append((cache['urban'], 'ransac gate 1 px', {'ransac.inlier_threshold_px': 1.0}))
    for clip in real.values():
        rows.append((clip, 'ransac gate 1 px', {'ransac.inlier_threshold_px': 1.0}))
    for clip, label, overrides in rows:
        s = summary(clip, runner(clip, **overrides))
        results['gate'][f'{clip.name}/{label}'] = s
        print(f'{clip.name[:16]:16s} {label:22s} {fmt(s["t_rel_pct"], 8, 3)} '
              f'{fmt(s["r_rel_deg_per_100m"], 6, 3)} {fmt(s["end_drift_pct"], 8, 3)} '
              f'{fmt(s["scale_pct"], 8, 2)} {s["inliers_per_frame"]:5.0f} '
              f'{fmt(s["mover_inlier_pct"], 5, 1)} {s["bad_inlier_pct"]:5.1f} '
              f'{s["slow_frames"]:5d} {s["first_slow_frame"]:5d}')
    print('\nb) Seed spread of the clean presets (seed 0 is table 3; the scene layout, route and '
          'vehicles change with the seed)')
    print(f'{"sequence":16s} {"seed":>4s} {"t_rel %":>8s} {"r_rel":>6s} {"drift %":>8s} '
          f'{"scale %":>8s} {"inl":>5s} {"mov%":>5s} {"bad%":>5s} {"slow":>5s}  target')
    results['seeds'] = {}
    for name in CLEAN_PRESETS:
        for seed in seeds:
            clip = render(specs[name].replace(seed=seed), f'{name} seed {seed}')
            s = summary(clip, runner(clip))
            del clip
            results['seeds'][f'{name}/{seed}'] = s
            ok = s['t_rel_pct'] <= TARGET_T_REL_PCT and s['r_rel_deg_per_100m'] <= \
                TARGET_R_REL_DEG
            print(f'{name:16s} {seed:4d} {fmt(s["t_rel_pct"], 8, 3)} '
                  f'{fmt(s["r_rel_deg_per_100m"], 6, 3)} {fmt(s["end_drift_pct"], 8, 3)} '
                  f'{fmt(s["scale_pct"], 8, 2)} {s["inliers_per_frame"]:5.0f} '
                  f'{fmt(s["mover_inlier_pct"], 5, 1)} {s["bad_inlier_pct"]:5.1f} '
                  f'{s["slow_frames"]:5d}  {verdict(ok)}')
    print('\nc) Zero motion: the first pair of a clip fed repeatedly (identical images, the '
          'frame period of the clip); dy: stereo offset v_R - v_L of the tracked points, '
          'which the transfer predicts as 0')
    print(f'{"clip":20s} {"frames":>6s} {"end m":>8s} {"end rot deg":>11s} '
          f'{"rot vec x/y/z deg":>24s} {"dy mean px":>10s} {"dy rms px":>9s}')
    clips = ([static] if static is not None else []) + list(real.values())
    for clip in clips:
        r = identical_pairs(clip, len(clip.frames))
        results['identical'][clip.name] = r
        rv = '/'.join(f'{v:+.3f}' for v in r['rotvec_deg'])
        print(f'{clip.name:20s} {r["frames"]:6d} {r["end_m"]:8.4f} {r["end_rot_deg"]:11.3f} '
              f'{rv:>24s} {r["dy_mean_px"]:10.3f} {r["dy_rms_px"]:9.3f}')
    return results


def jsonable(obj: object) -> object:
    """Turn NaN into None and NumPy scalars into Python numbers, recursively."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def main() -> int:
    """Run the benchmark; return the process exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--data', type=Path, default=SHARED_DATA,
                        help='folder holding the KITTI-layout clips (default: %(default)s)')
    parser.add_argument('--frames', type=int, default=None,
                        help='frames per rendered sequence (default: the preset count; '
                        'another count renders another scene)')
    parser.add_argument('--repeat', type=int, default=3, help='timing runs per clip')
    parser.add_argument('--seed', type=int, default=0, help='seed of the rendered scenes')
    parser.add_argument('--quick', action='store_true',
                        help='150 rendered frames and one timing run')
    parser.add_argument('--json', type=Path, default=None, help='also write the figures here')
    parser.add_argument('--set', nargs='*', default=[], metavar='SECTION.KEY=VALUE',
                        help='configuration overrides for every run (values as JSON), e.g. '
                        'road.enabled=true')
    parser.add_argument('--seeds', type=int, nargs='*', default=[1, 2, 3],
                        help='extra seeds of the clean presets in table 6 (default: 1 2 3)')
    parser.add_argument('--skip-diagnostics', action='store_true',
                        help='leave out table 6 (where the errors come from)')
    args = parser.parse_args()
    try:
        BASE_OVERRIDES.update(overrides_from_items(args.set))
        base_config()  # unknown keys and bad values fail here
    except ConfigError as exc:
        raise SystemExit(f'--set: {exc}') from None
    if BASE_OVERRIDES:
        print(f'configuration overrides for every run: {json.dumps(BASE_OVERRIDES)}')
    if args.quick:
        args.frames = args.frames or 150
        args.repeat = 1
        args.seeds = args.seeds[:1]
    cv2.setNumThreads(1)
    t_start = time.perf_counter()

    real = {}
    for name in KITTI_CLIPS:
        folder = args.data / name
        if (folder / 'calib.txt').exists():
            real[name] = load_real(folder)
        else:
            print(f'skipping {name}: no clip at {folder}')
    static = None
    if (args.data / STATIC_CLIP / 'calib.txt').exists():
        static = load_real(args.data / STATIC_CLIP)
    else:
        print(f'skipping {STATIC_CLIP}: no clip at {args.data / STATIC_CLIP}')

    overrides = {'seed': args.seed}
    if args.frames is not None:
        overrides['n_frames'] = args.frames
    specs = {name: SequenceSpec.preset(name, **overrides)
             for name in ('urban', 'highway', 'exposure')}
    cache = {'urban': render(specs['urban'], 'urban')}
    print(f'urban: {cache["urban"].info}; KITTI clips: '
          + (', '.join(f'{n} ({len(c.frames)} frames, {c.size[0]}x{c.size[1]})'
                       for n, c in real.items()) or 'none'))

    runner = Runner()
    out = {'command': ' '.join(sys.argv), 'frames': args.frames, 'seed': args.seed}
    out['real'] = table_real(real, static, runner)
    out['timing'] = table_timing(list(real.values()) + [cache['urban']], args.repeat)
    out['rendered'] = table_rendered(specs, cache, runner)
    cache.pop('exposure', None)
    out['degradations'] = table_degradations(specs['urban'], cache, runner)
    out['ablation'] = table_ablation([cache['urban']] + list(real.values()), runner)
    if not args.skip_diagnostics:
        out['diagnostics'] = table_diagnostics(cache, specs, real, static, runner,
                                               args.seeds)
    wall = time.perf_counter() - t_start
    out['wall_s'] = wall
    print(f'\n(benchmark took {wall:.0f} s)')
    if args.json is not None:
        args.json.write_text(json.dumps(jsonable(out), indent=1))
        print(f'figures written to {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
