#!/usr/bin/env python3
"""
Time per frame of the egomotion estimator (Kitt et al.) for several numbers of correspondences.

Runs :class:`stereo_vo_ros.estimation.estimator.MotionEstimator` (bucketing, RANSAC, final ISPKF
update) on simulated sequences (:mod:`stereo_vo_ros.synthetic.simulation`, 0.7 px noise, 20 %
outliers by default) with N = 40, 200 and 500 correspondences per frame pair, with and without
RANSAC, in a single thread. Every configuration is repeated; the table gives the median over
repeats of the per-frame median and 95th percentile (ms) of the wall clock and of the thread CPU
time (``time.thread_time`` around ``MotionEstimator.estimate``, which other loads on a shared
machine disturb less), the mean number of correspondences left after bucketing (the default grid
keeps at most 12 x 4 x 6 = 288) and the mean filter iterations. ``--defaults`` adds rows with the
package's default estimator configuration (robust reweighting, ground-plane weights, outlier
streaks, more samples after a reset) as the pipeline runs it.

Usage::

    python benchmarks/bench_estimator.py [--frames 300] [--repeats 3] [--points 40 200 500]
        [--filter ispkf] [--outliers 0.2] [--defaults] [--profile 200]
"""

import argparse
import cProfile
import os
import pstats
import sys
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from stereo_vo_ros.config import Config  # noqa: E402
from stereo_vo_ros.estimation.estimator import MotionEstimator  # noqa: E402
from stereo_vo_ros.io.correspondences import iter_estimates  # noqa: E402
from stereo_vo_ros.synthetic.simulation import (  # noqa: E402
    paper_config, simulate_sequence, SimulationSpec)
from stereo_vo_ros.tracking import bucketing  # noqa: E402

TARGET_MS = 2.0  #: target: estimator plus RANSAC for N = 200 (thread CPU time, median)


def time_config(seq, config, repeats):
    """
    Time one configuration over ``repeats`` passes.

    Returns the medians over repeats of the per-frame (wall median, wall p95, CPU median, CPU
    p95) ms and the mean iterations.
    """
    stats, iters = [], []
    for _ in range(repeats):
        estimator = MotionEstimator(config)
        inner, cpu = estimator.estimate, []

        def timed(*args, _inner=inner, _cpu=cpu, **kwargs):
            c0 = time.thread_time()
            out = _inner(*args, **kwargs)
            _cpu.append((time.thread_time() - c0) * 1e3)
            return out
        estimator.estimate = timed
        wall = []
        for fe in iter_estimates(seq.data, estimator=estimator):
            wall.append(fe.elapsed_ms)
            iters.append(fe.estimate.iterations)
        stats.append([np.median(wall), np.percentile(wall, 95), np.median(cpu),
                      np.percentile(cpu, 95)])
    return tuple(float(v) for v in np.median(stats, axis=0)) + (float(np.mean(iters)),)


def kept_after_bucketing(seq, config):
    """Mean number of correspondences bucketing keeps per frame pair."""
    size = seq.data.image_size()
    return float(np.mean([bucketing.select(seq.data.cur_left[k], size, config.bucketing).sum()
                          for k in range(len(seq.data))]))


def profile(seq, config, top=25):
    """Print the cProfile of one pass over the sequence (cumulative time)."""
    prof = cProfile.Profile()
    prof.enable()
    for _ in iter_estimates(seq.data, config):
        pass
    prof.disable()
    pstats.Stats(prof).sort_stats('cumulative').print_stats(top)
    pstats.Stats(prof).sort_stats('tottime').print_stats(top)


def main(argv=None):
    """Run the benchmark and print a Markdown table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--frames', type=int, default=300, help='frame pairs per sequence')
    ap.add_argument('--repeats', type=int, default=3, help='passes over each sequence')
    ap.add_argument('--points', type=int, nargs='+', default=[40, 200, 500])
    ap.add_argument('--filter', default='ispkf', choices=['ispkf', 'iekf', 'ukf', 'ekf'])
    ap.add_argument('--outliers', type=float, default=0.2, help='outlier ratio of the data')
    ap.add_argument('--noise', type=float, default=0.7, help='pixel noise (px)')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--defaults', action='store_true',
                    help="also time the package's default estimator configuration")
    ap.add_argument('--profile', type=int, default=0, metavar='N',
                    help='also print a cProfile of the RANSAC run with N points')
    args = ap.parse_args(argv)
    print(f'# estimator timing: {args.filter}, {args.frames} frame pairs, {args.repeats} '
          f'repeats, noise {args.noise} px, outliers {args.outliers:.0%}, numpy '
          f'{np.__version__}, 1 thread')
    print()
    print('| N | configuration | RANSAC | kept after bucketing | median ms | p95 ms | '
          'CPU median ms | CPU p95 ms | mean iterations |')
    print('|---|---|---|---|---|---|---|---|---|')
    for n in args.points:
        spec = SimulationSpec(frames=args.frames, points=n, noise_px=args.noise,
                              outlier_ratio=args.outliers, seed=args.seed)
        seq = simulate_sequence(spec)
        runs = [('paper', False), ('paper', True)] + ([('defaults', True)] if args.defaults
                                                      else [])
        for name, ransac in runs:
            config = paper_config(args.filter, ransac=ransac, noise_px=args.noise)
            if name == 'defaults':  # the same filter and pixel noise, the rest as shipped
                config = Config().replace(**{'filter.type': args.filter,
                                             'filter.pixel_noise_px':
                                             config.filter.pixel_noise_px})
            kept = kept_after_bucketing(seq, config)
            med, p95, cpu_med, cpu_p95, it = time_config(seq, config, args.repeats)
            flag = ''
            if ransac and n == 200 and name == 'paper':
                flag = f' (target <= {TARGET_MS:g} ms: ' + (
                    'met' if cpu_med <= TARGET_MS else
                    f'missed by {cpu_med - TARGET_MS:.2f} ms') + ')'
            print(f'| {n} | {name} | {"on" if ransac else "off"} | {kept:.1f} | {med:.2f} | '
                  f'{p95:.2f} | {cpu_med:.2f}{flag} | {cpu_p95:.2f} | {it:.2f} |', flush=True)
    if args.profile:
        spec = SimulationSpec(frames=args.frames, points=args.profile, noise_px=args.noise,
                              outlier_ratio=args.outliers, seed=args.seed)
        print(f'\n# cProfile: N = {args.profile}, RANSAC on')
        profile(simulate_sequence(spec), paper_config(args.filter, ransac=True,
                                                      noise_px=args.noise))


if __name__ == '__main__':
    main()
