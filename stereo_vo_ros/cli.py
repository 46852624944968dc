"""
Command line: ``stereo_vo {run,estimate,simulate,eval,plot,demo,config}``.

The only module that imports argparse and tqdm and turns errors into exit codes: user mistakes
(missing files, bags without the topics, unreadable calibration, bad options) print one line
``stereo_vo: error: ...`` and exit with status 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
import sys
import time

import numpy as np

from . import __version__
from .config import Config, load, to_yaml
from .errors import StereoVOError

LOG = logging.getLogger('stereo_vo')


def _config(args: argparse.Namespace) -> Config:
    return load(getattr(args, 'config', None))


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f'not JSON serialisable: {type(value).__name__}')


def _dump_json(data, path: Path | None = None) -> None:
    text = json.dumps(_finite_or_null(data), indent=2, default=_json_default, allow_nan=False)
    if path is None:
        sys.stdout.write(text + '\n')
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + '\n')


def _finite_or_null(data):
    """Replace NaN/Inf by None so that the JSON is standard."""
    if isinstance(data, dict):
        return {k: _finite_or_null(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_finite_or_null(v) for v in data]
    if isinstance(data, (float, np.floating)) and not math.isfinite(float(data)):
        return None
    return data


def _write_poses(path: Path, stamps: np.ndarray, poses: np.ndarray, fmt: str) -> None:
    from .evaluation.trajectory import write_kitti, write_tum
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == 'tum':
        write_tum(path, stamps, poses)
    else:
        write_kitti(path, poses)


# -- commands --------------------------------------------------------------------------
def cmd_run(args: argparse.Namespace) -> int:
    """Run the pipeline over a KITTI folder or a rosbag2 and write the trajectory."""
    from .io import open_sequence
    from .offline import run_frames, run_stats
    cfg = _config(args)
    if args.left_topic or args.right_topic:
        cfg = cfg.replace(**{k: v for k, v in (('ros.left_image_topic', args.left_topic),
                                               ('ros.right_image_topic', args.right_topic),
                                               ('ros.left_info_topic', args.left_info_topic),
                                               ('ros.right_info_topic', args.right_info_topic))
                             if v})
    seq = open_sequence(args.source, cfg)
    total = len(seq) if hasattr(seq, '__len__') else None
    if args.max_frames is not None and total is not None:
        total = min(total, args.max_frames)
    bar = None
    if sys.stderr.isatty() and not args.quiet:
        from tqdm import tqdm
        bar = tqdm(total=total, unit='frame', desc='stereo_vo', leave=False)
    t0 = time.perf_counter()
    try:
        out = run_frames(iter(seq), cfg, args.max_frames,
                         progress=(lambda res: bar.update(1)) if bar else None)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    _write_poses(Path(args.poses), out.stamps, out.poses, args.format)
    stats = run_stats(out, wall)
    if args.stats:
        _dump_json(stats, Path(args.stats))
    LOG.info('%d frames (%d without motion estimate), median %.1f ms/frame -> %s',
             stats['frames'], stats['lost_frames'],
             stats['ms'].get('total', {}).get('median', float('nan')), args.poses)
    if args.save_calibration:
        _save_calibration(Path(args.save_calibration), out)
    gt = getattr(seq, 'ground_truth', None)
    if args.gt_out and gt is not None:
        gt = np.asarray(gt)[:len(out.poses)]
        _write_poses(Path(args.gt_out), out.stamps, gt, args.format)
    return 0


def _save_calibration(path: Path, out) -> None:
    """Write the calibration refined by the run's rig estimate (camera_info YAML)."""
    from .estimation.rig_calibration import camera_info_yaml, refined_camera_infos
    if out.rig is None or out.calibration is None:
        raise StereoVOError('--save-calibration needs the rig refinement (rig.enabled: true) '
                            'and at least one frame')
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(camera_info_yaml(*refined_camera_infos(out.calibration, out.rig.theta)))
    LOG.info('refined calibration (%d pairs; row offset %+.3f px, disparity offset %+.3f px) '
             '-> %s: load it as raw input (pipeline.input_kind: raw)', out.rig.updates,
             out.rig.row_offset_px, out.rig.disparity_offset_px, path)


