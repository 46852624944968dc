"""
The stereo renderer: ray casting a Scene into rectified stereo pairs.

``StereoRenderer`` renders pair ``i`` of a ``SequenceSpec`` (deterministic, random access),
with the sensor effects; ``SyntheticSequence`` serves the pairs as a dataset.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
import math
from typing import Iterator

import cv2
import numpy as np

from .scene import _scene_for
from .spec import _MIN_T_M, _WALL_H_M, _WALL_W_M, RenderedFrame, SequenceSpec
from ..estimation.camera import StereoCalibration
from ..records import StereoFrame


def _cubic_weights(frac: np.ndarray) -> list[np.ndarray]:
    """Keys cubic convolution weights (a = -0.5) of the taps -1, 0, 1, 2 at ``frac``."""
    t = frac
    return [((-0.5 * t + 1.0) * t - 0.5) * t, (1.5 * t - 2.5) * t * t + 1.0,
            ((-1.5 * t + 2.0) * t + 0.5) * t, (0.5 * t - 0.5) * t * t]


# ---------------------------------------------------------------------------------------------
# Renderer
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Camera:
    """A level pinhole view: image size (pixels), focal length and principal point (pixels)."""

    width: int
    height: int
    f: float
    cx: float
    cy: float

    @functools.cached_property
    def xn(self) -> np.ndarray:
        """(W,) float64 normalised x of the column centres."""
        return (np.arange(self.width) - self.cx) / self.f


@dataclass
class _Layers:
    """Per-column visible wall layers (nearest first) of one view; arrays are (K, W)."""

    face: np.ndarray
    t: np.ndarray
    sigma: np.ndarray
    vtop: np.ndarray
    ok: np.ndarray


class StereoRenderer:
    """
    Render the stereo pairs of a SequenceSpec (deterministic, random access by index).

    Attributes
    ----------
    spec : SequenceSpec
        What is rendered.
    scene : Scene
        Boxes, vehicles, ground tile and camera path.
    calibration : StereoCalibration
        Rectified calibration of the pairs.
    stamps : np.ndarray
        (N,) float64 stamps (s).
    poses : np.ndarray
        (N, 4, 4) float64 ``T_world_cam`` of the left camera (metres).

    """

    MAX_LAYERS = 8
    MAX_RANGE_M = 5000.0

    def __init__(self, spec: SequenceSpec) -> None:
        self.spec = spec
        self.scene = _scene_for(spec)
        self.calibration = spec.calibration()
        self.stamps = spec.stamps
        self._times = np.arange(spec.n_frames) / spec.frame_rate_hz
        self.poses = self.scene.trajectory.poses(self._times)
        ss = spec.supersample
        cx, cy = spec.principal_point_px
        f = spec.true_focal_px
        self._cam = _Camera(spec.width, spec.height, f, cx, cy)
        self._cam_ss = _Camera(spec.width * ss, spec.height * ss, f * ss,
                               (cx + 0.5) * ss - 0.5, (cy + 0.5) * ss - 0.5)
        self._H_right = None if spec.exact_rig else spec.right_homography()
        self._vignette = [self._vignetting(cam) for cam in range(2)]
        faces = self.scene.boxes.faces()
        faces['moving'] = np.zeros(len(faces['q0']), bool)
        self._static_faces = faces
        self._gains = self._exposure_gains()

    def __len__(self) -> int:
        return self.spec.n_frames

    def __iter__(self) -> Iterator[RenderedFrame]:
        for i in range(len(self)):
            yield self.render(i)

    def _exposure_gains(self) -> np.ndarray:
        """(N, 2) gains of the left and right camera per frame."""
        spec = self.spec
        rng = np.random.default_rng([spec.seed, 11])
        t = self._times
        ph = rng.uniform(0, 2 * np.pi, 3)
        log_g = np.zeros_like(t)
        if spec.exposure_change > 0:
            amp = spec.exposure_change
            log_g += amp * (0.6 * np.sin(2 * np.pi * t / 9.0 + ph[0])
                            + 0.4 * np.sin(2 * np.pi * t / 3.7 + ph[1]))
            n_jumps = rng.poisson(max(t[-1], 1.0) / 4.0)
            for t_jump, size in zip(rng.uniform(0, t[-1] + 1e-9, n_jumps),
                                    rng.choice([-1, 1], n_jumps) * rng.uniform(0.5, 1.0, n_jumps)):
                late = t >= t_jump
                log_g[late] += amp * size * np.exp(-(t[late] - t_jump) / 0.8)
        left = np.exp(log_g)
        right = left * (1.0 + spec.stereo_gain_mismatch * np.sin(2 * np.pi * t / 5.0 + ph[2]))
        return np.stack([left, right], 1)

    def _vignetting(self, cam: int) -> np.ndarray | None:
        """(H, W) float32 vignetting gain of one camera (1 at its centre), None if none."""
        spec = self.spec
        if spec.vignetting <= 0:
            return None
        m = spec.vignetting_mismatch * cam
        strength = spec.vignetting * (1.0 + m)
        k = (1.0 - strength) ** -0.5 - 1.0
        H, W = spec.height, spec.width
        u0 = (W - 1) / 2.0 + m * 0.1 * W
        v0 = (H - 1) / 2.0 + m * 0.05 * H
        r2 = (((np.arange(W) - u0) ** 2)[None, :] + ((np.arange(H) - v0) ** 2)[:, None]) / (
            ((W - 1) / 2.0) ** 2 + ((H - 1) / 2.0) ** 2)
        return ((1.0 + k * r2) ** -2).astype(np.float32)

    def _warp_right(self, img: np.ndarray, nearest: bool = False) -> np.ndarray:
        """
        Apply the rig error homography to an exact right image (same size, border replicate).

        Bilinear interpolation in float32 with exact weights: OpenCV's ``warpPerspective`` and
        ``remap`` round the source coordinates to 1/32 pixel, too coarse for errors of a few
        hundredths of a pixel. ``nearest`` picks the nearest pixel (depth, masks).
        """
        H, W = img.shape
        Hinv = np.linalg.inv(self._H_right)
        u = np.arange(W, dtype=np.float64)[None, :]
        v = np.arange(H, dtype=np.float64)[:, None]
        w = Hinv[2, 0] * u + Hinv[2, 1] * v + Hinv[2, 2]
        x = np.clip((Hinv[0, 0] * u + Hinv[0, 1] * v + Hinv[0, 2]) / w, 0, W - 1)
        y = np.clip((Hinv[1, 0] * u + Hinv[1, 1] * v + Hinv[1, 2]) / w, 0, H - 1)
        if nearest:
            return img[np.rint(y).astype(np.intp), np.rint(x).astype(np.intp)]
        x0 = np.floor(x).astype(np.intp)
        y0 = np.floor(y).astype(np.intp)
        wx = _cubic_weights((x - x0).astype(np.float32))
        wy = _cubic_weights((y - y0).astype(np.float32))
        out = np.zeros((H, W), np.float32)
        for j in range(4):
            rows = np.clip(y0 + (j - 1), 0, H - 1)
            acc = np.zeros((H, W), np.float32)
            for i in range(4):
                acc += img[rows, np.clip(x0 + (i - 1), 0, W - 1)] * wx[i]
            out += acc * wy[j]
        return out

    # -- public ---------------------------------------------------------------------------
    def render(self, index: int, depth: bool = False) -> RenderedFrame:
        """Render stereo pair ``index`` (0-based); with ``depth`` also depth maps and masks."""
        if not 0 <= index < len(self):
            raise IndexError(f'frame index {index} outside [0, {len(self)})')
        spec = self.spec
        T = self.poses[index]
        t = float(self._times[index])
        hc = float(self.scene.trajectory.height(np.array([t]))[0])
        yaw = math.atan2(T[0, 2], T[2, 2])
        faces = self._faces_at(t)
        images, depths, statics = [], [], []
        for cam in range(2):
            cxz = np.array([T[0, 3], T[2, 3]]) + cam * spec.true_baseline_m * np.array(
                [math.cos(yaw), -math.sin(yaw)])
            img, dep, stat = self._view(self._cam_ss, cxz, yaw, hc, faces, shade=True,
                                        geometry=depth and spec.supersample == 1)
            if spec.supersample > 1:
                img = cv2.resize(img, (spec.width, spec.height), interpolation=cv2.INTER_AREA)
                if depth:
                    _, dep, stat = self._view(self._cam, cxz, yaw, hc, faces, shade=False,
                                              geometry=True)
            if cam == 1 and self._H_right is not None:
                img = self._warp_right(img)
                if dep is not None:
                    dep = self._warp_right(dep, nearest=True)
                    stat = self._warp_right(stat, nearest=True)
            images.append(self._sensor(img, index, cam))
            depths.append(dep)
            statics.append(stat)
        return RenderedFrame(index, float(self.stamps[index]), images[0], images[1], T.copy(),
                             depths[0], depths[1], statics[0], statics[1])

    def frames(self) -> Iterator[StereoFrame]:
        """Yield every pair as a StereoFrame."""
        for frame in self:
            yield frame.stereo_frame(self.calibration)

    # -- internals ------------------------------------------------------------------------
    def _faces_at(self, t: float) -> dict[str, np.ndarray]:
        moving = self.scene.movers.boxes(t).faces()
        moving['moving'] = np.ones(len(moving['q0']), bool)
        faces = {k: np.concatenate([v, moving[k]]) for k, v in self._static_faces.items()}
        faces['length'] = np.hypot(faces['e'][:, 0], faces['e'][:, 1])
        return faces

    def _sensor(self, img: np.ndarray, index: int, cam: int) -> np.ndarray:
        """
        Optical blur, vignetting, exposure gain and offset, sensor noise, 8-bit quantisation.

        The per-frame gain and offset jitter of each camera come from their own random stream
        (seed, index, camera), so a frame's images do not depend on the number of frames.
        """
        spec = self.spec
        if spec.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), spec.blur_sigma_px)
        gain = float(self._gains[index, cam])
        offset = 0.0
        if spec.gain_jitter > 0 or spec.gain_offset_jitter > 0:
            jitter = np.random.default_rng([spec.seed, index, cam, 17]).uniform(-1.0, 1.0, 2)
            gain *= 1.0 + spec.gain_jitter * jitter[0]
            offset = spec.gain_offset_jitter * jitter[1]
        if self._vignette[cam] is not None:
            img = img * self._vignette[cam]
        img = img * np.float32(gain)
        if offset:
            img += np.float32(offset)
        if spec.noise_std > 0:
            rng = np.random.default_rng([spec.seed, index, cam, 5])
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(spec.noise_std)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def _cull(self, faces: dict[str, np.ndarray], cxz: np.ndarray, fwd: np.ndarray,
              right: np.ndarray, cam: _Camera) -> np.ndarray:
        """Select the faces a camera at cxz can see (front-facing, in view); return indices."""
        q0 = faces['q0'] - cxz
        q1 = q0 + faces['e']
        facing = np.einsum('ij,ij->i', faces['n'], -q0) > 0
        xn_lo, xn_hi = cam.xn[0] - 1.0 / cam.f, cam.xn[-1] + 1.0 / cam.f
        x0, z0, x1, z1 = q0 @ right, q0 @ fwd, q1 @ right, q1 @ fwd
        out_r = (x0 - xn_hi * z0 > 0) & (x1 - xn_hi * z1 > 0)
        out_l = (x0 - xn_lo * z0 < 0) & (x1 - xn_lo * z1 < 0)
        behind = np.maximum(z0, z1) < _MIN_T_M
        # distance from the camera to the segment
        length2 = np.maximum(np.einsum('ij,ij->i', faces['e'], faces['e']), 1e-12)
        lam = np.clip(np.einsum('ij,ij->i', -q0, faces['e']) / length2, 0, 1)
        near = np.hypot(*(q0 + lam[:, None] * faces['e']).T) < self.MAX_RANGE_M
        return np.flatnonzero(facing & ~out_r & ~out_l & ~behind & near)

    def _layers(self, faces: dict[str, np.ndarray], sel: np.ndarray, cxz: np.ndarray,
                fwd: np.ndarray, right: np.ndarray, d: np.ndarray, hc: float,
                cam: _Camera) -> _Layers:
        """
        Visible wall layers per column, nearest first.

        Every face is intersected with the rays of the columns it projects to; per column the
        hits sorted by depth form a staircase: a farther wall is seen only if its top looks
        higher than the tops of all nearer walls (every wall stands on the road and is taller
        than the camera, so each layer covers the rows between its top and the next nearer
        layer's top).
        """
        W = cam.width
        q0 = faces['q0'][sel] - cxz
        e = faces['e'][sel]
        q1 = q0 + e
        x0, z0, x1, z1 = q0 @ right, q0 @ fwd, q1 @ right, q1 @ fwd
        with np.errstate(divide='ignore', invalid='ignore'):
            lam = (_MIN_T_M - z0) / (z1 - z0)  # clip the segment to the near plane
            x0c = np.where(z0 < _MIN_T_M, x0 + lam * (x1 - x0), x0)
            x1c = np.where(z1 < _MIN_T_M, x0 + lam * (x1 - x0), x1)
            u0 = cam.cx + cam.f * x0c / np.maximum(z0, _MIN_T_M)
            u1 = cam.cx + cam.f * x1c / np.maximum(z1, _MIN_T_M)
        lo = np.clip(np.floor(np.minimum(u0, u1)) - 1, 0, W).astype(np.int64)
        hi = np.clip(np.ceil(np.maximum(u0, u1)) + 1, -1, W - 1).astype(np.int64)
        count = np.maximum(hi - lo + 1, 0)
        total = int(count.sum())
        if total == 0:
            empty = np.zeros((0, W))
            return _Layers(empty.astype(np.int64), empty, empty, empty, empty.astype(bool))
        idx = np.repeat(np.arange(len(sel)), count)
        col = lo[idx] + np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        dc = d[col]
        ei, wi = e[idx], q0[idx]
        denom = dc[:, 0] * ei[:, 1] - dc[:, 1] * ei[:, 0]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (wi[:, 0] * ei[:, 1] - wi[:, 1] * ei[:, 0]) / denom
            sig = (wi[:, 0] * dc[:, 1] - wi[:, 1] * dc[:, 0]) / denom
        ok = (t > _MIN_T_M) & (sig >= 0.0) & (sig <= 1.0)
        idx, col, t, sig = idx[ok], col[ok], t[ok], sig[ok]
        vt = cam.cy - cam.f * (faces['height'][sel][idx] - hc) / t
        order = np.lexsort((t, col))
        idx, col, t, sig, vt = idx[order], col[order], t[order], sig[order], vt[order]
        # segmented running minimum of the tops along each column (columns in order)
        n = len(col)
        start = np.ones(n, bool)
        start[1:] = col[1:] != col[:-1]
        big = 4.0 * (1e6 + abs(cam.cy) + cam.height)
        key = np.maximum(vt, -1e6) - col * big
        prev = np.empty(n)
        prev[0] = np.inf
        prev[1:] = np.minimum.accumulate(key)[:-1]
        prev[start] = np.inf
        vis = key < prev
        first = np.maximum.accumulate(np.where(start, np.arange(n), 0))
        cs = np.cumsum(vis)
        rank = cs - 1 - (cs[first] - vis[first])
        keep = vis & (rank < self.MAX_LAYERS)
        K = int(rank[keep].max()) + 1 if keep.any() else 0
        lay = _Layers(np.zeros((K, W), np.int64), np.zeros((K, W)), np.zeros((K, W)),
                      np.full((K, W), -np.inf), np.zeros((K, W), bool))
        r, c = rank[keep], col[keep]
        lay.face[r, c] = sel[idx[keep]]
        lay.t[r, c] = t[keep]
        lay.sigma[r, c] = sig[keep]
        lay.vtop[r, c] = vt[keep]
        lay.ok[r, c] = True
        for k in range(1, K):  # nothing behind a wall whose top is above the image
            lay.ok[k] &= lay.ok[k - 1] & (lay.vtop[k - 1] > 0.0)
            lay.vtop[k][~lay.ok[k]] = -np.inf
        return lay

    def _view(self, cam: _Camera, cxz: np.ndarray, yaw: float, hc: float,
              faces: dict[str, np.ndarray], shade: bool, geometry: bool
              ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Render one level view: grey image (float32), depth (m) and static mask if asked."""
        H, W = cam.height, cam.width
        fwd = np.array([math.sin(yaw), math.cos(yaw)])
        right = np.array([math.cos(yaw), -math.sin(yaw)])
        d = fwd[None, :] + cam.xn[:, None] * right[None, :]  # (W, 2) rays with z_cam = 1
        sel = self._cull(faces, cxz, fwd, right, cam)
        lay = self._layers(faces, sel, cxz, fwd, right, d, hc, cam)
        v_h = min(H, max(0, int(math.floor(cam.cy)) + 1))  # first row below the horizon
        img = np.empty((H, W), np.float32) if shade else None
        if shade:
            self._sky(img[:v_h], cam, yaw)
            self._ground(img[v_h:], cam, v_h, cxz, d, yaw, hc)
        rows = np.arange(v_h, H)
        z_ground = (cam.f * hc / (rows - cam.cy)).astype(np.float32)
        depth = static = None
        if geometry:
            depth = np.full((H, W), np.inf, np.float32)
            depth[v_h:] = z_ground[:, None]
            static = np.ones((H, W), bool)
        n_lay = len(lay.t)
        if n_lay == 0:
            return img, depth, static
        vbot0 = np.where(lay.ok[0], cam.cy + cam.f * hc / np.where(lay.ok[0], lay.t[0], 1.0),
                         cam.cy)
        top = lay.vtop[lay.ok]
        r0 = max(0, int(math.floor(top.min())) if top.size else H)
        r1 = min(H, int(math.ceil(vbot0.max())) + 1)
        if r0 >= r1:
            return img, depth, static
        v = np.arange(r0, r1, dtype=np.float32)[:, None]
        level = np.zeros((r1 - r0, W), np.int8)
        for k in range(n_lay):
            level += v < lay.vtop[k][None, :].astype(np.float32)
        n_ok = lay.ok.sum(0).astype(np.int8)
        wall = (level < n_ok[None, :]) & ~(v > vbot0[None, :].astype(np.float32))
        flat = level.astype(np.int32) * W + np.arange(W, dtype=np.int32)[None, :]
        tabs = self._tables(lay, faces, cam, hc, d, shade)
        if shade:
            map_x = np.take(tabs['ax'], flat)
            map_y = np.take(tabs['ay0'], flat) + np.take(tabs['ay1'], flat) * v
            walls = cv2.remap(self.scene.atlas.atlas, map_x, map_y, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT).astype(np.float32)
            walls *= np.take(tabs['gain'], flat)
            np.copyto(img[r0:r1], walls, where=wall)
        if geometry:
            np.copyto(depth[r0:r1], np.take(tabs['t'], flat), where=wall)
            static[r0:r1] = ~(wall & np.take(tabs['moving'], flat))
        return img, depth, static

    def _tables(self, lay: _Layers, faces: dict[str, np.ndarray], cam: _Camera, hc: float,
                d: np.ndarray, shade: bool) -> dict[str, np.ndarray]:
        """Per-layer, per-column lookup tables (K + 1, W) flattened; the last row is unused."""
        K, W = lay.t.shape
        pad = np.zeros((1, W))
        tabs = {'t': np.concatenate([lay.t, pad]).astype(np.float32).ravel(),
                'moving': np.concatenate([faces['moving'][lay.face] & lay.ok,
                                          pad.astype(bool)]).ravel()}
        if not shade:
            return tabs
        atlas = self.scene.atlas
        face = lay.face
        t = np.where(lay.ok, lay.t, 1.0)
        n = faces['n'][face]  # (K, W, 2)
        cos_inc = np.abs(n[..., 0] * d[None, :, 0] + n[..., 1] * d[None, :, 1])
        foot_h = t / (cam.f * np.maximum(cos_inc, 1e-3))
        foot_v = t / cam.f
        tau = atlas.texel
        lx = np.clip(np.rint(np.log2(np.maximum(foot_h / tau, 1e-9))), 0, atlas.max_x).astype(int)
        ly = np.clip(np.rint(np.log2(np.maximum(foot_v / tau, 1e-9))), 0, atlas.max_y).astype(int)
        tex = faces['tex'][face]
        s_m = np.mod(faces['s_off'][face] + lay.sigma * faces['length'][face], _WALL_W_M)
        sx, sy = 0.5 ** lx, 0.5 ** ly
        ax = atlas.x0[tex, lx] + s_m / tau * sx - 0.5
        ay1 = t / (cam.f * tau) * sy
        ay0 = atlas.y0[ly] - 0.5 + (_WALL_H_M - hc) / tau * sy - ay1 * cam.cy
        gain = faces['gain'][face]
        for name, val in (('ax', ax), ('ay0', ay0), ('ay1', ay1), ('gain', gain)):
            tabs[name] = np.concatenate([np.where(lay.ok, val, 0.0), pad]).astype(
                np.float32).ravel()
        return tabs

    def _ground(self, out: np.ndarray, cam: _Camera, v_h: int, cxz: np.ndarray, d: np.ndarray,
                yaw: float, hc: float) -> None:
        """Fill rows v_h.. (below the horizon) with the rip-mapped road texture."""
        if out.shape[0] == 0:
            return
        scene = self.scene
        rip = scene.ground
        rows = np.arange(v_h, cam.height)
        z = cam.f * hc / (rows - cam.cy)
        lateral = z / cam.f
        along = z * z / (cam.f * hc)
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        foot_x = np.hypot(lateral * c, along * s)
        foot_z = np.hypot(lateral * s, along * c)
        lx = np.clip(np.rint(np.log2(foot_x / rip.texel_x)), 0, rip.max_x).astype(int)
        lz = np.clip(np.rint(np.log2(foot_z / rip.texel_y)), 0, rip.max_y).astype(int)
        key = lx * 64 + lz
        cuts = np.flatnonzero(np.diff(key)) + 1
        starts = np.concatenate([[0], cuts])
        ends = np.concatenate([cuts, [len(rows)]])
        px, pz = scene.ground_period
        ox = (cxz[0] - scene.ground_origin[0]) % px
        oz = (cxz[1] - scene.ground_origin[1]) % pz
        zf = z.astype(np.float32)[:, None]
        for a, b in zip(starts, ends):
            tex = rip.level(int(lx[a]), int(lz[a]))
            sx = rip.texel_x * 2 ** int(lx[a])
            sz = rip.texel_y * 2 ** int(lz[a])
            zz = zf[a:b]
            mx = np.mod(np.float32(ox / sx) + zz * (d[:, 0] / sx).astype(np.float32),
                        np.float32(tex.shape[1])) - np.float32(0.5)
            my = np.mod(np.float32(oz / sz) + zz * (d[:, 1] / sz).astype(np.float32),
                        np.float32(tex.shape[0])) - np.float32(0.5)
            out[a:b] = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _sky(self, out: np.ndarray, cam: _Camera, yaw: float) -> None:
        """Fill rows 0..horizon with a bright gradient and faint clouds at infinity."""
        if out.shape[0] == 0:
            return
        rows = np.arange(out.shape[0], dtype=np.float64)
        norm = np.sqrt(1.0 + cam.xn ** 2)
        tan_el = ((cam.cy - rows) / cam.f)[:, None] / norm[None, :]
        tan_el = np.clip(tan_el, 0.0, 2.0).astype(np.float32)
        sky = self.scene.sky
        az = (yaw + np.arctan(cam.xn)) / (2 * np.pi) * sky.shape[1]
        map_x = np.broadcast_to(az.astype(np.float32)[None, :], out.shape)
        map_y = tan_el * np.float32(sky.shape[0] / 1.2)
        clouds = cv2.remap(sky, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        ramp = np.minimum(tan_el * 8.0, 1.0)
        np.copyto(out, 228.0 - 55.0 * np.minimum(tan_el / 0.8, 1.0) ** 0.8 + clouds * ramp)


def render_sequence(spec: SequenceSpec) -> Iterator[RenderedFrame]:
    """Yield the rendered pairs of a spec in order."""
    yield from StereoRenderer(spec)


class SyntheticSequence:
    """
    A rendered sequence seen as a dataset: StereoFrames, calibration and ground truth.

    Attributes
    ----------
    renderer : StereoRenderer
        The renderer behind it.

    """

    def __init__(self, spec: SequenceSpec) -> None:
        self.renderer = StereoRenderer(spec)

    @property
    def calibration(self) -> StereoCalibration:
        """Rectified calibration of every pair."""
        return self.renderer.calibration

    @property
    def stamps(self) -> np.ndarray:
        """Frame stamps: (N,) float64, seconds."""
        return self.renderer.stamps.copy()

    @property
    def ground_truth(self) -> np.ndarray:
        """(N, 4, 4) float64 ``T_world_cam`` of the left camera (metres)."""
        return self.renderer.poses.copy()

    def __len__(self) -> int:
        return len(self.renderer)

    def __iter__(self) -> Iterator[StereoFrame]:
        return self.renderer.frames()
