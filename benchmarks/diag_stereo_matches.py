"""
Where the speed goes on a rendered sequence: wrong stereo matches and vehicles among the inliers.

Renders a preset (default: the highway, seed 4) with its depth and vehicle masks, runs the
pipeline with the default configuration and prints, for the frames asked for:

1. per frame: estimated / true step length, RANSAC inliers, inliers on moving vehicles, and the
   disparity error (px) of the static inliers against the renderer's depth;
2. over all frames: the share of stereo matches (static points, smooth depth) whose disparity
   is more than 1 px off, and how their 11x11 window correlates (ZNCC) at the match and at the
   best other position of the right row; the same for the matches within 0.3 px.

A stereo match too near (disparity too large) moves less than its depth says and reads as a
slower camera. Depth is sampled at the rounded pixel; points whose 3x1 depth neighbourhood
varies by more than 5 % (object borders) are left out.

Usage::

    python benchmarks/diag_stereo_matches.py [--preset highway] [--seed 4] [--first 20]
        [--last 60]

The README's "Known limitations" quotes seed 4, frames 20-59.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.config import Config  # noqa: E402
from stereo_vo_ros.pipeline import StereoOdometry  # noqa: E402
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer  # noqa: E402

#: Half side of the correlation windows (pixels): 11x11.
HALF = 5
#: Largest disparity searched along the right row (pixels).
MAX_DISPARITY_PX = 300


def row_scores(left: np.ndarray, right: np.ndarray, pl: np.ndarray, pr: np.ndarray
               ) -> tuple[float, float]:
    """ZNCC of the left window at the match and the best ZNCC elsewhere (> 3 px) on the row."""
    x, y = int(round(pl[0])), int(round(pl[1]))
    xr = pr[0] + (x - pl[0])
    h, w = left.shape
    if not (HALF <= y < h - HALF and HALF <= x < w - HALF):
        return np.nan, np.nan
    lo = max(int(x - MAX_DISPARITY_PX) - HALF, 0)
    hi = min(int(np.ceil(xr)) + 4 + HALF + 1, w)
    if hi - lo < 2 * HALF + 1:
        return np.nan, np.nan
    scores = cv2.matchTemplate(right[y - HALF:y + HALF + 1, lo:hi],
                               left[y - HALF:y + HALF + 1, x - HALF:x + HALF + 1],
                               cv2.TM_CCOEFF_NORMED)[0]
    dist = np.abs(np.arange(len(scores)) + lo + HALF - xr)
    near, far = scores[dist <= 1.5], scores[dist > 3.0]
    return (float(near.max()) if len(near) else np.nan,
            float(far.max()) if len(far) else np.nan)


def main() -> int:
    """Run the diagnosis and print it."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', default='highway')
    ap.add_argument('--seed', type=int, default=4)
    ap.add_argument('--first', type=int, default=20, help='first frame reported')
    ap.add_argument('--last', type=int, default=60, help='frames run (the last one excluded)')
    args = ap.parse_args()
    spec = SequenceSpec.preset(args.preset, seed=args.seed)
    renderer = StereoRenderer(spec)
    calib = renderer.calibration
    P0, P1 = spec.projections()
    bf = -P1[0, 3]  # focal length times baseline (pixels * m)
    vo = StereoOdometry(Config())
    gt = renderer.poses
    print(f'{args.preset} seed {args.seed}, {spec.width}x{spec.height}, frames '
          f'{args.first}-{args.last - 1}; default config')
    print(f'{"frame":>5s} {"step ratio":>10s} {"inliers":>7s} {"on vehicles":>11s} '
          f'{"static disp err median / mean px":>33s}')
    poses, rows = [], []
    for i in range(args.last):
        pair = renderer.render(i, depth=i >= args.first)
        res = vo.process(pair.stereo_frame(calib))
        poses.append(res.T_world_cam)
        if i < max(args.first, 1) or res.features is None or res.inliers is None:
            continue
        c = res.features
        px = np.clip(np.rint(c.cur_left).astype(int), 0, [spec.width - 1, spec.height - 1])
        depth = pair.depth_left
        z = depth[px[:, 1], px[:, 0]]
        around = depth[np.clip(px[:, 1][:, None] + [-1, 0, 1], 0, spec.height - 1),
                       px[:, 0][:, None]]
        with np.errstate(invalid='ignore'):
            smooth = np.abs(np.nanmax(around, 1) - np.nanmin(around, 1)) < 0.05 * z
        static = pair.static_left[px[:, 1], px[:, 0]]
        err = (c.cur_left[:, 0] - c.cur_right[:, 0]) - bf / z
        step_true = np.linalg.norm((np.linalg.inv(gt[i - 1]) @ gt[i])[:3, 3])
        step_est = np.linalg.norm((np.linalg.inv(poses[-2]) @ poses[-1])[:3, 3])
        inl = res.inliers
        good = static & smooth & inl
        print(f'{i:5d} {step_est / step_true:10.3f} {int(inl.sum()):7d} '
              f'{int((inl & ~static).sum()):11d} '
              f'{np.median(err[good]):+16.3f} / {np.mean(err[good]):+.3f}')
        for k in np.flatnonzero(static & smooth):
            rows.append((abs(err[k]), *row_scores(pair.left, pair.right, c.cur_left[k],
                                                  c.cur_right[k])))
    a = np.array(rows)
    bad, fine = a[:, 0] > 1.0, a[:, 0] < 0.3
    print(f'\nstereo matches of static points with smooth depth: {len(a)}; more than 1 px off in '
          f'disparity: {100 * bad.mean():.1f} %')
    for name, m in (('> 1 px off', bad), ('< 0.3 px off', fine)):
        d = a[m]
        beaten = np.mean(d[:, 2] >= d[:, 1]) * 100
        print(f'  {name:13s} {len(d):5d} matches: ZNCC at the match median '
              f'{np.nanmedian(d[:, 1]):.3f}, best elsewhere on the row '
              f'{np.nanmedian(d[:, 2]):.3f}; beaten by another window of the row: '
              f'{beaten:.1f} %')
    return 0


if __name__ == '__main__':
    sys.exit(main())
