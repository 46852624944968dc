"""
Benchmark of the stereo KLT tracker (Huang et al.) on the KITTI clips: timings and ablation.

Prints, for every clip in the data folder (KITTI-odometry layout):

1. milliseconds per pass and for the whole tracker (median, p95) at full resolution with
   ``cv2.setNumThreads(1)``, without a motion prior, with a constant-velocity prior (the previous
   ground-truth frame-to-frame motion, what the filter prediction approximates) and with the
   exact ground-truth motion as prior;
2. the ablation of the paper's Tables I/II per variant (and bi-circular mode): features kept
   per frame, fraction of quadruples consistent with the ground truth (reprojection error
   < 1 px), fraction consistent with a robust PnP fit of the frame (< 1 px, independent of the
   ground-truth accuracy), points tracked back by the left-right pass, features removed by
   each check, tracking ms;
3. the two readings of eq. 7 side by side on the quadruples of the ``dc`` variant: how many
   each would reject at several thresholds and how many of the rejected ones are really
   inconsistent (PnP-fit error > 1 px) compared with the kept ones.

Ground-truth consistency: every quadruple is triangulated from the previous rectified pair
(calib.txt P0/P1), moved with the ground-truth relative pose (poses.txt holds left-camera-to-
world poses) and reprojected into the current pair; its error is the larger of the left and
right reprojection errors.

Usage::

    python benchmarks/bench_tracker.py [--data ../shared/data] [--repeat 3] [--clock cpu]

``--clock cpu`` times with the thread CPU clock (``time.thread_time``), which a busy machine
disturbs less than the wall clock (OpenCV runs in the calling thread with one thread).
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.config import BucketingConfig, TrackerConfig  # noqa: E402
from stereo_vo_ros.estimation.camera import StereoCalibration  # noqa: E402
from stereo_vo_ros.tracking import tracker as tracker_module  # noqa: E402
from stereo_vo_ros.tracking.klt_checks import lk_pass, round_trip_error  # noqa: E402
from stereo_vo_ros.tracking.tracker import STAGES, StereoTracker  # noqa: E402

CHECK_KEYS = ('temporal', 'fb', 'stereo', 'dc', 'disparity', 'lr', 'bc')


#: The read-only clips next to the repository (``../shared/data``), as CI lays them out.
SHARED_DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'


def load_clip(folder: Path) -> tuple[list, list, StereoCalibration, np.ndarray]:
    """Load a KITTI-layout clip: left/right uint8 images, calibration, (N, 4, 4) T_world_cam."""
    proj = {}
    for line in (folder / 'calib.txt').read_text().splitlines():
        key, _, values = line.partition(':')
        if values.strip():
            proj[key.strip()] = np.array(values.split(), np.float64).reshape(3, 4)
    rows = np.loadtxt(folder / 'poses.txt').reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows
    left = [cv2.imread(str(folder / 'image_0' / f'{i:06d}.png'), cv2.IMREAD_UNCHANGED)
            for i in range(len(poses))]
    right = [cv2.imread(str(folder / 'image_1' / f'{i:06d}.png'), cv2.IMREAD_UNCHANGED)
             for i in range(len(poses))]
    h, w = left[0].shape
    calib = StereoCalibration.from_projections(proj['P0'], proj['P1'], w, h)
    return left, right, calib, poses


def triangulate(calib: StereoCalibration, xl: np.ndarray, xr: np.ndarray) -> np.ndarray:
    """(N, 3) points (m, left camera frame) from rectified left/right pixels (N, 2)."""
    K = calib.K_left
    disparity = np.maximum(xl[:, 0] - xr[:, 0], 1e-3)
    z = K[0, 0] * calib.baseline_m / disparity
    return np.stack([(xl[:, 0] - K[0, 2]) * z / K[0, 0], (xl[:, 1] - K[1, 2]) * z / K[1, 1], z],
                    axis=1)


def reproject(calib: StereoCalibration, X_prev: np.ndarray, T_prev_cur: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Move points from the previous to the current left frame and project into both images."""
    T_cur_prev = np.linalg.inv(T_prev_cur)
    X = X_prev @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3]
    Xh = np.hstack([X, np.ones((len(X), 1))])
    pl = Xh @ calib.projection_left().T
    pr = Xh @ calib.projection_right().T
    return pl[:, :2] / pl[:, 2:3], pr[:, :2] / pr[:, 2:3]


