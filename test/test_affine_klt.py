"""
Tests of the affine refinement of KLT matches (``tracking/affine_klt.py``) with real OpenCV.

The images are an analytic texture (a sum of random sinusoids) seen through exact affine maps,
so the true match of every point is known to machine precision.
"""

from __future__ import annotations

import numpy as np
import pytest

from stereo_vo_ros.tracking.affine_klt import refine_affine
from stereo_vo_ros.tracking.klt_checks import lk_pass

W, H = 360, 240


def texture(x: np.ndarray, y: np.ndarray, seed: int = 3) -> np.ndarray:
    """Return the grey levels of a sinusoid texture at float pixel coordinates (20..235)."""
    rng = np.random.default_rng(seed)
    v = np.zeros(np.broadcast(x, y).shape)
    for _ in range(30):
        k = 2 * np.pi / rng.uniform(5.0, 25.0)
        t = rng.uniform(0, np.pi)
        v += rng.uniform(0.5, 1.0) * np.sin(k * np.cos(t) * x + k * np.sin(t) * y
                                            + rng.uniform(0, 2 * np.pi))
    return 128.0 + 100.0 * v / 8.0


def warped(M: np.ndarray, t: np.ndarray, gain: float = 1.0, bias: float = 0.0) -> np.ndarray:
    """uint8 image whose content at p in ``texture`` appears at M p + t."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    Minv = np.linalg.inv(M)
    qx, qy = xs - t[0], ys - t[1]
    v = texture(Minv[0, 0] * qx + Minv[0, 1] * qy, Minv[1, 0] * qx + Minv[1, 1] * qy)
    return np.clip(np.round(gain * v + bias), 0, 255).astype(np.uint8)


def grid_points() -> np.ndarray:
    """Points well inside the image (pixels)."""
    xs, ys = np.meshgrid(np.linspace(60, W - 60, 8), np.linspace(60, H - 60, 5))
    return np.stack([xs.ravel(), ys.ravel()], axis=1) + 0.37


def truth(M: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Where the affine map sends points of the unwarped image."""
    return pts @ M.T + t


@pytest.mark.parametrize('M', [np.array([[1.10, 0.0], [0.0, 1.10]]),    # approaching wall
                               np.array([[1.0, 0.08], [0.0, 1.12]]),    # road-like stretch
                               np.array([[0.95, 0.03], [-0.03, 0.95]])])  # receding, turning
def test_refinement_recovers_deformed_windows_better_than_translation_klt(M):
    t = np.array([3.3, -2.1])
    img0 = warped(np.eye(2), np.zeros(2))
    img1 = warped(M, t)
    pts = grid_points()
    true = truth(M, t, pts)
    klt, ok = lk_pass(img0, img1, pts, true + 0.6, 1, 21, 30)
    assert ok.all()
    refined, ok = refine_affine(img0, img1, pts, klt, win_size_px=15, iterations=5)
    assert ok.all()
    err_klt = np.linalg.norm(klt - true, axis=1)
    err_ref = np.linalg.norm(refined - true, axis=1)
    assert np.median(err_ref) < 0.03
    assert np.median(err_ref) < 0.5 * np.median(err_klt)
    assert refined.dtype == np.float64
    # Every second pixel of a 21-pixel window (the default) does as well, with its samples
    # weighted to the centre too.
    for sigma in (0.0, 5.0):
        sparse, ok = refine_affine(img0, img1, pts, klt, win_size_px=21, iterations=5,
                                   step_px=2, sigma_px=sigma)
        assert ok.all()
        assert np.median(np.linalg.norm(sparse - true, axis=1)) < 0.03


def test_horizontal_mode_fixes_the_row_and_fits_a_disparity_plane():
    # Right image of a slanted plane: disparity 14 px + 0.3 px per row (like a road).
    M = np.array([[1.0, 0.3], [0.0, 1.0]])
    t = np.array([-14.0 - 0.3 * 0.0, 0.0])
    left = warped(np.eye(2), np.zeros(2))
    right = warped(M, t)
    pts = grid_points()
    true = truth(M, t, pts)
    start = true + np.array([0.7, 0.4])  # a KLT result off the row
    refined, ok = refine_affine(left, right, pts, start, win_size_px=15, iterations=5,
                                horizontal=True)
    assert ok.all()
    np.testing.assert_array_equal(refined[:, 1], pts[:, 1])
    assert np.max(np.abs(refined[:, 0] - true[:, 0])) < 0.05


def test_brightness_change_does_not_move_the_match():
    M, t = np.array([[1.05, 0.0], [0.0, 1.05]]), np.array([1.5, 0.5])
    img0 = warped(np.eye(2), np.zeros(2))
    img1 = warped(M, t, gain=0.7, bias=30.0)
    pts = grid_points()
    true = truth(M, t, pts)
    refined, ok = refine_affine(img0, img1, pts, true + 0.5, win_size_px=15, iterations=5)
    assert ok.all()
    assert np.median(np.linalg.norm(refined - true, axis=1)) < 0.03


