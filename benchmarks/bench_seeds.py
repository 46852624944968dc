"""
The KITTI metric of one rendered preset over many scenes (seeds), in parallel.

``bench_accuracy.py`` scores one scene per preset and a few more seeds in its diagnostics; a
single highway scene moves by a tenth of a percent with settings that should not matter, so a
claim about the highway needs many scenes. This script renders each seed of a preset
(``SequenceSpec.preset(name, seed=s)``, the preset's frame count unless ``--frames``), runs
``StereoOdometry`` over it frame by frame with the configuration given (default, a YAML file,
and ``--set`` overrides), and prints per seed the KITTI devkit metric (t_rel %, r_rel
deg/100 m), the same after one scale factor fitted to the whole trajectory (t_rel_s, r_rel_s:
``metrics.kitti_odometry_error_scale_aligned``; a rig whose true baseline or focal differs from
its calibration, presets ``*_rig``, scales the trajectory in a way no image reveals), the median
ratio of estimated to true step length, the number of pairs after the first whose status is not
OK (bad) and the seconds it took; then
the mean, median and worst t_rel, how many scenes meet the clean-scene target (t_rel <= 0.3 %
and r_rel <= 0.3 deg/100 m) and how many lock (t_rel above 5 %: the camera took the motion of
the vehicles ahead).

Usage::

    python benchmarks/bench_seeds.py [--preset highway] [--seeds 0-23] [--jobs 2]
        [--config FILE] [--set ransac.ground_weight=8 ...] [--frames N] [--cache DIR]

``--spec FIELD=VALUE ...`` changes fields of the scenes (``SequenceSpec``), for example a
rig error of another size (``rig_yaw_deg=-0.232 rig_disparity_offset_px=2.25``).

``--cache DIR`` keeps each render as ``DIR/<preset>_<seed>_<frames>.npz`` (about 280 MB for a
300-frame scene) so that another configuration can be scored on the same scenes without
rendering again. Each worker uses one thread for OpenCV and BLAS.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from multiprocessing import get_context
import os
from pathlib import Path
import sys
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros import config as config_mod  # noqa: E402
from stereo_vo_ros.errors import ConfigError  # noqa: E402
from stereo_vo_ros.evaluation import metrics  # noqa: E402
from stereo_vo_ros.offline import run_frames  # noqa: E402
from stereo_vo_ros.records import StereoFrame  # noqa: E402
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer  # noqa: E402

#: Clean-scene target of the accuracy benchmark (t_rel %, r_rel deg/100 m).
TARGET = (0.3, 0.3)
#: Above this t_rel (%) a run counts as locked onto moving vehicles.
LOCK_PCT = 5.0


def parse_seeds(text: list[str]) -> list[int]:
    """Seeds from items like ``0-23`` or ``5``."""
    seeds: list[int] = []
    for item in text:
        lo, _, hi = item.partition('-')
        seeds += list(range(int(lo), int(hi or lo) + 1))
    return seeds


def spec_overrides(items: list[str], preset: str) -> dict:
    """``FIELD=VALUE`` items (values as JSON, else strings) as a dict of ``preset``'s fields."""
    try:
        out = config_mod.overrides_from_items(items)  # the same item syntax as --set
        SequenceSpec.preset(preset, **out)
    except ConfigError as exc:
        raise SystemExit(f'bad --spec {items}: {exc}') from None
    return out


def scene(preset: str, seed: int, frames: int | None, cache: Path | None,
          spec_items: dict | None = None) -> dict:
    """
    Render the scene of one seed, or load it from the cache: images, stamps, true poses.

    ``spec_items``: fields of the preset's ``SequenceSpec`` to change (``--spec``); the cached
    render's name then ends with a digest of them.
    """
    extra = dict(spec_items or {})
    if frames is not None:
        extra['n_frames'] = frames
    spec = SequenceSpec.preset(preset, seed=seed, **extra)
    tag = ''
    if spec_items:
        text = json.dumps(spec_items, sort_keys=True).encode()
        tag = '_' + hashlib.sha1(text).hexdigest()[:10]
    path = None if cache is None else cache / f'{preset}_{seed}_{spec.n_frames}{tag}.npz'
    if path is not None and path.exists():
        with np.load(path) as data:
            return {'spec': spec, **{k: data[k] for k in data.files}}
    renderer = StereoRenderer(spec)
    pairs = [renderer.render(i) for i in range(spec.n_frames)]
    out = {'left': np.array([p.left for p in pairs]), 'right': np.array([p.right for p in pairs]),
           'stamps': np.array([p.stamp_s for p in pairs]),
           'poses': np.array([p.T_world_cam for p in pairs])}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **out)
    return {'spec': spec, **out}


