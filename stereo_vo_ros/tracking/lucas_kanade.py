"""
Pyramidal Lucas-Kanade (KLT) point tracking on image pyramids built once per image.

The tracker's KLT passes see each image several times: the left image of a pair is the target
of the temporal pass, the source of the forward-backward and stereo passes, and the source of
the next pair's temporal pass. ``cv2.calcOpticalFlowPyrLK`` rebuilds the pyramid and the Scharr
derivative images of the whole image at every call (40-60 % of a pass of 120-200 points at
1241x376), and OpenCV's Python binding does not accept a prebuilt pyramid. Here an
``ImagePyramid`` holds the levels of one image (built on first use with ``cv2.pyrDown``, as
OpenCV builds them; no padded copies: a window that reaches past a level reads its reflection,
as OpenCV's padded levels hold it) and ``track`` runs Bouguet's pyramidal Lucas-Kanade on them
with a compiled kernel: OpenCV's algorithm in OpenCV's fixed point (``calcOpticalFlowPyrLK``
with ``minEigThreshold`` 1e-4 and the same termination criteria), with the derivatives
computed only in the windows of the points (Scharr, as OpenCV) instead of over whole images.
Its sums of integer products are exact (integers, or float64) where OpenCV's are
single-precision floats: on the KITTI clips the tracked positions differ from OpenCV's by 1e-4
px or less (median) and 0.011 px or less at the 99th percentile of each kind of pass (more than
0.01 px: 1.1 % or fewer of the new corners searched from three levels up, 0.2 % or fewer
elsewhere), and the two fail the same points but for 1 in 2,500 or fewer.

Pixel coordinates are (x right, y down) of the base image.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np

from ..jit import kernel, readonly

#: Columns of the window the kernel processes at once (a SIMD-friendly width).
CHUNK = 16
#: Fixed-point bits of the bilinear weights (OpenCV's ``W_BITS``).
WEIGHT_BITS = 14
#: Rows a column's iteration sums add up in 32-bit integers before they are widened: a product
#: of a grey-level mismatch and a derivative (both times 32) is below 8160 * 4080 < 2**31 / 64.
LANE_ROWS = 64
#: Smallest eigenvalue of the window's gradient matrix (OpenCV's units, its default): below it
#: the window has too little texture to track.
MIN_EIGENVALUE = 1e-4


def finite_rows(pts: np.ndarray) -> np.ndarray:
    """Return (N,) bool: which rows of (N, 2) points are finite (two column tests, no reduce)."""
    fin = np.isfinite(pts)
    return fin[:, 0] & fin[:, 1]


class ImagePyramid:
    """
    The Gaussian pyramid of one grey image, levels built on first use.

    Level 0 is the image; level k + 1 is ``cv2.pyrDown`` of level k, as OpenCV builds its KLT
    pyramids. Windows that reach past a level read its reflection (``BORDER_REFLECT_101``, as
    OpenCV pads its levels) without a padded copy. Levels are built on first use without a
    lock: one thread at a time.

    Parameters
    ----------
    image : np.ndarray
        (H, W) uint8 grey image (kept by reference; not to be modified while in use).

    """

    def __init__(self, image: np.ndarray) -> None:
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f'ImagePyramid needs an (H, W) uint8 image, got {image.dtype} '
                             f'{image.shape}')
        self.image = image
        level = np.ascontiguousarray(image).view()  # read-only; the image itself stays as is
        level.flags.writeable = False
        self._levels = [level]

    def size(self, level: int) -> tuple[int, int]:
        """Return (width, height) of a level (pixels), without building it."""
        h, w = self.image.shape
        for _ in range(level):
            w, h = (w + 1) // 2, (h + 1) // 2
        return w, h

    def level(self, level: int) -> np.ndarray:
        """Return level ``level`` ((h, w) uint8, C-contiguous, read-only), built if need be."""
        while len(self._levels) <= level:
            out = cv2.pyrDown(self._levels[-1])
            out.flags.writeable = False
            self._levels.append(out)
        return self._levels[level]

    def usable_levels(self, levels: int, win_size_px: int) -> int:
        """
        Return the top level a pass may use: at most ``levels``, as OpenCV limits it.

        A level is used only if it is larger than the window in both directions.
        """
        top = 0
        while top < levels:
            w, h = self.size(top + 1)
            if w <= win_size_px or h <= win_size_px:
                break
            top += 1
        return top


def track(src: ImagePyramid, dst: ImagePyramid, pts: np.ndarray, guess: np.ndarray | None,
          levels: int, win_size_px: int, max_iterations: int, epsilon_px: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """
    Track points from one image into another (pyramidal Lucas-Kanade, Bouguet).

    Parameters
    ----------
    src, dst : ImagePyramid
        Pyramids of the two images (the same size).
    pts : np.ndarray
        (N, 2) float positions in ``src`` (pixels).
    guess : np.ndarray or None
        (N, 2) float initial positions in ``dst`` (pixels); None starts every point at its
        position in ``src``. Points with a non-finite guess fail.
    levels : int
        Pyramid levels above the base image (limited as ``ImagePyramid.usable_levels``).
    win_size_px : int
        Side of the square window (pixels).
    max_iterations : int
        Iterations per level at most (OpenCV's limit: 0 to 100).
    epsilon_px : float
        A level stops once a step moves the point less than this (pixels; 0 to 10).

    Returns
    -------
    tracked : np.ndarray
        (N, 2) float32 positions in ``dst``.
    ok : np.ndarray
        (N,) bool: the window stayed where it could be read and was textured enough
        (OpenCV's ``status``). Non-finite input points fail.

    """
    if src.image.shape != dst.image.shape:
        raise ValueError(f'KLT images differ in size: {src.image.shape} vs {dst.image.shape}')
    win = int(win_size_px)
    if win < 1:
        raise ValueError(f'KLT window of {win} pixels')
    n = len(pts)
    prev = np.ascontiguousarray(pts, np.float32).reshape(n, 2)
    ok = finite_rows(prev)
    if guess is None:
        nxt = prev.copy()
    else:
        nxt = np.array(guess, np.float32).reshape(n, 2)
        ok &= finite_rows(nxt)
    if not n or not src.image.size:
        return nxt, ok & (src.image.size > 0)
    # OpenCV's limits of the termination criteria.
    iterations = min(max(int(max_iterations), 0), 100)
    epsilon = min(max(float(epsilon_px), 0.0), 10.0)
    top = src.usable_levels(int(levels), win)
    for level in range(top, -1, -1):
        _track_level(src.level(level), dst.level(level), prev, nxt, ok, level, level == top,
                     guess is not None, win, iterations, np.float32(epsilon * epsilon),
                     MIN_EIGENVALUE)
    return nxt, ok


@kernel()
def _bilinear(x, y):
    """
    Return the pixel at or left of and above (x, y) and its bilinear weights, as OpenCV's KLT.

    The weights of the four pixels are OpenCV's fixed-point ones (``WEIGHT_BITS``, rounded as
    OpenCV rounds them, adding up to 1), as float32: a weighted sum of uint8 grey levels is then
    exact in float32, as OpenCV's integer sum is.
    """
    ix = int(math.floor(x))
    iy = int(math.floor(y))
    a = np.float32(x - ix)
    b = np.float32(y - iy)
    one = np.float32(1)
    unit = np.float32(1 << WEIGHT_BITS)
    w00 = np.rint((one - a) * (one - b) * unit)
    w01 = np.rint(a * (one - b) * unit)
    w10 = np.rint((one - a) * b * unit)
    w11 = unit - w00 - w01 - w10
    inv = one / unit
    return ix, iy, w00 * inv, w01 * inv, w10 * inv, w11 * inv


@kernel()
def _reflect(p, n):
    """Return pixel index ``p`` of a row or column of ``n`` (>= 1) as OpenCV's reflect-101."""
    if n <= 1:  # (an empty level has no pixel to read: the caller returns before)
        return 0
    while p < 0 or p >= n:
        p = -p if p < 0 else 2 * n - 2 - p
    return p


@kernel()
def _target_sums(img, base, stride, win, chunks, w00, w01, w10, w11, patch, grad_x, grad_y,
                 lane_1, lane_2):
    """
    Return one iteration's sums: the mismatch times each derivative, over the window.

    The target window is sampled from the bytes of ``img`` (a flat uint8 image or window, its
    top left pixel at ``base``, rows ``stride`` apart) with the bilinear weights ``w00`` ..
    ``w11``, a chunk of columns at a time (a fixed width the compiler vectorizes), times 32
    and rounded; ``patch``, ``grad_x``, ``grad_y`` hold the source window's values and
    derivatives (``win`` rows of ``chunks * CHUNK``, integers); ``lane_1``, ``lane_2``
    (``chunks * CHUNK``, int32) are scratch for the sums of each window column, widened to 64
    bits every ``LANE_ROWS`` rows. Integer arithmetic throughout: exact, as vectorized as the
    compiler makes it.
    """
    c32 = np.float32(32)
    rnd = np.float32(0.5)
    u1 = numba.uint64(1)
    wc = chunks * CHUNK
    b1 = 0
    b2 = 0
    for y_block in range(0, win, LANE_ROWS):
        lane_1[:] = 0
        lane_2[:] = 0
        for y in range(y_block, min(y_block + LANE_ROWS, win)):
            r0 = numba.uint64(base + y * stride)
            for c in range(chunks):
                o = numba.uint64(y * wc + c * CHUNK)
                q0 = r0 + numba.uint64(c * CHUNK)
                q1 = q0 + numba.uint64(stride)
                lane = c * CHUNK  # each window column has a lane of its own
                for x in range(CHUNK):
                    k = numba.uint64(x)
                    v = (np.float32(img[q0 + k]) * w00 + np.float32(img[q0 + k + u1]) * w01
                         + np.float32(img[q1 + k]) * w10 + np.float32(img[q1 + k + u1]) * w11)
                    d = np.int32(np.floor(v * c32 + rnd)) - patch[o + k]
                    lane_1[lane + x] += d * grad_x[o + k]
                    lane_2[lane + x] += d * grad_y[o + k]
        for x in range(wc):
            b1 += np.int64(lane_1[x])
            b2 += np.int64(lane_2[x])
    return np.float64(b1), np.float64(b2)


_u8 = readonly(numba.types.uint8, 2)
_i64, _f32, _b1 = numba.types.int64, numba.types.float32, numba.types.boolean


@kernel([numba.types.void(
    _u8, _u8, readonly(_f32, 2), numba.types.Array(_f32, 2, 'C'), numba.types.Array(_b1, 1, 'C'),
    _i64, _b1, _b1, _i64, _i64, _f32, numba.types.float64)])
def _track_level(img_i, img_j, prev, nxt, ok, level, top, use_guess, win, max_iter, eps2,
                 min_eig):
    """
    One pyramid level of Lucas-Kanade for every point still ``ok``, in place in ``nxt``.

    ``img_i``, ``img_j``: the level of the source and target image (the same size; windows
    that reach past it read its reflection, as OpenCV's padded levels). ``prev`` holds
    base-level source positions; ``nxt`` the base-level guesses at the top level
    (``use_guess``), else the previous level's result at its scale; it is left at this level's
    scale. As OpenCV, with its fixed-point weights and roundings: the window's grey levels
    (times 32) and Scharr derivatives are sampled bilinearly at the source point and rounded to
    integers; each iteration moves the point by the solution of the 2x2 normal equations; a
    level stops after ``max_iter`` iterations, a step shorter than sqrt(``eps2``), or a step
    that undoes the last one (the point then goes back half of it).
    A point fails (``ok`` False, on the base level only) whose window lies a window or more
    past the image (OpenCV's limit) or whose gradient matrix has a smallest eigenvalue below
    ``min_eig`` (per pixel, in OpenCV's scale) or is singular. The sums of integer products are
    exact (the gradient matrix's in float64, the iterations' in integers), where OpenCV's are
    single-precision floats: no summation order changes a result.
    """
    n = prev.shape[0]
    wc = ((win + CHUNK - 1) // CHUNK) * CHUNK  # window columns processed
    half = np.float32((win - 1) * 0.5)
    scale = np.float32(1.0 / (1 << level))
    h, w = img_i.shape
    flat_i = img_i.ravel()
    flat_j = img_j.ravel()
    sf = wc + 3  # source pixels around the window (one more on each side for the derivatives)
    sg = wc + 2  # sampled source values on the window's grid, plus one on each side
    sr = wc + 1
    raw = np.empty((win + 3) * sf, np.float32)
    grid = np.empty((win + 2) * sg, np.float32)
    patch = np.zeros(win * wc, np.int32)  # grey levels times 32, rounded
    grad_x = np.zeros(win * wc, np.int32)  # Scharr derivatives (32 times grey levels per
    grad_y = np.zeros(win * wc, np.int32)  # pixel), rounded
    chunks = wc // CHUNK
    lane_1 = np.zeros(wc, np.int32)  # the sums of an iteration per window column
    lane_2 = np.zeros(wc, np.int32)
    inside = np.zeros(wc, np.float32)  # 1 on the window's columns, 0 on the padding columns
    inside[:win] = 1
    edge_x = np.empty((win + 1) * sr, np.float32)  # derivatives at pixels, windows at the border
    edge_y = np.empty((win + 1) * sr, np.float32)
    target = np.empty((win + 1) * sr, np.uint8)  # the target window, reflected at the border
    fixed = np.float32(1.0 / (1 << 20))  # OpenCV's scale of the sums
    c3 = np.float32(3)
    c10 = np.float32(10)
    c32 = np.float32(32)
    rnd = np.float32(0.5)  # rounding to the nearest integer, halves up, as OpenCV's shifts
    one = np.float32(1)
    u1 = numba.uint64(1)
    u2 = numba.uint64(2)
    for i in range(n):
        px = prev[i, 0] * scale - half
        py = prev[i, 1] * scale - half
        if top:
            if use_guess:
                nx = nxt[i, 0] * scale
                ny = nxt[i, 1] * scale
            else:
                nx = prev[i, 0] * scale
                ny = prev[i, 1] * scale
        else:
            nx = nxt[i, 0] * np.float32(2.0)
            ny = nxt[i, 1] * np.float32(2.0)
        nxt[i, 0] = nx
        nxt[i, 1] = ny
        if not ok[i]:
            continue
        ix, iy, w00, w01, w10, w11 = _bilinear(px, py)
        if ix < -win or ix >= w or iy < -win or iy >= h:
            if level == 0:
                ok[i] = False
            continue
        x0 = ix - 1  # the source pixels read: x0 .. x0 + sf - 1, y0 .. y0 + win + 2
        y0 = iy - 1
        if x0 >= 0 and y0 >= 0 and x0 + sf <= w and y0 + win + 3 <= h:
            for y in range(win + 3):
                src = numba.uint64((y0 + y) * w + x0)
                dst = numba.uint64(y * sf)
                for x in range(sf):
                    raw[dst + numba.uint64(x)] = np.float32(flat_i[src + numba.uint64(x)])
        else:
            for y in range(win + 3):
                row = _reflect(y0 + y, h) * w
                for x in range(sf):
                    raw[y * sf + x] = np.float32(flat_i[row + _reflect(x0 + x, w)])
        for y in range(win + 2):
            f0 = numba.uint64(y * sf)
            f1 = f0 + numba.uint64(sf)
            g = numba.uint64(y * sg)
            for x in range(sg):
                k = numba.uint64(x)
                grid[g + k] = (raw[f0 + k] * w00 + raw[f0 + k + u1] * w01
                               + raw[f1 + k] * w10 + raw[f1 + k + u1] * w11)
        # The rounded values are integers (``np.floor`` of float32 keeps float32, exact below
        # 2**24); their products and sums are exact (float64 here, integers in the
        # iterations), so no summation order (SIMD, per-column partial sums, the alignment of
        # the buffers) changes a result. Sums in float32 would, and one and two threads would
        # then differ.
        a11 = 0.0
        a12 = 0.0
        a22 = 0.0
        if ix >= 0 and iy >= 0 and ix + win < w and iy + win < h:
            # Inside the image: the Scharr derivatives of the sampled window (sampling and
            # differencing are both linear: OpenCV's sampled derivative images).
            for y in range(win):
                g0 = numba.uint64(y * sg)
                g1 = g0 + numba.uint64(sg)
                g2 = g1 + numba.uint64(sg)
                o = numba.uint64(y * wc)
                for x in range(wc):
                    k = numba.uint64(x)
                    patch[o + k] = np.int32(np.floor(grid[g1 + k + u1] * c32 + rnd))
                    gx = np.float64(np.floor(
                        c3 * (grid[g0 + k + u2] - grid[g0 + k] + grid[g2 + k + u2] - grid[g2 + k])
                        + c10 * (grid[g1 + k + u2] - grid[g1 + k]) + rnd) * inside[k])
                    gy = np.float64(np.floor(
                        c3 * (grid[g2 + k] - grid[g0 + k] + grid[g2 + k + u2] - grid[g0 + k + u2])
                        + c10 * (grid[g2 + k + u1] - grid[g0 + k + u1]) + rnd) * inside[k])
                    grad_x[o + k] = np.int32(gx)
                    grad_y[o + k] = np.int32(gy)
                    a11 += gx * gx
                    a12 += gx * gy
                    a22 += gy * gy
        else:
            # The window reaches past the image: as OpenCV, the derivatives are those of the
            # image's pixels (its border reflected) and 0 outside the image, then sampled.
            for y in range(win + 1):
                out_y = iy + y < 0 or iy + y >= h
                f0 = y * sf
                f1 = f0 + sf
                f2 = f1 + sf
                for x in range(wc + 1):
                    k = y * sr + x
                    if out_y or ix + x < 0 or ix + x >= w:
                        edge_x[k] = 0.0
                        edge_y[k] = 0.0
                        continue
                    edge_x[k] = (c3 * (raw[f0 + x + 2] - raw[f0 + x] + raw[f2 + x + 2]
                                       - raw[f2 + x]) + c10 * (raw[f1 + x + 2] - raw[f1 + x]))
                    edge_y[k] = (c3 * (raw[f2 + x] - raw[f0 + x] + raw[f2 + x + 2]
                                       - raw[f0 + x + 2]) + c10 * (raw[f2 + x + 1]
                                                                   - raw[f0 + x + 1]))
            for y in range(win):
                o = y * wc
                e0 = y * sr
                e1 = e0 + sr
                for x in range(wc):
                    patch[o + x] = np.int32(math.floor(grid[(y + 1) * sg + x + 1] * c32 + rnd))
                    gx = math.floor(edge_x[e0 + x] * w00 + edge_x[e0 + x + 1] * w01
                                    + edge_x[e1 + x] * w10 + edge_x[e1 + x + 1] * w11 + rnd) \
                        * inside[x]
                    gy = math.floor(edge_y[e0 + x] * w00 + edge_y[e0 + x + 1] * w01
                                    + edge_y[e1 + x] * w10 + edge_y[e1 + x + 1] * w11 + rnd) \
                        * inside[x]
                    grad_x[o + x] = np.int32(gx)
                    grad_y[o + x] = np.int32(gy)
                    a11 += gx * gx
                    a12 += gx * gy
                    a22 += gy * gy
        a11 *= fixed
        a12 *= fixed
        a22 *= fixed
        det = a11 * a22 - a12 * a12
        disc = (a11 - a22) * (a11 - a22) + np.float32(4) * a12 * a12
        min_eigenvalue = (a22 + a11 - np.float32(math.sqrt(disc))) / np.float32(2 * win * win)
        if min_eigenvalue < min_eig or det < np.float32(1.1920929e-07):
            if level == 0:
                ok[i] = False
            continue
        inv_det = one / det
        nx -= half
        ny -= half
        last_x = np.float32(0.0)
        last_y = np.float32(0.0)
        for j in range(max_iter):
            jx, jy, w00, w01, w10, w11 = _bilinear(nx, ny)
            if jx < -win or jx >= w or jy < -win or jy >= h:
                if level == 0:
                    ok[i] = False
                break
            if jx >= 0 and jy >= 0 and jx + sr <= w and jy + win + 1 <= h:
                b1, b2 = _target_sums(flat_j, jy * w + jx, w, win, chunks, w00, w01, w10, w11,
                                      patch, grad_x, grad_y, lane_1, lane_2)
            else:
                for y in range(win + 1):
                    row = _reflect(jy + y, h) * w
                    for x in range(sr):
                        target[y * sr + x] = flat_j[row + _reflect(jx + x, w)]
                b1, b2 = _target_sums(target, 0, sr, win, chunks, w00, w01, w10, w11, patch,
                                      grad_x, grad_y, lane_1, lane_2)
            b1 *= fixed
            b2 *= fixed
            dx = (a12 * b2 - a22 * b1) * inv_det
            dy = (a12 * b1 - a11 * b2) * inv_det
            nx += dx
            ny += dy
            nxt[i, 0] = nx + half
            nxt[i, 1] = ny + half
            if dx * dx + dy * dy <= eps2:
                break
            if j > 0 and abs(dx + last_x) < 0.01 and abs(dy + last_y) < 0.01:
                nxt[i, 0] -= dx * np.float32(0.5)
                nxt[i, 1] -= dy * np.float32(0.5)
                break
            last_x = dx
            last_y = dy
