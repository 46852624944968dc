"""
The rendered world: boxes on the ground, moving vehicles and the route through them.

``Scene`` builds a city grid or a highway from a seed (blocks, parked vans, noise walls,
vehicles driving along the lanes) and ray-casts depths against its boxes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import functools
import logging
import math
import time

import numpy as np

from .camera_path import _TURN_C, Trajectory
from .spec import (_FLOOR_M, _GROUND_FLOOR_M, _HW_LANE_M, _HW_LANES, _HW_MEDIAN_M, _LANE_OFFSET_M,
                   _ROAD_HALF_M, _SIDEWALK_M, _VEHICLES, _WALL_W_M, KITTI_FOCAL_PX, SequenceSpec)
from .textures import (_facade, _ground_city, _ground_highway, _plain_wall, _RipMaps, _sky,
                       _vehicle, _WallAtlas)
from ..errors import ConfigError

logger = logging.getLogger(__name__)


@dataclass
class _Boxes:
    """Axis-aligned boxes standing on the ground: x/z extents (m), height (m), looks."""

    xmin: np.ndarray
    xmax: np.ndarray
    zmin: np.ndarray
    zmax: np.ndarray
    height: np.ndarray
    tex: np.ndarray  # (N,) int atlas texture
    gain: np.ndarray  # (N,) brightness factor
    s_off: np.ndarray  # (N, 4) texture offset (m) of faces +x, -x, +z, -z

    @staticmethod
    def concat(items: list['_Boxes']) -> '_Boxes':
        return _Boxes(*[np.concatenate([getattr(b, f.name) for b in items])
                        for f in dataclasses.fields(_Boxes)])

    def __len__(self) -> int:
        return len(self.xmin)

    def faces(self) -> dict[str, np.ndarray]:
        """
        Return the four vertical faces of every box (4N entries, outward normals).

        ``q0`` (F, 2) start and ``e`` (F, 2) edge vector in world (x, z), oriented so that the
        texture runs left to right for a viewer outside; ``n`` outward unit normal.
        """
        n = len(self)
        q0 = np.empty((n, 4, 2))
        e = np.empty((n, 4, 2))
        nrm = np.zeros((n, 4, 2))
        q0[:, 0] = np.stack([self.xmax, self.zmin], 1)  # +x face, runs +z
        e[:, 0] = np.stack([np.zeros(n), self.zmax - self.zmin], 1)
        q0[:, 1] = np.stack([self.xmin, self.zmax], 1)  # -x face, runs -z
        e[:, 1] = np.stack([np.zeros(n), self.zmin - self.zmax], 1)
        q0[:, 2] = np.stack([self.xmax, self.zmax], 1)  # +z face, runs -x
        e[:, 2] = np.stack([self.xmin - self.xmax, np.zeros(n)], 1)
        q0[:, 3] = np.stack([self.xmin, self.zmin], 1)  # -z face, runs +x
        e[:, 3] = np.stack([self.xmax - self.xmin, np.zeros(n)], 1)
        nrm[:, 0, 0], nrm[:, 1, 0], nrm[:, 2, 1], nrm[:, 3, 1] = 1, -1, 1, -1
        rep = np.repeat
        return {'q0': q0.reshape(-1, 2), 'e': e.reshape(-1, 2), 'n': nrm.reshape(-1, 2),
                'height': rep(self.height, 4), 'tex': rep(self.tex, 4),
                'gain': rep(self.gain, 4) * np.tile([1.0, 0.82, 0.92, 0.72], n),
                's_off': self.s_off.reshape(-1)}

    def distance(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Return the horizontal distances (P, N), metres, of P points to the boxes; 0 inside."""
        dx = np.maximum(np.maximum(self.xmin[None] - x[:, None], x[:, None] - self.xmax[None]), 0)
        dz = np.maximum(np.maximum(self.zmin[None] - z[:, None], z[:, None] - self.zmax[None]), 0)
        return np.hypot(dx, dz)


