"""
Detection of new corners where the stereo tracker lacks features (Huang et al., replenishment).

Shi-Tomasi corners (``shi_tomasi``: the corners of ``cv2.goodFeaturesToTrack``, in a compiled
kernel that releases the GIL) are searched only in the buckets of the bucketing grid that lack
features (``plan_detection``), away from the features already tracked, and spread over the grid
(``detect_corners``). Positions are raw pixels (x right, y down) of the image as given.
"""

from __future__ import annotations

import functools
import math
from typing import Callable

import cv2
import numba
import numpy as np

from . import bucketing
from .klt_checks import flow_edge_ratio
from ..config import BucketingConfig, TrackerConfig
from ..jit import kernel, readonly

#: Detection searches buckets whose free slots add up to this many times the features needed.
DETECTION_OVERSAMPLING = 1.0


def plan_detection(existing: np.ndarray, need: int, size: tuple[int, int],
                   bcfg: BucketingConfig, blocked: np.ndarray | None = None) -> np.ndarray:
    """
    Choose the buckets to search for new corners.

    The buckets below their quota (``bcfg.max_per_bucket``) that are not ``blocked`` are taken
    emptiest first (ties in a fixed scattered order, not row by row) until their free slots
    reach ``DETECTION_OVERSAMPLING * need``, so the detection cost follows the number of
    features to replace. Without existing features every bucket is searched.

    Parameters
    ----------
    existing : np.ndarray
        (N, 2) float pixel positions of the tracked features.
    need : int
        Number of features to add.
    size : tuple
        Image (width, height) in pixels.
    bcfg : BucketingConfig
        The bucketing grid.
    blocked : np.ndarray or None
        (rows, cols) bool buckets to skip (recently found empty); ignored when there are no
        existing features.

    Returns
    -------
    np.ndarray
        (rows, cols) bool chosen buckets.

    """
    occ = bucketing.occupancy(existing, size, bcfg)
    free = np.clip(bcfg.max_per_bucket - occ, 0, None).ravel()
    chosen = np.zeros(free.size, bool)
    if len(existing) == 0:
        chosen[free > 0] = True
        return chosen.reshape(occ.shape)
    if blocked is not None:
        free = np.where(blocked.ravel(), 0, free)
    order = np.lexsort((_scatter(free.size), -free))
    order = order[free[order] > 0]
    cum = np.cumsum(free[order])
    count = int(np.searchsorted(cum, DETECTION_OVERSAMPLING * need, side='left')) + 1
    chosen[order[:count]] = True
    return chosen.reshape(occ.shape)


@functools.lru_cache(maxsize=8)
def _scatter(n: int) -> np.ndarray:
    """Return a fixed permutation of ``n`` buckets (``plan_detection``'s tie order), read-only."""
    order = np.random.default_rng(0).permutation(n)
    order.flags.writeable = False
    return order


def _regions(chosen: np.ndarray, size: tuple[int, int], bcfg: BucketingConfig
             ) -> tuple[list[tuple[int, int, int, int]], list[int]]:
    """
    Rectangles (x0, y0, x1, y1) of horizontal runs of chosen buckets (pixels, end exclusive).

    Returns the rectangles and the number of buckets in each.
    """
    w, h = size
    if not bcfg.enabled:
        return [(0, 0, w, h)], [1]
    x_lo, x_hi, y_lo, y_hi = _bucket_edges(w, h, bcfg.rows, bcfg.cols, bcfg.roi_margin_px)
    rects, counts = [], []
    for r, row in enumerate(chosen.tolist()):  # a few rows of a few dozen buckets
        c, n = 0, len(row)
        while c < n:
            if not row[c]:
                c += 1
                continue
            c0 = c
            while c < n and row[c]:
                c += 1
            rects.append((x_lo[c0], y_lo[r], x_hi[c], y_hi[r + 1]))
            counts.append(c - c0)
    return rects, counts