def cmd_estimate(args: argparse.Namespace) -> int:
    """Run the estimator on correspondences from an .npz file."""
    from .io.correspondences import estimate_trajectory, load_npz
    from .evaluation.trajectory import write_kitti
    poses = estimate_trajectory(load_npz(args.correspondences), _config(args))
    Path(args.poses).parent.mkdir(parents=True, exist_ok=True)
    write_kitti(args.poses, poses)
    LOG.info('%d poses -> %s', len(poses), args.poses)
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Kitt et al.'s simulation (sections IV-A to IV-C); prints JSON."""
    from .synthetic.simulation import run_simulation, SimulationSpec
    cfg = _config(args).replace(**{
        'filter.type': args.filter, 'ransac.enabled': not args.no_ransac,
        'filter.pixel_noise_px': max(args.noise, 0.05),
        'filter.threshold_velocity': args.threshold,
        'filter.threshold_angular_deg': args.threshold,
        'filter.max_iterations': args.max_iterations})
    spec = SimulationSpec(frames=args.frames, points=args.points, noise_px=args.noise,
                          outlier_ratio=args.outliers, seed=args.seed)
    _dump_json(run_simulation(spec, cfg))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    """Score an estimated trajectory against ground truth."""
    from .evaluation.metrics import evaluate
    from .evaluation.trajectory import read_poses
    gt = read_poses(args.gt).poses
    est = read_poses(args.est).poses
    if len(gt) != len(est):
        n = min(len(gt), len(est))
        LOG.warning('ground truth has %d poses and the estimate %d: scoring the first %d',
                    len(gt), len(est), n)
        gt, est = gt[:n], est[:n]
    result = evaluate(gt, est)
    if args.json:
        _dump_json(result)
    else:
        for key, value in result.items():
            sys.stdout.write(f'{key:>22}: {value}\n')
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """Plot a trajectory (and ground truth, timings) into a PNG."""
    from .evaluation.plotting import save_report
    from .evaluation.trajectory import read_poses
    est = read_poses(args.est).poses
    gt = read_poses(args.gt).poses if args.gt else None
    if gt is not None and len(gt) != len(est):
        n = min(len(gt), len(est))
        gt, est = gt[:n], est[:n]
    timings = None
    if args.timings:
        timings = json.loads(Path(args.timings).read_text())
        if isinstance(timings, dict):
            timings = timings.get('per_frame_ms')
    out = save_report(args.out, gt, est, timings=timings, title=args.title)
    sys.stdout.write(f'{out}\n')
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Synthetic bag -> node (real rclpy) -> trajectory, metrics and plot."""
    from .ros import is_ours, missing_ros
    try:
        from .ros.demo import run_demo
        summary = run_demo(Path(args.out), frames=args.frames, preset=args.preset,
                           config=_config(args), timeout_s=args.timeout)
    except ModuleNotFoundError as exc:  # rclpy and the messages are imported when it starts
        if is_ours(exc):
            raise
        raise missing_ros(exc, 'the demo (it runs the ROS node)') from None
    _dump_json(summary)
    return 0 if summary.get('ok') else 1


def cmd_config(args: argparse.Namespace) -> int:
    """Print a configuration (defaults, or a file after validation) as a ROS params file."""
    sys.stdout.write(to_yaml(_config(args)))
    return 0


# -- parser ----------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``stereo_vo``."""
    p = argparse.ArgumentParser(prog='stereo_vo', description='Stereo visual odometry '
                                '(light adaptive KLT + trifocal ISPKF) offline tools.')
    p.add_argument('--version', action='version', version=f'stereo_vo_ros {__version__}')
    p.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    sub = p.add_subparsers(dest='command', required=True)

    def add_config(sp):
        sp.add_argument('--config', help='YAML parameter file (config/stereo_vo.yaml form)')

    sp = sub.add_parser('run', help='run the pipeline over a KITTI folder or a rosbag2')
    sp.add_argument('source', help='KITTI-odometry folder, rosbag2 folder, .db3 or .mcap')
    sp.add_argument('--poses', required=True, help='output trajectory file')
    sp.add_argument('--stats', help='output stats JSON')
    sp.add_argument('--format', choices=('kitti', 'tum'), default='kitti')
    sp.add_argument('--max-frames', type=int)
    sp.add_argument('--gt-out', help='also write the ground truth (same format) if known')
    sp.add_argument('--left-topic')
    sp.add_argument('--right-topic')
    sp.add_argument('--left-info-topic')
    sp.add_argument('--right-info-topic')
    sp.add_argument('-q', '--quiet', action='store_true', help='no progress bar')
    sp.add_argument('--save-calibration', metavar='FILE',
                    help='write the stereo calibration refined by the run (camera_info YAML, '
                    'left and right; load it with pipeline.input_kind raw)')
    add_config(sp)
    sp.set_defaults(func=cmd_run)

    sp = sub.add_parser('estimate', help='estimate a trajectory from correspondences (.npz)')
    sp.add_argument('correspondences', help='.npz with prev_left, prev_right, cur_left, '
                    'cur_right (M, N, 2), P0, P1 (3x4), rate (Hz)')
    sp.add_argument('--poses', required=True, help='output KITTI trajectory (M+1 poses)')
    add_config(sp)
    sp.set_defaults(func=cmd_estimate)

    sp = sub.add_parser('simulate', help="Kitt et al.'s simulation; prints JSON")
    sp.add_argument('--filter', choices=('ispkf', 'iekf', 'ukf', 'ekf'), default='ispkf')
    sp.add_argument('--frames', type=int, default=2000)
    sp.add_argument('--points', type=int, default=40)
    sp.add_argument('--noise', type=float, default=0.7, help='pixel noise std')
    sp.add_argument('--outliers', type=float, default=0.0, help='outlier fraction')
    sp.add_argument('--seed', type=int, default=1)
    sp.add_argument('--no-ransac', action='store_true')
    sp.add_argument('--threshold', type=float, default=1e-3,
                    help='termination threshold (m/s and deg/s)')
    sp.add_argument('--max-iterations', type=int, default=1000)
    add_config(sp)
    sp.set_defaults(func=cmd_simulate)

    sp = sub.add_parser('eval', help='KITTI metric, ATE and RPE of a trajectory')
    sp.add_argument('gt', help='ground-truth trajectory (KITTI or TUM)')
    sp.add_argument('est', help='estimated trajectory (KITTI or TUM)')
    sp.add_argument('--json', action='store_true')
    sp.set_defaults(func=cmd_eval)

    sp = sub.add_parser('plot', help='trajectory top view, error and timing PNG')
    sp.add_argument('est', help='estimated trajectory')
    sp.add_argument('--gt', help='ground-truth trajectory')
    sp.add_argument('--timings', help='per-frame timings JSON (list of dicts of ms)')
    sp.add_argument('--out', required=True, help='output PNG')
    sp.add_argument('--title', default='Stereo visual odometry')
    sp.set_defaults(func=cmd_plot)

    sp = sub.add_parser('demo', help='synthetic bag -> ROS node -> trajectory, metrics, plot')
    sp.add_argument('--out', default='demo_out', help='output folder')
    sp.add_argument('--frames', type=int, default=160,
                    help='frames to render (160 at 10 Hz: about 130 m with a 90-degree turn)')
    sp.add_argument('--preset', default='demo')
    sp.add_argument('--timeout', type=float, default=110.0, help='seconds for the replay')
    add_config(sp)
    sp.set_defaults(func=cmd_demo)

    sp = sub.add_parser('config', help='print the (validated) configuration as YAML')
    add_config(sp)
    sp.set_defaults(func=cmd_config)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``stereo_vo``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format='%(levelname)s %(name)s: %(message)s')
    try:
        return int(args.func(args) or 0)
    except (StereoVOError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        parser.exit(2, f'stereo_vo: error: {exc}\n')
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