def score(job: tuple) -> dict:
    """Render or load one seed, run the pipeline and return its figures."""
    preset, seed, frames, cache, cfg, spec_items = job
    import cv2
    cv2.setNumThreads(1)
    data = scene(preset, seed, frames, cache, spec_items)
    calib = data['spec'].calibration()
    t0 = time.perf_counter()
    out = run_frames((StereoFrame(left, right, stamp, calib) for left, right, stamp in
                      zip(data['left'], data['right'], data['stamps'])), cfg)
    seconds = time.perf_counter() - t0
    gt, est = data['poses'], out.poses
    if len(est) != len(gt):
        return {'seed': seed, 't_rel': float('nan'), 'r_rel': float('nan'),
                't_rel_scaled': float('nan'), 'r_rel_scaled': float('nan'),
                'step_ratio': float('nan'), 'lost': -1, 'seconds': seconds,
                'note': f'{len(est)} of {len(gt)} frames accepted'}
    t_rel, r_rel, _ = metrics.kitti_odometry_error(gt, est)
    t_rel_s, r_rel_s, _, _ = metrics.kitti_odometry_error_scale_aligned(gt, est)
    step_gt = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    step_est = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1)
    lost = sum(1 for st in out.statuses[1:] if st.name != 'OK')
    return {'seed': seed, 't_rel': float(t_rel), 'r_rel': float(r_rel),
            't_rel_scaled': float(t_rel_s), 'r_rel_scaled': float(r_rel_s),
            'step_ratio': float(np.median(step_est / np.maximum(step_gt, 1e-9))),
            'lost': lost, 'seconds': seconds, 'note': ''}


def main() -> int:
    """Score the seeds and print the table and its summary."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', default='highway')
    ap.add_argument('--seeds', nargs='+', default=['0-23'], help='e.g. 0-23 or 3 5 7')
    ap.add_argument('--frames', type=int, default=None, help="default: the preset's")
    ap.add_argument('--config', type=Path, default=None, help='parameter YAML (default: none)')
    ap.add_argument('--set', nargs='*', default=[], metavar='SECTION.KEY=VALUE',
                    help='configuration overrides (values as JSON)')
    ap.add_argument('--jobs', type=int, default=2, help='worker processes')
    ap.add_argument('--cache', type=Path, default=None, help='keep renders here (npz)')
    ap.add_argument('--json', type=Path, default=None, help='also write the figures here')
    ap.add_argument('--spec', nargs='*', default=[], metavar='FIELD=VALUE',
                    help='scene fields to change (SequenceSpec, values as JSON), e.g. '
                    'rig_yaw_deg=-0.2 rig_disparity_offset_px=2')
    args = ap.parse_args()
    cfg = config_mod.load(args.config)
    overrides = config_mod.overrides_from_items(args.set)
    if overrides:
        cfg = cfg.replace(**overrides)
    spec_items = spec_overrides(args.spec, args.preset)
    seeds = parse_seeds(args.seeds)
    print(f'{args.preset}, seeds {args.seeds}, config {args.config or "default"}'
          f'{", overrides " + json.dumps(overrides) if overrides else ""}'
          f'{", scene " + json.dumps(spec_items) if spec_items else ""}', flush=True)
    jobs = [(args.preset, s, args.frames, args.cache, cfg, spec_items) for s in seeds]
    print(f'{"seed":>5s} {"t_rel %":>8s} {"r_rel":>7s} {"t_rel_s %":>9s} {"r_rel_s":>7s} '
          f'{"step ratio":>10s} {"bad":>4s} {"s":>5s}')
    rows = []
    with get_context('fork').Pool(max(1, args.jobs), maxtasksperchild=1) as pool:
        for row in pool.imap(score, jobs):
            rows.append(row)
            print(f'{row["seed"]:5d} {row["t_rel"]:8.3f} {row["r_rel"]:7.3f} '
                  f'{row["t_rel_scaled"]:9.3f} {row["r_rel_scaled"]:7.3f} '
                  f'{row["step_ratio"]:10.4f} {row["lost"]:4d} {row["seconds"]:5.0f} '
                  f'{row["note"]}', flush=True)
    t = np.array([r['t_rel'] for r in rows])
    r = np.array([r['r_rel'] for r in rows])
    met = int(np.count_nonzero((t <= TARGET[0]) & (r <= TARGET[1])))
    locked = [row['seed'] for row in rows if not row['t_rel'] <= LOCK_PCT]
    worst = rows[int(np.nanargmax(t))]['seed'] if np.isfinite(t).any() else None
    print(f't_rel over {len(t)} scenes: mean {np.nanmean(t):.3f} %, median '
          f'{np.nanmedian(t):.3f} %, worst {np.nanmax(t):.3f} % (seed {worst}); r_rel mean '
          f'{np.nanmean(r):.3f} deg/100 m')
    ts = np.array([r['t_rel_scaled'] for r in rows])
    print(f'scale-aligned (one scale factor per trajectory, least squares over the step '
          f'lengths) t_rel: mean {np.nanmean(ts):.3f} %, median {np.nanmedian(ts):.3f} %, '
          f'worst {np.nanmax(ts):.3f} %; pairs not OK (degenerate, too few inliers or lost): '
          f'{sum(max(r["lost"], 0) for r in rows)}')
    print(f'meet t_rel <= {TARGET[0]} % and r_rel <= {TARGET[1]} deg/100 m: {met} of {len(t)}; '
          f'locked (t_rel > {LOCK_PCT:g} % or failed): {len(locked)} {locked if locked else ""}')
    if args.json:
        args.json.write_text(json.dumps({'preset': args.preset, 'overrides': overrides,
                                         'scene': spec_items, 'rows': rows}, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