def test_failures_keep_the_start_and_inputs_are_not_modified():
    img0 = warped(np.eye(2), np.zeros(2))
    flat = np.full((H, W), 90, np.uint8)
    pts = grid_points()
    start = pts + 1.0
    before = start.copy()
    refined, ok = refine_affine(img0, flat, pts, start, horizontal=True)
    assert np.all(np.isfinite(refined))
    np.testing.assert_array_equal(start, before)  # caller's array untouched
    # Nothing to fit on a flat image: every point is refused and stays where it started.
    assert not ok.any()
    np.testing.assert_array_equal(refined, start)
    # A match that would jump farther than max_shift_px is refused.
    far = truth(np.eye(2), np.array([6.0, 0.0]), pts)
    img1 = warped(np.eye(2), np.array([6.0, 0.0]))
    refined, ok = refine_affine(img0, img1, pts, far - 1.5, max_shift_px=1.0)
    np.testing.assert_array_equal(refined[~ok], (far - 1.5)[~ok])
    assert not ok.all()
    out, ok = refine_affine(img0, img0, np.zeros((0, 2)), np.zeros((0, 2)))
    assert out.shape == (0, 2) and ok.shape == (0,)
    with pytest.raises(ValueError):  # one template per match
        refine_affine(img0, img1, pts[:3], far[:4])
    # Any memory layout of the points.
    out, ok = refine_affine(img0, img1, np.asfortranarray(pts), np.asfortranarray(far - 1.5),
                            max_shift_px=1.0)
    np.testing.assert_array_equal(out, refined)


def test_each_point_is_refined_on_its_own_for_any_image_type():
    """The tracker refines more matches than it keeps, and passes uint8 images: both exact."""
    M, t = np.array([[1.05, 0.02], [-0.01, 1.08]]), np.array([2.2, 1.4])
    img0, img1 = warped(np.eye(2), np.zeros(2)), warped(M, t)
    pts = grid_points()
    start = truth(M, t, pts) + 0.4
    refined, ok = refine_affine(img0, img1, pts, start, win_size_px=21, step_px=2)
    assert ok.all()
    some = np.array([3, 17, 18, 30])
    sub, sub_ok = refine_affine(img0, img1, pts[some], start[some], win_size_px=21, step_px=2)
    np.testing.assert_array_equal(sub, refined[some])
    as_float, _ = refine_affine(img0.astype(np.float32), img1.astype(np.float64), pts, start,
                                win_size_px=21, step_px=2)
    np.testing.assert_array_equal(as_float, refined)


def test_points_at_the_border_and_non_finite_inputs_do_not_break_it():
    """Windows past the image edge sample the replicated border; NaN points are refused."""
    img0 = warped(np.eye(2), np.zeros(2))
    img1 = warped(np.eye(2), np.array([1.5, 0.0]))
    edge = np.array([[2.0, 2.0], [W - 1.5, H - 3.0], [W / 2, 0.0], [np.nan, 50.0],
                     [80.0, 60.0]])
    start = edge + [1.5, 0.0]
    start[4] = [np.inf, 60.0]
    refined, ok = refine_affine(img0, img1, edge, start, win_size_px=21)
    assert not ok[3] and not ok[4]
    np.testing.assert_array_equal(refined[~ok], start[~ok])
    assert np.all(np.abs(refined[ok] - start[ok]) <= 2.0)
    # Far outside the image: every sample is the border, nothing to fit, nothing crashes.
    out, ok = refine_affine(img0, img1, np.array([[-5e3, 1e9]]), np.array([[1e12, -3e3]]))
    assert not ok.any()


@pytest.mark.parametrize('horizontal, win, sigma, edge', [
    (True, 15, 3.0, 5.0),    # a stereo window (the match along the row)
    (False, 21, 5.0, 7.0)])  # a temporal window (the default weighting)
def test_centre_weighting_lets_a_nearer_surface_in_the_window_pull_less(
        horizontal, win, sigma, edge):
    """
    A window on a far surface whose side shows a nearer one (an object's border).

    The far texture moves by 2 px between the images; a nearer surface with its own texture
    moves by 5 px and fills the window's columns from ``edge`` px left of the point. With every
    sample alike the match is pulled towards the nearer surface's motion by about half a pixel;
    weighting the samples by their distance to the centre pulls it less, and leaves matches
    without a border where they were.
    """
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    pts = grid_points()
    far_d, near_d = 2.0, 5.0
    near_from, near_to = np.zeros((H, W), bool), np.zeros((H, W), bool)
    for x, y in pts:  # the nearer surface in the first image, and in the second one
        rows = np.abs(ys - y) < 12
        near_from |= rows & (xs < x - edge) & (xs > x - 20.0)
        near_to |= rows & (xs < x - edge - near_d) & (xs > x - 20.0 - near_d)
    img0 = np.where(near_from, texture(xs, ys, seed=5), texture(xs, ys))
    img1 = np.where(near_to, texture(xs + near_d, ys, seed=5), texture(xs + far_d, ys))
    img0, img1 = (np.clip(np.round(v), 0, 255).astype(np.uint8) for v in (img0, img1))
    true = pts - np.array([far_d, 0.0])
    start = true + np.array([0.3, 0.0 if horizontal else 0.2])
    err = {}
    for s in (0.0, sigma):
        out, ok = refine_affine(img0, img1, pts, start, win_size_px=win, iterations=5,
                                horizontal=horizontal, step_px=2, sigma_px=s)
        assert ok.all()
        err[s] = out - true
    # Pulled towards the nearer surface: the match lies left (a stereo disparity too large).
    assert np.median(err[0.0][:, 0]) < -0.3
    dist = {s: np.median(np.linalg.norm(e, axis=1)) for s, e in err.items()}
    assert dist[sigma] < 0.5 * dist[0.0]
    # Without a border in the window the weighting changes nothing that matters.
    plain = warped(np.eye(2), np.zeros(2))
    shifted = warped(np.eye(2), np.array([-far_d, 0.0]))
    for s in (0.0, sigma):
        out, ok = refine_affine(plain, shifted, pts, start, win_size_px=win, iterations=5,
                                horizontal=horizontal, step_px=2, sigma_px=s)
        assert ok.all()
        assert np.abs(out - true).max() < 0.03
