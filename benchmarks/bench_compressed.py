"""
Compressed image bags: accuracy of the pipeline on jpeg against raw images, and decode time.

Recorded robot bags usually hold ``sensor_msgs/CompressedImage`` (image_transport
``compressed``). For each scene this script writes the same stereo pairs twice as rosbag2, raw
mono8 and jpeg (``--quality``, default 90) on ``<topic>/compressed``, reads both back through
``RosbagSequence`` (the reader ``stereo_vo run BAG`` uses: the jpeg bag has no raw topics, so
it reads the compressed ones), runs the pipeline over each with the default configuration and
prints t_rel / r_rel (KITTI metric; end-point drift for the 51-frame real clips), their ratio,
and the median time to decode the two jpeg images of a pair (OpenCV, one thread).

Scenes: the rendered ``--preset`` (default urban) for ``--seeds`` at ``--frames`` frames, and
the real KITTI clips of ``--data`` when present (skipped with a note otherwise).

Target: t_rel on jpeg quality 90 within 1.2x of the raw bag's.

Usage::

    python benchmarks/bench_compressed.py [--preset urban] [--seeds 0-3] [--frames 150]
        [--quality 90] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import tempfile
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_seeds import parse_seeds  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402

from stereo_vo_ros.config import Config  # noqa: E402
from stereo_vo_ros.evaluation import metrics  # noqa: E402
from stereo_vo_ros.io import open_sequence  # noqa: E402
from stereo_vo_ros.io.compressed import compress_grey, grey_from_compressed  # noqa: E402
from stereo_vo_ros.io.rosbag import BagTopics, RosbagSequence  # noqa: E402
from stereo_vo_ros.io.rosbag import write_stereo_bag  # noqa: E402
from stereo_vo_ros.offline import run_frames  # noqa: E402
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'
KITTI_CLIPS = ('kitti06_f0000-0050', 'kitti01_f0000-0050')


def score(frames: list, gt: np.ndarray, short: bool) -> tuple[float, float]:
    """(t_rel %, r_rel deg/100 m) of the pipeline over the frames, or the end drift (%, nan)."""
    out = run_frames(iter(frames), Config())
    if short:
        return float(metrics.end_point_drift(gt, out.poses)), float('nan')
    t_rel, r_rel, _ = metrics.kitti_odometry_error(gt, out.poses)
    return float(t_rel), float(r_rel)


def compare(name: str, frames: list, gt: np.ndarray, quality: int, tmp: Path,
            short: bool = False) -> dict:
    """Write raw and jpeg bags of the frames, read them back, score both."""
    calib = frames[0].calibration
    raw_bag, jpeg_bag = tmp / f'{name}_raw', tmp / f'{name}_jpeg'
    write_stereo_bag(raw_bag, frames, calib)
    write_stereo_bag(jpeg_bag, frames, calib, encoding='jpeg', jpeg_quality=quality,
                     topics=BagTopics(transport='compressed'))
    raw = list(RosbagSequence(raw_bag))
    jpeg_seq = RosbagSequence(jpeg_bag)
    assert jpeg_seq.topics.transport == 'compressed'
    jpeg = list(jpeg_seq)
    decode_ms = []
    for f in frames[:30]:
        coded = [compress_grey(img, 'jpeg', quality) for img in (f.left, f.right)]
        t0 = time.perf_counter()
        for fmt, data in coded:
            grey_from_compressed(fmt, data)
        decode_ms.append((time.perf_counter() - t0) * 1e3)
    size_kb = np.mean([compress_grey(f.left, 'jpeg', quality)[1].size for f in frames[:30]]) / 1e3
    t_raw, r_raw = score(raw, gt, short)
    t_jpg, r_jpg = score(jpeg, gt, short)
    return {'name': name, 't_raw': t_raw, 'r_raw': r_raw, 't_jpeg': t_jpg, 'r_jpeg': r_jpg,
            'decode_ms': float(np.median(decode_ms)), 'kb': float(size_kb)}


def main() -> int:
    """Run the comparison and print one row per scene and a summary."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', default='urban')
    ap.add_argument('--seeds', nargs='+', default=['0-3'])
    ap.add_argument('--frames', type=int, default=150)
    ap.add_argument('--quality', type=int, default=90)
    ap.add_argument('--data', type=Path, default=SHARED_DATA)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rows = []
    print(f'jpeg quality {args.quality}; t_rel % / r_rel deg/100 m (KITTI metric); real clips: '
          'end-point drift %')
    print(f'{"scene":>22s} {"raw t_rel":>9s} {"jpeg t_rel":>10s} {"ratio":>6s} {"raw r_rel":>9s} '
          f'{"jpeg r_rel":>10s} {"decode ms":>9s} {"kB/img":>7s}')
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        jobs = []
        for seed in parse_seeds(args.seeds):
            jobs.append((f'{args.preset}_{seed}', 'synthetic', seed))
        for clip in KITTI_CLIPS:
            if (args.data / clip / 'calib.txt').exists():
                jobs.append((clip, 'kitti', None))
            else:
                print(f'{clip}: not found under {args.data} (skipped)')
        for name, kind, seed in jobs:
            if kind == 'synthetic':
                spec = SequenceSpec.preset(args.preset, seed=seed, n_frames=args.frames)
                renderer = StereoRenderer(spec)
                frames = list(renderer.frames())
                gt, short = renderer.poses, False
            else:
                seq = open_sequence(args.data / name)
                frames, gt, short = list(seq), seq.ground_truth, True
            row = compare(name, frames, gt, args.quality, tmp, short)
            rows.append(row)
            print(f'{name:>22s} {row["t_raw"]:9.3f} {row["t_jpeg"]:10.3f} '
                  f'{row["t_jpeg"] / row["t_raw"]:6.2f} {row["r_raw"]:9.3f} '
                  f'{row["r_jpeg"]:10.3f} {row["decode_ms"]:9.2f} {row["kb"]:7.1f}', flush=True)
    ratios = np.array([r['t_jpeg'] / r['t_raw'] for r in rows])
    decode = np.median([r['decode_ms'] for r in rows])
    print(f'jpeg / raw t_rel: mean ratio {ratios.mean():.2f}, worst {ratios.max():.2f} '
          f'(target <= 1.2); decoding a pair: median {decode:.2f} ms')
    return 0


if __name__ == '__main__':
    sys.exit(main())
