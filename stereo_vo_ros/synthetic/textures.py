"""
Procedural textures of the rendered street: road tiles, facades, vehicles, sky.

Value noise and fBm, the city and highway ground tiles with markings, facades and plain walls,
vehicle sides, the sky, and the rip-maps and wall atlas that prefilter them.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .spec import (_FLOOR_M, _GROUND_FLOOR_M, _HW_LANE_M, _HW_LANES, _HW_MEDIAN_M, _ROAD_HALF_M,
                   _SIDEWALK_M, _VEHICLES, _WALL_H_M, _WALL_W_M)
from ..errors import ConfigError


def _pow2_divisor(n: int, target: float) -> int:
    """Largest power of two that divides ``n`` and is at most ``max(target, 1)``."""
    g = 1
    while n % (g * 2) == 0 and g * 2 <= max(target, 1.0):
        g *= 2
    return g


def _noise(rng: np.random.Generator, h: int, w: int, cell_y: float,
           cell_x: float | None = None) -> np.ndarray:
    """
    Return periodic smooth noise (h, w) float32 of unit standard deviation.

    Cubic interpolation of a random grid with about ``cell`` pixels per grid cell; the result
    tiles seamlessly (period h rows, w columns).
    """
    cell_x = cell_y if cell_x is None else cell_x
    gh, gw = _pow2_divisor(h, h / cell_y), _pow2_divisor(w, w / cell_x)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    if gh == h and gw == w:
        return grid
    sy, sx = h // gh, w // gw
    pad = 2
    padded = np.pad(grid, pad, mode='wrap')
    big = cv2.resize(padded, ((gw + 2 * pad) * sx, (gh + 2 * pad) * sy),
                     interpolation=cv2.INTER_CUBIC)
    out = big[pad * sy:pad * sy + h, pad * sx:pad * sx + w]
    return out / max(float(out[::4, ::4].std()), 1e-6)


def _fbm(rng: np.random.Generator, h: int, w: int, cells: tuple[float, ...],
         amps: tuple[float, ...]) -> np.ndarray:
    """Sum of periodic noise octaves (h, w) float32 with the given cell sizes and amplitudes."""
    out = np.zeros((h, w), np.float32)
    for cell, amp in zip(cells, amps):
        if cell >= 0.5:
            out += amp * _noise(rng, h, w, cell)
    return out


def _cover(signed_dist: np.ndarray, texel: float) -> np.ndarray:
    """Approximate area coverage (0..1) of a region with the given signed distance (m)."""
    return np.clip(signed_dist / texel + 0.5, 0.0, 1.0).astype(np.float32)


def _ground_city(rng: np.random.Generator, n: int, period_m: float) -> np.ndarray:
    """Texture (n, n) of one city grid cell: streets cross at the tile centre (rows: z)."""
    tex = period_m / n
    c = ((np.arange(n) + 0.5) * tex - period_m / 2).astype(np.float32)  # centred coordinate
    x, z = c[None, :], c[:, None]
    ax, az = np.abs(x), np.abs(z)
    px = 1.0 / tex  # pixels per metre
    cells = (1, 0.04 * px, 0.15 * px, 0.6 * px, 3.0 * px, 12.0 * px)
    octaves = [_noise(rng, n, n, cell) for cell in cells]

    def mix(weights: tuple[float, ...]) -> np.ndarray:
        out = np.zeros((n, n), np.float32)
        for w, octave in zip(weights, octaves):
            out += np.float32(w) * octave
        return out

    grain = mix((5.0, 5.0, 4.0, 5.0, 6.0, 6.0))
    half, walk = _ROAD_HALF_M, _ROAD_HALF_M + _SIDEWALK_M
    road_cov = np.maximum(_cover(half - ax, tex), _cover(half - az, tex))
    walk_cov = np.maximum(_cover(walk - ax, tex), _cover(walk - az, tex))
    out = 75.0 + mix((13.0, 11.0, -9.0, 11.0, -9.0, 8.0))  # grass
    # sidewalk: 0.5 m slabs with joints and a per-slab tone
    slab = 0.5
    slabs = rng.normal(0.0, 7.0, (int(round(period_m / slab)),) * 2).astype(np.float32)
    idx = (np.floor((c + period_m / 2) / slab).astype(np.int64) % slabs.shape[0])
    jx = _cover(np.abs(np.mod(x, slab) - slab / 2) - (slab / 2 - 0.012), tex)
    jz = _cover(np.abs(np.mod(z, slab) - slab / 2) - (slab / 2 - 0.012), tex)
    joints = np.maximum(jx, jz)
    sidewalk = 150.0 + slabs[idx[:, None], idx[None, :]] + 0.8 * grain - 45.0 * joints
    out += walk_cov * (sidewalk - out)
    del sidewalk
    kerb = np.maximum(_cover(half + 0.25 - ax, tex) * _cover(ax - half, tex),
                      _cover(half + 0.25 - az, tex) * _cover(az - half, tex)) * walk_cov
    stone_joint = np.maximum(_cover(0.015 - np.abs(np.mod(z, 1.0) - 0.5), tex),
                             _cover(0.015 - np.abs(np.mod(x, 1.0) - 0.5), tex))
    out += kerb * (175.0 + 0.5 * grain - 60.0 * stone_joint - out)
    out += road_cov * (92.0 + grain - out)

    def markings(a: np.ndarray, b: np.ndarray, hand: float) -> np.ndarray:
        """Return the marking coverage of a street with centre line a = 0 along b."""
        outside = _cover(np.abs(b) - (walk + 0.3), tex)
        dashes = _cover(1.5 - np.abs(np.mod(b, 6.0) - 3.0), tex)  # 3 m dash, 3 m gap
        centre = _cover(0.06 - np.abs(a), tex) * dashes * outside
        edge = _cover(0.06 - np.abs(np.abs(a) - 3.5), tex) * outside
        zebra_band = _cover(1.5 - np.abs(np.abs(b) - (half + 2.5)), tex)
        zebra = zebra_band * _cover(0.25 - np.abs(np.mod(a, 1.0) - 0.5), tex) * \
            _cover(half - 0.3 - np.abs(a), tex)
        stop = _cover(0.2 - np.abs(np.abs(b) - (half + 4.6)), tex) * \
            _cover(np.sign(-b) * a * hand, tex) * _cover(3.3 - np.abs(a), tex)
        return np.maximum.reduce([centre, edge, zebra, stop]) * _cover(half - np.abs(a), tex)

    strip = np.flatnonzero(np.abs(c) < half + tex)  # the street along z (columns) ...
    # worn paint: patches where the paint is gone or thin, ragged edges
    wear = np.clip(1.6 + 0.5 * octaves[1] + 0.9 * octaves[2] + 0.5 * octaves[3], 0.0, 1.0)
    white = 92.0 + grain + wear * (113.0 - 0.5 * grain)
    cols = (slice(None), strip)
    mark = markings(x[:, strip], z, 1.0)
    out[cols] += mark * (white[cols] - out[cols])
    rows = (strip, slice(None))  # ... and the street along x (rows)
    mark = markings(z[strip], x, -1.0)
    out[rows] += mark * (white[rows] - out[rows])
    _draw_blemishes(rng, out, tex, period_m, road_cov)
    return np.clip(out, 0, 255).astype(np.uint8)


def _draw_blemishes(rng: np.random.Generator, img: np.ndarray, tex: float, period_m: float,
                    road: np.ndarray) -> None:
    """Draw cracks, patches and manhole covers on the road part of a ground tile (in place)."""
    n_rows, n_cols = img.shape
    layer = np.zeros_like(img)
    area = period_m * period_m * float(road.mean())
    for _ in range(int(area / 60.0)):
        pts = [np.array([rng.uniform(0, n_cols), rng.uniform(0, n_rows)])]
        heading = rng.uniform(0, 2 * np.pi)
        for _ in range(rng.integers(3, 9)):
            heading += rng.normal(0, 0.6)
            pts.append(pts[-1] + rng.uniform(0.2, 0.8) / tex *
                       np.array([np.cos(heading), np.sin(heading)]))
        cv2.polylines(layer, [np.round(np.array(pts) * 16).astype(np.int32)], False,
                      -35.0, max(1, int(round(0.012 / tex))), cv2.LINE_AA, 4)
    for _ in range(int(area / 150.0)):
        centre = (int(rng.uniform(0, n_cols) * 16), int(rng.uniform(0, n_rows) * 16))
        if rng.random() < 0.3:
            radius = int(0.32 / tex * 16)
            cv2.circle(layer, centre, radius, -40.0, -1, cv2.LINE_AA, 4)
            cv2.circle(layer, centre, int(radius * 0.8), 10.0, max(1, int(0.03 / tex)),
                       cv2.LINE_AA, 4)
        else:
            size = (int(rng.uniform(0.5, 2.5) / tex * 16), int(rng.uniform(0.4, 1.5) / tex * 16))
            box = ((centre[0] / 16, centre[1] / 16), (size[0] / 16, size[1] / 16),
                   float(rng.uniform(0, 180)))
            cv2.fillPoly(layer, [np.round(cv2.boxPoints(box) * 16).astype(np.int32)],
                         float(rng.choice([-18.0, 12.0])), cv2.LINE_AA, 4)
    img += layer * road


def _ground_highway(rng: np.random.Generator, nx: int, nz: int, lx_m: float,
                    lz_m: float) -> np.ndarray:
    """Texture (nz, nx) of a highway section: median at the tile centre, along z (rows)."""
    tex = lx_m / nx
    x = ((np.arange(nx) + 0.5) * tex - lx_m / 2).astype(np.float32)[None, :]
    z = ((np.arange(nz) + 0.5) * tex).astype(np.float32)[:, None]
    ax = np.abs(x)
    px = 1.0 / tex
    grain = _fbm(rng, nz, nx, (1, 0.15 * px, 0.6 * px, 3 * px, 12 * px),
                 (5.0, 5.0, 5.0, 6.0, 6.0))
    asphalt = 88.0 + grain
    grass = 80.0 + 2.4 * _fbm(rng, nz, nx, (1, 0.05 * px, 0.3 * px, 2 * px, 8 * px, 24 * px),
                              (6.0, 5.0, 4.0, 5.0, 5.0, 5.0))
    inner, outer = _HW_MEDIAN_M, _HW_MEDIAN_M + _HW_LANES * _HW_LANE_M
    road = _cover(ax - inner, tex) * _cover(outer + 2.5 - ax, tex)
    gravel = _cover(outer + 4.0 - ax, tex) * _cover(ax - inner + 0.8, tex)
    out = grass + gravel * (125.0 + 1.5 * grain - grass)
    out += road * (asphalt - out)
    white = 210.0 + 0.5 * grain
    dash = _cover(1.5 - np.abs(np.mod(z, 12.0) - 1.5), tex)  # 3 m dash every 12 m
    lines = np.maximum(_cover(0.08 - np.abs(ax - inner - 0.3), tex),
                       _cover(0.12 - np.abs(ax - outer), tex))
    for k in range(1, _HW_LANES):
        lines = np.maximum(lines, dash * _cover(0.08 - np.abs(ax - inner - k * _HW_LANE_M), tex))
    out += lines * (white - out)
    _draw_blemishes(rng, out, tex, lz_m, road)
    return np.clip(out, 0, 255).astype(np.uint8)


def _wall_canvas(h: int, w: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Coordinates of a wall texture: along (1, w) and height (h, 1) in metres, texel (m)."""
    tex = _WALL_W_M / w
    along = ((np.arange(w) + 0.5) * tex).astype(np.float32)[None, :]
    height = (_WALL_H_M - (np.arange(h) + 0.5) * tex).astype(np.float32)[:, None]
    return along, height, tex