@dataclass
class _Movers:
    """Vehicles moving at constant velocity along a lane (axis-aligned)."""

    x0: np.ndarray  # (M,) centre at t = 0 (m)
    z0: np.ndarray
    vx: np.ndarray  # (M,) velocity (m/s), along x or z
    vz: np.ndarray
    kind: np.ndarray  # (M,) index into _VEHICLES
    tex: np.ndarray
    gain: np.ndarray

    def boxes(self, t: float, wall_w_m: float = _WALL_W_M) -> _Boxes:
        """Boxes of the vehicles at time t (s) after the first frame."""
        dims = np.array(_VEHICLES)[self.kind] if len(self.kind) else np.zeros((0, 3))
        along_x = np.abs(self.vx) > np.abs(self.vz)
        half_x = np.where(along_x, dims[:, 0], dims[:, 1]) / 2
        half_z = np.where(along_x, dims[:, 1], dims[:, 0]) / 2
        cx, cz = self.x0 + self.vx * t, self.z0 + self.vz * t
        rear = wall_w_m - 3.0
        # faces +x, -x, +z, -z: side design (offset 0) on faces parallel to the motion
        s_off = np.where(along_x[:, None], [[rear, rear, 0.0, 0.0]], [[0.0, 0.0, rear, rear]])
        return _Boxes(cx - half_x, cx + half_x, cz - half_z, cz + half_z, dims[:, 2],
                      self.tex.copy(), self.gain.copy(), s_off)


