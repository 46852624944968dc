"""
How close the online rig refinement gets to the rendered rig error.

The renderer's rig presets render the right image with a known error of the right camera
(``SequenceSpec.rig_*``: roll, pitch, yaw, focal ratio, disparity offset), which the pipeline
does not know. This runs the pipeline over a rendered scene and compares its estimate
(``StereoOdometry.rig.theta``) with that error: the row and disparity offsets at the right
principal point (``offsets_at_centre``, pixels) and the largest difference between the estimated
error homography and the one the renderer applied (``SequenceSpec.right_homography``) over the
image corners and edge middles (x and y, pixels). An exact rig (presets
without ``_rig``) should stay at zero.

Usage::

    python benchmarks/diag_rig_convergence.py [--presets urban_rig highway_rig urban]
        [--seed 0] [--frames 300] [--cache DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_seeds import scene  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from stereo_vo_ros.config import Config  # noqa: E402
from stereo_vo_ros.estimation.rig_calibration import (  # noqa: E402
    apply_homography, offsets_at_centre, right_homography)
from stereo_vo_ros.pipeline import StereoOdometry  # noqa: E402
from stereo_vo_ros.records import StereoFrame  # noqa: E402


def true_theta(spec) -> np.ndarray:
    """Return the rendered rig error as the refinement's state (rad, rad, rad, 1, px)."""
    return np.array([np.radians(spec.rig_roll_deg), np.radians(spec.rig_pitch_deg),
                     np.radians(spec.rig_yaw_deg), spec.rig_focal_ratio,
                     spec.rig_disparity_offset_px])


def main() -> int:
    """Run each preset and print the estimate against the rendered error."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--presets', nargs='+', default=['urban_rig', 'highway_rig', 'urban'])
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--frames', type=int, default=300)
    ap.add_argument('--cache', type=Path, default=None, help='keep renders here (npz)')
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f'seed {args.seed}, {args.frames} pairs; offsets at the principal point (px): row '
          'v_R - v_L and disparity; max |difference| of the error homographies over corners '
          'and edge middles (px)')
    print(f'{"preset":14s} {"true row":>9s} {"est row":>8s} {"true disp":>9s} '
          f'{"est disp":>8s} {"max dx":>7s} {"max dy":>7s} {"updates":>7s}')
    for preset in args.presets:
        data = scene(preset, args.seed, args.frames, args.cache)
        spec = data['spec']
        calib = spec.calibration()
        vo = StereoOdometry(Config())
        for left, right, stamp in zip(data['left'], data['right'], data['stamps']):
            vo.process(StereoFrame(left, right, float(stamp), calib))
        vo.close()  # also runs the last pair's rig update
        est, true = vo.rig.theta, true_theta(spec)
        c = offsets_at_centre(calib.K_right)
        w, h = calib.size
        pts = np.array([[x, y] for x in (0, w / 2, w - 1) for y in (0, h / 2, h - 1)], float)
        diff = np.abs(apply_homography(right_homography(calib.K_right, est), pts)
                      - apply_homography(spec.right_homography(), pts)).max(axis=0)
        (tr, td), (er, ed) = c @ true, c @ est
        print(f'{preset:14s} {tr:9.3f} {er:8.3f} {td:9.3f} {ed:8.3f} {diff[0]:7.3f} '
              f'{diff[1]:7.3f} {vo.rig.updates:7d}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
