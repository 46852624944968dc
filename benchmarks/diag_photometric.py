"""
Where tracking breaks under per-camera exposure jumps and vignetting, against ground truth.

Renders the first frames of a preset twice with the same scene (``SequenceSpec.preset(name,
seed=s)``, once as given and once with the photometric fields at 0), runs ``StereoOdometry``
over both with the configuration given, and prints per run: the pairs whose status is not OK,
features tracked and RANSAC inliers per pair, the features each tracker check removed per pair
(``TrackerStats.failed``), and the error of the tracked quadruples against the renderer's exact
geometry (pixels): each previous left point is lifted with the true depth (inverse depth
interpolated bilinearly, exact on planes; points on moving vehicles or depth edges left out),
moved with the true motion and projected into the current left and right images and the
previous right image. Medians and the 90th percentile over all quadruples.

Usage::

    python benchmarks/diag_photometric.py [--preset urban_photometric] [--seed 0]
        [--frames 40] [--set tracker.photometric_compensation=false ...]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import sys

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros import config as config_mod  # noqa: E402
from stereo_vo_ros.pipeline import StereoOdometry  # noqa: E402
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer  # noqa: E402
from stereo_vo_ros.tracking.tracker import CHECKS  # noqa: E402

PHOTOMETRIC_FIELDS = ('gain_jitter', 'gain_offset_jitter', 'vignetting', 'vignetting_mismatch',
                      'exposure_change', 'stereo_gain_mismatch')


def inverse_depth_at(depth: np.ndarray, static: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """
    Inverse depth (1/m) at sub-pixel positions, NaN off planes, on movers or outside.

    Parameters
    ----------
    depth : np.ndarray
        (H, W) float32 depth z (m), inf on the sky.
    static : np.ndarray
        (H, W) bool, False on moving vehicles.
    pts : np.ndarray
        (N, 2) float pixel positions (x, y).

    Returns
    -------
    np.ndarray
        (N,) float64 bilinear inverse depth.

    """
    h, w = depth.shape
    x0 = np.floor(pts[:, 0]).astype(int)
    y0 = np.floor(pts[:, 1]).astype(int)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
    x0 = np.clip(x0, 0, w - 2)
    y0 = np.clip(y0, 0, h - 2)
    inv = 1.0 / depth.astype(np.float64)
    q = np.stack([inv[y0, x0], inv[y0, x0 + 1], inv[y0 + 1, x0], inv[y0 + 1, x0 + 1]], 1)
    s = np.stack([static[y0, x0], static[y0, x0 + 1], static[y0 + 1, x0],
                  static[y0 + 1, x0 + 1]], 1).all(1)
    ax = pts[:, 0] - x0
    ay = pts[:, 1] - y0
    val = ((q[:, 0] * (1 - ax) + q[:, 1] * ax) * (1 - ay)
           + (q[:, 2] * (1 - ax) + q[:, 3] * ax) * ay)
    flat = (q.max(1) - q.min(1)) <= 0.02 * q.max(1)
    return np.where(inside & s & flat & (q.min(1) > 0), val, np.nan)


def quad_errors(spec: SequenceSpec, pairs: list, i: int, corr) -> np.ndarray:
    """(M, 3) errors (px) of cur-left, cur-right and prev-right against the true geometry."""
    prev, cur = pairs[i - 1], pairs[i]
    f = spec.true_focal_px
    cx, cy = spec.principal_point_px
    b = spec.true_baseline_m
    inv = inverse_depth_at(prev.depth_left, prev.static_left, corr.prev_left)
    z = 1.0 / inv
    X = np.stack([(corr.prev_left[:, 0] - cx) * z / f, (corr.prev_left[:, 1] - cy) * z / f, z],
                 1)
    T = np.linalg.inv(cur.T_world_cam) @ prev.T_world_cam  # prev cam -> cur cam
    Xc = X @ T[:3, :3].T + T[:3, 3]
    ul = np.stack([cx + f * Xc[:, 0] / Xc[:, 2], cy + f * Xc[:, 1] / Xc[:, 2]], 1)
    ur = np.stack([cx + f * (Xc[:, 0] - b) / Xc[:, 2], ul[:, 1]], 1)
    pr = np.stack([corr.prev_left[:, 0] - f * b * inv, corr.prev_left[:, 1]], 1)
    err = np.stack([np.linalg.norm(corr.cur_left - ul, axis=1),
                    np.linalg.norm(corr.cur_right - ur, axis=1),
                    np.linalg.norm(corr.prev_right - pr, axis=1)], 1)
    return err[np.isfinite(err).all(1)]


def run(spec: SequenceSpec, cfg) -> dict:
    """Render, run the pipeline and collect the figures of one spec."""
    renderer = StereoRenderer(spec)
    pairs = [renderer.render(i, depth=True) for i in range(spec.n_frames)]
    vo = StereoOdometry(cfg)
    captured = []
    original = vo.tracker.track

    def track(*args, **kwargs):
        out = original(*args, **kwargs)
        captured.append(out)
        return out

    vo.tracker.track = track
    calib = spec.calibration()
    status, inliers, errors = [], [], []
    for i, pair in enumerate(pairs):
        res = vo.process(pair.stereo_frame(calib))
        status.append(res.status.name)
        inliers.append(res.n_inliers)
        if i and len(captured[-1].correspondences):
            errors.append(quad_errors(spec, pairs, i, captured[-1].correspondences))
    stats = [c.stats for c in captured[1:]]
    err = np.concatenate(errors) if errors else np.zeros((0, 3))
    return {'not_ok': sum(s != 'OK' for s in status[1:]),
            'tracked': float(np.mean([s.n_tracked for s in stats])),
            'inliers': float(np.mean(inliers[1:])),
            'failed': {k: float(np.mean([s.failed[k] for s in stats])) for k in CHECKS},
            'added': float(np.mean([s.n_added for s in stats])),
            'detected': float(np.mean([s.n_detected for s in stats])),
            'track_ms': float(np.median([s.timings_ms['total'] for s in stats])),
            'err_median': np.median(err, 0).tolist() if len(err) else [],
            'err_p90': np.percentile(err, 90, axis=0).tolist() if len(err) else []}


def main() -> int:
    """Run both versions of the scene and print the comparison."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', default='urban_photometric')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--frames', type=int, default=40)
    ap.add_argument('--set', nargs='*', default=[], metavar='SECTION.KEY=VALUE')
    ap.add_argument('--json', type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cfg = config_mod.load(None)
    overrides = config_mod.overrides_from_items(args.set)
    if overrides:
        cfg = cfg.replace(**overrides)
    spec = SequenceSpec.preset(args.preset, seed=args.seed, n_frames=args.frames)
    clean = spec.replace(**dict.fromkeys(PHOTOMETRIC_FIELDS, 0.0))
    out = {}
    for label, s in (('as given', spec), ('photometric off', clean)):
        r = run(s, cfg)
        out[label] = r
        print(f'{args.preset} seed {args.seed}, {args.frames} frames, {label}: not OK '
              f'{r["not_ok"]}, tracked {r["tracked"]:.0f}, inliers {r["inliers"]:.0f}, added '
              f'{r["added"]:.0f} of {r["detected"]:.0f} detected, tracker {r["track_ms"]:.1f} ms')
        print('  removed per pair: ' + ', '.join(f'{k} {v:.1f}' for k, v in r['failed'].items()))
        print('  quadruple error vs truth (px, cur-left / cur-right / prev-right): median '
              + ' / '.join(f'{v:.3f}' for v in r['err_median']) + ', p90 '
              + ' / '.join(f'{v:.3f}' for v in r['err_p90']), flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