@functools.lru_cache(maxsize=8)
def _bucket_edges(w: int, h: int, rows: int, cols: int, margin: int
                  ) -> tuple[list[int], list[int], list[int], list[int]]:
    """
    Return the bucket grid's column and row edges (pixels), rounded down and up, as ints.

    Column edge c lies at ``x0 + (x1 - x0) * c / cols`` over the region of interest (x0, x1)
    (``bucketing.region_of_interest``); ``_regions`` starts a run at the edge rounded down and
    ends it at the edge rounded up.
    """
    x0, y0, x1, y1 = bucketing.region_of_interest((w, h), margin)
    xe = x0 + (x1 - x0) * np.arange(cols + 1) / cols
    ye = y0 + (y1 - y0) * np.arange(rows + 1) / rows
    return (np.floor(xe).astype(int).tolist(), np.ceil(xe).astype(int).tolist(),
            np.floor(ye).astype(int).tolist(), np.ceil(ye).astype(int).tolist())


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """
    Return the (N, M) squared distances (pixels^2) between points a (N, 2) and b (M, 2).

    In their dtype, ``dx * dx + dy * dy``: the same values as summing the squared differences
    over the last axis, without NumPy's slow reduction over an axis of two.
    """
    dx = a[:, None, 0] - b[None, :, 0]
    dy = a[:, None, 1] - b[None, :, 1]
    dx *= dx
    dy *= dy
    dx += dy
    return dx


def bucket_ids(points: np.ndarray, size: tuple[int, int], bcfg: BucketingConfig
               ) -> np.ndarray:
    """(N,) int64 bucket indices of points inside the region of interest."""
    idx = bucketing.bucket_index(points, size, bcfg)
    return idx[idx >= 0]


def _free_mask(points: np.ndarray, shape: tuple[int, int], radius: float,
               rects: list[tuple[int, int, int, int]] | None = None) -> np.ndarray:
    """
    (H, W) uint8 mask: 255 on pixels at least ``radius`` from every point, 0 near them.

    Filled discs drawn with OpenCV (a distance transform of the whole image costs ten times
    more); the disc radius is rounded up, so the mask errs on the side of keeping away. With
    ``rects`` ((x0, y0, x1, y1), end exclusive) the mask is exact inside them only: discs that
    reach none of them are not drawn.
    """
    free = np.full(shape, 255, np.uint8)
    r = int(math.ceil(radius))
    h, w = shape
    centres = np.round(points).astype(np.int64).reshape(-1, 2)
    near = ((centres[:, 0] >= -r) & (centres[:, 0] < w + r) & (centres[:, 1] >= -r)
            & (centres[:, 1] < h + r))
    if rects is not None:
        box = np.asarray(rects, np.int64).reshape(-1, 4)
        near &= ((centres[:, None, 0] + r >= box[None, :, 0])
                 & (centres[:, None, 0] - r < box[None, :, 2])
                 & (centres[:, None, 1] + r >= box[None, :, 1])
                 & (centres[:, None, 1] - r < box[None, :, 3])).any(axis=1)
    for x, y in centres[near].tolist():
        cv2.circle(free, (x, y), r, 0, -1)
    return free


#: ``shi_tomasi``'s keep-away mask when there is nothing to keep away from (0 x 0).
NOTHING_BLOCKED = np.zeros((0, 0), np.uint8)