def gt_errors(calib: StereoCalibration, corr, T_prev_cur: np.ndarray) -> np.ndarray:
    """(N,) max of left and right reprojection errors (pixels) under the motion T_prev_cur."""
    pl, pr = reproject(calib, triangulate(calib, corr.prev_left, corr.prev_right), T_prev_cur)
    return np.maximum(np.linalg.norm(pl - corr.cur_left, axis=1),
                      np.linalg.norm(pr - corr.cur_right, axis=1))


def fit_errors(calib: StereoCalibration, corr) -> np.ndarray:
    """(N,) left reprojection errors (pixels) after a RANSAC PnP fit of the frame's motion."""
    X = triangulate(calib, corr.prev_left, corr.prev_right)
    if len(X) < 6:
        return np.full(len(X), np.inf)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X, corr.cur_left, calib.K_left, None,
                                             reprojectionError=1.0, iterationsCount=300)
    if not ok or inl is None or len(inl) < 6:
        return np.full(len(X), np.inf)
    rvec, tvec = cv2.solvePnPRefineLM(X[inl.ravel()], corr.cur_left[inl.ravel()],
                                      calib.K_left, None, rvec, tvec)
    proj, _ = cv2.projectPoints(X, rvec, tvec, calib.K_left, None)
    return np.linalg.norm(proj.reshape(-1, 2) - corr.cur_left, axis=1)


def make_prior(calib: StereoCalibration, T_prev_cur: np.ndarray):
    """Motion prior: triangulate the previous features and reproject them with a motion."""
    def prior(prev_left: np.ndarray, prev_right: np.ndarray):
        return reproject(calib, triangulate(calib, prev_left, prev_right), T_prev_cur)
    return prior


def run(clip, tracker_cfg: TrackerConfig, prior_kind: str, evaluate: bool) -> dict:
    """Track one clip; return per-frame stats, and the consistency figures if ``evaluate``."""
    left, right, calib, poses = clip
    tracker = StereoTracker(tracker_cfg, BucketingConfig())
    out = {'timings': {k: [] for k in STAGES + ('total',)}, 'kept': [], 'gt': [], 'fit': [],
           'failed': {k: [] for k in CHECK_KEYS}, 'delta_d': [], 'lr_points': []}
    for i in range(len(left)):
        prior = None
        if i > 0 and prior_kind == 'gt':
            prior = make_prior(calib, np.linalg.inv(poses[i - 1]) @ poses[i])
        elif i > 1 and prior_kind == 'cv':
            prior = make_prior(calib, np.linalg.inv(poses[i - 2]) @ poses[i - 1])
        res = tracker.track(left[i], right[i], calib, prior)
        if i == 0:
            continue
        st = res.stats
        for k in out['timings']:
            out['timings'][k].append(st.timings_ms[k])
        for k in CHECK_KEYS:
            out['failed'][k].append(st.failed[k])
        out['kept'].append(st.n_tracked)
        out['lr_points'].append(st.pass_points['stereo_bwd'])
        out['delta_d'].append(st.delta_d_px)
        if evaluate:
            corr = res.correspondences
            out['gt'].append(gt_errors(calib, corr, np.linalg.inv(poses[i - 1]) @ poses[i]))
            out['fit'].append(fit_errors(calib, corr))
    return out


def frame_times(clip, cfg: TrackerConfig, prior: str, repeat: int) -> dict:
    """
    Return per-frame milliseconds per stage: the minimum over ``repeat`` identical runs.

    The tracker is deterministic, so every repeat does the same work; the minimum removes the
    delays a busy machine adds to single frames.
    """
    runs = [run(clip, cfg, prior, evaluate=False)['timings'] for _ in range(repeat)]
    return {k: np.min([r[k] for r in runs], axis=0) for k in runs[0]}