class Scene:
    """
    The static boxes, the moving vehicles, the ground tile and the camera path of a spec.

    The geometry and the path depend on ``spec.seed`` and the motion fields only, not on the
    image size; textures are generated at a texel size matched to the focal length.

    Attributes
    ----------
    trajectory : Trajectory
        Path of the left camera.
    boxes : _Boxes
        Static axis-aligned boxes in ``world`` (x, z extents and height, metres).
    movers : _Movers
        Vehicles at constant velocity; ``movers.boxes(t)`` gives their boxes at time t (s).
    ground_y : float
        World y of the road plane (m); the camera height at the first frame.
    route_nodes : np.ndarray
        (K, 2) world (x, z) of the crossings the city route meets (m); empty on the highway.

    """

    def __init__(self, spec: SequenceSpec) -> None:
        t0 = time.perf_counter()
        self.spec = spec
        rng = np.random.default_rng([spec.seed, 7])  # geometry: independent of resolution
        self._tex_rng = np.random.default_rng([spec.seed, 8])  # textures
        f = spec.focal_px  # textures follow the output resolution, not the supersampling
        scale = KITTI_FOCAL_PX / f  # texel sizes grow when the images shrink
        wall_w = int(2 ** np.clip(round(math.log2(_WALL_W_M / (0.025 * scale))), 5, 10))
        self._wall_px = (2 * wall_w, wall_w)
        self.ground_y = spec.camera_height_m  # world y of the road; refined below
        self.duration_s = (spec.n_frames - 1) / spec.frame_rate_hz
        if spec.scene == 'city':
            self._build_city(rng, scale)
        else:
            self._build_highway(rng, scale)
        self.ground_y = float(self.trajectory.height(np.zeros(1))[0])
        self._check_clearance()
        logger.debug('scene %s built in %.2f s (%d boxes, %d movers)', spec.name,
                     time.perf_counter() - t0, len(self.boxes), len(self.movers.x0))

    # -- textures -------------------------------------------------------------------------
    def _wall_textures(self, rng: np.random.Generator, facades: int) -> None:
        h, w = self._wall_px
        tex = [_facade(rng, h, w, i) for i in range(facades)]
        self.tex_pole = len(tex)
        tex.append(_plain_wall(rng, h, w, 'pole'))
        self.tex_concrete = len(tex)
        tex.append(_plain_wall(rng, h, w, 'concrete'))
        self.tex_warehouse = len(tex)
        tex.append(_plain_wall(rng, h, w, 'warehouse'))
        self.tex_vehicle = len(tex)
        tex.extend(_vehicle(rng, h, w, k) for k in range(len(_VEHICLES)))
        self.n_facades = facades
        self.atlas = _WallAtlas(tex)
        self.sky = _sky(rng, 64, 1024)

    # -- city -----------------------------------------------------------------------------
    def _build_city(self, rng: np.random.Generator, scale: float) -> None:
        spec = self.spec
        P, a = spec.block_m, _LANE_OFFSET_M
        n = int(2 ** round(math.log2(P / (0.02 * scale))))
        n = int(np.clip(n, 256, 8192))
        self.ground = _RipMaps(_ground_city(self._tex_rng, n, P), P / n, P / n)
        # tile coordinate = world - origin; streets at tile P/2 -> world x = -a, z = P/2
        self.ground_origin = (-a - P / 2, 0.0)
        self.ground_period = (P, P)
        self._wall_textures(self._tex_rng, 6)
        self._plan_city_route(rng)
        self._city_blocks(rng)
        self._city_movers(rng)

    def _plan_city_route(self, rng: np.random.Generator) -> None:
        spec = self.spec
        P, a = spec.block_m, _LANE_OFFSET_M
        turn_len = 22.0
        e = _TURN_C * turn_len
        need = spec.speed_mps * 1.12 * self.duration_s + 60.0
        pos = np.array([0.0, 0.0])
        heading = 0  # multiples of 90 degrees
        node = np.array([-a, P / 2])
        s, turns, nodes = 0.0, [], []
        while True:
            f = np.array([math.sin(heading * np.pi / 2), math.cos(heading * np.pi / 2)])
            r = np.array([f[1], -f[0]])
            nodes.append(node.copy())
            turn = spec.turns and rng.random() < spec.turn_probability
            side = 1 if rng.random() < 0.5 else -1
            corner = node - a * f + a * r if side > 0 else node + a * f + a * r
            start = corner - e * f
            dist = float((start - pos) @ f)
            if turn and dist > 2.0 and s + dist < need:
                turns.append((s + dist, turn_len, side * np.pi / 2))
                s += dist + turn_len
                pos = corner + side * e * r
                heading = (heading + side) % 4
                f = np.array([math.sin(heading * np.pi / 2), math.cos(heading * np.pi / 2)])
            elif s + float((node - pos) @ f) > need:
                s += float((node - pos) @ f) + P / 2
                break
            node = node + P * f
        self.route_nodes = np.array(nodes)
        self.trajectory = Trajectory(s, np.array(turns), np.zeros((0, 3)), spec.speed_mps,
                                     7.5, rng, spec.camera_height_m, spec.bounce_m)

    def _path_samples(self, step_s: float | None = None) -> tuple[np.ndarray, ...]:
        """Sample the left camera path densely: times (s), x, z (m), yaw (rad)."""
        step = step_s or 0.25 / self.spec.frame_rate_hz
        t = np.arange(0.0, self.duration_s + step, step)
        x, z, yaw = self.trajectory.planar(t)
        return t, x, z, yaw

    def _city_blocks(self, rng: np.random.Generator) -> None:
        spec = self.spec
        P, a = spec.block_m, _LANE_OFFSET_M
        _, px, pz, _ = self._path_samples(0.5)
        reach = 170.0
        ix = np.floor((px + a) / P).astype(int)
        iz = np.floor((pz - P / 2) / P).astype(int)
        cells = set()
        k = int(math.ceil(reach / P))
        for i, j in set(zip(ix.tolist(), iz.tolist())):
            for di in range(-k, k + 1):
                for dj in range(-k, k + 1):
                    cells.add((i + di, j + dj))
        setback0 = _ROAD_HALF_M + _SIDEWALK_M
        boxes: list[tuple] = []
        for i, j in sorted(cells):
            x0, z0 = -a + i * P, P / 2 + j * P  # street centre lines bounding the block
            if np.min(np.hypot(px - (x0 + P / 2), pz - (z0 + P / 2))) > reach + P:
                continue
            lo, hi = setback0, P - setback0
            for side in range(4):
                u = lo
                while u < hi - 3.0:
                    width = min(float(rng.uniform(8.0, 22.0)), hi - u)
                    if hi - (u + width) < 6.0:
                        width = hi - u
                    depth = float(rng.uniform(10.0, 16.0))
                    back = setback0 + float(rng.choice([0.0, 0.0, rng.uniform(0.5, 4.0)]))
                    storeys = int(rng.integers(2, 7))
                    height = _GROUND_FLOOR_M + storeys * _FLOOR_M - 0.5
                    along = (u, u + width)
                    across = (back, back + depth)
                    if side == 0:  # facing -z street
                        bx, bz = along, across
                    elif side == 1:  # facing +z street
                        bx, bz = along, (P - across[1], P - across[0])
                    elif side == 2:  # facing -x street
                        bx, bz = across, along
                    else:
                        bx, bz = (P - across[1], P - across[0]), along
                    boxes.append((x0 + bx[0], x0 + bx[1], z0 + bz[0], z0 + bz[1], height,
                                  int(rng.integers(0, self.n_facades)),
                                  float(rng.uniform(0.8, 1.15))))
                    u += width + float(rng.choice([0.0, 0.0, 0.0, rng.uniform(1.5, 5.0)]))
            # lamp posts along the four kerbs, away from the crossings
            for side in range(4):
                for u in np.arange(setback0 + 8.0, P - setback0 - 8.0, 24.0):
                    off = _ROAD_HALF_M + 0.6
                    cx, cz = [(u, off), (u, P - off), (off, u), (P - off, u)][side]
                    boxes.append((x0 + cx - 0.1, x0 + cx + 0.1, z0 + cz - 0.1, z0 + cz + 0.1,
                                  7.2, self.tex_pole, 1.0))
        if spec.parked_vehicles:
            boxes.extend(self._parked(rng))
        arr = np.array(boxes, np.float64).reshape(-1, 7)
        keep = self._clear_of_path(arr, 1.0)
        if not np.all(keep[arr[:, 5] < self.n_facades]):
            raise ConfigError(f'synthetic city (seed {spec.seed}) puts a building on the path')
        arr = arr[keep]
        s_off = rng.uniform(0, _WALL_W_M, (len(arr), 4))
        vehicle = arr[:, 5] >= self.tex_vehicle
        along_x = (arr[:, 1] - arr[:, 0]) > (arr[:, 3] - arr[:, 2])
        rear = _WALL_W_M - 3.0
        s_off[vehicle] = np.where(along_x[vehicle, None], [[rear, rear, 0.0, 0.0]],
                                  [[0.0, 0.0, rear, rear]])
        self.boxes = _Boxes(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4],
                            arr[:, 5].astype(np.int64), arr[:, 6], s_off)

    def _clear_of_path(self, arr: np.ndarray, margin: float) -> np.ndarray:
        """
        Mask the boxes (rows xmin, xmax, zmin, zmax, ...) away from both cameras' paths.

        Path samples are processed in short stretches against the boxes near each stretch.
        """
        keep = np.ones(len(arr), bool)
        if len(arr) == 0:
            return keep
        _, x, z, yaw = self._path_samples()
        b = self.spec.baseline_m
        xmin, xmax, zmin, zmax = arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3]
        for px, pz in ((x, z), (x + b * np.cos(yaw), z - b * np.sin(yaw))):
            for i in range(0, len(px), 256):
                sx, sz = px[i:i + 256], pz[i:i + 256]
                near = np.flatnonzero((xmin < sx.max() + margin) & (xmax > sx.min() - margin)
                                      & (zmin < sz.max() + margin) & (zmax > sz.min() - margin))
                if near.size:
                    dx = np.maximum(np.maximum(xmin[near] - sx[:, None], sx[:, None] - xmax[near]),
                                    0)
                    dz = np.maximum(np.maximum(zmin[near] - sz[:, None], sz[:, None] - zmax[near]),
                                    0)
                    keep[near[np.hypot(dx, dz).min(0) <= margin]] = False
        return keep

    def _parked(self, rng: np.random.Generator) -> list[tuple]:
        """Vans parked on the kerb-side strips of the streets around the route's crossings."""
        P = self.spec.block_m
        length, width, height = _VEHICLES[0]
        out = []
        nodes = {tuple(np.round(n, 3)) for n in self.route_nodes.tolist()}
        for node in sorted(nodes):
            for axis in range(2):  # street along world x (0) or z (1)
                for arm in (-1.0, 1.0):
                    for kerb in (-1.0, 1.0):
                        for u in np.arange(_ROAD_HALF_M + _SIDEWALK_M + 6.0, P / 2 - 3.0, 7.0):
                            if rng.random() > 0.3:
                                continue
                            c = np.array(node, np.float64)
                            c[axis] += arm * (u + length / 2)
                            c[1 - axis] += kerb * 4.75
                            half = np.array([length, width])[[axis, 1 - axis]] / 2
                            out.append((c[0] - half[0], c[0] + half[0], c[1] - half[1],
                                        c[1] + half[1], height, self.tex_vehicle, 0.9))
        return out

    def _city_movers(self, rng: np.random.Generator) -> None:
        spec = self.spec
        a = _LANE_OFFSET_M
        t, x, z, yaw = self._path_samples()
        cands = []
        for _ in range(40 * max(spec.moving_objects, 1)):
            if len(cands) >= spec.moving_objects:
                break
            kind = int(rng.integers(0, len(_VEHICLES)))
            speed = float(rng.uniform(6.0, 12.0))
            if rng.random() < 0.6:  # oncoming, in view at time tm
                k = int(rng.integers(0, len(t)))
                h = yaw[k] / (np.pi / 2)
                if abs(h - round(h)) > 1e-6:
                    continue
                f = np.array([math.sin(yaw[k]), math.cos(yaw[k])])
                r = np.array([f[1], -f[0]])
                p = np.array([x[k], z[k]]) - 2 * a * r + f * rng.uniform(15.0, 70.0)
                v = -speed * f
                p0 = p - v * t[k]
            else:  # crossing the route at an intersection, before or after the camera
                node = self.route_nodes[int(rng.integers(0, len(self.route_nodes)))]
                k = int(np.argmin(np.hypot(x - node[0], z - node[1])))
                f = np.array([math.sin(yaw[k]), math.cos(yaw[k])])
                r = np.array([f[1], -f[0]])
                d = r * rng.choice([-1.0, 1.0])
                lane = node + a * np.array([d[1], -d[0]])
                v = speed * d
                tc = t[k] + rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 8.0)
                p0 = lane - v * tc
            cand = (p0[0], p0[1], v[0], v[1], kind, self.tex_vehicle + kind,
                    float(rng.uniform(0.85, 1.1)))
            if self._mover_ok(cand, cands, t, x, z, yaw):
                cands.append(cand)
        self.movers = self._movers(cands)

    @staticmethod
    def _movers(cands: list[tuple]) -> _Movers:
        arr = np.array(cands, np.float64).reshape(-1, 7)
        return _Movers(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4].astype(np.int64),
                       arr[:, 5].astype(np.int64), arr[:, 6])

    def _mover_ok(self, cand: tuple, others: list[tuple], t: np.ndarray, x: np.ndarray,
                  z: np.ndarray, yaw: np.ndarray) -> bool:
        """Reject a vehicle that comes near a camera, a static box or another vehicle."""
        def track(c: tuple) -> tuple[np.ndarray, ...]:
            length, width, _ = _VEHICLES[int(c[4])]
            along_x = abs(c[2]) > abs(c[3])
            hx, hz = (length / 2, width / 2) if along_x else (width / 2, length / 2)
            return c[0] + c[2] * t, c[1] + c[3] * t, hx, hz

        cx, cz, hx, hz = track(cand)
        b = self.spec.baseline_m
        for px, pz in ((x, z), (x + b * np.cos(yaw), z - b * np.sin(yaw))):
            d = np.hypot(np.maximum(np.abs(px - cx) - hx, 0), np.maximum(np.abs(pz - cz) - hz, 0))
            if d.min() < 2.0:
                return False
        for other in others:
            ox, oz, ohx, ohz = track(other)
            gap = np.maximum(np.abs(cx - ox) - hx - ohx, np.abs(cz - oz) - hz - ohz)
            if gap.min() < 0.5:
                return False
        bx = self.boxes
        near = np.flatnonzero((bx.xmin < cx.max() + hx + 1) & (bx.xmax > cx.min() - hx - 1)
                              & (bx.zmin < cz.max() + hz + 1) & (bx.zmax > cz.min() - hz - 1))
        step = max(1, int(0.5 / (max(abs(cand[2]), abs(cand[3])) * (t[1] - t[0]) + 1e-9)))
        for i in range(0, len(near), 64):  # boxes along the lane (a straight line) only
            n = near[i:i + 64]
            sx, sz = cx[::step, None], cz[::step, None]
            gap = np.maximum(np.maximum(bx.xmin[n] - sx - hx, sx - hx - bx.xmax[n]),
                             np.maximum(bx.zmin[n] - sz - hz, sz - hz - bx.zmax[n]))
            if gap.min() < 0.3:
                return False
        return True

    # -- highway --------------------------------------------------------------------------
    def _build_highway(self, rng: np.random.Generator, scale: float) -> None:
        spec = self.spec
        lx_m, lz_m = 96.0, 48.0
        nx = int(np.clip(2 ** round(math.log2(lx_m / (0.02 * scale))), 256, 8192))
        self.ground = _RipMaps(_ground_highway(self._tex_rng, nx, nx // 2, lx_m, lz_m), lx_m / nx,
                               lz_m / (nx // 2))
        ego_x = _HW_MEDIAN_M + 1.5 * _HW_LANE_M  # middle lane centre right of the median
        self.highway_centre_x = -ego_x
        self.ground_origin = (-ego_x - lx_m / 2, 0.0)
        self.ground_period = (lx_m, lz_m)
        self._wall_textures(self._tex_rng, 2)
        need = spec.speed_mps * 1.12 * self.duration_s + 60.0
        lane_changes, lane, s = [], 1, float(rng.uniform(40.0, 120.0))
        while spec.turns and s < need:
            length = 4.0 * spec.speed_mps
            step = int(rng.choice([-1, 1])) if lane == 1 else (1 - lane)
            lane_changes.append((s, length, step * _HW_LANE_M))
            lane += step
            s += length + float(rng.uniform(6.0, 14.0)) * spec.speed_mps
        self.route_nodes = np.zeros((0, 2))
        self.trajectory = Trajectory(need, np.zeros((0, 3)), np.array(lane_changes),
                                     spec.speed_mps, spec.speed_mps, rng, spec.camera_height_m,
                                     spec.bounce_m)
        boxes = []
        edge = _HW_MEDIAN_M + _HW_LANES * _HW_LANE_M + 4.0
        z = -60.0
        while z < need + 250.0:  # sign posts, noise walls and warehouses on both sides
            for sign in (-1.0, 1.0):
                xc = self.highway_centre_x + sign * (edge + 1.0)
                boxes.append((xc - 0.15, xc + 0.15, z - 0.15, z + 0.15, 6.5, self.tex_pole, 1.0))
                if rng.random() < 0.35:
                    wall_len = float(rng.uniform(40.0, 140.0))
                    xw = self.highway_centre_x + sign * (edge + 5.0)
                    boxes.append((xw - 0.2, xw + 0.2, z, z + wall_len,
                                  float(rng.uniform(3.0, 4.5)), self.tex_concrete, 1.0))
                if rng.random() < 0.4:
                    dist = float(rng.uniform(25.0, 90.0))
                    size_x, size_z = rng.uniform(15.0, 40.0, 2)
                    x_in = self.highway_centre_x + sign * (edge + dist)
                    x_out = x_in + sign * size_x
                    tex = int(rng.choice([self.tex_warehouse, 0, 1]))
                    boxes.append((min(x_in, x_out), max(x_in, x_out), z, z + size_z,
                                  float(rng.uniform(6.0, 16.0)), tex, float(rng.uniform(0.8,
                                                                                        1.1))))
            z += float(rng.uniform(40.0, 70.0))
        arr = np.array(boxes, np.float64).reshape(-1, 7)
        s_off = rng.uniform(0, _WALL_W_M, (len(arr), 4))
        self.boxes = _Boxes(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4],
                            arr[:, 5].astype(np.int64), arr[:, 6], s_off)
        t, x, zz, yaw = self._path_samples()
        cands: list[tuple] = []
        lanes_same = [-_HW_LANE_M, 0.0, _HW_LANE_M]
        c = self.highway_centre_x
        lanes_opp = [c - (_HW_MEDIAN_M + (k + 0.5) * _HW_LANE_M) for k in range(_HW_LANES)]
        for _ in range(40 * max(spec.moving_objects, 1)):
            if len(cands) >= spec.moving_objects:
                break
            kind = int(rng.integers(0, len(_VEHICLES)))
            tm = float(rng.uniform(0.0, max(self.duration_s, 1.0)))
            ego_z = float(np.interp(tm, t, zz))
            if rng.random() < 0.6:
                vz = spec.speed_mps + float(rng.uniform(-7.0, 5.0))
                lane_x = float(rng.choice(lanes_same))
                zm = ego_z + float(rng.choice([-1.0, 1.0])) * rng.uniform(15.0, 60.0)
            else:
                vz = -spec.speed_mps * float(rng.uniform(0.8, 1.2))
                lane_x = float(rng.choice(lanes_opp))
                zm = ego_z + float(rng.uniform(40.0, 150.0))
            cand = (lane_x, zm - vz * tm, 0.0, vz, kind, self.tex_vehicle + kind,
                    float(rng.uniform(0.85, 1.1)))
            if self._mover_ok(cand, cands, t, x, zz, yaw):
                cands.append(cand)
        self.movers = self._movers(cands)

    # -- checks and queries ---------------------------------------------------------------
    def _check_clearance(self) -> None:
        arr = np.stack([self.boxes.xmin, self.boxes.xmax, self.boxes.zmin, self.boxes.zmax,
                        self.boxes.height, self.boxes.gain, self.boxes.gain], 1)
        if not np.all(self._clear_of_path(arr, 1.0)):
            raise ConfigError(f'synthetic scene {self.spec.name!r} (seed {self.spec.seed}) puts '
                              'a box on the camera path')

    def boxes_at(self, t: float) -> _Boxes:
        """All boxes (static and moving) at time t (s after the first frame)."""
        return _Boxes.concat([self.boxes, self.movers.boxes(t)])

    def ray_depth(self, origin: np.ndarray, directions: np.ndarray, t: float) -> np.ndarray:
        """
        Distance parameter of the first hit of rays ``origin + lam * direction`` (brute force).

        Parameters
        ----------
        origin : np.ndarray
            (3,) ray origin in ``world`` (m).
        directions : np.ndarray
            (N, 3) ray directions in ``world`` (any length).
        t : float
            Time after the first frame (s), for the moving vehicles.

        Returns
        -------
        np.ndarray
            (N,) float64 ``lam`` of the nearest hit (ground or a box face), inf for the sky.

        """
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        o = np.asarray(origin, np.float64).reshape(3)
        lam = np.full(len(d), np.inf)
        down = d[:, 1] > 1e-12
        lam[down] = (self.ground_y - o[1]) / d[down, 1]
        faces = self.boxes_at(t).faces()
        q0, e = faces['q0'], faces['e']
        denom = d[:, 0, None] * e[None, :, 1] - d[:, 2, None] * e[None, :, 0]
        w = q0 - o[[0, 2]][None]
        with np.errstate(divide='ignore', invalid='ignore'):
            lf = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0])[None] / denom
            sf = (w[None, :, 0] * d[:, 2, None] - w[None, :, 1] * d[:, 0, None]) / denom
        y = o[1] + lf * d[:, 1, None]
        ok = (lf > 1e-9) & (sf >= 0) & (sf <= 1) & (y <= self.ground_y) & (
            y >= self.ground_y - faces['height'][None])
        lf = np.where(ok, lf, np.inf)
        return np.minimum(lam, lf.min(1) if lf.shape[1] else lam)


@functools.lru_cache(maxsize=2)
def _scene_for(spec: SequenceSpec) -> Scene:
    return Scene(spec)