def _finish(img: np.ndarray) -> np.ndarray:
    """Clip to grey levels and store as uint8."""
    return np.clip(img, 0, 255).astype(np.uint8)


def _facade(rng: np.random.Generator, h: int, w: int, style: int) -> np.ndarray:
    """Draw a facade texture (h, w): storeys of windows, shop front, plaster or bricks."""
    x, y, tex = _wall_canvas(h, w)
    H, W = h, w
    px = 1.0 / tex
    base = float(rng.uniform(115, 195))
    img = base + _fbm(rng, H, W, (1, 0.04 * px, 0.2 * px, 1.0 * px, 4 * px),
                      (3.0, 3.0, 3.0, 5.0, 6.0))
    img *= 1.0 + 0.06 * _noise(rng, H, W, 3.0 * px, 0.15 * px)  # vertical grime streaks
    if style % 3 == 1:  # bricks
        course, brick = 0.075, 0.25
        row = np.floor(y / course)
        shift = np.mod(row, 2) * brick / 2
        col = np.floor((x + shift) / brick)
        tones = rng.normal(0, 9.0, 4096).astype(np.float32)
        bid = (row.astype(np.int64) * 97 + col.astype(np.int64) * 13) % 4096
        mortar = np.maximum(_cover(0.006 - np.mod(y, course), tex),
                            _cover(0.006 - np.mod(x + shift, brick), tex))
        img += tones[bid] - 0.25 * (base - 90.0)
        img += mortar * (base + 25.0 - img)
    n_cols = int(rng.choice([3, 4, 5]))
    pitch = _WALL_W_M / n_cols
    win_w = float(rng.uniform(0.9, min(1.7, 0.6 * pitch)))
    win_h = float(rng.uniform(1.3, 1.9))
    sill = float(rng.uniform(0.7, 1.0))
    frame_t = 0.07
    storey = np.floor((y - _GROUND_FLOOR_M) / _FLOOR_M)
    yin = y - _GROUND_FLOOR_M - storey * _FLOOR_M - sill
    colx = np.floor(x / pitch)
    xin = x - colx * pitch - (pitch - win_w) / 2
    inside = _cover(np.minimum(xin, win_w - xin), tex) * _cover(np.minimum(yin, win_h - yin),
                                                                tex)
    inside *= (storey >= 0)
    glass_tab = rng.uniform(25, 95, 4096).astype(np.float32)
    lit = rng.random(4096) < 0.2
    glass_tab[lit] = rng.uniform(110, 175, int(lit.sum()))
    wid = ((storey.astype(np.int64) + 8) * 31 + colx.astype(np.int64) * 7) % 4096
    glass = glass_tab[wid] + 25.0 * np.clip(yin / win_h, 0, 1)
    glass -= 10.0 * np.clip(xin / win_w, 0, 1)
    glass += 2.0 * _noise(rng, H, W, 0.05 * px)
    frame = 1.0 - _cover(np.minimum(np.minimum(xin, win_w - xin),
                                    np.minimum(yin, win_h - yin)) - frame_t, tex)
    mullion = _cover(0.03 - np.abs(xin - win_w / 2), tex) + _cover(
        0.03 - np.abs(yin - 0.62 * win_h), tex)
    frame = np.clip(frame + (style % 2) * mullion, 0, 1)
    frame_tone = 215.0 if base < 160 else 60.0
    pane = glass + frame * (frame_tone - glass)
    img += inside * (pane - img)
    sill_band = _cover(0.06 - np.abs(yin + 0.05), tex) * _cover(
        np.minimum(xin, win_w - xin) + 0.12, tex) * (storey >= 0)
    img += sill_band * (225.0 - img)
    if style % 2 == 0:  # cornice between storeys, with brackets every 0.4 m
        brackets = _cover(0.05 - np.abs(np.mod(x, 0.4) - 0.2), tex) * _cover(
            0.12 - np.abs(y - _GROUND_FLOOR_M - storey * _FLOOR_M + 0.1), tex)
        img += brackets * (base - 45.0 - img) * (storey >= 0)
        cornice = _cover(0.08 - np.abs(y - _GROUND_FLOOR_M - storey * _FLOOR_M), tex) * (
            storey >= 0)
        img += cornice * (base + 40.0 - img)
    # ground floor: shop windows and doors, with a sign band
    shop_w = pitch * float(rng.uniform(0.55, 0.8))
    sx = x - colx * pitch - (pitch - shop_w) / 2
    shop = _cover(np.minimum(sx, shop_w - sx), tex) * _cover(np.minimum(y - 0.3, 2.9 - y), tex)
    door = (np.mod(colx, 3) == 1)
    shop_glass = 45.0 + 30.0 * _noise(rng, H, W, 0.4 * px) * 0.5 + 35.0 * (y / 3.0)
    shop_glass = np.where(door & (y < 2.4), 70.0 + 10.0 * np.mod(np.floor(sx / 0.3), 2),
                          shop_glass)
    img += shop * (shop_glass - img)
    sign = _cover(np.minimum(y - 3.1, 3.6 - y), tex) * _cover(np.minimum(sx, shop_w - sx), tex)
    letters = 40.0 * (np.mod(np.floor(sx / 0.18) * 7 + np.floor(y / 0.13) * 3, 5) < 2)
    img += sign * (200.0 - letters * (np.mod(colx, 2) == 0) - img)
    pipe = _cover(0.05 - np.abs(x - 0.25), tex)
    img += pipe * (base - 50.0 - img)
    return _finish(img)


