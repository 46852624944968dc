"""
Affine refinement of KLT matches (not in the papers).

OpenCV's pyramidal KLT fits a translation of the whole window. Where the window deforms between
the two images the translation is biased and noisy: a car moving at 1 m per frame sees a wall
10 m ahead grow by 10 % per frame, and the road's disparity changes by a third of a pixel per
row, so a 21-pixel window is sheared by 7 pixels between the left and the right image. On the
rendered urban scene (exact depth, so exact ground truth) the median error of a translational
KLT match is 0.16 px; this refinement, started from the KLT result, brings it to 0.06-0.09 px.

``refine_affine`` runs a few Gauss-Newton steps of the inverse-compositional affine
Lucas-Kanade algorithm (Baker and Matthews, "Lucas-Kanade 20 years on", 2004) on every point:
the window of the first image (the template) is fixed; the second image is sampled at
``c + A x`` for the window offsets ``x``, and the centre ``c`` and the 2x2 matrix ``A`` are
updated. Brightness is compared after removing each window's mean and scaling it to the
template's contrast, so exposure changes do not move the estimate. The samples can be weighted
by a Gaussian of their distance to the window's centre (``sigma_px``): a window across an
object's border holds two surfaces that move (or shift between the cameras) differently, and
an unweighted fit follows both.

The loop over points is compiled with Numba (``_refine_points``, as the module is imported;
see ``jit``): one pass over each window per step, bilinear sampling in float64 with the border
replicated, no temporary arrays, and the GIL released. The vectorised NumPy form it
replaced (``cv2.remap`` with weights quantised to 1/32 pixel, on float copies of the images)
took about three times as long per KITTI pair (3.2-3.5 against 1.0-1.3 ms), with the same
accuracy within the scene-to-scene spread (``docs/benchmarks.md``).

A point whose refinement leaves the plausible range (centre moved more than ``max_shift_px``,
``A`` far from a similarity of scale 0.5-2, windows that do not correlate, non-finite) keeps
its KLT position.

Pixel coordinates are (x right, y down), pixel centres at integers as in OpenCV.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..config import TrackerConfig
from ..jit import (cholesky, cholesky_solve, finite, image_signatures, kernel, kernel_image,
                   readonly)

#: Largest accepted move of a point by the refinement (pixels).
MAX_SHIFT_PX = 2.0
#: Accepted range of the determinant of A (area ratio of the two windows).
DET_RANGE = (0.25, 4.0)
#: Smallest accepted normalised cross-correlation of the two windows at the last iteration.
MIN_ZNCC = 0.7
#: Tikhonov term on the Gauss-Newton matrix, relative to its trace.
DAMPING = 1e-3
#: Largest accepted absolute entry of A.
MAX_A = 2.0


@kernel()
def _template(img, px, py, half, out):
    """
    Bilinear samples of ``img`` at ``(px + i, py + j)`` for i, j in [-half - 1, half + 1].

    One fractional offset for the whole window, so one set of weights; rows are ``out``'s
    first index. Border replicated.
    """
    h, w = img.shape
    side = out.shape[0]
    x0f, y0f = math.floor(px), math.floor(py)
    fx, fy = px - x0f, py - y0f
    x0, y0 = int(x0f) - half - 1, int(y0f) - half - 1
    inside = x0 >= 0 and y0 >= 0 and x0 + side < w and y0 + side < h
    w00, w01 = (1.0 - fx) * (1.0 - fy), fx * (1.0 - fy)
    w10, w11 = (1.0 - fx) * fy, fx * fy
    for r in range(side):
        ya, yb = y0 + r, y0 + r + 1
        if not inside:
            ya, yb = min(max(ya, 0), h - 1), min(max(yb, 0), h - 1)
        for c in range(side):
            xa, xb = x0 + c, x0 + c + 1
            if not inside:
                xa, xb = min(max(xa, 0), w - 1), min(max(xb, 0), w - 1)
            out[r, c] = (w00 * img[ya, xa] + w01 * img[ya, xb]
                         + w10 * img[yb, xa] + w11 * img[yb, xb])


@kernel()
def _warped(img, cx, cy, a00, a01, a10, a11, xs, ys, out):
    """Bilinear samples of ``img`` at ``(cx, cy) + A (xs, ys)`` (finite; border replicated)."""
    h, w = img.shape
    lo_x = hi_x = cx
    lo_y = hi_y = cy
    last = len(xs) - 1
    for i in (0, last):  # the window's corners: xs and ys run from their minimum to maximum
        for j in (0, last):
            u = cx + a00 * xs[i] + a01 * ys[j]
            v = cy + a10 * xs[i] + a11 * ys[j]
            lo_x, hi_x = min(lo_x, u), max(hi_x, u)
            lo_y, hi_y = min(lo_y, v), max(hi_y, v)
    # A margin: the samples below are computed again, and may round differently.
    inside = (lo_x >= 1e-3 and lo_y >= 1e-3 and hi_x < w - 1.001 and hi_y < h - 1.001)
    for k in range(len(xs)):
        u = cx + a00 * xs[k] + a01 * ys[k]
        v = cy + a10 * xs[k] + a11 * ys[k]
        if not inside:  # clamped before int(), which is undefined for huge values
            u, v = min(max(u, -1.0), w + 0.0), min(max(v, -1.0), h + 0.0)
        uf, vf = math.floor(u), math.floor(v)
        fx, fy = u - uf, v - vf
        xa, ya = int(uf), int(vf)
        xb, yb = xa + 1, ya + 1
        if not inside:
            xa, xb = min(max(xa, 0), w - 1), min(max(xb, 0), w - 1)
            ya, yb = min(max(ya, 0), h - 1), min(max(yb, 0), h - 1)
        p00, p01 = float(img[ya, xa]), float(img[ya, xb])  # float before any difference
        p10, p11 = float(img[yb, xa]), float(img[yb, xb])
        top = p00 + fx * (p01 - p00)
        bottom = p10 + fx * (p11 - p10)
        out[k] = top + fy * (bottom - top)


_F8, _I8, _B1 = numba.types.float64, numba.types.int64, numba.types.boolean


@kernel(image_signatures(lambda img: numba.types.void(
    img, img, readonly(_F8, 2), readonly(_F8, 2), _I8, _I8, _I8, _B1, _F8, _F8,
    numba.types.Array(_F8, 2, 'C'), numba.types.Array(_B1, 1, 'C'))))
def _refine_points(src, dst, pts_from, pts_to, half, step, iterations, horizontal, max_shift,
                   sigma, out, ok):
    """
    Refine as ``refine_affine`` (its parameters) does, into ``out`` (N, 2) and ``ok`` (N,).

    Steepest-descent images of the parameters (dA00, dA01, dA10, dA11, dcx, dcy), or of
    (dA00, dA01, dcx) along the row, are the template gradient times the window offsets.
    """
    side = 2 * half + 3  # the window and a one-pixel border for the gradients
    xs_l, ys_l = [], []
    for r in range(1, side - 1, step):
        for c in range(1, side - 1, step):
            xs_l.append(c - half - 1.0)
            ys_l.append(r - half - 1.0)
    xs, ys = np.array(xs_l), np.array(ys_l)
    k_n = len(xs)
    # Weight of each sample: a Gaussian of the distance to the window centre, or 1.
    wt = np.ones(k_n)
    if sigma > 0.0:
        for k in range(k_n):
            wt[k] = math.exp(-0.5 * (xs[k] * xs[k] + ys[k] * ys[k]) / (sigma * sigma))
    w_sum = 0.0
    for k in range(k_n):
        w_sum += wt[k]
    n_par = 3 if horizontal else 6
    patch = np.empty((side, side))
    tpl = np.empty(k_n)
    sd = np.empty((n_par, k_n))  # steepest-descent images, one row per parameter
    smp = np.empty(k_n)
    hess = np.empty((n_par, n_par))
    chol = np.zeros((n_par, n_par))
    mean_sd = np.empty(n_par)
    dp = np.zeros(6)
    tmp = np.empty(n_par)
    rhs = np.empty(n_par)
    for i in range(len(pts_from)):
        px, py = pts_from[i, 0], pts_from[i, 1]
        gx0, gy0 = pts_to[i, 0], pts_to[i, 1]
        out[i, 0], out[i, 1] = gx0, gy0
        ok[i] = False
        if not (finite(px) and finite(py) and finite(gx0) and finite(gy0)):
            continue
        _template(src, px, py, half, patch)
        k = 0
        t_mean = 0.0
        for r in range(1, side - 1, step):
            for c in range(1, side - 1, step):
                gx = 0.5 * (patch[r, c + 1] - patch[r, c - 1])
                gy = 0.5 * (patch[r + 1, c] - patch[r - 1, c])
                sd[0, k] = gx * xs[k]
                sd[1, k] = gx * ys[k]
                if horizontal:
                    sd[2, k] = gx
                else:
                    sd[2, k] = gy * xs[k]
                    sd[3, k] = gy * ys[k]
                    sd[4, k] = gx
                    sd[5, k] = gy
                tpl[k] = patch[r, c]
                t_mean += wt[k] * patch[r, c]
                k += 1
        t_mean /= w_sum
        t_var = 0.0
        for k in range(k_n):
            tpl[k] -= t_mean
            t_var += wt[k] * tpl[k] * tpl[k]
        tpl_std = math.sqrt(t_var / w_sum) + 1e-3
        # Gauss-Newton matrix, centred (the comparison is blind to the window mean), damped.
        for a in range(n_par):
            s = 0.0
            for k in range(k_n):
                s += wt[k] * sd[a, k]
            mean_sd[a] = s / w_sum
        trace = 0.0
        for a in range(n_par):
            for b in range(a + 1):
                s = 0.0
                for k in range(k_n):
                    s += wt[k] * sd[a, k] * sd[b, k]
                hess[a, b] = s - w_sum * mean_sd[a] * mean_sd[b]
            trace += hess[a, a]
        for a in range(n_par):
            hess[a, a] += DAMPING * trace + 1e-6
        cholesky(hess, n_par, chol)  # not positive definite: NaN, and the point fails
        a00, a01, a10, a11 = 1.0, 0.0, 0.0, 1.0
        cx, cy = gx0, (py if horizontal else gy0)
        img_std = err2 = 0.0
        finite_model = True
        for _ in range(iterations):
            _warped(dst, cx, cy, a00, a01, a10, a11, xs, ys, smp)
            m = 0.0
            for k in range(k_n):
                m += wt[k] * smp[k]
            m /= w_sum
            var = 0.0
            for k in range(k_n):
                smp[k] -= m
                var += wt[k] * smp[k] * smp[k]
            img_std = math.sqrt(var / w_sum)
            scale = tpl_std / (img_std + 1e-3)
            err2 = 0.0
            for k in range(k_n):
                e = smp[k] * scale - tpl[k]  # the brightness error (zero mean)
                smp[k] = wt[k] * e
                err2 += wt[k] * e * e
            err2 /= w_sum
            for a in range(n_par):
                s = 0.0
                for k in range(k_n):
                    s += sd[a, k] * smp[k]
                rhs[a] = s
            cholesky_solve(chol, n_par, rhs, tmp, dp)  # H dp = sd . e
            if horizontal:  # (dA00, dA01, dcx) -> (dA00, dA01, 0, 0, dcx, 0)
                dp[4], dp[2] = dp[2], 0.0
            # Inverse composition: A <- A (I + dA)^-1, c <- c - A dc.
            d00, d01, d10, d11 = 1.0 + dp[0], dp[1], dp[2], 1.0 + dp[3]
            det = d00 * d11 - d01 * d10
            i00, i01, i10, i11 = d11 / det, -d01 / det, -d10 / det, d00 / det
            a00, a01, a10, a11 = (a00 * i00 + a01 * i10, a00 * i01 + a01 * i11,
                                  a10 * i00 + a11 * i10, a10 * i01 + a11 * i11)
            cx, cy = cx - (a00 * dp[4] + a01 * dp[5]), cy - (a10 * dp[4] + a11 * dp[5])
            finite_model = (finite(cx) and finite(cy) and finite(a00)
                            and finite(a01) and finite(a10) and finite(a11))
            if not finite_model:
                break
        # Correlation of the windows at the last step: 1 - mean squared error / (2 var).
        zncc = 1.0 - err2 / (2.0 * tpl_std * tpl_std) if img_std > 1e-3 else 0.0
        det_a = a00 * a11 - a01 * a10
        if (finite_model and zncc > MIN_ZNCC and DET_RANGE[0] < det_a < DET_RANGE[1]
                and max(abs(a00), abs(a01), abs(a10), abs(a11)) < MAX_A
                and math.hypot(cx - gx0, cy - gy0) <= max_shift):
            out[i, 0], out[i, 1] = cx, cy
            ok[i] = True


def refine_affine(img_from: np.ndarray, img_to: np.ndarray, pts_from: np.ndarray,
                  pts_to: np.ndarray, win_size_px: int = 21, iterations: int = 3,
                  max_shift_px: float = MAX_SHIFT_PX, horizontal: bool = False,
                  step_px: int = 1, sigma_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """
    Refine matches ``pts_from`` -> ``pts_to`` with an affine window model.

    Parameters
    ----------
    img_from, img_to : np.ndarray
        (H, W) grey images (uint8 or float).
    pts_from : np.ndarray
        (N, 2) positions in ``img_from`` (pixels): the window centres of the templates.
    pts_to : np.ndarray
        (N, 2) matched positions in ``img_to`` (pixels), e.g. from ``lk_pass``: the start.
    win_size_px : int
        Side of the square window (pixels, odd).
    iterations : int
        Gauss-Newton steps.
    max_shift_px : float
        A point moved farther than this from ``pts_to`` keeps ``pts_to`` (pixels).
    horizontal : bool
        Rectified stereo: the match lies on the row of ``pts_from`` and only x moves; the
        window maps ``(x, y) -> (c_x + a00 x + a01 y, c_y + y)`` (a plane of disparity
        across the window). Fixes the row, so an oblique edge cannot slide along itself.
    step_px : int
        Use every ``step_px``-th pixel of the window in both directions (gradients still come
        from the full-resolution template): 2 costs about half as much on 21-pixel windows.
    sigma_px : float
        Std (pixels) of the Gaussian weight of each sample by its distance to the window's
        centre, in the fit and in the correlation test; 0 weights all samples alike.

    Returns
    -------
    refined : np.ndarray
        (N, 2) float64 positions in ``img_to``; rows that failed hold ``pts_to``.
    ok : np.ndarray
        (N,) bool, the refinement was accepted.

    """
    given = np.ascontiguousarray(np.asarray(pts_to, np.float64).reshape(-1, 2))
    start = np.ascontiguousarray(np.asarray(pts_from, np.float64).reshape(-1, 2))
    if len(start) != len(given):
        raise ValueError(f'{len(start)} template points for {len(given)} matches')
    refined, ok = np.empty((len(given), 2)), np.zeros(len(given), bool)
    if len(given) == 0:
        return refined, ok
    src, dst = kernel_image(img_from), kernel_image(img_to)
    if src.dtype != dst.dtype:
        src, dst = src.astype(np.float32), dst.astype(np.float32)
    _refine_points(src, dst, start, given, int(win_size_px) // 2, max(int(step_px), 1),
                   int(iterations), bool(horizontal), float(max_shift_px), float(sigma_px),
                   refined, ok)
    return refined, ok


def refine_matches(cfg: TrackerConfig, img_from: np.ndarray, img_to: np.ndarray,
                   pts_from: np.ndarray, pts_to: np.ndarray, stereo: bool = False,
                   rectified: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """
    ``refine_affine`` with the tracker's settings for temporal or stereo matches.

    ``stereo`` takes the stereo window and weighting (``affine_stereo_*``); ``rectified``
    stereo matches keep their row (``horizontal``). Returns as ``refine_affine`` does.
    """
    win = cfg.affine_stereo_win_size_px if stereo else cfg.affine_win_size_px
    sigma = cfg.affine_stereo_sigma_px if stereo else cfg.affine_sigma_px
    return refine_affine(img_from, img_to, pts_from, pts_to, win, cfg.affine_iterations,
                         horizontal=stereo and rectified, step_px=cfg.affine_step_px,
                         sigma_px=sigma)
