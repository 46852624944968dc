"""
Detection of new corners where the stereo tracker lacks features (Huang et al., replenishment).

Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) are searched only in the buckets of the
bucketing grid that lack features (``plan_detection``), away from the features already tracked,
and spread over the grid (``detect_corners``). Positions are raw pixels (x right, y down) of the
image as given.
"""

from __future__ import annotations

import functools
import math
from typing import Callable

import cv2
import numpy as np

from . import bucketing
from .klt_checks import flow_edge_ratio
from ..config import BucketingConfig, TrackerConfig

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
    (the whole image when the margin leaves nothing); ``_regions`` starts a run at the edge
    rounded down and ends it at the edge rounded up.
    """
    x0, y0, x1, y1 = margin, margin, w - margin, h - margin
    if x1 <= x0 or y1 <= y0:
        x0, y0, x1, y1 = 0, 0, w, h
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
    free = _free_mask(existing, (h, w), cfg.min_distance_px, crops) if len(existing) else None
    found, ranks = [], []
    for (x0, y0, x1, y1), (cx0, cy0, cx1, cy1), count in zip(rects, crops, counts):
        mask = np.zeros((cy1 - cy0, cx1 - cx0), np.uint8)
        mask[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0] = 255 if free is None else free[y0:y1, x0:x1]
        limit = need if not bcfg.enabled else 2 * count * bcfg.max_per_bucket
        corners = cv2.goodFeaturesToTrack(
            img[cy0:cy1, cx0:cx1], maxCorners=int(limit), qualityLevel=cfg.quality_level,
            minDistance=cfg.min_distance_px, mask=mask, blockSize=cfg.block_size)
        if corners is None or len(corners) == 0:
            continue
        found.append(corners.reshape(-1, 2) + np.array([cx0, cy0], np.float32))
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
