"""
What each stage's time buys: time saved against accuracy lost with the stage off or cheaper.

Every optional stage is turned off (or made cheaper) in turn and scored over many rendered
scenes and the real clips.

A stage earns its place when the accuracy it buys is larger than the scene-to-scene spread; one
scene per kind says little (a single highway scene moves by a tenth of a percent with settings
that should not matter). For each variant (the default configuration with some items changed)
this prints:

* the time saved per pair on the KITTI clips (and on rendered urban scenes of the sizes given
  with ``--render WxH``, 60 pairs each): median total ms per pair, timed interleaved with the
  default round by round (as ``bench_speed.py`` does; first pair left out, one thread), the
  saving paired within rounds;
* mean t_rel (%) over seeds of rendered presets (``bench_seeds.score``, renders cached with
  ``--cache``): the clean city and highway, the city with exposure jumps and vignetting, the
  highway with a rig error; and in how many of the scenes the variant is worse than the default;
* end drift (%) and the median features tracked per pair on the KITTI clips in
  ``../shared/data`` (skipped, and said so, without them); ``--every N`` takes every N-th frame
  of them (a lower frame rate: the motion prior's predictions are further off). The rendered
  scenes of ``--render`` get an end drift and features column too, at their own frame rate.
  Without the clips the timing's reference pass runs on the first rendered scene, so it does
  not compare with reference figures of the clips.

Usage::

    python benchmarks/bench_stage_value.py [--data ../shared/data] [--seeds 0-7]
        [--frames 150] [--cache DIR] [--rounds 3] [--presets urban highway ...] [--every 1]
        [--render 1280x720]

Time figures need an otherwise idle machine; the accuracy figures do not.
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
    Clip, image_size, KITTI_CLIPS, load_real, render_urban, run_clip, SHARED_DATA)
from bench_seeds import parse_seeds, score  # noqa: E402
from bench_speed import reference_ms, total_ms  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from stereo_vo_ros.config import Config, overrides_from_items  # noqa: E402
from stereo_vo_ros.evaluation import metrics  # noqa: E402

#: (label, configuration items) of the variants; the default comes first.
VARIANTS = (
    ('default', []),
    ('no affine refinement', ['tracker.affine_refinement=false']),
    ('no aperture checks', ['tracker.min_eigen_ratio=0', 'tracker.min_flow_edge_ratio=0',
                            'tracker.min_flow_edge_ratio_tracked=0']),
    ('no brightness map', ['tracker.photometric_compensation=false']),
    ('no rig refinement', ['rig.enabled=false']),
    ('no bi-circular check', ['tracker.variant=dc']),
    ('no robust reweighting', ['filter.robust_loss=none']),
    ('affine: 2 iterations', ['tracker.affine_iterations=2']),
    ('KLT: 10 iterations', ['tracker.max_iterations=10']),
    ('KLT from a start: base', ['tracker.predicted_pyramid_levels=0',
                                'tracker.stereo_pyramid_levels=0']),
    ('temporal, bc KLT: base', ['tracker.predicted_pyramid_levels=0']),
    ('stereo KLT: base', ['tracker.stereo_pyramid_levels=0']),
)
PRESETS = ('urban', 'highway', 'urban_photometric', 'highway_rig')


def short(clip: Clip) -> str:
    """Return a clip's column label: ``kitti06`` for ``kitti06_f0000-0050``, ``1280x720``."""
    return clip.name.split('_')[0].split()[0]


def config_of(items: list[str]) -> Config:
    """Return the default configuration with one pipeline thread and ``items`` applied."""
    return Config().replace(**overrides_from_items(['pipeline.threads=1', *items]))


def timing(clips: list, configs: list[Config], rounds: int) -> np.ndarray:
    """(variants, clips, rounds) median ms per pair, timed interleaved round by round."""
    out = np.full((len(configs), len(clips), rounds), np.nan)
    for r in range(rounds):
        order = np.roll(np.arange(len(configs)), r)
        for c, clip in enumerate(clips):
            for v in order:
                out[v, c, r] = total_ms(clip, configs[v])['total']
        print(f'  timing round {r + 1}/{rounds}: reference KLT pass '
              f'{reference_ms(clips[0]):.2f} ms', flush=True)
    return out


