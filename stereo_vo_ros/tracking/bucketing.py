"""
Bucketing (Kitt et al., section III-C): keep at most k features per cell of a grid over a ROI.

The region of interest is the image minus a margin; the ROI is divided into ``rows x cols``
non-overlapping rectangles and in each at most ``max_per_bucket`` features are kept, the best
ones first. Features outside the ROI are dropped.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..config import BucketingConfig
from ..jit import kernel, readonly


def region_of_interest(size: tuple[int, int], margin: int) -> tuple[int, int, int, int]:
    """
    Return the bucketed region (x0, y0, x1, y1) of a (width, height) image, pixels.

    The image minus ``margin`` pixels on every side; the whole image when that leaves nothing.
    """
    width, height = size
    x0, y0, x1, y1 = margin, margin, width - margin, height - margin
    if x1 <= x0 or y1 <= y0:
        return 0, 0, width, height
    return x0, y0, x1, y1


def bucket_index(points: np.ndarray, size: tuple[int, int], cfg: BucketingConfig) -> np.ndarray:
    """
    Return the bucket index of each point, -1 outside the region of interest.

    Parameters
    ----------
    points : np.ndarray
        (N, 2) float pixel coordinates (x right, y down).
    size : tuple of int
        (width, height) of the image in pixels.
    cfg : BucketingConfig
        Bucketing configuration.

    Returns
    -------
    (N,) int64 bucket index in ``[0, rows*cols)`` or -1.

    """
    points = np.ascontiguousarray(points, np.float64).reshape(-1, 2)
    x0, y0, x1, y1 = region_of_interest(size, cfg.roi_margin_px)
    out = np.empty(len(points), np.int64)
    _bucket_index(points, float(x0), float(y0), float(x1), float(y1), int(cfg.cols),
                  int(cfg.rows), out)
    return out


@kernel(numba.types.void(readonly(numba.types.float64, 2), *[numba.types.float64] * 4,
                         numba.types.int64, numba.types.int64,
                         numba.types.Array(numba.types.int64, 1, 'C')), exact=True)
def _bucket_index(points, x0, y0, x1, y1, cols, rows, out):
    """
    ``bucket_index`` into ``out``: region (x0, y0, x1, y1), ``rows`` x ``cols`` buckets.

    Exact arithmetic (the bucket of a point on a bucket's edge is the one of the same
    operations in NumPy: ``floor((x - x0) * cols / (x1 - x0))``).
    """
    for i in range(points.shape[0]):
        x, y = points[i, 0], points[i, 1]
        if x >= x0 and x < x1 and y >= y0 and y < y1:  # (NaN is outside)
            col = min(max(int(math.floor((x - x0) * cols / (x1 - x0))), 0), cols - 1)
            row = min(max(int(math.floor((y - y0) * rows / (y1 - y0))), 0), rows - 1)
            out[i] = row * cols + col
        else:
            out[i] = -1


def select(points: np.ndarray, size: tuple[int, int], cfg: BucketingConfig,
           priority: np.ndarray | None = None, max_per_bucket: int | None = None) -> np.ndarray:
    """
    Select features by bucketing.

    Parameters
    ----------
    points : np.ndarray
        (N, 2) float pixel coordinates.
    size : tuple of int
        (width, height) in pixels.
    cfg : BucketingConfig
        Bucketing configuration.
    priority : np.ndarray, optional
        (N,) float, larger is better (e.g. feature age); ties keep the input order. None keeps
        the input order.
    max_per_bucket : int, optional
        Overrides ``cfg.max_per_bucket`` when given.

    Returns
    -------
    (N,) bool mask of the kept features. With bucketing disabled, every point is kept.

    """
    n = len(points)
    if not cfg.enabled or n == 0:
        return np.ones(n, bool)
    k = cfg.max_per_bucket if max_per_bucket is None else max_per_bucket
    idx = bucket_index(points, size, cfg)
    prio = np.zeros(n) if priority is None else np.asarray(priority, np.float64)
    # Stable sort by bucket, then by descending priority, then by input order.
    order = np.lexsort((np.arange(n), -prio, idx))
    sorted_idx = idx[order]
    starts = np.searchsorted(sorted_idx, sorted_idx, side='left')
    rank = np.arange(n) - starts
    keep_sorted = (rank < k) & (sorted_idx >= 0)
    keep = np.zeros(n, bool)
    keep[order[keep_sorted]] = True
    return keep


def occupancy(points: np.ndarray, size: tuple[int, int], cfg: BucketingConfig) -> np.ndarray:
    """Return (rows, cols) int counts of points per bucket (ROI points only)."""
    idx = bucket_index(points, size, cfg)
    counts = np.bincount(idx[idx >= 0], minlength=cfg.rows * cfg.cols)
    return counts.reshape(cfg.rows, cfg.cols)
