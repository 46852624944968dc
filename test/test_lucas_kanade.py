"""The pyramidal Lucas-Kanade kernel against OpenCV's, and the tracker's shared pyramids."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereo_vo_ros.estimation.camera import StereoCalibration
from stereo_vo_ros.tracking import tracker as tracker_module
from stereo_vo_ros.tracking.klt_checks import KLT_EPSILON_PX, lk_pass
from stereo_vo_ros.tracking.lucas_kanade import ImagePyramid, track

WIN = 13
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, KLT_EPSILON_PX)


def textured(shape=(240, 320), seed=0):
    """Return a smooth random texture (uint8) with corners at many scales."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(shape[0] // 4, shape[1] // 4)).astype(np.float32)
    img = cv2.resize(noise, shape[::-1], interpolation=cv2.INTER_CUBIC)
    img = cv2.GaussianBlur(img, (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min()) * 200 + 25
    return img.astype(np.uint8)


def shifted(img, dx, dy):
    """Return the image moved by (dx, dy) pixels (bicubic), borders reflected."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, img.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT_101)


def opencv(img0, img1, pts, guess, levels, win=WIN):
    """``cv2.calcOpticalFlowPyrLK`` with the tracker's settings: (N, 2) positions, (N,) status."""
    p = pts.astype(np.float32).reshape(-1, 1, 2)
    if guess is None:
        out, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p, None, winSize=(win, win),
                                              maxLevel=levels, criteria=CRITERIA)
    else:
        out, st, _ = cv2.calcOpticalFlowPyrLK(
            img0, img1, p, guess.astype(np.float32).reshape(-1, 1, 2).copy(),
            winSize=(win, win), maxLevel=levels, criteria=CRITERIA,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    return out.reshape(-1, 2), st.ravel().astype(bool)


@pytest.mark.parametrize('levels', [0, 1, 3])
@pytest.mark.parametrize('with_guess', [False, True])
@pytest.mark.parametrize('win', [WIN, 21])  # one and two chunks of window columns
def test_tracks_like_opencv_and_finds_the_true_shift(levels, with_guess, win):
    img0 = textured()
    shift = np.array([3.0, -2.0]) * (4 if levels == 3 else 1)  # whole pixels: an exact warp
    img1 = shifted(img0, *shift)
    pts = cv2.goodFeaturesToTrack(img0, 150, 0.01, 10).reshape(-1, 2)
    guess = pts + shift + 0.8 if with_guess else None
    ours, ok = track(ImagePyramid(img0), ImagePyramid(img1), pts, guess, levels, win,
                     30, KLT_EPSILON_PX)
    ref, ref_ok = opencv(img0, img1, pts, guess, levels, win)
    assert ours.dtype == np.float32 and ours.shape == pts.shape
    both = ok & ref_ok
    assert both.sum() > 0.8 * len(pts)
    assert np.count_nonzero(ok != ref_ok) <= 0.02 * len(pts)
    gap = np.linalg.norm(ours[both] - ref[both], axis=1)
    assert np.median(gap) < 1e-4 and np.percentile(gap, 90) < 1e-3
    # Both find the motion of the points whose window stays inside both images.
    away = both & np.all((pts > 12 + np.abs(shift).max()) & (pts < [320 - 12 - 14, 240 - 26]),
                         axis=1)
    err = np.linalg.norm(ours[away] - (pts[away] + shift), axis=1)
    assert np.median(err) < 0.01


def test_windows_past_the_border_read_it_as_opencv_does():
    """Points at the image's edge: the derivatives are 0 outside it, as OpenCV pads them."""
    img0 = textured(seed=1)
    img1 = shifted(img0, 1.4, 0.6)
    ys, xs = np.meshgrid(np.linspace(2, 237, 12), [1.5, 4.2, 7.0, 312.3, 317.8])
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    for levels, win in ((0, WIN), (2, WIN), (0, 21)):
        ours, ok = track(ImagePyramid(img0), ImagePyramid(img1), pts, None, levels, win, 30,
                         KLT_EPSILON_PX)
        ref, ref_ok = opencv(img0, img1, pts, None, levels, win)
        assert np.array_equal(ok, ref_ok)
        gap = np.linalg.norm(ours[ok] - ref[ok], axis=1)
        assert np.percentile(gap, 90) < 1e-3
    # Images smaller than the window: reads reflected more than once, as OpenCV pads them.
    small0, small1 = textured((9, 14), seed=2), textured((9, 14), seed=2)[:, ::-1].copy()
    grid = np.mgrid[-3:17:2.5, -3:12:2.5].reshape(2, -1).T
    ours, ok = track(ImagePyramid(small0), ImagePyramid(small1), grid, None, 0, WIN, 30,
                     KLT_EPSILON_PX)
    ref, ref_ok = opencv(small0, small1, grid, None, 0)
    assert np.array_equal(ok, ref_ok) and ok.sum() > 10
    assert np.percentile(np.linalg.norm(ours[ok] - ref[ok], axis=1), 90) < 1e-3


@pytest.mark.parametrize('win', [41, 61])  # three and four chunks of window columns
def test_large_windows_on_hard_edges_track_as_opencv(win):
    """The largest sums an iteration adds up: full-contrast edges over a large window."""
    yy, xx = np.mgrid[:300, :400]
    board = (((xx // 8) + (yy // 8)) % 2 * 255).astype(np.uint8)
    moved = cv2.warpAffine(board, np.float32([[1, 0, 1.3], [0, 1, 0.7]]), (400, 300),
                           flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REFLECT_101)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(40, 360, 200), rng.uniform(40, 260, 200)])
    ours, ok = track(ImagePyramid(board), ImagePyramid(moved), pts, None, 0, win, 30,
                     KLT_EPSILON_PX)
    ref, ref_ok = opencv(board, moved, pts, None, 0, win)
    assert np.array_equal(ok, ref_ok) and ok.sum() > 150
    assert np.max(np.linalg.norm(ours[ok] - ref[ok], axis=1)) < 0.01


def test_pyramid_levels_and_their_limit_follow_opencv():
    img = textured((50, 200))
    pyr = ImagePyramid(img)
    level = img
    for k in range(3):
        assert pyr.size(k) == level.shape[::-1]
        np.testing.assert_array_equal(pyr.level(k), level)
        assert not pyr.level(k).flags.writeable
        level = cv2.pyrDown(level)
    # Level 0 is the image itself (not a copy), which stays writable.
    assert np.shares_memory(pyr.level(0), img) and img.flags.writeable
    # OpenCV stops where a level would not be larger than the window (50 -> 25 -> 13 rows).
    for asked in range(5):
        top, _ = cv2.buildOpticalFlowPyramid(img, (WIN, WIN), asked)
        assert pyr.usable_levels(asked, WIN) == top
    with pytest.raises(ValueError):
        ImagePyramid(img.astype(np.float32))


def test_bad_points_fail_and_bad_pyramids_raise():
    img = textured()
    pyr = ImagePyramid(img)
    pts = np.array([[100.0, 100.0], [np.nan, 50.0], [-500.0, 10.0], [160.0, 120.0]])
    out, ok = track(pyr, pyr, pts, None, 2, WIN, 30, KLT_EPSILON_PX)
    assert ok.tolist() == [True, False, False, True]
    np.testing.assert_allclose(out[ok], pts[ok], atol=1e-3)  # the same image: no motion
    out, ok = track(pyr, pyr, np.zeros((0, 2)), None, 2, WIN, 30, KLT_EPSILON_PX)
    assert out.shape == (0, 2) and ok.shape == (0,)
    flat = ImagePyramid(np.full((240, 320), 90, np.uint8))
    _, ok = track(flat, flat, pts[:1], None, 0, WIN, 30, KLT_EPSILON_PX)
    assert not ok[0]  # no texture: the gradient matrix is singular
    with pytest.raises(ValueError):
        track(pyr, ImagePyramid(img[:200]), pts, None, 0, WIN, 30, KLT_EPSILON_PX)
    with pytest.raises(ValueError):
        track(pyr, pyr, pts, None, 0, 0, 30, KLT_EPSILON_PX)  # no window
    # lk_pass takes images or pyramids alike.
    img1 = shifted(img, 2.0, 1.0)
    a = lk_pass(img, img1, pts[[0, 3]], None, 1, WIN, 30)
    b = lk_pass(pyr, ImagePyramid(img1), pts[[0, 3]], None, 1, WIN, 30)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_tracker_builds_each_images_pyramid_once(monkeypatch):
    """The tracker's passes of a pair share pyramids; the next pair reuses the last pair's."""
    built = []

    class Counted(ImagePyramid):
        def __init__(self, image):
            super().__init__(image)
            built.append(image)

    monkeypatch.setattr(tracker_module, 'ImagePyramid', Counted)
    h, w = 240, 320
    p_left = np.array([[300.0, 0, 160.0, 0], [0, 300.0, 120.0, 0], [0, 0, 1, 0]])
    p_right = p_left.copy()
    p_right[0, 3] = -300.0 * 0.5
    calib = StereoCalibration.from_projections(p_left, p_right, w, h)
    scene = textured((h, w + 40), seed=3)
    pairs = [(np.ascontiguousarray(scene[:, 20 + k:20 + k + w]),
              np.ascontiguousarray(scene[:, 28 + k:28 + k + w])) for k in range(4)]
    tracker = tracker_module.StereoTracker()
    tracker.track(*pairs[0], calib)
    for k in (1, 2, 3):
        built.clear()
        last = tracker.last_pair()
        res = tracker.track(*pairs[k], calib)
        assert res.stats.n_tracked > 50
        left, right = tracker.last_pair()
        # Each image at most once: this pair's two (the last pair's were built before) and the
        # brightness-mapped ones, if any.
        assert len(built) == len({id(img) for img in built})
        assert sum(img is left for img in built) == 1 and sum(img is right for img in built) == 1
        if k > 1:  # the first pair's images were not tracked from, so had no pyramid
            assert not any(img is last[0] or img is last[1] for img in built)
        assert {id(p.image) for p in tracker._pyramids} == {id(left), id(right)}