def shi_tomasi(img: np.ndarray, crop: tuple[int, int, int, int],
               rect: tuple[int, int, int, int], free: np.ndarray, max_corners: int,
               quality_level: float, min_distance_px: float, block_size: int) -> np.ndarray:
    """
    Shi-Tomasi corners of the ``crop`` of ``img``, inside ``rect`` where ``free`` allows.

    The corners of ``cv2.goodFeaturesToTrack`` on the crop with the mask of ``rect`` and
    ``free`` (3x3 Sobel gradients, no Harris), by its steps in a compiled kernel
    (``_shi_tomasi``): the smallest eigenvalue of each pixel's gradient matrix, summed over a
    ``block_size`` square; the largest in the mask times ``quality_level`` as the threshold; the
    3x3 maxima above it in the mask, off the crop's border, by value (ties: the later pixel, row
    by row, first); each kept unless closer than ``min_distance_px`` to one kept before. The
    gradient products are integers summed exactly and the eigenvalue is computed in float64,
    where OpenCV rounds to float32 on the way: corners whose rounded values tie or nearly tie
    (or sit at the threshold) may come in another order (on the KITTI clips' 1026 detection
    calls, once: two corners 3e-6 apart swapped). OpenCV's function runs where the sums would
    reach past the crop's edge (``rect`` within ``block_size // 2 + 2`` pixels of it: of the
    image's edge), for block sizes outside [2, 31] (the kernel's sums are int32; a 1-pixel
    block has no corner in exact sums, OpenCV picks them from its rounding), for images that
    are not uint8, a ``quality_level`` not above 0, ``min_distance_px`` below 1 or no corner
    limit.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image.
    crop, rect : tuple
        (x0, y0, x1, y1) pixel boxes of ``img`` (end exclusive), ``rect`` inside ``crop``:
        the image the corners are detected in (its edges are OpenCV's borders), and the part
        of it they may lie in.
    free : np.ndarray
        (H, W) uint8, non-zero where corners may lie; ``NOTHING_BLOCKED``: everywhere.
    max_corners, quality_level, min_distance_px, block_size
        As ``cv2.goodFeaturesToTrack``'s ``maxCorners``, ``qualityLevel``, ``minDistance``
        and ``blockSize``.

    Returns
    -------
    np.ndarray
        (M, 2) float32 corner positions (pixels, x right, y down) in the crop, best first.

    Raises
    ------
    ValueError
        ``free`` neither the image's size nor 0 x 0.

    """
    if free.size and free.shape != img.shape[:2]:
        raise ValueError(f'keep-away mask {free.shape} does not match the image {img.shape}')
    cx0, cy0, cx1, cy1 = crop
    rx0, ry0, rx1, ry1 = rect
    reach = block_size // 2 + 2  # the sums' reach past a candidate's neighbour, and Sobel's
    inside = (rx0 - reach >= cx0 and ry0 - reach >= cy0 and rx1 + reach <= cx1
              and ry1 + reach <= cy1)
    if rx1 <= rx0 or ry1 <= ry0:
        return np.zeros((0, 2), np.float32)
    if not inside or img.dtype != np.uint8 or max_corners <= 0 or not quality_level > 0 \
            or min_distance_px < 1 or not 2 <= block_size <= 31:
        mask = np.zeros((cy1 - cy0, cx1 - cx0), np.uint8)
        mask[ry0 - cy0:ry1 - cy0, rx0 - cx0:rx1 - cx0] = \
            255 if not free.size else free[ry0:ry1, rx0:rx1]
        corners = cv2.goodFeaturesToTrack(
            img[cy0:cy1, cx0:cx1], maxCorners=max_corners, qualityLevel=quality_level,
            minDistance=min_distance_px, mask=mask, blockSize=block_size)
        return np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)
    out = np.empty((min(max_corners, (rx1 - rx0) * (ry1 - ry0)), 2), np.float32)
    n = _shi_tomasi(np.ascontiguousarray(img), cx0, cy0, cx1, cy1, rx0, ry0, rx1, ry1,
                    np.ascontiguousarray(free, np.uint8), int(block_size),
                    float(quality_level), float(min_distance_px), out)
    return out[:n]


_INT = numba.types.int64


@kernel(_INT(readonly(numba.types.uint8, 2), _INT, _INT, _INT, _INT, _INT, _INT, _INT, _INT,
             readonly(numba.types.uint8, 2), _INT, numba.types.float64, numba.types.float64,
             numba.types.Array(numba.types.float32, 2, 'C')))