def _vehicle(rng: np.random.Generator, h: int, w: int, kind: int) -> np.ndarray:
    """
    Vehicle texture (h, w): side design on [0, L] and rear design on [W_tex - 3, W_tex - 0.5].

    ``kind`` indexes ``_VEHICLES`` (van, truck, bus).
    """
    x, y, tex = _wall_canvas(h, w)
    H, W = h, w
    px = 1.0 / tex
    length, width, height = _VEHICLES[kind]
    body = float(rng.choice([rng.uniform(50, 90), rng.uniform(150, 215)]))
    img = body + _fbm(rng, H, W, (1, 0.1 * px, 0.5 * px, 2 * px), (2.0, 2.0, 3.0, 4.0))
    img += 10.0 * np.clip(y / height, 0, 1)  # sky reflection on the upper body
    under = _cover(0.35 - y, tex)
    img += under * (30.0 - img)
    # side: panel lines, windows, wheels, logo
    panels = _cover(0.012 - np.abs(np.mod(x, length / 3) - 0.01), tex) * (x < length)
    img += panels * (body * 0.6 - img)
    if kind == 2:  # bus: a band of windows
        band = _cover(np.minimum(y - 1.25, 2.55 - y), tex) * _cover(
            np.minimum(x - 0.4, length - 0.3 - x), tex)
        bars = _cover(0.05 - np.abs(np.mod(x, 1.5) - 0.75), tex)
        img += band * (50.0 + 60.0 * bars + 15.0 * (y - 1.25) - img)
    else:  # cab window near the front
        cab = _cover(np.minimum(x - (length - 1.7), length - 0.35 - x), tex) * _cover(
            np.minimum(y - 1.25, height - 0.35 - y), tex)
        img += cab * (55.0 + 20.0 * (y - 1.2) - img)
        logo = _cover(np.minimum(x - 1.0, length - 2.6 - x), tex) * _cover(
            np.minimum(y - 1.0, height - 0.6 - y), tex)
        stripes = np.mod(np.floor(x / 0.35) * 3 + np.floor(y / 0.22) * 5, 7) < 3
        img += logo * stripes * ((230.0 if body < 128 else 40.0) - img) * 0.7
    for cx in (1.0, length - 1.3):
        r = np.sqrt((x - cx) ** 2 + (y - 0.45) ** 2)
        tyre = _cover(0.45 - r, tex) * (x < length)
        img += tyre * (28.0 - img)
        rim = _cover(0.22 - r, tex) * (x < length)
        img += rim * (150.0 - 40.0 * _cover(0.06 - r, tex) - img)
    # rear (also used for the front): doors, lights, plate
    rx = x - (_WALL_W_M - 3.0)
    rear = (rx > 0) & (rx < width)
    img = np.where(rear, body + 0.5 * _fbm(rng, H, W, (1, 0.2 * px), (2.0, 3.0)), img)
    img += rear * (under * (30.0 - img))
    seam = _cover(0.015 - np.abs(rx - width / 2), tex) * rear * (y > 0.4)
    img += seam * (body * 0.5 - img)
    window = _cover(np.minimum(rx - 0.25, width - 0.25 - rx), tex) * _cover(
        np.minimum(y - (height - 1.1), height - 0.25 - y), tex)
    img += window * (45.0 - img)
    for lx in (0.2, width - 0.2):
        light = _cover(0.12 - np.abs(rx - lx), tex) * _cover(0.2 - np.abs(y - 0.9), tex)
        img += light * (235.0 - img)
    plate = _cover(0.26 - np.abs(rx - width / 2), tex) * _cover(0.06 - np.abs(y - 0.55), tex)
    chars = np.mod(np.floor((rx - width / 2) / 0.045), 3) == 0
    img += plate * (225.0 - 170.0 * chars * _cover(0.035 - np.abs(y - 0.55), tex) - img)
    return _finish(img)