def main() -> int:
    """Run every variant on the presets and the clips and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--data', type=Path, default=SHARED_DATA, help='folder of the real clips')
    ap.add_argument('--seeds', nargs='+', default=['0-7'])
    ap.add_argument('--frames', type=int, default=150, help='frames per rendered scene')
    ap.add_argument('--presets', nargs='*', default=list(PRESETS), help='none: time only')
    ap.add_argument('--cache', type=Path, default=None, help='keep renders here (npz)')
    ap.add_argument('--rounds', type=int, default=3, help='timing rounds (0: no timing)')
    ap.add_argument('--every', type=int, default=1,
                    help='take every N-th frame of the real clips: a lower frame rate, whose '
                         'larger steps put the motion prior further off')
    ap.add_argument('--render', action='append', default=[], metavar='WxH',
                    help='also time and run a rendered urban scene of this size (60 pairs), '
                         'e.g. 1280x720 (repeatable)')
    args = ap.parse_args()
    if args.every < 1 or (args.every > 1 and args.rounds > 0):
        ap.error('--every takes N >= 1, and above 1 needs --rounds 0 (the timing and its '
                 'reference pass are for the clips at their own frame rate)')
    render_sizes = [image_size(size) for size in args.render]
    for size, width_height in zip(args.render, render_sizes):
        if width_height is None or min(width_height) < 64:
            ap.error(f'--render wants WxH, at least 64x64, got {size!r}')
    cv2.setNumThreads(1)
    seeds = parse_seeds(args.seeds)
    configs = [config_of(items) for _, items in VARIANTS]
    clips = [load_real(args.data / name) for name in KITTI_CLIPS
             if (args.data / name).is_dir()]
    if args.every > 1:
        clips = [Clip(f'{c.name} every {args.every}', c.frames[::args.every],
                      c.gt[::args.every]) for c in clips]
        sizes = ', '.join(str(len(c.frames)) for c in clips)
        print(f'real clips: every {args.every}th frame ({sizes} pairs)')
    if not clips:
        print(f'KITTI clips not found in {args.data}: no real-clip time or drift')
    for width, height in render_sizes:
        clips.append(render_urban(width, height, f'{width}x{height}'))
        print(f'rendered urban scene {width}x{height}: {clips[-1].info}')

    saved = None
    if clips and args.rounds > 0:
        print(f'timing {len(configs)} configurations on {len(clips)} clips, '
              f'{args.rounds} rounds', flush=True)
        ms = timing(clips, configs, args.rounds)
        saved = ms[0:1] - ms  # paired within rounds
        for v, (label, _) in enumerate(VARIANTS):
            print(f'  {label:24s} ' + '  '.join(
                f'{short(clip)} {np.median(ms[v, c]):6.2f} ms (saves '
                f'{np.median(saved[v, c]):+5.2f})' for c, clip in enumerate(clips)), flush=True)

    t_rel = np.full((len(configs), len(args.presets), len(seeds)), np.nan)
    for p, preset in enumerate(args.presets):
        for v, cfg in enumerate(configs):
            t0 = time.perf_counter()
            rows = [score((preset, s, args.frames, args.cache, cfg, None)) for s in seeds]
            t_rel[v, p] = [r['t_rel'] for r in rows]
            print(f'  {preset:18s} {VARIANTS[v][0]:24s} mean t_rel '
                  f'{np.nanmean(t_rel[v, p]):.3f} % ({time.perf_counter() - t0:.0f} s)',
                  flush=True)

    drift = np.full((len(configs), len(clips)), np.nan)
    tracked = np.full((len(configs), len(clips)), np.nan)
    for c, clip in enumerate(clips):
        for v, cfg in enumerate(configs):
            run = run_clip(clip, cfg)
            drift[v, c] = metrics.evaluate(clip.gt, run['poses'])['end_drift_pct']
            tracked[v, c] = np.median(run['tracked'][1:])

    print(f'\nseeds {args.seeds}, {args.frames} frames per scene; mean t_rel % (scenes worse '
          'than the default); end drift % and median features tracked per pair on the clips; ms '
          'saved per pair (median over rounds, range)')
    head = f'{"variant":24s} ' + ' '.join(f'{short(c) + " ms":>22s}' for c in clips) if \
        saved is not None else f'{"variant":24s}'
    head += ' ' + ' '.join(f'{p[:18]:>18s}' for p in args.presets)
    head += ' ' + ' '.join(f'{short(c) + " drift":>14s}' for c in clips)
    head += ' ' + ' '.join(f'{short(c) + " feats":>14s}' for c in clips)
    print(head)
    for v, (label, _) in enumerate(VARIANTS):
        line = f'{label:24s} '
        if saved is not None:
            line += ' '.join(f'{np.median(saved[v, c]):+6.2f} ({saved[v, c].min():+5.2f}..'
                             f'{saved[v, c].max():+5.2f})'.rjust(22) for c in range(len(clips)))
        for p in range(len(args.presets)):
            worse = int(np.count_nonzero(t_rel[v, p] > t_rel[0, p])) if v else 0
            cell = f'{np.nanmean(t_rel[v, p]):.3f}' + (f' ({worse}/{len(seeds)})' if v else '')
            line += ' ' + cell.rjust(18)
        line += ' ' + ' '.join(f'{drift[v, c]:14.2f}' for c in range(len(clips)))
        line += ' ' + ' '.join(f'{tracked[v, c]:14.0f}' for c in range(len(clips)))
        print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
