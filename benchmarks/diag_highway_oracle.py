"""
Where the speed goes on a rendered sequence: the pipeline with parts of its input made exact.

Renders a preset (default: the highway, seed 4) with the renderer's depth and vehicle masks and
runs the default pipeline once per mode. In every mode the tracker runs as usual; what reaches
the estimator is changed, using the exact geometry of the render:

* ``tracked``: nothing changed (the pipeline as shipped);
* ``static``: correspondences on moving vehicles (at t-1 or t) removed;
* ``static+temporal``: ... and the current left point of every verified static feature moved
  to its exact position (its tracked disparity kept);
* ``static+stereo``: ... and both stereo matches (previous and current right points) made
  exact (the tracked temporal match kept);
* ``exact``: only verified static features, all four points exact;
* ``exact+noise_prev`` / ``exact+noise_cur``: as ``exact`` with Gaussian noise of
  ``--noise`` px added to the previous / current pair only.

A feature is *verified* when the inverse depth around its previous left point is smooth (the
2x2 pixels within 5 %), its 3-D point is static, and its exact current projection is visible
(the depth there agrees within 2 %). Exact points come from the previous left point, the
renderer's depth (inverse depth interpolated bilinearly, exact on planes) and the true poses.

Printed per mode: the KITTI metric (t_rel %, r_rel deg/100 m), the median ratio of estimated
to true step length, and inliers per frame. Then, for the ``static`` run, which features pull
the forward speed: each inlier's least-squares pull on the forward speed at the true motion
(``J^T r / sum J^T J``, J the derivative of its predicted current pixels with respect to the
forward speed, r its residual), summed by image region and depth.

Usage::

    python benchmarks/diag_highway_oracle.py [--preset highway] [--seed 4] [--frames N]
        [--modes tracked static ...] [--noise 0.5] [--road]

The road alignment (``road.enabled``) is off unless ``--road``: the modes are about the
feature correspondences. ``docs/highway.md`` quotes seed 4 (300 frames, about 4 minutes).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'  # before NumPy loads its BLAS

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.config import Config  # noqa: E402
from stereo_vo_ros.estimation.motion import TransferModel, velocity_from_transform  # noqa: E402
from stereo_vo_ros.evaluation import metrics  # noqa: E402
from stereo_vo_ros.pipeline import StereoOdometry  # noqa: E402
from stereo_vo_ros.records import Correspondences  # noqa: E402
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer  # noqa: E402

MODES = ('tracked', 'static', 'static+temporal', 'static+stereo', 'exact', 'exact+noise_prev',
         'exact+noise_cur')
#: Rows this far below the principal point and lower count as road (pixels).
ROAD_ROWS_BELOW_CY = 20


class Scene:
    """The rendered frames with depth, masks and poses, and the exact geometry they give."""

    def __init__(self, spec: SequenceSpec) -> None:
        renderer = StereoRenderer(spec)
        self.calib = renderer.calibration
        P0, P1 = spec.projections()
        self.f, self.cx, self.cy = P0[0, 0], P0[0, 2], P0[1, 2]
        self.bf = -P1[0, 3]
        self.size = (spec.width, spec.height)
        self.frames = [renderer.render(i, depth=True) for i in range(spec.n_frames)]
        self.dt = 1.0 / spec.frame_rate_hz

    def inverse_depth(self, depth: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Bilinear inverse depth (1/m) at pixels p (N, 2); NaN where not smooth or outside."""
        w, h = self.size
        x0 = np.clip(np.floor(p[:, 0]).astype(int), 0, w - 2)
        y0 = np.clip(np.floor(p[:, 1]).astype(int), 0, h - 2)
        inside = np.all(np.isfinite(p), axis=1) & (p[:, 0] >= 0) & (p[:, 1] >= 0) & (
            p[:, 0] < w - 1) & (p[:, 1] < h - 1)
        ax, ay = p[:, 0] - x0, p[:, 1] - y0
        q = np.stack([1.0 / depth[y0 + dy, x0 + dx] for dy in (0, 1) for dx in (0, 1)], axis=1)
        wts = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], axis=1)
        out = (q * wts).sum(axis=1)
        smooth = (q.max(axis=1) - q.min(axis=1)) < 0.05 * q.max(axis=1)
        return np.where(inside & smooth & (out > 0), out, np.nan)

    def static(self, mask: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Whether the pixels p (N, 2) (rounded) see static scene."""
        w, h = self.size
        pix = np.clip(np.rint(np.nan_to_num(p)).astype(int), 0, [w - 1, h - 1])
        return mask[pix[:, 1], pix[:, 0]]

    def exact(self, i: int, prev_left: np.ndarray) -> dict:
        """Exact previous right and current left / right points of previous left points."""
        fp, fc = self.frames[i - 1], self.frames[i]
        T_cur_prev = np.linalg.inv(np.linalg.inv(fp.T_world_cam) @ fc.T_world_cam)
        rho = self.inverse_depth(fp.depth_left, prev_left)
        ray = np.stack([(prev_left[:, 0] - self.cx) / self.f,
                        (prev_left[:, 1] - self.cy) / self.f, np.ones(len(prev_left))], axis=1)
        X = (T_cur_prev[:3, :3] @ (ray / rho[:, None]).T).T + T_cur_prev[:3, 3]
        with np.errstate(invalid='ignore', divide='ignore'):
            cur = np.stack([self.f * X[:, 0] / X[:, 2] + self.cx,
                            self.f * X[:, 1] / X[:, 2] + self.cy], axis=1)
            seen = self.inverse_depth(fc.depth_left, np.where(np.isfinite(cur), cur, -1.0))
            visible = np.abs(seen * X[:, 2] - 1.0) < 0.02
        shift = np.zeros_like(prev_left)
        shift[:, 0] = self.bf * rho
        cur_shift = np.zeros_like(prev_left)
        cur_shift[:, 0] = self.bf / X[:, 2]
        return {'prev_right': prev_left - shift, 'cur_left': cur, 'cur_right': cur - cur_shift,
                'depth_ok': np.isfinite(rho), 'visible': np.isfinite(rho) & visible}


def oracle_correspondences(scene: Scene, i: int, corr: Correspondences, mode: str,
                           noise_px: float, rng: np.random.Generator) -> Correspondences:
    """Return the correspondences of frame i as the mode changes them (see the module)."""
    if mode == 'tracked':
        return corr
    fp, fc = scene.frames[i - 1], scene.frames[i]
    pl, pr = corr.prev_left.copy(), corr.prev_right.copy()
    cl, cr = corr.cur_left.copy(), corr.cur_right.copy()
    ex = scene.exact(i, pl)
    static = scene.static(fp.static_left, pl) & scene.static(fc.static_left, cl)
    verified = static & ex['visible']
    keep = static
    parts = mode.split('+')
    if 'temporal' in parts:
        disparity = cl[verified, 0] - cr[verified, 0]
        cl[verified] = ex['cur_left'][verified]
        cr[verified] = cl[verified]
        cr[verified, 0] -= disparity
    if 'stereo' in parts:
        ok = static & ex['depth_ok']
        pr[ok] = ex['prev_right'][ok]
        rho = scene.inverse_depth(fc.depth_left, cl)
        ok = static & np.isfinite(rho)
        cr[ok] = cl[ok]
        cr[ok, 0] -= scene.bf * rho[ok]
    if 'exact' in parts:
        keep = verified
        pr[keep] = ex['prev_right'][keep]
        cl[keep] = ex['cur_left'][keep]
        cr[keep] = ex['cur_right'][keep]
    if 'noise_prev' in parts:
        pl = pl + rng.normal(0.0, noise_px, pl.shape)
        pr = pr + rng.normal(0.0, noise_px, pr.shape)
    if 'noise_cur' in parts:
        cl = cl + rng.normal(0.0, noise_px, cl.shape)
        cr = cr + rng.normal(0.0, noise_px, cr.shape)
    return Correspondences(pl, pr, cl, cr, corr.ids.copy(), corr.ages.copy()).subset(keep)


def speed_pull(scene: Scene, i: int, corr: Correspondences) -> np.ndarray:
    """(N, 4): forward-speed pull numerator and weight, row, exact depth (m) of each feature."""
    fp, fc = scene.frames[i - 1], scene.frames[i]
    y = velocity_from_transform(np.linalg.inv(fp.T_world_cam) @ fc.T_world_cam, scene.dt)
    model = TransferModel(scene.calib, corr.prev_left, corr.prev_right, scene.dt)
    step = np.zeros(6)
    step[2] = 0.01
    J = (model.predict(y + step) - model.predict(y - step)) / 0.02  # (N, 4) px per m/s
    r = np.hstack([corr.cur_left, corr.cur_right]) - model.predict(y)
    depth = 1.0 / scene.inverse_depth(fp.depth_left, corr.prev_left)
    return np.stack([np.sum(J * r, axis=1), np.sum(J * J, axis=1), corr.prev_left[:, 1],
                     depth], axis=1)


def run(scene: Scene, mode: str, noise_px: float, road: bool) -> tuple[dict, np.ndarray]:
    """
    Run the pipeline in one mode; return its figures and the speed pulls of its inliers.

    Without ``road`` the road alignment is off: the modes replace the correspondences, and the
    road alignment (which reads the images) would otherwise overrule them.
    """
    vo = StereoOdometry(Config().replace(**{'road.enabled': road}))
    estimate = vo.estimator.estimate
    rng = np.random.default_rng(0)
    state = {'i': 0, 'pulls': [], 'inliers': []}

    def oracle_estimate(corr, calib, dt, calib_cur=None, image_size=None):
        sub = oracle_correspondences(scene, state['i'], corr, mode, noise_px, rng)
        out = estimate(sub, calib, dt, calib_cur=calib_cur, image_size=image_size)
        if out.inliers is not None and out.inliers.any():
            state['inliers'].append(int(out.inliers.sum()))
            state['pulls'].append(speed_pull(scene, state['i'], sub.subset(out.inliers)))
        return out

    vo.estimator.estimate = oracle_estimate  # this instance only
    poses = []
    for i, frame in enumerate(scene.frames):
        state['i'] = i
        poses.append(vo.process(frame.stereo_frame(scene.calib)).T_world_cam)
    est = np.array(poses)
    gt = np.array([np.linalg.inv(scene.frames[0].T_world_cam) @ f.T_world_cam
                   for f in scene.frames])
    ev = metrics.evaluate(gt, est)
    step_gt = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    step_est = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1)
    figures = {'t_rel': ev['t_rel_pct'], 'r_rel': ev['r_rel_deg_per_100m'],
               'step_ratio': float(np.median(step_est / step_gt)),
               'inliers': float(np.mean(state['inliers'])) if state['inliers'] else 0.0}
    pulls = np.vstack(state['pulls']) if state['pulls'] else np.zeros((0, 4))
    return figures, pulls


def print_pulls(pulls: np.ndarray, cy: float, speed: float) -> None:
    """Print which inliers pull the forward speed, by region and depth."""
    num, weight, row, depth = pulls.T
    total = weight.sum()
    print(f'\nforward-speed pull of the inliers at the true motion (static run; true speed '
          f'{speed:.1f} m/s): all {num.sum() / total:+.3f} m/s')
    print(f'{"features":>22s} {"count":>6s} {"share of information":>20s} {"pull m/s":>9s} '
          f'{"own bias m/s":>12s}')
    road = row > cy + ROAD_ROWS_BELOW_CY
    groups = [('road (below horizon)', road), ('above the road', ~road)]
    for lo, hi in ((0, 20), (20, 40), (40, 80), (80, np.inf)):
        groups.append((f'depth {lo}-{hi} m', (depth >= lo) & (depth < hi)))
    for name, m in groups:
        if not m.any():
            continue
        print(f'{name:>22s} {int(m.sum()):6d} {100 * weight[m].sum() / total:19.1f}% '
              f'{num[m].sum() / total:+9.3f} {num[m].sum() / weight[m].sum():+12.3f}')


def main() -> int:
    """Run the modes and print their figures."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', default='highway')
    ap.add_argument('--seed', type=int, default=4)
    ap.add_argument('--frames', type=int, default=None, help="default: the preset's")
    ap.add_argument('--modes', nargs='+', default=list(MODES), choices=MODES)
    ap.add_argument('--noise', type=float, default=0.5, help='noise of the noise modes (px)')
    ap.add_argument('--road', action='store_true',
                    help='keep the road alignment on (default: off, the features alone)')
    args = ap.parse_args()
    extra = {} if args.frames is None else {'n_frames': args.frames}
    spec = SequenceSpec.preset(args.preset, seed=args.seed, **extra)
    scene = Scene(spec)
    print(f'{args.preset} seed {args.seed}, {spec.n_frames} frames, {spec.width}x{spec.height}, '
          f'default config, road alignment {"on" if args.road else "off"}; noise modes '
          f'{args.noise} px')
    print(f'{"mode":>18s} {"t_rel %":>8s} {"r_rel":>7s} {"step ratio":>10s} '
          f'{"inliers":>8s}')
    static_pulls = None
    for mode in args.modes:
        fig, pulls = run(scene, mode, args.noise, args.road)
        print(f'{mode:>18s} {fig["t_rel"]:8.3f} {fig["r_rel"]:7.3f} {fig["step_ratio"]:10.4f} '
              f'{fig["inliers"]:8.1f}', flush=True)
        if mode == 'static':
            static_pulls = pulls
    if static_pulls is not None and len(static_pulls):
        print_pulls(static_pulls, scene.cy, spec.speed_mps)
    return 0


if __name__ == '__main__':
    sys.exit(main())
