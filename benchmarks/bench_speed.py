"""
Time configurations of the pipeline against each other, interleaved, on the KITTI clips.

This machine's speed drifts: the same code timed minutes apart can take 10-40 % longer. Two
configurations timed at different moments therefore compare badly. This benchmark alternates
them. Each round times every configuration once on every clip (the order of the
configurations turns from round to round), and a fixed OpenCV workload that follows the
machine's speed: a reference pass, ``calcOpticalFlowPyrLK`` of 200 Shi-Tomasi
corners with 21x21 windows and 4 pyramid levels and no initial flow, from a clip's first left
image to its second (median of 20 calls; 6-10 ms seen here).

Prints, per round, the median total ms per pair of every configuration on every clip (first
pair left out, image loading excluded) and the reference; then, per configuration, the median
over rounds and the verdict against the target (half of libviso2's time per pair), the median
up to the pose (without the last pair's work after its pose, which a node runs after
publishing: the rig refinement's update, on every second pair, and taking the worker's new
corners), the medians of the pairs after one whose rig update measured and of the others, the
CPU time per pair of every thread and of the pipeline's worker process added and split by where
it ran (the caller's thread, the process's other threads, the worker process), and that mean
CPU time over the CPUs the process may use (pairs cannot take less on average: a configuration
near it gains nothing from more overlap, only from less work); and per variant its extra ms and
extra CPU over the first configuration, paired within rounds (median and range).

Usage::

    python benchmarks/bench_speed.py [--data ../shared/data] [--rounds 3] [--render 1280x720]
        [--variant pipeline.threads=2] [--variant "road.enabled=true road.levels=1"]

The first configuration is one thread with the replenishment after every check, the defaults
on two cores (``--base`` items replace that); the variants are whole configurations of their own
(overrides of the defaults). By default: a worker process with the replenishment after the
temporal checks, the road vehicle profile, and a worker process with the replenishment after
every check (results identical to the first). Without the KITTI clips a rendered urban scene at
1241x376 is timed instead, and the script says so; ``--render WxH`` adds a rendered urban scene
of that size (60 pairs).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_accuracy import (  # noqa: E402
    Clip, image_size, KITTI_CLIPS, LIBVISO2_MS, load_real, render, render_urban, run_clip,
    SHARED_DATA, TARGET_TOTAL_MS, verdict)
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from stereo_vo_ros.config import Config, overrides_from_items  # noqa: E402
from stereo_vo_ros.errors import ConfigError  # noqa: E402
from stereo_vo_ros.synthetic import SequenceSpec  # noqa: E402

#: The first configuration: one thread, the replenishment after every check (the defaults).
BASE = ['pipeline.threads=1', 'tracker.replenish_after="all"']
#: The configurations timed against it by default (overrides of the defaults).
VARIANTS = ['pipeline.threads=2 tracker.replenish_after="temporal"',
            'road.enabled=true vehicle.nonholonomic=true',
            'pipeline.threads=2 tracker.replenish_after="all"']
#: The reference KLT pass: corners, window side (px), pyramid levels above the base.
REFERENCE_POINTS, REFERENCE_WINDOW, REFERENCE_LEVELS = 200, 21, 3
REFERENCE_CALLS = 20


def reference_ms(clip: Clip) -> float:
    """Median ms of the reference KLT pass from the clip's first left image to its second."""
    img0, img1 = clip.frames[0].left, clip.frames[1].left
    cv2.setNumThreads(1)  # a pipeline run before may have set more
    pts = cv2.goodFeaturesToTrack(img0, REFERENCE_POINTS, 0.01, 10).astype(np.float32)
    times = []
    for _ in range(REFERENCE_CALLS):
        t0 = time.perf_counter()
        cv2.calcOpticalFlowPyrLK(img0, img1, pts, None,
                                 winSize=(REFERENCE_WINDOW, REFERENCE_WINDOW),
                                 maxLevel=REFERENCE_LEVELS)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def total_ms(clip: Clip, config: Config) -> dict:
    """
    One run over the clip: ms per pair (median), CPU, the caller's share, where the CPU went.

    Pairs after the first count (the worker's start-up left out). Keys: ``total`` the median
    ms per pair; ``cpu`` the mean CPU ms per pair of every thread of this process and of the
    pipeline's worker process; ``caller`` the CPU time of the caller's thread alone
    (``process()``'s) over the mean total time per pair; ``where`` (3,) the mean CPU ms per
    pair of the caller's thread, of the process's other threads (the helper, and a worker
    thread if any) and of the worker process; ``to_pose`` the median ms per pair up to its
    pose: ``process()`` first runs the last pair's work after its pose (``after_pose``: the
    rig refinement's update, on every ``rig.measure_every``-th pair, and taking the worker's
    new corners), which a node runs after publishing that pose; ``after_update`` and
    ``no_update`` the median ms of the pairs after one whose rig update measured and of the
    others (NaN when there are none).
    """
    run = run_clip(clip, config)
    cpu = float(np.mean(run['all_cpu_ms'][1:]))
    totals = np.array([t['total'] for t in run['timings'][1:]])
    to_pose = [t['total'] - last.get('after_pose', 0.0)
               for last, t in zip(run['timings'][:-1], run['timings'][1:])]
    measured = run['rig_measured'][:-1]  # the work before each counted pair
    own = float(np.mean(run['cpu_ms'][1:]))
    worker = float(np.mean(run['worker_cpu_ms'][1:]))

    def median(values: np.ndarray) -> float:
        return float(np.median(values)) if len(values) else float('nan')

    return {'total': float(np.median(totals)), 'cpu': cpu,
            'caller': own / float(np.mean(totals)),
            'where': np.array([own, cpu - own - worker, worker]),
            'to_pose': float(np.median(to_pose)), 'after_update': median(totals[measured]),
            'no_update': median(totals[~measured])}


