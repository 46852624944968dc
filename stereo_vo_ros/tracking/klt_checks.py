"""
KLT passes and the consistency checks of the light adaptive feature tracking paper (Huang et al.).

One pyramidal Lucas-Kanade pass (``lk_pass``, on pyramids ``lucas_kanade`` builds once per image);
the checks are pure functions on the points it returns:

* forward-backward check (eq. 4) and left-right check (eq. 5): ``round_trip_error`` below the
  threshold delta1 / delta2;
* disparity constraint (eq. 6): ``disparity_constraint`` (|y_left - y_right| < delta3 on
  rectified input, the distance to the epipolar line on raw input);
* plausible disparity: ``disparity_in_range``;
* light bi-circular check (eq. 7): ``bicircular_error`` in its two readings (``roundtrip`` and
  ``closure``, see the function);
* aperture check (not in the paper): ``eigen_ratio`` of the KLT window's gradient matrix, small
  on straight edges, where KLT only fixes the displacement across the edge; and its
  flow-aligned form ``flow_edge_ratio``, small where the window's structure runs along the
  expected flow (lane lines, which point at the focus of expansion).

``CheckSet.for_variant`` maps the ablation variants of the paper (Tables I and II) to the checks
that run. Pixel coordinates are (x right, y down) in the image named by each argument; ``raw``
means the pixels of the image as given to the tracker, ``ideal`` the undistorted pinhole pixels
of the calibration (identical on rectified input).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .lucas_kanade import finite_rows, ImagePyramid, track
from ..config import TRACKER_VARIANTS
from ..errors import ConfigError
from ..estimation.camera import StereoCalibration
from ..jit import image_signatures, kernel, kernel_image, readonly

#: Convergence threshold of one KLT iteration (pixels), as VINS-Fusion uses.
KLT_EPSILON_PX = 0.01
#: Default border of ``inside_image`` (pixels).
BORDER_PX = 1.0
#: Pyramid levels of the reverse passes (forward-backward, left-right, bi-circular return);
#: they start at the point they should return to, so the base image suffices.
REVERSE_PYRAMID_LEVELS = 0
#: The two readings of eq. 7.
BICIRCULAR_MODES = ('roundtrip', 'closure')


@dataclass(frozen=True)
class CheckSet:
    """
    Which checks run (the forward-backward and left-right checks always run).

    Attributes
    ----------
    disparity_constraint : bool
        Apply eq. 6 after the stereo forward pass, before the left-right reverse pass.
    bicircular : bool
        Apply the light bi-circular check (eq. 7).
    adaptive : bool
        Use the adaptive threshold of eq. 8 for the bi-circular check instead of a fixed one.

    """

    disparity_constraint: bool
    bicircular: bool
    adaptive: bool

    @classmethod
    def for_variant(cls, variant: str) -> 'CheckSet':
        """
        Return the checks of one ablation variant of the paper.

        ``baseline`` (VINS-Fusion: forward-backward + left-right), ``dc`` (+ disparity
        constraint), ``bc`` (+ bi-circular check, fixed threshold), ``db`` (dc + bc, fixed
        threshold), ``full`` (dc + bc with the adaptive threshold).

        Raises
        ------
        ConfigError
            Unknown variant name.

        """
        table = {
            'baseline': cls(False, False, False),
            'dc': cls(True, False, False),
            'bc': cls(False, True, False),
            'db': cls(True, True, False),
            'full': cls(True, True, True),
        }
        if variant not in table:
            raise ConfigError(
                f'tracker.variant must be one of {list(TRACKER_VARIANTS)}, got {variant!r}')
        return table[variant]


def lk_pass(img_from: np.ndarray | ImagePyramid, img_to: np.ndarray | ImagePyramid,
            pts: np.ndarray, guess: np.ndarray | None, levels: int, win_size_px: int,
            max_iterations: int, border_px: float | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """
    Track points from one image into another with pyramidal KLT (``lucas_kanade.track``).

    Parameters
    ----------
    img_from, img_to : np.ndarray or ImagePyramid
        (H, W) uint8 grey images, or their pyramids (built once, shared between passes).
    pts : np.ndarray
        (N, 2) float pixel positions in ``img_from`` (raw pixels).
    guess : np.ndarray or None
        (N, 2) float initial positions in ``img_to`` (raw pixels), used as the initial flow;
        None starts every point at its position in ``img_from``.
    levels : int
        Pyramid levels above the base image (0: base image only).
    win_size_px : int
        Side of the square KLT window (pixels).
    max_iterations : int
        Iterations per pyramid level.
    border_px : float or None
        Tracked points must lie this far inside ``img_to`` (pixels); None: half the window,
        so that the whole KLT window lies inside the image (a window that sticks out of the
        image biases the result by tenths of a pixel).

    Returns
    -------
    tracked : np.ndarray
        (N, 2) float32 positions in ``img_to`` (raw pixels); rows that failed hold the input.
    ok : np.ndarray
        (N,) bool: KLT converged and the point lies inside ``img_to``.

    """
    n = len(pts)
    src = np.ascontiguousarray(pts, np.float32).reshape(n, 2)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    win = int(win_size_px)
    pyr_from, pyr_to = (p if isinstance(p, ImagePyramid) else ImagePyramid(p)
                        for p in (img_from, img_to))
    init = None
    if guess is not None:
        init = np.array(guess, np.float32).reshape(n, 2)
        bad = ~finite_rows(init)
        init[bad] = src[bad]
    tracked, ok = track(pyr_from, pyr_to, src, init, int(levels), win, int(max_iterations),
                        KLT_EPSILON_PX)
    border = win_size_px // 2 if border_px is None else border_px
    ok &= inside_image(tracked, pyr_to.image.shape[::-1], border)
    tracked = np.where(ok[:, None], tracked, src).astype(np.float32)
    return tracked, ok


def inside_image(pts: np.ndarray, size: tuple[int, int], border_px: float = BORDER_PX
                 ) -> np.ndarray:
    """Return (N,) bool: finite points at least ``border_px`` inside a (width, height) image."""
    pts = np.asarray(pts).reshape(-1, 2)
    w, h = size
    x, y = pts[:, 0], pts[:, 1]
    # NaN and inf fail the bounds (a comparison with NaN is False, and warns of nothing).
    return (x >= border_px) & (y >= border_px) & (x <= w - 1 - border_px) & \
        (y <= h - 1 - border_px)


def gradient_matrix(img: np.ndarray, pts: np.ndarray, win_size_px: int, sobel: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    KLT gradient matrix ``G = sum [gx^2, gx gy; gx gy, gy^2]`` over square windows.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image.
    pts : np.ndarray
        (N, 2) float pixel positions (x, y) of the window centres (rounded to pixels).
    win_size_px : int
        Side of the square window (pixels).
    sobel : bool
        Gradients from the 3x3 Sobel operator (central differences smoothed across, scaled to
        grey levels per pixel) instead of plain central differences: the pixel steps of a thin
        oblique line then add little gradient along the line.

    Returns
    -------
    gxx, gxy, gyy : np.ndarray
        (N,) float64 entries of G; 0 where a point is not finite.
    ok : np.ndarray
        (N,) bool, the point is finite.

    """
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(pts), axis=1)
    centre = np.where(ok[:, None], np.round(pts), 0.0).astype(np.int64)
    sums = np.zeros((len(pts), 3))
    _gradient_sums(kernel_image(img), centre, ok, int(win_size_px) // 2, bool(sobel), sums)
    return sums[:, 0], sums[:, 1], sums[:, 2], ok


@kernel(image_signatures(lambda img: numba.types.void(
    img, readonly(numba.types.int64, 2), readonly(numba.types.boolean, 1), numba.types.int64,
    numba.types.boolean, numba.types.Array(numba.types.float64, 2, 'C'))))
def _gradient_sums(img, centre, ok, half, sobel, out):
    """
    ``gradient_matrix`` entries (gxx, gxy, gyy) of the windows at integer centres, into ``out``.

    Pixels outside the image repeat its border. The gradients are sums of grey levels scaled by
    a power of two, exactly what OpenCV's float filters give; their products are summed in
    float64.
    """
    h, w = img.shape
    for i in range(len(centre)):
        if not ok[i]:
            continue
        sxx = sxy = syy = 0.0
        for dy in range(-half, half + 1):
            y = centre[i, 1] + dy
            ym, y0, yp = (min(max(y - 1, 0), h - 1), min(max(y, 0), h - 1),
                          min(max(y + 1, 0), h - 1))
            for dx in range(-half, half + 1):
                x = centre[i, 0] + dx
                xm, x0, xp = (min(max(x - 1, 0), w - 1), min(max(x, 0), w - 1),
                              min(max(x + 1, 0), w - 1))
                if sobel:  # the central difference smoothed with (1, 2, 1) across, / 8
                    gx = 0.125 * ((float(img[ym, xp]) - float(img[ym, xm]))
                                  + 2.0 * (float(img[y0, xp]) - float(img[y0, xm]))
                                  + (float(img[yp, xp]) - float(img[yp, xm])))
                    gy = 0.125 * ((float(img[yp, xm]) - float(img[ym, xm]))
                                  + 2.0 * (float(img[yp, x0]) - float(img[ym, x0]))
                                  + (float(img[yp, xp]) - float(img[ym, xp])))
                else:
                    gx = 0.5 * (float(img[y0, xp]) - float(img[y0, xm]))
                    gy = 0.5 * (float(img[yp, x0]) - float(img[ym, x0]))
                sxx += gx * gx
                sxy += gx * gy
                syy += gy * gy
        out[i, 0], out[i, 1], out[i, 2] = sxx, sxy, syy


def eigen_ratio(img: np.ndarray, pts: np.ndarray, win_size_px: int) -> np.ndarray:
    """
    Conditioning of the KLT window: smaller / larger eigenvalue of its gradient matrix.

    KLT solves ``G d = b`` with the gradient matrix ``G = sum [gx^2, gx gy; gx gy, gy^2]`` over
    the window; on a straight edge (a lane line, a kerb) ``G`` is nearly singular and the
    displacement along the edge is fixed by the initial flow, not by the image (aperture
    problem). The ratio is scale-free (independent of contrast): 1 for an isotropic corner,
    0 for a perfect edge or a flat window. Lowe's edge test (SIFT, r = 10) rejects ratios
    below 0.1.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image.
    pts : np.ndarray
        (N, 2) float pixel positions (x, y) of the window centres (rounded to pixels).
    win_size_px : int
        Side of the square KLT window (pixels).

    Returns
    -------
    np.ndarray
        (N,) float64 ratio in [0, 1]; 0 for a window without gradient.

    """
    if len(np.asarray(pts).reshape(-1, 2)) == 0:
        return np.zeros(0)
    a, b, c, _ = gradient_matrix(img, pts, win_size_px)
    disc = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    lmax = 0.5 * (a + c) + disc
    lmin = np.maximum(0.5 * (a + c) - disc, 0.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(lmax > 0, lmin / lmax, 0.0)


def aperture_checks(img: np.ndarray, pts: np.ndarray, flow: np.ndarray | None,
                    win_size_px: int, flow_win_size_px: int, min_eigen_ratio: float,
                    min_flow_edge_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Which KLT windows are well conditioned: ``eigen_ratio`` and ``flow_edge_ratio`` tests.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image holding the windows.
    pts : np.ndarray
        (N, 2) float pixel positions of the window centres.
    flow : np.ndarray or None
        (N, 2) expected displacements (pixels), or None (no flow test).
    win_size_px, flow_win_size_px : int
        Window sides of the two tests (pixels).
    min_eigen_ratio, min_flow_edge_ratio : float
        Thresholds (0: that test is off).

    Returns
    -------
    eigen_ok, flow_ok : np.ndarray
        (N,) bool each; a test that is off passes every point. Every point is tested by both
        (per point, so the same values as testing only the points the other one passed).

    """
    n = len(np.asarray(pts).reshape(-1, 2))
    eigen_ok = np.ones(n, bool)
    flow_ok = np.ones(n, bool)
    if min_eigen_ratio > 0 and n:
        eigen_ok = eigen_ratio(img, pts, win_size_px) >= min_eigen_ratio
    if flow is not None and min_flow_edge_ratio > 0 and n:
        flow_ok = flow_edge_ratio(img, pts, flow, flow_win_size_px) >= min_flow_edge_ratio
    return eigen_ok, flow_ok


def flow_edge_ratio(img: np.ndarray, pts: np.ndarray, flow: np.ndarray,
                    win_size_px: int, min_flow_px: float = 1.0) -> np.ndarray:
    """
    Gradient energy of the KLT window along the expected flow over that across it.

    With ``u`` the unit flow direction and ``v`` its normal, the ratio is ``u^T G u / v^T G v``
    (``G`` from ``gradient_matrix`` with Sobel gradients: with plain central differences the
    pixel steps of a thin line drawn obliquely count as structure along it): about 0 when the
    window holds an edge or a line parallel to the flow, 1 for an isotropic corner, large for
    an edge across the flow. A window that
    is edge-like along its own flow fixes the match across the flow only; along it the match
    slides, and the slide looks like a change of speed, so RANSAC keeps it. On a road lane
    lines and their dashes point at the focus of expansion, i.e. along the flow: on the
    rendered highway (seed 6), 43 % of the inliers with a ratio below 0.1 were more than 1 px
    off their true position along the flow, against 3 % above 0.4.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image holding the windows.
    pts : np.ndarray
        (N, 2) float pixel positions (x, y) of the window centres (rounded to pixels).
    flow : np.ndarray
        (N, 2) expected displacement of each point (pixels); only its direction is used.
    win_size_px : int
        Side of the square window (pixels).
    min_flow_px : float
        Below this expected displacement (pixels) the direction is meaningless and the ratio
        is ``inf`` (the point passes any threshold); likewise for a non-finite flow.

    Returns
    -------
    np.ndarray
        (N,) float64 ratio >= 0; 0 for a window without gradient.

    """
    flow = np.asarray(flow, np.float64).reshape(-1, 2)
    if len(flow) == 0:
        return np.zeros(0)
    a, b, c, _ = gradient_matrix(img, pts, win_size_px, sobel=True)
    norm = np.linalg.norm(flow, axis=1)
    moving = np.isfinite(norm) & (norm >= min_flow_px)
    u = np.where(moving[:, None], flow, [1.0, 0.0]) / np.where(moving, norm, 1.0)[:, None]
    along = a * u[:, 0] ** 2 + 2.0 * b * u[:, 0] * u[:, 1] + c * u[:, 1] ** 2
    across = a * u[:, 1] ** 2 - 2.0 * b * u[:, 0] * u[:, 1] + c * u[:, 0] ** 2
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = np.where(across > 0, along / across, 0.0)
    return np.where(moving, np.maximum(ratio, 0.0), np.inf)


def round_trip_error(start: np.ndarray, returned: np.ndarray) -> np.ndarray:
    """
    Distance between a point and its reverse point (pixels), eqs. 4, 5 and 7.

    Parameters
    ----------
    start, returned : np.ndarray
        (N, 2) float pixel positions in the same image.

    Returns
    -------
    np.ndarray
        (N,) float64 Euclidean distance (pixels); ``inf`` where an input is not finite.

    """
    d = np.asarray(start, np.float64) - np.asarray(returned, np.float64)
    d *= d
    d = np.sqrt(d[:, 0] + d[:, 1])  # the 2-norm of each row, as np.linalg.norm sums it
    return np.where(np.isfinite(d), d, np.inf)


def disparity_constraint(calib: StereoCalibration, left_ideal: np.ndarray,
                         right_ideal: np.ndarray, threshold_px: float) -> np.ndarray:
    """
    Disparity constraint of eq. 6: the stereo match lies near its epipolar line.

    Parameters
    ----------
    calib : StereoCalibration
        The stereo calibration; rectified input tests |y_left - y_right|, raw input the
        distance to the epipolar line of the calibrated fundamental matrix.
    left_ideal, right_ideal : np.ndarray
        (N, 2) float ideal (undistorted) pixel positions in the left and right image at t2.
    threshold_px : float
        delta3 (pixels).

    Returns
    -------
    np.ndarray
        (N,) bool, True where the match passes.

    """
    if len(left_ideal) == 0:
        return np.zeros(0, bool)
    d = calib.epipolar_distance(left_ideal, right_ideal)
    return np.isfinite(d) & (d < threshold_px)


def disparity_in_range(calib: StereoCalibration, left_ideal: np.ndarray,
                       right_ideal: np.ndarray, min_px: float, max_px: float) -> np.ndarray:
    """
    Reject negative and implausible disparities.

    Parameters
    ----------
    calib : StereoCalibration
        The stereo calibration (the disparity is measured in its rectified geometry).
    left_ideal, right_ideal : np.ndarray
        (N, 2) float ideal pixel positions (left and right image of the same instant).
    min_px, max_px : float
        Accepted disparity range x_left - x_right (pixels); the minimum is exclusive.

    Returns
    -------
    np.ndarray
        (N,) bool, True where ``min_px < disparity <= max_px``.

    """
    if len(left_ideal) == 0:
        return np.zeros(0, bool)
    d = calib.disparity(left_ideal, right_ideal)
    with np.errstate(invalid='ignore'):
        return np.isfinite(d) & (d > min_px) & (d <= max_px)


def bicircular_error(mode: str, right_t2: np.ndarray, back_t1: np.ndarray,
                     stored_t1: np.ndarray, again_t2: np.ndarray | None) -> np.ndarray:
    """
    Error of the light bi-circular check (eq. 7) in one of its two readings.

    ``roundtrip`` tracks right(t2) -> right(t1) -> right(t2) and measures the distance of the
    returned point to the start (``again_t2`` vs ``right_t2``); ``closure`` tracks right(t2) ->
    right(t1) once and measures the distance to the right(t1) point stored for the feature in
    the previous frame (``back_t1`` vs ``stored_t1``), which closes the loop
    left(t1) -> left(t2) -> right(t2) -> right(t1) -> left(t1).

    Parameters
    ----------
    mode : str
        ``roundtrip`` or ``closure``.
    right_t2 : np.ndarray
        (N, 2) float raw pixel positions in the right image at t2 (the stereo matches).
    back_t1 : np.ndarray
        (N, 2) float raw positions of ``right_t2`` tracked into the right image at t1.
    stored_t1 : np.ndarray
        (N, 2) float raw positions of the features in the right image at t1 (previous frame).
    again_t2 : np.ndarray or None
        (N, 2) float raw positions of ``back_t1`` tracked back into the right image at t2
        (``roundtrip`` only).

    Returns
    -------
    np.ndarray
        (N,) float64 error (pixels).

    Raises
    ------
    ConfigError
        Unknown mode, or ``roundtrip`` without ``again_t2``.

    """
    if mode == 'closure':
        return round_trip_error(stored_t1, back_t1)
    if mode == 'roundtrip':
        if again_t2 is None:
            raise ConfigError('bicircular_mode roundtrip needs the points tracked back to t2')
        return round_trip_error(right_t2, again_t2)
    raise ConfigError(
        f'tracker.bicircular_mode must be one of {list(BICIRCULAR_MODES)}, got {mode!r}')
