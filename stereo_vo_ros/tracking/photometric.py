"""
Photometric compensation of a KLT pass: one gain and offset between two images.

OpenCV's pyramidal KLT minimises the sum of squared differences of the two windows, so a gain
or offset between the images moves the estimate and, beyond about 10 %, breaks the tracking
(rendered urban scenes with each camera's gain jumping independently by a factor 0.7-1.3 per
frame plus vignetting, preset ``urban_photometric``: 65-111 of 150 pairs not OK and 23 % mean
t_rel over seeds 0-5; see ``benchmarks/diag_photometric.py``). Before every KLT pass between
two images, the second image is mapped to the brightness of the first with one affine
grey-level map ``I' = gain I + offset`` (a 256-entry lookup table):

* from the windows around corresponding points (``window_stats``, ``transfer_from_stats``):
  ``gain`` is the median ratio of the standard deviations of 21x21 windows (at most 64
  windows, every second pixel) and ``offset`` the median difference of their means after the
  gain, over the textured, unsaturated windows (medians as the mean of the middle half).
  With a motion prior the tracker takes the windows of the four images of a step at once
  (``PhotometricMatcher.observe``: the features in the previous pair and their predicted
  positions in the current one); a fit whose ratios disagree (``MAX_LOG_SPREAD``: the
  windows do not show the same surfaces, a prior that is off at the start of a turn) is
  replaced by one from measured positions where the pass has them (stereo: the left points
  after the temporal pass and their previous disparity; bi-circular: the right points and
  the stored previous right points);
* otherwise (first pair, no prior, or no usable windows) from the grey-level histograms of
  the two images (``brightness_transfer``): their quantiles 5 %, 10 %, ..., 95 % are matched
  and a line is fitted to the pairs, leaving out saturated grey levels;
* a map that moves no grey level of 16-240 by 8 or more is not applied, so an exactly exposed
  pair is tracked on the images as given (exact renders: none applied in 450 pairs).

Measured with ``benchmarks/bench_seeds.py --seeds 0-5 --jobs 2 --cache /tmp/svo_cache``
(mean t_rel over the seeds, preset length 300 pairs, pipeline of commit c9d0b74; pairs not OK
in brackets): urban 0.078 % without, 0.077 % with the compensation (0); highway 0.460 % both
(no map applied: identical runs); urban_photometric 0.088 % (0; 1.14 x the exactly exposed
scenes); highway_photometric 0.617 % (0; 1.34 x, three seeds as exposed and three about
twice: on seed 4, ``diag_photometric.py`` finds the same tracks, inliers and quadruple errors
against the truth as on the exactly exposed scene, median 0.19 px). Without the compensation
(150 pairs, commit 2c72b1f): urban_photometric 22.9 % with 474 of 894 pairs not OK,
highway_photometric 55.4 % with 606.

A fixed per-camera vignetting is not a global gain; between the two cameras it leaves a
residual gain that varies slowly across the image (a few % for 30 % vignetting that differs by
10 % between the cameras), which KLT tolerates, and the affine refinement (``affine_klt``)
compares zero-mean windows scaled to equal contrast, which removes any local gain and offset.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import cv2
import numba
import numpy as np

from ..jit import kernel, readonly

#: Quantiles matched between the two histograms.
QUANTILES = np.arange(0.05, 0.951, 0.05)
#: Grey levels at either end treated as saturated (quantiles there are left out).
SATURATED_GREY = 2
#: A map is applied only when it moves some grey level of ``TYPICAL_GREY`` by at least this
#: (grey levels): on exactly exposed renders the maps from corresponding windows have gains of
#: 0.99-1.02 and offsets of -2..+1.4 grey levels (5-95 %, urban and highway seed 0), but a
#: zooming texture or a turn gives 3-4 % now and then (highway seed 2: 9 maps in 150 pairs at
#: 4 grey levels, and an end drift that moved by 0.6 %); KLT does not need maps that small.
#: At 8 grey levels no map is applied on urban seed 0 and highway seeds 0 and 2 (150 pairs).
MIN_CHANGE_GREY = 8.0
#: Range of the grey levels that decide whether a map is applied (the bulk of an image).
TYPICAL_GREY = (16.0, 240.0)
#: Accepted gain range; outside it the images are taken as too different to compare.
GAIN_RANGE = (0.25, 4.0)
#: Half side of the windows whose statistics give the map from corresponding points (pixels).
WINDOW_HALF_PX = 10
#: Windows flatter than this (standard deviation, grey levels) are left out.
MIN_WINDOW_STD_GREY = 4.0
#: Fewest usable windows for a map from corresponding points (else the histograms are used).
MIN_WINDOWS = 12
#: Largest interquartile range of the log contrast ratios of a fit (windows that show the same
#: surfaces: 0.06 median, 0.10 at the 90th percentile on the urban renders, with or without
#: exposure jumps; 0.25-0.75 where the motion prior was off at the start of a turn).
MAX_LOG_SPREAD = 0.2
#: At most this many windows (spread over the points given) are sampled, every
#: ``WINDOW_STEP_PX``-th pixel in both directions: the medians need no more, and the cost
#: stays at about 0.1 ms per map.
MAX_WINDOWS = 64
WINDOW_STEP_PX = 2


def histogram(img: np.ndarray) -> np.ndarray:
    """
    Return the normalised cumulative grey-level histogram of a uint8 image.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image.

    Returns
    -------
    np.ndarray
        (256,) float64 share of the pixels at or below each grey level (last value 1).

    """
    hist = cv2.calcHist([img], [0], None, [256], [0, 256]).ravel().astype(np.float64)
    cdf = np.cumsum(hist)
    return cdf / max(cdf[-1], 1.0)


def _quantiles(cdf: np.ndarray) -> np.ndarray:
    """Grey levels (float64) of ``QUANTILES`` from a cumulative histogram (interpolated)."""
    # Grey level g holds the values in [g - 0.5, g + 0.5); the CDF reaches cdf[g] at g + 0.5.
    edges = np.arange(257, dtype=np.float64) - 0.5
    cum = np.concatenate([[0.0], cdf])
    # Strictly increasing support for np.interp: drop empty bins.
    keep = np.concatenate([[True], np.diff(cum) > 0])
    return np.interp(QUANTILES, cum[keep], edges[keep])


def brightness_transfer(cdf_from: np.ndarray, cdf_to: np.ndarray) -> tuple[float, float]:
    """
    Gain and offset that map the grey levels of one image to those of another.

    Parameters
    ----------
    cdf_from, cdf_to : np.ndarray
        (256,) cumulative histograms (``histogram``) of the image to be mapped and of the
        reference image.

    Returns
    -------
    gain : float
        Unitless; ``gain * I_from + offset`` has the brightness of the reference.
    offset : float
        Grey levels. (1, 0) when too few quantiles are usable or the fit is implausible.

    """
    q_from, q_to = _quantiles(cdf_from), _quantiles(cdf_to)
    lo, hi = SATURATED_GREY - 0.5, 255.5 - SATURATED_GREY
    ok = (q_from > lo) & (q_from < hi) & (q_to > lo) & (q_to < hi)
    if np.count_nonzero(ok) < 4 or np.ptp(q_from[ok]) < 8.0:
        return 1.0, 0.0
    gain, offset = np.polyfit(q_from[ok], q_to[ok], 1)
    if not (GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]) or not np.isfinite(offset):
        return 1.0, 0.0
    return float(gain), float(offset)


def window_stats(images: tuple[np.ndarray, ...], points: tuple[np.ndarray, ...],
                 half: int = WINDOW_HALF_PX
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """
    Mean and standard deviation of the windows around the same scene points in several images.

    Parameters
    ----------
    images : tuple of np.ndarray
        M (H, W) uint8 grey images of one size (else ValueError).
    points : tuple of np.ndarray
        M (N, 2) float positions (pixels), row i of each the same scene point (predicted
        positions suffice). At most ``MAX_WINDOWS`` rows, spread over the N, are used.
    half : int
        Half side of the square windows (pixels); every ``WINDOW_STEP_PX``-th pixel is read.

    Returns
    -------
    tuple of np.ndarray or None
        ``(mean, std, usable)``, each (M, n): window mean and standard deviation (grey
        levels) and whether the window lies inside its image, is textured (standard deviation
        above ``MIN_WINDOW_STD_GREY``) and is not saturated. None without points, or when not
        one window fits in the images.

    """
    pts = [np.asarray(p, np.float64).reshape(-1, 2) for p in points]
    n_all = len(pts[0])
    if n_all == 0 or any(len(p) != n_all for p in pts):
        return None
    if n_all > MAX_WINDOWS:
        pick = _spread(n_all)
        pts = [p[pick] for p in pts]
    m, n = len(images), len(pts[0])
    h, w = images[0].shape
    if min(h, w) < 2 * half + 1:
        return None  # not one window fits
    p = np.concatenate(pts)
    ok = np.isfinite(p).all(axis=1)
    c = np.rint(np.where(ok[:, None], p, float(half))).astype(np.int64)
    ok &= ((c[:, 0] >= half) & (c[:, 0] < w - half) & (c[:, 1] >= half)
           & (c[:, 1] < h - half))
    c[~ok] = half
    sums = np.empty((m * n, 4), np.int64)  # sum, sum of squares, min, max of each window
    for i, img in enumerate(images):
        if img.shape != (h, w):
            raise ValueError(f'images of different sizes: {img.shape} and {(h, w)}')
        _window_sums(np.ascontiguousarray(img, np.uint8), c[i * n:(i + 1) * n], half,
                     WINDOW_STEP_PX, sums[i * n:(i + 1) * n])
    sums = sums.reshape(m, n, 4)
    ok = ok.reshape(m, n) & (sums[:, :, 3] < 255 - SATURATED_GREY) & (
        sums[:, :, 2] > SATURATED_GREY)
    # With the default windows (121 samples) the sums of grey levels and of their squares are
    # integers below 2^24: exact in float32, as the float32 sums of the samples were.
    k = np.float32(1.0 / len(range(-half, half + 1, WINDOW_STEP_PX)) ** 2)
    mean = sums[:, :, 0].astype(np.float32) * k
    std = np.sqrt(np.maximum(sums[:, :, 1].astype(np.float32) * k - mean * mean, 0.0))
    return mean, std, ok & (std > MIN_WINDOW_STD_GREY)


@functools.lru_cache(maxsize=16)
def _spread(n_all: int) -> np.ndarray:
    """(MAX_WINDOWS,) int64 rows spread evenly over ``n_all`` (first and last included)."""
    return np.linspace(0, n_all - 1, MAX_WINDOWS).astype(np.int64)


@kernel(numba.types.void(readonly(numba.types.uint8, 2), readonly(numba.types.int64, 2),
                         numba.types.int64, numba.types.int64,
                         numba.types.Array(numba.types.int64, 2, 'C')))
def _window_sums(img, centres, half, step, out):
    """
    Write sum, sum of squares, min and max of the windows at (x, y) ``centres`` to ``out``.

    Every ``step``-th pixel of a window of half side ``half`` (pixels) around each (n, 2)
    centre, which must lie ``half`` inside the (H, W) uint8 image; ``out`` is (n, 4).
    """
    for i in range(centres.shape[0]):
        x, y = centres[i, 0], centres[i, 1]
        total, squares, lo, hi = 0, 0, 255, 0
        for r in range(y - half, y + half + 1, step):
            for c in range(x - half, x + half + 1, step):
                v = np.int64(img[r, c])
                total += v
                squares += v * v
                lo = min(lo, v)
                hi = max(hi, v)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = total, squares, lo, hi


def transfer_from_stats(mean_from: np.ndarray, std_from: np.ndarray, ok_from: np.ndarray,
                        mean_to: np.ndarray, std_to: np.ndarray, ok_to: np.ndarray
                        ) -> tuple[float, float] | None:
    """
    Gain and offset between two images from the statistics of corresponding windows.

    Parameters
    ----------
    mean_from, std_from, ok_from : np.ndarray
        (n,) rows of ``window_stats`` of the image to be mapped.
    mean_to, std_to, ok_to : np.ndarray
        (n,) rows of the reference image, the same scene points.

    Returns
    -------
    tuple of float or None
        ``(gain, offset)`` (unitless, grey levels): ``gain`` the median ratio of the standard
        deviations, ``offset`` the median of ``mean_to - gain * mean_from`` (medians as the
        mean of the middle half of the sorted values), over the windows usable in both; None
        with fewer than ``MIN_WINDOWS``, a gain outside ``GAIN_RANGE`` or ratios that
        disagree (interquartile range of their logarithms above ``MAX_LOG_SPREAD``: the
        windows do not show the same surfaces, e.g. a motion prior that is off in a turn).

    """
    ok = ok_from & ok_to
    if np.count_nonzero(ok) < MIN_WINDOWS:
        return None
    ratio = std_to[ok] / std_from[ok]
    n = len(ratio)
    q = n // 4
    # The quartiles of the logarithms by selection, not a sort (float32 ``np.log`` need not keep
    # the order of its inputs, so they are taken of the logarithms themselves).
    log_ratio = np.partition(np.log(ratio), (q, n - 1 - q))
    if log_ratio[n - 1 - q] - log_ratio[q] > MAX_LOG_SPREAD:
        return None
    gain = _middle_mean(ratio)
    if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
        return None
    return gain, _middle_mean(mean_to[ok] - gain * mean_from[ok])


def window_transfer(img_from: np.ndarray, pts_from: np.ndarray, img_to: np.ndarray,
                    pts_to: np.ndarray, half: int = WINDOW_HALF_PX
                    ) -> tuple[float, float] | None:
    """
    Gain and offset from the windows around corresponding points of two images.

    Parameters
    ----------
    img_from, img_to : np.ndarray
        (H, W) uint8 grey images of one size: the one to be mapped and the reference.
    pts_from, pts_to : np.ndarray
        (N, 2) float positions (pixels) of the same scene points in each.
    half : int
        Half side of the square windows (pixels).

    Returns
    -------
    tuple of float or None
        ``transfer_from_stats`` of their ``window_stats``: ``gain * I_from + offset`` has the
        brightness of ``img_to``.

    """
    stats = window_stats((img_from, img_to), (pts_from, pts_to), half)
    if stats is None:
        return None
    mean, std, ok = stats
    return transfer_from_stats(mean[0], std[0], ok[0], mean[1], std[1], ok[1])


def _middle_mean(values: np.ndarray) -> float:
    """Mean of the middle half of the sorted values (a robust, cheap median)."""
    v = np.sort(values)
    q = len(v) // 4
    return float(v[q:len(v) - q].mean())


def apply_transfer(img: np.ndarray, gain: float, offset: float,
                   min_change: float = MIN_CHANGE_GREY) -> np.ndarray:
    """
    Map a uint8 image through ``gain * I + offset`` (rounded, clipped), or return it as is.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image. Not modified.
    gain, offset : float
        The map (unitless, grey levels), e.g. from ``brightness_transfer``.
    min_change : float
        The image itself is returned when no grey level of ``TYPICAL_GREY`` moves by this
        much (grey levels).

    Returns
    -------
    np.ndarray
        (H, W) uint8 mapped image (a new array), or ``img`` itself.

    """
    ends = np.array(TYPICAL_GREY)
    if np.max(np.abs(gain * ends + offset - ends)) < min_change:
        return img
    levels = np.arange(256, dtype=np.float64)
    lut = np.clip(np.rint(gain * levels + offset), 0, 255).astype(np.uint8)
    return cv2.LUT(img, lut)


class PhotometricMatcher:
    """
    Brightness maps between the images of two stereo pairs, with their inputs cached.

    ``matched(reference, img)`` returns ``img`` mapped to the brightness of ``reference`` (or
    ``img`` itself when they already match). Window statistics (``observe``), histograms and
    mapped images are cached by image identity; ``carry`` starts the next pair.
    """

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._cdfs: list[tuple[np.ndarray, np.ndarray]] = []
        #: (reference, img, mapped image or the pending result of ``prefetch``)
        self._mapped: list[tuple[np.ndarray, np.ndarray, Any]] = []
        self._stats: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]] = []
        #: (gain, offset) of the last map computed.
        self.last: tuple[float, float] = (1.0, 0.0)

    def carry(self, pairs: tuple[tuple[np.ndarray, np.ndarray], ...]) -> None:
        """
        Start the next pair: keep only the histograms of the images that stay.

        Parameters
        ----------
        pairs : tuple
            ``(image, kept)`` pairs: the histogram of ``image``, if computed, is kept for
            ``kept`` (the same pixels, possibly a copy); every other entry is forgotten.

        """
        cdfs = []
        for img, kept in pairs:
            for src, cdf in self._cdfs:
                if src is img:
                    cdfs.append((kept, cdf))
                    break
        self._cdfs = cdfs
        self._mapped = []
        self._stats = []

    def observe(self, images: tuple[np.ndarray, ...], points: tuple[np.ndarray, ...]) -> None:
        """
        Take the window statistics of the same scene points in several images at once.

        Later ``matched`` calls between two of these images (without points) fit their map
        to these statistics: one batched ``window_stats`` instead of one call per pass.

        Parameters
        ----------
        images : tuple of np.ndarray
            (H, W) uint8 grey images.
        points : tuple of np.ndarray
            (N, 2) float positions (pixels) of the same N scene points in each image.

        """
        if not self.enabled:
            return
        stats = window_stats(images, points)
        self._stats = [] if stats is None else [
            (img, (stats[0][i], stats[1][i], stats[2][i])) for i, img in enumerate(images)]

    def prefetch(self, pairs: tuple[tuple[np.ndarray, np.ndarray], ...],
                 submit: Callable[..., Any]) -> None:
        """
        Start mapping observed images ahead of the ``matched`` calls that will want them.

        For every ``(reference, img)`` pair whose map ``matched`` would fit to the statistics of
        ``observe``, the map is fitted now and applied by ``submit(apply_transfer, img, gain,
        offset)`` (e.g. on a helper thread: ``cv2.LUT`` releases the GIL); ``matched`` then
        takes the result, the same image it would have made. Other pairs are left to
        ``matched``.

        Parameters
        ----------
        pairs : tuple
            ``(reference, img)`` pairs of observed (H, W) uint8 images.
        submit : callable
            ``submit(fn, *args)`` returns an object whose ``result()`` is ``fn(*args)``.

        """
        if not self.enabled:
            return
        for reference, img in pairs:
            if reference is img or self._cached(reference, img) is not None:
                continue
            fit = self._observed_fit(reference, img)
            if fit is None:
                continue
            self.last = fit
            self._mapped.append((reference, img, submit(apply_transfer, img, *fit)))

    def _cached(self, reference: np.ndarray, img: np.ndarray) -> int | None:
        """Return the index of the pair in ``_mapped`` (by identity), or None."""
        for k, (ref, src, _) in enumerate(self._mapped):
            if ref is reference and src is img:
                return k
        return None

    def _observed_fit(self, reference: np.ndarray, img: np.ndarray
                      ) -> tuple[float, float] | None:
        """Return the map fitted to the statistics of ``observe`` (None without them or a fit)."""
        seen_img, seen_ref = self._observed(img), self._observed(reference)
        if seen_img is None or seen_ref is None:
            return None
        return transfer_from_stats(*seen_img, *seen_ref)

    def _observed(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        for src, stats in self._stats:
            if src is img:
                return stats
        return None

    def cdf(self, img: np.ndarray) -> np.ndarray:
        """Return the cumulative histogram of an image (cached by identity)."""
        for src, cdf in self._cdfs:
            if src is img:
                return cdf
        cdf = histogram(img)
        self._cdfs.append((img, cdf))
        return cdf

    def matched(self, reference: np.ndarray, img: np.ndarray,
                pts_reference: np.ndarray | None = None, pts_img: np.ndarray | None = None
                ) -> np.ndarray:
        """
        Return ``img`` mapped to the brightness of ``reference``.

        Parameters
        ----------
        reference, img : np.ndarray
            (H, W) uint8 grey images.
        pts_reference, pts_img : np.ndarray or None
            (N, 2) float positions (pixels) of corresponding points in each image (predicted
            positions suffice). The map comes from the statistics of ``observe`` when both
            images were observed and they give a fit; else from the windows at these points
            (``window_transfer``); else from the histograms (``brightness_transfer``).

        Returns
        -------
        np.ndarray
            (H, W) uint8: ``img`` itself when disabled or already matching, else a new image.
            When ``prefetch`` started this pair's map, its result (waited for; its error, if
            any, raised here).

        """
        if not self.enabled or reference is img:
            return img
        k = self._cached(reference, img)
        if k is not None:
            out = self._mapped[k][2]
            if not isinstance(out, np.ndarray):  # started by ``prefetch``
                out = out.result()
                self._mapped[k] = (reference, img, out)
            return out
        fit = self._observed_fit(reference, img)
        if fit is None and pts_reference is not None and pts_img is not None:
            fit = window_transfer(img, pts_img, reference, pts_reference)
        if fit is None:
            fit = brightness_transfer(self.cdf(img), self.cdf(reference))
        gain, offset = fit
        self.last = (gain, offset)
        out = apply_transfer(img, gain, offset)
        self._mapped.append((reference, img, out))
        return out