def timing_table(clips: dict, repeat: int, clock: str, cfg: TrackerConfig) -> None:
    """Print per-pass milliseconds (median, p95 over frames) per clip and prior."""
    print(f'\n== Timing per pass (ms, median / p95 over frames of the per-frame minimum of '
          f'{repeat} runs, {clock} clock), cv2.setNumThreads(1), variant {cfg.variant}, '
          f'bicircular_mode {cfg.bicircular_mode} ==')
    cols = STAGES + ('total',)
    print(f'{"clip":24s} {"prior":5s} ' + ' '.join(f'{c:>13s}' for c in cols))
    for name, clip in clips.items():
        for prior in ('none', 'cv', 'gt'):
            ms = frame_times(clip, cfg, prior, repeat)
            cells = ' '.join(f'{np.median(ms[k]):6.2f}/{np.percentile(ms[k], 95):6.2f}'
                             for k in cols)
            print(f'{name:24s} {prior:5s} {cells}')


def ablation_table(clips: dict, prior: str, repeat: int) -> None:
    """Print the per-variant ablation (paper Tables I/II) per clip."""
    print(f'\n== Ablation per variant (prior: {prior}; consistent: reprojection error < 1 px; '
          'lr pts: points tracked back right -> left per frame; track ms: median of the '
          f'per-frame minimum of {repeat} runs) ==')
    print(f'{"clip":24s} {"variant":9s} {"bc mode":9s} {"kept":>6s} {"gt<1px":>7s} '
          f'{"gt med":>7s} {"fit<1px":>8s} {"delta_d":>8s} {"lr pts":>7s} {"track ms":>9s}  '
          f'removed per check ({", ".join(CHECK_KEYS)})')
    runs = [('baseline', 'roundtrip'), ('dc', 'roundtrip')]
    runs += [(v, m) for v in ('bc', 'db', 'full') for m in ('roundtrip', 'closure')]
    for name, clip in clips.items():
        for variant, mode in runs:
            cfg = TrackerConfig(variant=variant, bicircular_mode=mode)
            res = run(clip, cfg, prior, evaluate=True)
            ms = frame_times(clip, cfg, prior, repeat)['total']
            gt = np.concatenate(res['gt'])
            fit = np.concatenate(res['fit'])
            dd = np.array(res['delta_d'], np.float64)
            dd_txt = f'{np.nanmedian(dd):8.2f}' if np.isfinite(dd).any() else f'{"-":>8s}'
            removed = ' '.join(f'{np.mean(res["failed"][k]):5.1f}' for k in CHECK_KEYS)
            shown_mode = mode if variant in ('bc', 'db', 'full') else '-'
            print(f'{name:24s} {variant:9s} {shown_mode:9s} {np.mean(res["kept"]):6.1f} '
                  f'{np.mean(gt < 1.0):7.3f} {np.median(gt):7.3f} {np.mean(fit < 1.0):8.3f} '
                  f'{dd_txt} {np.mean(res["lr_points"]):7.1f} {np.median(ms):9.2f}  {removed}')


