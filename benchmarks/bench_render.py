"""
Time the synthetic stereo renderer: milliseconds per stereo pair for every preset.

Run from the repository root::

    python benchmarks/bench_render.py [--frames 40] [--threads 1]

Presets are rendered at KITTI size (1241 x 376) except ``demo`` (its own size). Scene
construction (procedural textures, city layout) is timed separately; ``--threads 1`` limits
OpenCV to one core (the budget is about 250 ms per pair on one core).
"""

import argparse
from pathlib import Path
import statistics
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.synthetic import PRESETS, SequenceSpec, StereoRenderer  # noqa: E402


def time_renderer(spec: SequenceSpec, frames: int, depth: bool = False) -> tuple[float, list]:
    """Return (build seconds, list of ms per pair) over ``frames`` pairs spread over the run."""
    t0 = time.perf_counter()
    renderer = StereoRenderer(spec)
    build = time.perf_counter() - t0
    indices = np.linspace(0, len(renderer) - 1, frames).round().astype(int)
    renderer.render(int(indices[0]), depth=depth)  # warm up lazily built texture levels
    times = []
    for i in indices:
        t0 = time.perf_counter()
        renderer.render(int(i), depth=depth)
        times.append(1000.0 * (time.perf_counter() - t0))
    return build, times


def main() -> None:
    """Print a table of render timings."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=40, help='pairs timed per preset')
    parser.add_argument('--threads', type=int, default=1, help='OpenCV threads (0: default)')
    args = parser.parse_args()
    if args.threads > 0:
        cv2.setNumThreads(args.threads)
    print(f'OpenCV threads: {cv2.getNumThreads()}, pairs per preset: {args.frames}')
    print(f'{"preset":<22} {"size":>10} {"build s":>8} {"mean ms":>8} {"median":>8} '
          f'{"max":>8}')
    rows = [(name, {}, False) for name in PRESETS]
    rows += [('urban', {'supersample': 2}, False), ('urban', {}, True)]
    for name, extra, depth in rows:
        spec = SequenceSpec.preset(name, **extra)
        build, times = time_renderer(spec, args.frames, depth)
        label = name + ''.join(f' {k}={v}' for k, v in extra.items())
        label += ' +depth' if depth else ''
        print(f'{label:<22} {spec.width:>5}x{spec.height:<4} {build:8.2f} '
              f'{statistics.mean(times):8.1f} {statistics.median(times):8.1f} '
              f'{max(times):8.1f}')


if __name__ == '__main__':
    main()