def parse_config(items: list[str]) -> Config:
    """Config with ``SECTION.KEY=VALUE`` overrides (values as JSON)."""
    try:
        return Config().replace(**overrides_from_items(items))
    except ConfigError as exc:
        raise SystemExit(f'bad configuration {items}: {exc}') from None


def main() -> int:
    """Run the benchmark; return the process exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--data', type=Path, default=SHARED_DATA,
                        help='folder holding the KITTI clips (default: %(default)s)')
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--base', nargs='*', default=BASE, metavar='SECTION.KEY=VALUE',
                        help='overrides of the first configuration (default: %(default)s)')
    parser.add_argument('--variant', action='append', default=[], metavar='"K=V [K=V ...]"',
                        help='a configuration to compare, as space-separated overrides of the '
                        f'defaults (repeatable; default: {VARIANTS})')
    parser.add_argument('--render', action='append', default=[], metavar='WxH',
                        help='also time a rendered urban scene of this size (60 pairs), e.g. '
                        '1280x720 (repeatable)')
    args = parser.parse_args()
    cv2.setNumThreads(1)
    # The CPUs this process may run on (its affinity), the worker process inheriting them.
    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else \
        os.cpu_count() or 1
    variants = args.variant or VARIANTS
    names = [' '.join(args.base) or 'default'] + [v or 'default' for v in variants]
    configs = [parse_config(args.base)] + [parse_config(v.split()) for v in variants]

    clips = []
    for name in KITTI_CLIPS:
        if (args.data / name / 'calib.txt').exists():
            clips.append(load_real(args.data / name))
        else:
            print(f'skipping {name}: no clip at {args.data / name}')
    if not clips:
        print('no KITTI clip: timing a rendered urban scene (1241x376, 60 frames) instead')
        clips.append(render(SequenceSpec.preset('urban', n_frames=60), 'urban'))
    for size in args.render:
        width_height = image_size(size)
        if width_height is None:
            raise SystemExit(f'--render wants WxH, got {size!r}')
        width, height = width_height
        clips.append(render_urban(width, height, f'urban{width}x{height}'))
    print(f'{len(clips)} clip(s): ' + ', '.join(
        f'{c.name} ({len(c.frames)} pairs, {c.size[0]}x{c.size[1]})' for c in clips))
    print('configurations: ' + '; '.join(f'[{i}] {n}' for i, n in enumerate(names)))
    print(f'OMP/OpenBLAS threads 1 (OpenCV threads: pipeline.threads - 1), '
          f'{cores} CPUs usable, load average {os.getloadavg()[0]:.2f}')

    # totals, cpu and caller[round][config][clip], reference[round]
    totals = np.full((args.rounds, len(configs), len(clips)), np.nan)
    cpu = np.full_like(totals, np.nan)
    caller = np.full_like(totals, np.nan)
    where = np.full((*totals.shape, 3), np.nan)  # caller's thread, other threads, worker
    to_pose = np.full_like(totals, np.nan)
    groups = np.full((*totals.shape, 2), np.nan)  # after a rig measurement, after none
    reference = np.full(args.rounds, np.nan)
    print(f'\n{"round":>5s} {"reference ms":>12s}  ' + '  '.join(
        f'[{i}] {c.name[:14]:>14s}' for i in range(len(configs)) for c in clips))
    for r in range(args.rounds):
        reference[r] = reference_ms(clips[0])
        order = np.roll(np.arange(len(configs)), -r)
        for i in order:
            for k, clip in enumerate(clips):
                run = total_ms(clip, configs[i])
                totals[r, i, k], cpu[r, i, k], caller[r, i, k] = (
                    run['total'], run['cpu'], run['caller'])
                where[r, i, k], to_pose[r, i, k] = run['where'], run['to_pose']
                groups[r, i, k] = run['after_update'], run['no_update']
        print(f'{r + 1:5d} {reference[r]:12.2f}  ' + '  '.join(
            f'{totals[r, i, k]:19.2f}' for i in range(len(configs))
            for k in range(len(clips))))

    print(f'\nreference KLT pass: median {np.median(reference):.2f} ms, '
          f'{reference.min():.2f}-{reference.max():.2f} over the rounds (6-10 ms seen here)')
    print('total ms per pair, median over rounds (range):')

    def per_clip(cell) -> str:
        """``clip cell(k); ...`` over the clips."""
        return '; '.join(f'{clip.name} {cell(k)}' for k, clip in enumerate(clips))

    def medians(values: np.ndarray) -> str:
        """Medians over rounds of (rounds, n) values, as ``a / b / ...``."""
        return ' / '.join(f'{v:.2f}' for v in np.median(values, axis=0))

    for i, name in enumerate(names):
        cells = []
        for k, clip in enumerate(clips):
            med = float(np.median(totals[:, i, k]))
            cells.append(f'{clip.name} {med:.2f} ({totals[:, i, k].min():.2f}-'
                         f'{totals[:, i, k].max():.2f}), CPU {np.median(cpu[:, i, k]):.2f} '
                         f'{verdict(med <= TARGET_TOTAL_MS)}')
        print(f'  [{i}] {name}: ' + '; '.join(cells))
        # One line per figure: what it is, and its cell for clip k.
        for text, cell in (
                ("ms per pair up to its pose, without the last pair's work after its pose (which "
                 'a node runs after publishing; medians over rounds)',
                 lambda k: f'{np.median(to_pose[:, i, k]):.2f}'),
                ('ms per pair after a pair whose rig update measured / after one whose did not '
                 '(medians over the pairs, then over rounds)',
                 lambda k: medians(groups[:, i, k])),
                ("share of the time per pair the caller's thread was busy (its CPU time over the "
                 'total; near 100 %: it bounds the pair)',
                 lambda k: f'{100 * np.median(caller[:, i, k]):.0f} %'),
                ("CPU per pair where it ran (the caller's thread / the process's other threads / "
                 'the worker process, ms; medians over rounds)',
                 lambda k: medians(where[:, i, k])),
                (f'mean CPU per pair over the {cores} CPUs (pairs cannot take less on average)',
                 lambda k: f'{np.median(cpu[:, i, k]) / cores:.2f} ms')):
            print(f'  [{i}] {text}: {per_clip(cell)}')
    for i in range(1, len(configs)):
        extra = totals[:, i] - totals[:, 0]
        extra_cpu = cpu[:, i] / cpu[:, 0] - 1.0
        print(f'  [{i}] CPU / [0] CPU - 1, paired within rounds: ' + '; '.join(
            f'{clip.name} {100 * np.median(extra_cpu[:, k]):+.0f} %'
            for k, clip in enumerate(clips)))
        print(f'  [{i}] - [0], paired within rounds: ' + '; '.join(
            f'{clip.name} {np.median(extra[:, k]):+.2f} ms ({extra[:, k].min():+.2f} to '
            f'{extra[:, k].max():+.2f})' for k, clip in enumerate(clips)))
    print(f'target: total median <= {TARGET_TOTAL_MS:.1f} ms per pair (half of libviso2 at '
          f'{LIBVISO2_MS:.1f} ms on kitti06 in one run of the same machine), CPU per pair at '
          'most 10 % above the first configuration')
    return 0


if __name__ == '__main__':
    sys.exit(main())