def _shi_tomasi(img, cx0, cy0, cx1, cy1, rx0, ry0, rx1, ry1, free, block, quality,
                min_distance, out):
    """
    Write the corners of ``shi_tomasi`` to ``out`` (at most its rows); return their number.

    Image boxes as there; the sums' pixels must lie inside the crop (``shi_tomasi`` checks).
    """
    w = cx1 - cx0
    # 1. Smallest eigenvalues on the rect grown by a pixel (the candidates' neighbours):
    #    products of the 3x3 Sobel gradients (integers: exact), summed over the block as running
    #    sums along each row, then down the columns. OpenCV's scale factor is left out: it
    #    changes no comparison below.
    r0 = block // 2
    ex0, ey0 = rx0 - 1, ry0 - 1
    nx, ny = rx1 - rx0 + 2, ry1 - ry0 + 2
    nr, nc = ny + block - 1, nx + block - 1
    xs, ys = ex0 - r0, ey0 - r0
    hxx = np.empty((nr, nx), np.int32)
    hxy = np.empty((nr, nx), np.int32)
    hyy = np.empty((nr, nx), np.int32)
    pxx = np.empty(nc, np.int32)
    pxy = np.empty(nc, np.int32)
    pyy = np.empty(nc, np.int32)
    for i in range(nr):
        a = img[ys + i - 1, xs - 1:xs + nc + 1]
        b = img[ys + i, xs - 1:xs + nc + 1]
        c = img[ys + i + 1, xs - 1:xs + nc + 1]
        for j in range(nc):
            gx = (np.int32(a[j + 2]) + 2 * np.int32(b[j + 2]) + np.int32(c[j + 2])) - (
                np.int32(a[j]) + 2 * np.int32(b[j]) + np.int32(c[j]))
            gy = (np.int32(c[j]) + 2 * np.int32(c[j + 1]) + np.int32(c[j + 2])) - (
                np.int32(a[j]) + 2 * np.int32(a[j + 1]) + np.int32(a[j + 2]))
            pxx[j] = gx * gx
            pxy[j] = gx * gy
            pyy[j] = gy * gy
        oxx, oxy, oyy = hxx[i], hxy[i], hyy[i]
        sa, sb, sc = np.int32(0), np.int32(0), np.int32(0)
        for k in range(block - 1):
            sa += pxx[k]
            sb += pxy[k]
            sc += pyy[k]
        for j in range(nx):  # a running sum along the row
            sa += pxx[j + block - 1]
            sb += pxy[j + block - 1]
            sc += pyy[j + block - 1]
            oxx[j] = sa
            oxy[j] = sb
            oyy[j] = sc
            sa -= pxx[j]
            sb -= pxy[j]
            sc -= pyy[j]
    sxx = np.zeros(nx, np.int32)
    sxy = np.zeros(nx, np.int32)
    syy = np.zeros(nx, np.int32)
    for i in range(block - 1):
        axx, axy, ayy = hxx[i], hxy[i], hyy[i]
        for j in range(nx):
            sxx[j] += axx[j]
            sxy[j] += axy[j]
            syy[j] += ayy[j]
    eig = np.empty((ny, nx), np.float64)
    for y in range(ny):
        last = y + block - 1
        axx, axy, ayy = hxx[last], hxy[last], hyy[last]
        for j in range(nx):
            sxx[j] += axx[j]
            sxy[j] += axy[j]
            syy[j] += ayy[j]
        e = eig[y]
        for j in range(nx):
            p, q, r = np.float64(sxx[j]), np.float64(sxy[j]), np.float64(syy[j])
            d = 0.5 * (p - r)
            e[j] = 0.5 * (p + r) - math.sqrt(d * d + q * q)
        axx, axy, ayy = hxx[y], hxy[y], hyy[y]
        for j in range(nx):
            sxx[j] -= axx[j]
            sxy[j] -= axy[j]
            syy[j] -= ayy[j]
    # 2. The threshold: the largest value in the mask times the quality level (0 without one).
    limit = free.shape[0] > 0
    top = -np.inf
    for y in range(1, ny - 1):
        e = eig[y, 1:nx - 1]
        if limit:
            f = free[ry0 + y - 1, rx0:rx1]
            for x in range(nx - 2):
                v = e[x] if f[x] != 0 else -np.inf
                top = v if v > top else top
        else:
            for x in range(nx - 2):
                top = e[x] if e[x] > top else top
    threshold = (top if top > -np.inf else 0.0) * quality
    # 3. Candidates in the mask, off the crop's border (never reached here), not below a
    #    neighbour, where values at or below the threshold count as 0; later pixels first.
    n_max = (ny - 2) * (nx - 2)
    values = np.empty(n_max, np.float64)
    where = np.empty(n_max, np.int64)
    n = 0
    if threshold >= 0.0:  # then: above the threshold and no neighbour larger
        most = np.empty((ny, nx - 2), np.float64)
        for y in range(ny):
            left, mid, right = eig[y, :nx - 2], eig[y, 1:nx - 1], eig[y, 2:]
            m = most[y]
            for x in range(nx - 2):
                v = left[x] if left[x] > mid[x] else mid[x]
                m[x] = v if v > right[x] else right[x]
        flag = np.empty(nx - 2, np.uint8)
        for y in range(1, ny - 1):
            e = eig[y, 1:nx - 1]
            up, mid, down = most[y - 1], most[y], most[y + 1]
            for x in range(nx - 2):
                v = e[x]
                flag[x] = (np.uint8(v > threshold) & np.uint8(v >= up[x])
                           & np.uint8(v >= mid[x]) & np.uint8(v >= down[x]))
            row = (ry0 + y - 1 - cy0) * w + rx0 - cx0
            for x in range(nx - 2):
                if flag[x] and (not limit or free[ry0 + y - 1, rx0 + x] != 0):
                    values[n] = e[x]
                    where[n] = row + x
                    n += 1
        values[:n] = values[:n][::-1].copy()
        where[:n] = where[:n][::-1].copy()
    else:
        for y in range(ny - 2, 0, -1):
            for x in range(nx - 2, 0, -1):
                v = eig[y, x]
                if not v > threshold or v == 0.0:
                    continue
                if limit and free[ry0 + y - 1, rx0 + x - 1] == 0:
                    continue
                peak = True
                for yy in range(y - 1, y + 2):
                    for xx in range(x - 1, x + 2):
                        u = eig[yy, xx]
                        if (u if u > threshold else 0.0) > v:
                            peak = False
                if peak:
                    values[n] = v
                    where[n] = (ry0 + y - 1 - cy0) * w + rx0 + x - 1 - cx0
                    n += 1
    # 4. By value (a stable sort keeps the later pixel first among equals), spaced out.
    order = np.argsort(-values[:n], kind='mergesort')
    kept = 0
    d2 = min_distance * min_distance
    for i in range(n):
        if kept == out.shape[0]:
            break
        y, x = divmod(where[order[i]], w)
        good = True
        for j in range(kept):
            dx = np.float32(x) - out[j, 0]
            dy = np.float32(y) - out[j, 1]
            if dx * dx + dy * dy < d2:
                good = False
                break
        if good:
            out[kept, 0] = np.float32(x)
            out[kept, 1] = np.float32(y)
            kept += 1
    return kept