def _plain_wall(rng: np.random.Generator, h: int, w: int, kind: str) -> np.ndarray:
    """Pole, concrete noise wall or warehouse texture (h, w)."""
    x, y, tex = _wall_canvas(h, w)
    H, W = h, w
    px = 1.0 / tex
    if kind == 'pole':
        img = 135.0 + 12.0 * np.sin(x * 40.0)
        img = img + _fbm(rng, H, W, (1, 0.2 * px, 1.0 * px), (2.0, 4.0, 6.0))
        img += _cover(0.05 - np.abs(np.mod(y, 2.3) - 0.05), tex) * 40.0
        img += _cover(0.9 - y, tex) * (70.0 - img)
        img += _cover(0.25 - np.abs(y - 6.9), tex) * (240.0 - img)
        return _finish(img)
    if kind == 'concrete':
        img = 150.0 + _fbm(rng, H, W, (1, 0.02 * px, 0.08 * px, 0.5 * px, 2 * px),
                           (6.0, 6.0, 6.0, 7.0, 8.0))
        img *= 1.0 + 0.08 * _noise(rng, H, W, 2.0 * px, 0.1 * px)
        grooves = _cover(0.02 - np.abs(np.mod(x, 3.2) - 1.6), tex)
        img += grooves * (80.0 - img)
        post = _cover(0.1 - np.abs(np.mod(x, 3.2)), tex) + _cover(np.mod(x, 3.2) - 3.1, tex)
        img += np.clip(post, 0, 1) * (95.0 - img)
        img += _cover(0.03 - np.abs(np.mod(y, 1.0) - 0.5), tex) * 20.0
        return _finish(img)
    # warehouse: corrugated cladding, loading doors, high windows, a logo
    base = float(rng.uniform(120, 190))
    img = base + 18.0 * np.sin(x * 2 * np.pi / 0.2) + _fbm(
        rng, H, W, (1, 0.1 * px, 1.0 * px, 4 * px), (3.0, 3.0, 6.0, 8.0))
    dx = np.mod(x, 6.4) - 0.8
    door = _cover(np.minimum(dx, 3.5 - dx), tex) * _cover(4.0 - y, tex)
    img += door * (95.0 + 25.0 * (np.mod(y, 0.25) < 0.03) - img)
    band = _cover(np.minimum(y - 6.0, 7.0 - y), tex) * _cover(0.9 - np.abs(np.mod(x, 3.2)
                                                                           - 1.6), tex)
    img += band * (60.0 - img)
    logo = _cover(np.minimum(y - 8.0, 10.0 - y), tex) * _cover(4.0 - np.abs(x - 6.4), tex)
    img += logo * (np.mod(np.floor(x / 0.5) + np.floor(y / 0.4), 3) < 1) * (40.0 - img)
    return _finish(img)