def bicircular_table(clips: dict, prior: str) -> None:
    """Compare the two readings of eq. 7 on the quadruples of the ``dc`` variant."""
    print(f'\n== Bi-circular readings on the dc-variant quadruples (prior: {prior}): rejected '
          'at delta_d, and the share of PnP-inconsistent (> 1 px) features among the rejected '
          'and the kept ==')
    print(f'{"clip":24s} {"delta_d":>7s} {"mode":9s} {"rejected":>9s} {"%":>6s} '
          f'{"bad|rej":>8s} {"bad|kept":>9s}')
    cfg = TrackerConfig(variant='dc')
    for name, clip in clips.items():
        left, right, calib, poses = clip
        tracker = StereoTracker(cfg, BucketingConfig())
        errs = {'closure': [], 'roundtrip': []}
        fit = []
        for i in range(len(left)):
            prior_fn = None
            if i > 1 and prior == 'cv':
                prior_fn = make_prior(calib, np.linalg.inv(poses[i - 2]) @ poses[i - 1])
            elif i > 0 and prior == 'gt':
                prior_fn = make_prior(calib, np.linalg.inv(poses[i - 1]) @ poses[i])
            res = tracker.track(left[i], right[i], calib, prior_fn)
            if i == 0:
                continue
            raw = res.raw
            guess = raw.cur_right + (raw.prev_left - raw.cur_left)
            back, ok = lk_pass(right[i], right[i - 1], raw.cur_right, guess,
                               cfg.predicted_pyramid_levels, cfg.win_size_px,
                               cfg.max_iterations)
            again, ok2 = lk_pass(right[i - 1], right[i], back, raw.cur_right, 0,
                                 cfg.win_size_px, cfg.max_iterations)
            errs['closure'].append(np.where(ok, round_trip_error(raw.prev_right, back), np.inf))
            errs['roundtrip'].append(
                np.where(ok & ok2, round_trip_error(raw.cur_right, again), np.inf))
            fit.append(fit_errors(calib, res.correspondences))
        bad = np.concatenate(fit) > 1.0
        for delta_d in (0.5, 1.0, 2.0, 5.0):
            for mode in ('closure', 'roundtrip'):
                rejected = np.concatenate(errs[mode]) >= delta_d
                bad_rej = f'{np.mean(bad[rejected]):8.2f}' if rejected.any() else f'{"-":>8s}'
                print(f'{name:24s} {delta_d:7.1f} {mode:9s} {rejected.sum():9d} '
                      f'{100 * rejected.mean():6.1f} {bad_rej} {np.mean(bad[~rejected]):9.2f}')


def main() -> int:
    """Run the benchmark; return the process exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', type=Path, default=SHARED_DATA,
                        help='folder holding KITTI-layout clips (default: %(default)s)')
    parser.add_argument('--clips', nargs='*', default=['kitti06_f0000-0050',
                                                       'kitti01_f0000-0050'])
    parser.add_argument('--repeat', type=int, default=3, help='timing repeats per clip')
    parser.add_argument('--prior', default='cv', choices=('none', 'cv', 'gt'),
                        help='motion prior of the ablation runs (default: %(default)s)')
    parser.add_argument('--mode', choices=('roundtrip', 'closure'), default=None,
                        help='bicircular_mode of the timing runs (default: the config default)')
    parser.add_argument('--clock', default='wall', choices=('wall', 'cpu'),
                        help='wall: time.perf_counter; cpu: time.thread_time')
    parser.add_argument('--skip-timing', action='store_true')
    parser.add_argument('--skip-ablation', action='store_true')
    parser.add_argument('--skip-bicircular', action='store_true')
    args = parser.parse_args()
    cv2.setNumThreads(1)
    if args.clock == 'cpu':
        tracker_module.CLOCK = time.thread_time
    clips = {}
    for name in args.clips:
        folder = args.data / name
        if not (folder / 'calib.txt').exists():
            print(f'skipping {name}: no clip at {folder}')
            continue
        clips[name] = load_clip(folder)
    if not clips:
        print(f'no KITTI clips found under {args.data}; nothing to benchmark')
        return 1
    for name, (left, _, calib, _) in clips.items():
        print(f'{name}: {len(left)} frames, {calib.size[0]}x{calib.size[1]}')
    t0 = time.perf_counter()
    if not args.skip_timing:
        cfg = TrackerConfig() if args.mode is None else TrackerConfig(bicircular_mode=args.mode)
        timing_table(clips, args.repeat, args.clock, cfg)
    if not args.skip_ablation:
        ablation_table(clips, args.prior, args.repeat)
    if not args.skip_bicircular:
        bicircular_table(clips, args.prior)
    print(f'\n(benchmark took {time.perf_counter() - t0:.1f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