def detect_corners(img: np.ndarray, existing: np.ndarray, need: int, cfg: TrackerConfig,
                   bcfg: BucketingConfig, chosen: np.ndarray | None = None,
                   flow: Callable[[np.ndarray], np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """
    Detect Shi-Tomasi corners only where features are missing.

    Detection runs on crops of the ``chosen`` buckets (whole image with bucketing disabled),
    masked to stay ``cfg.min_distance_px`` away from the existing features; the candidates are
    spread with ``bucketing.select`` (at most ``bcfg.max_per_bucket`` per bucket, counting the
    existing features) and ordered round-robin over the buckets (best corner of every bucket
    first).

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image.
    existing : np.ndarray
        (N, 2) float raw pixel positions of the features already tracked in ``img``.
    need : int
        Maximum number of corners to return.
    cfg, bcfg : TrackerConfig, BucketingConfig
        Detector and bucketing settings.
    chosen : np.ndarray or None
        (rows, cols) bool buckets to search; None: ``plan_detection`` without blocked buckets.
    flow : callable or None
        ``flow(points) -> (M, 2)`` expected displacement (pixels) of (M, 2) raw positions in
        the next frame. With it, candidates whose ``flow_edge_ratio`` over the KLT window is
        below ``cfg.min_flow_edge_ratio`` are dropped before the per-bucket choice, so the next
        corner of their bucket takes the slot.

    Returns
    -------
    corners : np.ndarray
        (M, 2) float32 raw pixel positions, M <= need, best first.
    found : np.ndarray
        (rows * cols,) int64 corners found per bucket before the ``need`` cut (empty with
        bucketing disabled).

    """
    h, w = img.shape
    n_buckets = bcfg.rows * bcfg.cols if bcfg.enabled else 0
    empty = np.zeros((0, 2), np.float32), np.zeros(n_buckets, np.int64)
    if need <= 0:
        return empty
    existing = np.asarray(existing, np.float64).reshape(-1, 2)
    if bcfg.enabled and chosen is None:
        chosen = plan_detection(existing, need, (w, h), bcfg)
    pad = cfg.block_size // 2 + 2
    rects, counts = _regions(chosen, (w, h), bcfg)
    crops = [(max(x0 - pad, 0), max(y0 - pad, 0), min(x1 + pad, w), min(y1 + pad, h))
             for x0, y0, x1, y1 in rects]
    free = (_free_mask(existing, (h, w), cfg.min_distance_px, crops) if len(existing) else
            NOTHING_BLOCKED)
    found, ranks = [], []
    for rect, crop, count in zip(rects, crops, counts):
        limit = need if not bcfg.enabled else 2 * count * bcfg.max_per_bucket
        corners = shi_tomasi(img, crop, rect, free, int(limit), cfg.quality_level,
                             cfg.min_distance_px, cfg.block_size)
        if not len(corners):
            continue
        found.append(corners + np.array(crop[:2], np.float32))
        ranks.append(np.arange(len(corners)))
    if not found:
        return empty
    cand = np.concatenate(found).astype(np.float32)
    rank = np.concatenate(ranks).astype(np.float64)
    if flow is not None and cfg.min_flow_edge_ratio > 0:
        expected = np.asarray(flow(cand.astype(np.float64)), np.float64).reshape(-1, 2)
        keep = flow_edge_ratio(img, cand, expected, cfg.win_size_px) >= cfg.min_flow_edge_ratio
        cand, rank = cand[keep], rank[keep]
        if not len(cand):
            return empty
    if not bcfg.enabled:
        return cand[np.argsort(rank, kind='stable')][:need], empty[1]
    # Per-bucket quota: existing features first, then candidates by their rank in their crop.
    allpts = np.vstack([existing, cand.astype(np.float64)])
    prio = np.concatenate([np.full(len(existing), 1e12), -rank])
    keep = bucketing.select(allpts, (w, h), bcfg, prio)[len(existing):]
    cand, rank = cand[keep], rank[keep]
    # Candidates of neighbouring crops may be too close: drop the worse of such pairs.
    if len(cand) > 1:
        d = np.sqrt(squared_distances(cand, cand))
        order = np.arange(len(cand))
        worse = (rank[None, :] > rank[:, None]) | (
            (rank[None, :] == rank[:, None]) & (order[None, :] > order[:, None]))
        clash = ((d < cfg.min_distance_px) & worse).any(axis=0)
        cand, rank = cand[~clash], rank[~clash]
    idx = bucketing.bucket_index(cand, (w, h), bcfg)
    per_bucket = np.bincount(idx[idx >= 0], minlength=n_buckets).astype(np.int64)
    # Round robin over buckets: the best corner of every bucket, then the second, ...
    order = np.lexsort((rank, idx))
    sorted_idx = idx[order]
    in_bucket = np.arange(len(order)) - np.searchsorted(sorted_idx, sorted_idx, side='left')
    round_robin = order[np.lexsort((rank[order], in_bucket))]
    return cand[round_robin][:need], per_bucket