def _sky(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Cloud brightness (h, w) float32 around 0 (grey levels): azimuth along x, elevation y."""
    coarse = _noise(rng, h, w, h / 4.0, w / 24.0)
    return 6.0 * coarse + 3.0 * _noise(rng, h, w, h / 16.0, w / 96.0)


class _RipMaps:
    """Rip-maps of one periodic texture: level (lx, ly) halves x lx times and y ly times."""

    def __init__(self, base: np.ndarray, texel_x: float, texel_y: float) -> None:
        self.texel_x, self.texel_y = texel_x, texel_y
        self.max_x = max(0, int(math.log2(base.shape[1])) - 2)
        self.max_y = max(0, int(math.log2(base.shape[0])) - 2)
        self._levels: dict[tuple[int, int], np.ndarray] = {(0, 0): base}
        for ly in range(self.max_y + 1):  # box filtered, still periodic
            if ly:
                src = self._levels[(0, ly - 1)]
                self._levels[(0, ly)] = cv2.resize(src, (src.shape[1], src.shape[0] // 2),
                                                   interpolation=cv2.INTER_AREA)
            for lx in range(1, self.max_x + 1):
                src = self._levels[(lx - 1, ly)]
                self._levels[(lx, ly)] = cv2.resize(src, (src.shape[1] // 2, src.shape[0]),
                                                    interpolation=cv2.INTER_AREA)

    def level(self, lx: int, ly: int) -> np.ndarray:
        """Return the (H >> ly, W >> lx) uint8 level."""
        return self._levels[(lx, ly)]


class _WallAtlas:
    """
    All wall textures with their rip-maps packed into one padded uint8 atlas.

    Texture ``i`` at level (lx, ly) starts at atlas column ``x0[i, lx]`` and row ``y0[ly]``;
    every level is padded by wrapping horizontally and by replication vertically so that
    bilinear lookups at the seams are correct.
    """

    PAD = 2

    def __init__(self, textures: list[np.ndarray]) -> None:
        h, w = textures[0].shape
        self.h, self.w = h, w
        self.texel = _WALL_W_M / w
        self.max_x = max(0, int(math.log2(w)) - 2)
        self.max_y = max(0, int(math.log2(h)) - 2)
        p = self.PAD
        widths = [(w >> lx) + 2 * p for lx in range(self.max_x + 1)]
        heights = [(h >> ly) + 2 * p for ly in range(self.max_y + 1)]
        block_w = sum(widths)
        self.x0 = np.zeros((len(textures), self.max_x + 1), np.float64)
        self.y0 = np.cumsum([0] + heights[:-1]).astype(np.float64) + p
        atlas = np.zeros((sum(heights), block_w * len(textures)), np.uint8)
        for i, tex in enumerate(textures):
            rip = _RipMaps(tex, 1.0, 1.0)
            xs = i * block_w + np.cumsum([0] + widths[:-1])
            self.x0[i] = xs + p
            for lx in range(self.max_x + 1):
                for ly in range(self.max_y + 1):
                    lev = rip.level(lx, ly)
                    lev = np.pad(np.pad(lev, ((0, 0), (p, p)), mode='wrap'), ((p, p), (0, 0)),
                                 mode='edge')
                    y = int(self.y0[ly]) - p
                    atlas[y:y + lev.shape[0], xs[lx]:xs[lx] + lev.shape[1]] = lev
        if atlas.shape[1] >= 32767 or atlas.shape[0] >= 32767:
            raise ConfigError(f'wall texture atlas too large ({atlas.shape}); lower the width')
        self.atlas = atlas


# ---------------------------------------------------------------------------------------------
# Trajectory
# ---------------------------------------------------------------------------------------------
