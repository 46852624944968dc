"""
Tests of the stereo KLT tracker (Huang et al.) with real OpenCV.

Synthetic stereo pairs are rendered from an analytic texture (a sum of random sinusoids), so
sub-pixel shifts, disparities, lens distortion and plane-induced homographies are exact and the
true position of every feature is known. The KITTI clips in /work/shared/data check the
quadruples against the ground-truth motion (skipped when the data are absent).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import threading

import cv2
import numpy as np
import pytest

from stereo_vo_ros.config import BucketingConfig, TRACKER_VARIANTS, TrackerConfig
from stereo_vo_ros.errors import ConfigError, ImageError
from stereo_vo_ros.estimation.camera import CameraModel, StereoCalibration
from stereo_vo_ros.parallel import inline, Workers
from stereo_vo_ros.tracking import bucketing, photometric
from stereo_vo_ros.tracking.adaptive_threshold import adaptive_threshold, bicircular_threshold
from stereo_vo_ros.tracking.detection import detect_corners
from stereo_vo_ros.tracking.klt_checks import (aperture_checks, bicircular_error, CheckSet,
                                               disparity_constraint, eigen_ratio,
                                               flow_edge_ratio, gradient_matrix, inside_image,
                                               round_trip_error)
from stereo_vo_ros.tracking.lucas_kanade import finite_rows
from stereo_vo_ros.tracking.replenish import replenish, ReplenishJob
from stereo_vo_ros.tracking.tracker import StereoTracker

W, H = 400, 300
FOCAL = 300.0
BASELINE = 0.1
DISPARITY = 12.4  # pixels, fronto-parallel plane at FOCAL * BASELINE / DISPARITY metres


# -- synthetic scenes ----------------------------------------------------------------------
def texture(x: np.ndarray, y: np.ndarray, seed: int, period_x: float | None = None
            ) -> np.ndarray:
    """Analytic grey texture at float pixel coordinates (values about 20..235)."""
    rng = np.random.default_rng(seed)
    n = 40
    if period_x is None:
        wavelength = rng.uniform(6.0, 30.0, n)
        theta = rng.uniform(0, np.pi, n)
        kx, ky = 2 * np.pi / wavelength * np.cos(theta), 2 * np.pi / wavelength * np.sin(theta)
    else:
        kx = 2 * np.pi * rng.integers(1, 3, n) / period_x * rng.choice([-1, 1], n)
        ky = 2 * np.pi * rng.uniform(-1 / 6, 1 / 6, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    amp = rng.uniform(0.5, 1.0, n)
    v = np.zeros(np.broadcast(x, y).shape)
    for i in range(n):
        v += amp[i] * np.sin(kx[i] * x + ky[i] * y + phase[i])
    return 128.0 + 107.0 * v / np.abs(amp).sum() * 3.0


def render(shift: tuple[float, float], seed: int = 1, period_x: float | None = None,
           size: tuple[int, int] = (W, H)) -> np.ndarray:
    """uint8 image of the texture moved by ``shift`` (content at p appears at p + shift)."""
    ys, xs = np.mgrid[0:size[1], 0:size[0]].astype(np.float64)
    v = texture(xs - shift[0], ys - shift[1], seed, period_x)
    return np.clip(np.round(v), 0, 255).astype(np.uint8)


def pair(motion: tuple[float, float], seed: int = 1, period_x: float | None = None,
         size: tuple[int, int] = (W, H)) -> tuple[np.ndarray, np.ndarray]:
    """Rectified pair of a fronto-parallel textured plane moved by ``motion`` (pixels)."""
    left = render(motion, seed, period_x, size)
    right = render((motion[0] - DISPARITY, motion[1]), seed, period_x, size)
    return left, right


def rectified_calib(size: tuple[int, int] = (W, H)) -> StereoCalibration:
    """Rectified calibration: focal FOCAL, principal point at the centre, baseline BASELINE."""
    w, h = size
    P0 = np.array([[FOCAL, 0, w / 2], [0, FOCAL, h / 2], [0, 0, 1.0]])
    P0 = np.hstack([P0, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -FOCAL * BASELINE
    return StereoCalibration.from_projections(P0, P1, w, h)


#: KLT window of these tests (pixels). They check exactness on a rigidly shifted texture, where
#: a larger window averages more texture; the default (13 px, chosen for deforming road
#: surfaces) is checked on the same shift by ``test_default_windows_on_a_pure_shift``.
WIN_PX = 21


def config(**kw) -> TrackerConfig:
    """Tracker configuration with the defaults of the paper, 21-pixel windows, and overrides."""
    kw.setdefault('win_size_px', WIN_PX)
    return TrackerConfig(**kw)


def shift_prior(delta: tuple[float, float]):
    """Motion prior predicting a pure image shift of both cameras."""
    def prior(prev_left: np.ndarray, prev_right: np.ndarray):
        return prev_left + np.array(delta), prev_right + np.array(delta)
    return prior


def shift_errors(c, delta: tuple[float, float]) -> list[np.ndarray]:
    """Absolute errors (N, 2) of prev right, cur left and cur right after a pure ``pair`` shift."""
    p = c.prev_left
    d = np.array([DISPARITY, 0.0])
    return [np.abs(got - want) for got, want in ((c.prev_right, p - d), (c.cur_left, p + delta),
                                                 (c.cur_right, p + delta - d))]


def inside(points: np.ndarray, box: tuple[float, float, float, float], margin: float
           ) -> np.ndarray:
    """(N,) bool: points inside box (x0, y0, x1, y1) shrunk by margin."""
    x0, y0, x1, y1 = box
    return (points[:, 0] > x0 + margin) & (points[:, 0] < x1 - margin) & \
        (points[:, 1] > y0 + margin) & (points[:, 1] < y1 - margin)


def patch(img: np.ndarray, replacement: np.ndarray, box: tuple[int, int, int, int]
          ) -> np.ndarray:
    """Copy of img with the box (x0, y0, x1, y1) taken from replacement."""
    out = img.copy()
    x0, y0, x1, y1 = box
    out[y0:y1, x0:x1] = replacement[y0:y1, x0:x1]
    return out


def noise(seed: int, size: tuple[int, int] = (W, H)) -> np.ndarray:
    """Blurred uint8 pixel noise: a texture that no KLT window matches consistently."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, (size[1], size[0])).astype(np.float32)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 1.2) * 2.5 - 190, 0, 255).astype(np.uint8)


def assert_finite(result) -> None:
    """Every output array is finite float64."""
    c = result.correspondences
    for arr in (c.prev_left, c.prev_right, c.cur_left, c.cur_right, result.features_left_raw,
                result.features_right_raw):
        assert arr.dtype == np.float64
        assert np.all(np.isfinite(arr))


M1, M2, M3 = (0.0, 0.0), (2.3, -1.7), (4.1, -2.9)
BOX = (140, 90, 270, 210)  # corrupted region (x0, y0, x1, y1)
MARGIN = 16.0  # half a KLT window plus the motion


# -- accuracy --------------------------------------------------------------------------
@pytest.mark.parametrize('use_prior', [False, True])
def test_quadruples_match_true_positions(use_prior):
    calib = rectified_calib()
    tracker = StereoTracker(config(), BucketingConfig())
    first = tracker.track(*pair(M1), calib)
    assert first.stats.initialized and len(first.correspondences) == 0
    assert first.stats.n_features > 100
    delta = (M2[0] - M1[0], M2[1] - M1[1])
    res = tracker.track(*pair(M2), calib, shift_prior(delta) if use_prior else None)
    c = res.correspondences
    assert res.stats.used_prior == use_prior
    assert len(c) > 0.9 * first.stats.n_features
    for err in shift_errors(c, delta):
        assert err.max() < 0.1
    assert_finite(res)
    assert np.all(c.ages == 1)
    # A third frame: the same ids, older.
    res3 = tracker.track(*pair(M3), calib)
    kept = np.isin(res3.correspondences.ids, c.ids)
    assert kept.sum() > 0.9 * len(c)
    assert np.all(res3.correspondences.ages[kept] == 2)
    np.testing.assert_allclose(
        res3.correspondences.prev_left[kept],
        c.cur_left[np.searchsorted(c.ids, res3.correspondences.ids[kept])])


def zoomed_pair(scale: float, disparity: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the rectified pair of the textured plane ``scale`` times closer (zoom about c)."""
    cx, cy = W / 2, H / 2
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)

    def plane(x, y):
        v = texture(cx + (x - cx) / scale, cy + (y - cy) / scale, seed=1)
        return np.clip(np.round(v), 0, 255).astype(np.uint8)
    return plane(xs, ys), plane(xs + scale * disparity, ys)


def test_affine_refinement_tracks_an_approaching_plane_more_precisely():
    # The plane comes 9 % closer between the pairs: every KLT window grows by 9 % and the
    # disparity with it. Translational KLT matches it to 0.19 px (median), the affine
    # refinement fits the growth (0.009 px).
    calib = rectified_calib()
    scale = 1.09
    c = np.array([W / 2, H / 2])
    errors = {}
    for refine in (False, True):
        tracker = StereoTracker(config(affine_refinement=refine), BucketingConfig())
        tracker.track(*zoomed_pair(1.0, DISPARITY), calib)

        def prior(prev_left, prev_right):
            cur = c + scale * (prev_left - c)
            return cur, cur - [scale * DISPARITY, 0.0]
        res = tracker.track(*zoomed_pair(scale, DISPARITY), calib, prior)
        q = res.correspondences
        assert len(q) > 80
        want_left = c + scale * (q.prev_left - c)
        want_right = want_left - [scale * DISPARITY, 0.0]
        errors[refine] = np.concatenate([np.linalg.norm(q.cur_left - want_left, axis=1),
                                         np.linalg.norm(q.cur_right - want_right, axis=1)])
        assert_finite(res)
    assert np.median(errors[True]) < 0.2 * np.median(errors[False])
    assert np.percentile(errors[True], 95) < np.percentile(errors[False], 95)
    assert np.median(errors[True]) < 0.03


def test_default_windows_on_a_pure_shift():
    """The default 13-pixel windows track a rigid shift to a few hundredths of a pixel."""
    assert TrackerConfig().win_size_px == 13
    calib = rectified_calib()
    delta = (M2[0] - M1[0], M2[1] - M1[1])
    for prior in (None, shift_prior(delta)):
        tracker = StereoTracker(TrackerConfig(), BucketingConfig())
        first = tracker.track(*pair(M1), calib)
        c = tracker.track(*pair(M2), calib, prior).correspondences
        assert len(c) > 0.9 * first.stats.n_features
        for err in shift_errors(c, delta):
            assert np.median(err) < 0.02
            assert err.max() < 0.3


def test_prior_switch_and_bad_predictions():
    calib = rectified_calib()
    delta = (M2[0] - M1[0], M2[1] - M1[1])
    off = StereoTracker(config(use_motion_prior=False))
    off.track(*pair(M1), calib)
    assert not off.track(*pair(M2), calib, shift_prior(delta)).stats.used_prior

    def nan_rows(prev_left, prev_right):  # every other prediction unusable
        cur_l, cur_r = prev_left + delta, prev_right + delta
        cur_l[::2] = np.nan
        return cur_l, cur_r

    def wrong_shape(prev_left, prev_right):
        return prev_left[:3], prev_right[:3]

    for prior, used in ((nan_rows, True), (wrong_shape, False)):
        tracker = StereoTracker(config())
        first = tracker.track(*pair(M1), calib)
        res = tracker.track(*pair(M2), calib, prior)
        assert res.stats.used_prior == used
        assert len(res.correspondences) > 0.8 * first.stats.n_features
        assert np.abs(res.correspondences.cur_left - res.correspondences.prev_left
                      - np.array(delta)).max() < 0.1
        assert_finite(res)


def test_stereo_pyramid_levels_set_the_reach_of_the_stereo_pass():
    """A predicted disparity 8 px off: the stereo pass needs a pyramid level to reach it."""
    calib = rectified_calib()
    delta = np.array([M2[0] - M1[0], M2[1] - M1[1]])

    def wrong_disparity(prev_left, prev_right):  # the left motion right, the right 8 px off
        return prev_left + delta, prev_right + delta - np.array([8.0, 0.0])

    found, temporal = {}, {}
    for levels in (0, 1):
        tracker = StereoTracker(config(stereo_pyramid_levels=levels))
        first = tracker.track(*pair(M1), calib)
        res = tracker.track(*pair(M2), calib, wrong_disparity)
        assert res.stats.used_prior
        found[levels], temporal[levels] = res.correspondences, res.stats.failed['temporal']
        assert_finite(res)
    assert temporal[0] == temporal[1]  # the temporal pass follows its own setting
    assert len(found[1]) > 0.95 * first.stats.n_features
    for err in shift_errors(found[1], tuple(delta)):
        assert np.median(err) < 0.02
    assert len(found[0]) < 0.9 * len(found[1])


def test_stereo_pyramid_levels_set_the_reach_of_the_new_corners_stereo_search():
    """New corners start at a nearby tracked feature's disparity, here 8 px off."""
    calib = rectified_calib()
    left, right = pair(M1)
    rng = np.random.default_rng(0)
    tracked = np.column_stack([rng.uniform(40, W - 40, 30),
                               rng.uniform(40, H - 40, 30)]).astype(np.float32)
    found = {}
    for off, levels in ((0.0, 0), (8.0, 0), (8.0, 1)):
        job = ReplenishJob(config(stereo_pyramid_levels=levels), BucketingConfig(), calib,
                           tracked, tracked - np.float32([DISPARITY + off, 0.0]), 60, None,
                           None, True)
        new = replenish(left, right, right, job)
        disparity = new.left_raw[:, 0] - new.right_raw[:, 0]
        assert np.median(np.abs(disparity - DISPARITY)) < 0.02
        found[off, levels] = len(new.left_raw)
    assert found[8.0, 1] > 0.95 * found[0.0, 0]
    assert found[8.0, 0] < 0.9 * found[8.0, 1]


def test_detection_respects_max_features_buckets_and_min_distance():
    calib = rectified_calib()
    cfg = config(max_features=120)
    bcfg = BucketingConfig()
    res = StereoTracker(cfg, bcfg).track(*pair(M1), calib)
    pts = res.features_left_raw
    assert 60 < len(pts) <= 120
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    assert d.min() >= cfg.min_distance_px - 1.0
    assert bucketing.occupancy(pts, (W, H), bcfg).max() <= bcfg.max_per_bucket
    # Detection only where features are missing: nothing new near the existing ones.
    img = pair(M1)[0]
    new, _ = detect_corners(img, pts[:60], 60, cfg, bcfg)
    near = np.linalg.norm(new[:, None] - pts[None, :60], axis=2).min(axis=1)
    assert len(new) > 0 and near.min() >= cfg.min_distance_px - 1.0


@pytest.mark.parametrize('size,margin', [((1241, 376), 10), ((640, 480), 0), ((333, 97), 7),
                                         ((30, 20), 40)])
def test_detection_searches_the_runs_of_chosen_buckets_through_their_masks(size, margin):
    """Crops, masks and corners of ``detect_corners`` as a plain reading of its contract."""
    from stereo_vo_ros.tracking import detection
    w, h = size
    rng = np.random.default_rng(w + margin)
    cfg = config()
    for rows, cols in ((4, 12), (3, 5), (1, 1)):
        bcfg = BucketingConfig(rows=rows, cols=cols, roi_margin_px=margin)
        x0, y0, x1, y1 = (margin, margin, w - margin, h - margin) if \
            w - margin > margin and h - margin > margin else (0, 0, w, h)
        xe = [x0 + (x1 - x0) * c / cols for c in range(cols + 1)]
        ye = [y0 + (y1 - y0) * r / rows for r in range(rows + 1)]
        for _ in range(20):
            chosen = rng.random((rows, cols)) < rng.random()
            expected = []
            for r in range(rows):
                c = 0
                while c < cols:
                    if chosen[r, c]:
                        c1 = c
                        while c1 < cols and chosen[r, c1]:
                            c1 += 1
                        expected.append(((int(np.floor(xe[c])), int(np.floor(ye[r])),
                                          int(np.ceil(xe[c1])), int(np.ceil(ye[r + 1]))), c1 - c))
                        c = c1
                    else:
                        c += 1
            rects, counts = detection._regions(chosen, size, bcfg)
            assert list(zip(rects, counts)) == expected
    # Each crop is searched inside its run, away from the existing features, and its corners
    # are goodFeaturesToTrack's with that mask.
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), 1.5)
    bcfg = BucketingConfig(rows=3, cols=5, roi_margin_px=margin)
    chosen = np.array([[1, 1, 0, 1, 0], [0, 1, 1, 1, 1], [1, 0, 0, 0, 1]], bool)
    existing = rng.uniform([0, 0], [w, h], (25, 2))
    seen = []
    original = detection.shi_tomasi

    def spy(img, crop, rect, free, *args):
        corners = original(img, crop, rect, free, *args)
        seen.append((crop, rect, free, args, corners))
        return corners

    detection.shi_tomasi = spy
    try:
        detect_corners(img, existing, 40, cfg, bcfg, chosen)
    finally:
        detection.shi_tomasi = original
    rects, counts = detection._regions(chosen, size, bcfg)
    pad = cfg.block_size // 2 + 2
    assert [rect for _, rect, *_ in seen] == rects
    yy, xx = np.mgrid[0:h, 0:w]
    far = np.ones((h, w), bool)
    r = int(np.ceil(cfg.min_distance_px))
    for x, y in np.round(existing).astype(int):
        far &= (xx - x) ** 2 + (yy - y) ** 2 > r * r
    # The discs are OpenCV's: their rim may differ from the exact circle by a pixel.
    rim = np.abs(np.sqrt((xx[..., None] - np.round(existing)[:, 0]) ** 2
                         + (yy[..., None] - np.round(existing)[:, 1]) ** 2) - r).min(axis=2) < 1.5
    for ((cx0, cy0, cx1, cy1), (rx0, ry0, rx1, ry1), free, args, corners), count in zip(
            seen, counts):
        assert (cx0, cy0, cx1, cy1) == (max(rx0 - pad, 0), max(ry0 - pad, 0), min(rx1 + pad, w),
                                        min(ry1 + pad, h))
        assert args == (2 * count * bcfg.max_per_bucket, cfg.quality_level, cfg.min_distance_px,
                        cfg.block_size)
        inside = (slice(ry0, ry1), slice(rx0, rx1))
        assert np.array_equal((free[inside] > 0) | rim[inside], far[inside] | rim[inside])
        mask = np.zeros((cy1 - cy0, cx1 - cx0), np.uint8)
        mask[ry0 - cy0:ry1 - cy0, rx0 - cx0:rx1 - cx0] = free[inside]
        expected = cv2.goodFeaturesToTrack(
            img[cy0:cy1, cx0:cx1], maxCorners=args[0], qualityLevel=cfg.quality_level,
            minDistance=cfg.min_distance_px, mask=mask, blockSize=cfg.block_size)
        assert np.array_equal(corners, np.zeros((0, 2), np.float32) if expected is None else
                              expected.reshape(-1, 2))


def _shi_tomasi_cases(rng, h, w, n, interior_share=0.7, blocks=(1, 2, 3, 4, 5, 7, 8, 11, 30, 31)):
    """Random crops, runs, keep-away masks and settings of ``detection.shi_tomasi``."""
    from stereo_vo_ros.tracking.detection import NOTHING_BLOCKED
    for case in range(n):
        block = int(rng.choice(blocks))
        reach = block // 2 + 2
        if rng.random() < interior_share:  # sums inside the crop: the package's kernel
            rx0 = int(rng.integers(reach, w // 2))
            ry0 = int(rng.integers(reach, h // 2))
            rx1 = int(rng.integers(rx0 + 1, w - reach + 1))
            ry1 = int(rng.integers(ry0 + 1, h - reach + 1))
            grow = int(rng.integers(0, 3))
            crop = (max(rx0 - reach - grow, 0), ry0 - reach, min(rx1 + reach + grow, w),
                    ry1 + reach)
        else:  # near the image's edge: OpenCV's function
            rx0, ry0 = int(rng.integers(0, 12)), int(rng.integers(0, 12))
            rx1, ry1 = int(rng.integers(rx0 + 1, w + 1)), int(rng.integers(ry0 + 1, h + 1))
            crop = (max(rx0 - 2, 0), max(ry0 - 2, 0), min(rx1 + 2, w), min(ry1 + 2, h))
        free = NOTHING_BLOCKED
        if rng.random() < 0.5:
            free = np.full((h, w), 255, np.uint8)
            for _ in range(6):
                cv2.circle(free, (int(rng.integers(0, w)), int(rng.integers(0, h))),
                           int(rng.integers(3, 30)), 0, -1)
        yield (crop, (rx0, ry0, rx1, ry1), free, int(rng.choice([1, 5, 50, 1000])),
               float(rng.choice([0.001, 0.01, 0.1, 0.5])), float(rng.choice([1.0, 2.5, 15.0])),
               block)


def _opencv_corners(img, crop, rect, free, max_corners, quality, min_distance, block):
    cx0, cy0, cx1, cy1 = crop
    rx0, ry0, rx1, ry1 = rect
    mask = np.zeros((cy1 - cy0, cx1 - cx0), np.uint8)
    mask[ry0 - cy0:ry1 - cy0, rx0 - cx0:rx1 - cx0] = free[ry0:ry1, rx0:rx1] if free.size else 255
    corners = cv2.goodFeaturesToTrack(img[cy0:cy1, cx0:cx1], maxCorners=max_corners,
                                      qualityLevel=quality, minDistance=min_distance, mask=mask,
                                      blockSize=block)
    return np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)


def test_shi_tomasi_finds_opencvs_corners_on_camera_like_images():
    """On textured images the package's Shi-Tomasi gives goodFeaturesToTrack's corners."""
    from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence
    from stereo_vo_ros.tracking.detection import shi_tomasi
    rng = np.random.default_rng(7)
    frame = next(iter(SyntheticSequence(SequenceSpec.preset('urban', n_frames=2))))
    rendered = frame.left[100:300, 300:640].copy()
    images = [rendered] + [cv2.GaussianBlur(rng.integers(0, 256, (120, 160)).astype(np.uint8),
                                            (0, 0), sigma) for sigma in (0.7, 1.5, 3.0)]
    n_corners = n_kernel = 0
    for img in images:
        for args in _shi_tomasi_cases(rng, *img.shape, 80):
            expected = _opencv_corners(img, *args)
            assert np.array_equal(shi_tomasi(img, *args), expected), args[1:]
            crop, (rx0, ry0, rx1, ry1), block = args[0], args[1], args[-1]
            reach = block // 2 + 2
            if 2 <= block and rx0 - reach >= crop[0] and ry0 - reach >= crop[1] \
                    and rx1 + reach <= crop[2] and ry1 + reach <= crop[3]:
                n_kernel += 1
                n_corners += len(expected)
    assert n_kernel > 150 and n_corners > 2000  # through the kernel, not OpenCV's fallback
    # A keep-away mask of another size is refused; other image types go to OpenCV.
    with pytest.raises(ValueError):
        shi_tomasi(images[1], (0, 0, 160, 120), (20, 20, 60, 60), np.ones((50, 50), np.uint8),
                   10, 0.01, 5.0, 7)
    as_float = images[1].astype(np.float32)
    assert np.array_equal(shi_tomasi(as_float, (0, 0, 160, 120), (20, 20, 60, 60),
                                     np.ones((120, 160), np.uint8), 10, 0.01, 5.0, 7),
                          _opencv_corners(as_float, (0, 0, 160, 120), (20, 20, 60, 60),
                                          np.ones((120, 160), np.uint8), 10, 0.01, 5.0, 7))


def _shi_tomasi_reference(img, crop, rect, free, max_corners, quality, min_distance, block):
    """``shi_tomasi``'s documented steps in NumPy, with the sums in int64 (exact)."""
    cx0, cy0, cx1, cy1 = crop
    rx0, ry0, rx1, ry1 = rect
    p = np.pad(img[cy0:cy1, cx0:cx1].astype(np.int64), 1, mode='reflect')
    gx = (p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[1:-1, :-2] + p[2:, :-2])
    gy = (p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[:-2, 1:-1] + p[:-2, 2:])
    r0 = block // 2

    def box(a):
        a = np.pad(a, ((r0, block - 1 - r0), (r0, block - 1 - r0)), mode='reflect')
        c = np.pad(a, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
        return c[block:, block:] - c[:-block, block:] - c[block:, :-block] + c[:-block, :-block]

    a, b, c = box(gx * gx).astype(float), box(gx * gy).astype(float), box(gy * gy).astype(float)
    d = 0.5 * (a - c)
    eig = 0.5 * (a + c) - np.sqrt(d * d + b * b)
    h, w = eig.shape
    mask = np.zeros((h, w), bool)
    mask[ry0 - cy0:ry1 - cy0, rx0 - cx0:rx1 - cx0] = free[ry0:ry1, rx0:rx1] > 0 if free.size \
        else True
    threshold = (eig[mask].max() if mask.any() else 0.0) * quality
    counted = np.pad(np.where(eig > threshold, eig, 0.0), 1, constant_values=-np.inf)
    most = np.max([counted[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] for dy in (-1, 0, 1)
                   for dx in (-1, 0, 1)], axis=0)
    cand = mask & (counted[1:-1, 1:-1] != 0) & (counted[1:-1, 1:-1] == most)
    cand[[0, -1], :] = cand[:, [0, -1]] = False
    ys, xs = np.nonzero(cand)
    order = np.lexsort((-(ys * w + xs), -eig[ys, xs]))
    kept = []
    for y, x in zip(ys[order], xs[order]):
        if len(kept) < max_corners and all((x - u) ** 2 + (y - v) ** 2 >= min_distance ** 2
                                           for u, v in kept):
            kept.append((x, y))
    return np.array(kept, np.float32).reshape(-1, 2)


def test_shi_tomasi_follows_its_steps_where_values_tie():
    """Checkerboards, stripes and blocks (many equal values): corners of the exact sums."""
    from stereo_vo_ros.tracking.detection import shi_tomasi
    rng = np.random.default_rng(3)
    h, w = 90, 120
    yy, xx = np.mgrid[0:h, 0:w]
    images = [(((yy // s + xx // s) % 2) * 200).astype(np.uint8) for s in (2, 3, 8)]
    images.append(np.tile((127 + 120 * np.sin(np.arange(w) / 2.5)).astype(np.uint8), (h, 1)))
    blocks = np.zeros((h, w), np.uint8)
    for _ in range(10):
        x0, y0 = rng.integers(0, w - 10), rng.integers(0, h - 10)
        blocks[y0:y0 + rng.integers(3, 30), x0:x0 + rng.integers(3, 30)] = rng.integers(0, 256)
    images += [blocks, np.full((h, w), 90, np.uint8)]
    n_corners = 0
    for img in images:
        for args in _shi_tomasi_cases(rng, h, w, 40, interior_share=1.0,
                                      blocks=(2, 3, 4, 5, 7, 8, 11, 30, 31)):
            expected = _shi_tomasi_reference(img, *args)
            assert np.array_equal(shi_tomasi(img, *args), expected), args[1:]
            n_corners += len(expected)
    assert n_corners > 1000


# -- checks ----------------------------------------------------------------------------
def test_disparity_constraint_rejects_vertical_mismatch_before_reverse_pass():
    calib = rectified_calib()
    left2, right2 = pair(M2)
    displaced = render((M2[0] - DISPARITY, M2[1] + 4.0))  # right content 4 px lower
    right2 = patch(right2, displaced, BOX)
    out = {}
    for variant in ('baseline', 'dc'):
        tracker = StereoTracker(config(variant=variant), BucketingConfig())
        tracker.track(*pair(M1), calib)
        out[variant] = tracker.track(left2, right2, calib)
    c_base = out['baseline'].correspondences
    in_box = inside(c_base.cur_left - [DISPARITY, 0.0], BOX, MARGIN)
    assert in_box.sum() >= 5
    # The baseline keeps them, with the vertical mismatch.
    np.testing.assert_allclose(c_base.cur_right[in_box, 1] - c_base.cur_left[in_box, 1], 4.0,
                               atol=0.15)
    st = out['dc'].stats
    assert not np.any(np.isin(out['dc'].correspondences.ids, c_base.ids[in_box]))
    assert st.failed['dc'] >= in_box.sum()
    # Rejected features are not tracked back.
    assert st.pass_points['stereo_bwd'] == (st.pass_points['stereo_fwd'] - st.failed['stereo']
                                            - st.failed['dc'] - st.failed['disparity'])
    assert st.failed['lr'] == 0
    assert out['baseline'].stats.pass_points['stereo_bwd'] == \
        out['baseline'].stats.pass_points['stereo_fwd'] - out['baseline'].stats.failed['stereo']


@pytest.mark.parametrize('corrupted', ['left', 'right'])
def test_corrupted_region_is_removed_by_fb_or_lr(corrupted):
    """
    Noise pasted into left(t2) is caught by fb, into right(t2) by lr.

    The checks of the full variant leave (almost) nothing.
    """
    calib = rectified_calib()
    left2, right2 = pair(M2)
    if corrupted == 'left':
        left2 = patch(left2, noise(7), BOX)
    else:
        right2 = patch(right2, noise(7), BOX)
    survivors = {}
    for variant in ('baseline', 'full'):
        tracker = StereoTracker(config(variant=variant), BucketingConfig())
        first = tracker.track(*pair(M1), calib)
        res = tracker.track(left2, right2, calib)
        # Features whose left(t2) (fb) or right(t2) (lr) window lies in the noise.
        where = first.features_left_raw + np.array(M2)
        if corrupted == 'right':
            where = where - [DISPARITY, 0.0]
        doomed = inside(where, BOX, MARGIN)
        assert doomed.sum() >= 10
        survivors[variant] = np.isin(first.feature_ids[doomed], res.correspondences.ids).sum()
        f = res.stats.failed
        if variant == 'baseline':
            check, other = ('fb', 'lr') if corrupted == 'left' else ('lr', 'fb')
            assert f[check] >= doomed.sum()
            assert f[other] <= 0.3 * doomed.sum()
    # A KLT pass and its reverse may settle in the same local minimum of the noise: the
    # baseline checks are not thorough (the motivation of the paper); dc and bc help.
    assert survivors['baseline'] <= doomed.sum() / 3
    assert survivors['full'] <= max(1, survivors['baseline'] - 1)


def test_bicircular_closure_catches_a_stereo_match_one_period_off():
    """Stereo matches one texture period off pass every check but the bi-circular closure."""
    period = 40.0  # the texture repeats every 40 px along x
    calib = rectified_calib()
    frames = [pair(m, seed=3, period_x=period) for m in (M1, M2, M3)]
    d12 = (M2[0] - M1[0], M2[1] - M1[1])
    d23 = (M3[0] - M2[0], M3[1] - M2[1])

    def wrong_right_prior(prev_left, prev_right):  # right prediction one period too far
        return prev_left + d12, prev_right + d12 - np.array([period, 0.0])

    def true_prior(prev_left, prev_right):  # exact prediction, ignores the stored right
        cur = prev_left + np.array(d23)
        return cur, cur - np.array([DISPARITY, 0.0])

    mid, last = {}, {}
    for variant, mode in (('baseline', 'roundtrip'), ('bc', 'roundtrip'), ('bc', 'closure')):
        # New corners after every check: the corners an earlier replenishment adds at t1 change
        # the brightness map of t2 and with it which wrong matches the baseline keeps.
        tracker = StereoTracker(config(variant=variant, bicircular_mode=mode, pyramid_levels=1,
                                       max_disparity_px=100.0, replenish_after='all'),
                                BucketingConfig())
        tracker.track(*frames[0], calib)
        mid[mode, variant] = tracker.track(*frames[1], calib, wrong_right_prior)
        last[mode, variant] = tracker.track(*frames[2], calib, true_prior)

    def disparity(c, when):
        if when == 'prev':
            return c.prev_left[:, 0] - c.prev_right[:, 0]
        return c.cur_left[:, 0] - c.cur_right[:, 0]

    # Baseline: at t1 the stereo matches are one period off, consistent in the images ...
    base_mid = mid['roundtrip', 'baseline'].correspondences
    assert len(base_mid) >= 10
    np.testing.assert_allclose(disparity(base_mid, 'cur'), DISPARITY + period, atol=0.1)
    # ... and at t2 they are kept with the wrong right(t1) point.
    base = last['roundtrip', 'baseline'].correspondences
    wrong = np.abs(disparity(base, 'prev') - (DISPARITY + period)) < 0.1
    assert wrong.sum() >= len(base_mid) - 2
    np.testing.assert_allclose(disparity(base, 'cur'), DISPARITY, atol=0.1)
    # The closure of eq. 7 catches the inconsistent quadruple at once, at t1 ...
    st = mid['closure', 'bc'].stats
    assert len(mid['closure', 'bc'].correspondences) == 0
    assert st.failed['bc'] == st.pass_points['bicircular'] == len(base_mid)
    # ... so nothing inconsistent reaches t2.
    c = last['closure', 'bc'].correspondences
    assert len(c) > 0
    np.testing.assert_allclose(disparity(c, 'prev'), DISPARITY, atol=0.1)
    # The round trip right(t2) -> right(t1) -> right(t2) cannot see it: it keeps them all.
    for res in (mid['roundtrip', 'bc'], last['roundtrip', 'bc']):
        assert res.stats.failed['bc'] == 0 and res.stats.pass_points['bicircular'] > 0
    c = last['roundtrip', 'bc'].correspondences
    kept_wrong = np.abs(disparity(c, 'prev') - (DISPARITY + period)) < 0.1
    assert kept_wrong.sum() == wrong.sum()


def test_bicircular_error_readings():
    r2 = np.array([[10.0, 10.0], [20.0, 20.0]])
    back = np.array([[8.0, 10.0], [18.0, 21.0]])
    stored = np.array([[8.0, 10.0], [18.0, 20.0]])
    again = np.array([[10.0, 10.5], [20.0, 20.0]])
    np.testing.assert_allclose(bicircular_error('closure', r2, back, stored, None), [0, 1])
    np.testing.assert_allclose(bicircular_error('roundtrip', r2, back, stored, again), [0.5, 0])
    with pytest.raises(ConfigError):
        bicircular_error('loop', r2, back, stored, again)


def test_disparity_constraint_function_on_raw_geometry():
    calib = distorted_calib()
    x_left = np.array([[100.0, 80.0], [200.0, 150.0]])
    Hm = plane_homography(calib)
    on_line = cv2.perspectiveTransform(x_left[None], Hm)[0]
    off_line = on_line + np.array([[0.0, 3.0], [0.0, -3.0]])
    assert disparity_constraint(calib, x_left, on_line, 2.0).all()
    assert not disparity_constraint(calib, x_left, off_line, 2.0).any()


# -- adaptive threshold and variants -----------------------------------------------------
def test_adaptive_threshold_follows_eq8():
    assert adaptive_threshold(0, 10, 0.23, 5.0) == pytest.approx(5.0)
    assert adaptive_threshold(100, 1, 0.23, 5.0) == pytest.approx(28.0)
    assert adaptive_threshold(40, 8, 0.23, 5.0) == pytest.approx(0.23 * 40 / 8 + 5.0)
    assert adaptive_threshold(40, 0, 0.23, 5.0) == pytest.approx(0.23 * 40 + 5.0)
    # More loss loosens, older features tighten.
    assert adaptive_threshold(50, 5, 0.23, 5) > adaptive_threshold(10, 5, 0.23, 5)
    assert adaptive_threshold(50, 50, 0.23, 5) < adaptive_threshold(50, 5, 0.23, 5)
    assert bicircular_threshold(config(variant='db', bc_threshold_px=3.0), 99, 1) == 3.0
    assert bicircular_threshold(config(variant='full', adaptive_rho=1.0,
                                       adaptive_epsilon_px=2.0), 10, 4) == pytest.approx(4.5)


def test_tracker_uses_eq8_with_loss_and_maxtrack():
    calib = rectified_calib()
    tracker = StereoTracker(config(variant='full'), BucketingConfig())
    tracker.track(*pair(M1), calib)
    tracker.track(*pair(M2), calib)
    left3, right3 = pair(M3)
    res = tracker.track(patch(left3, noise(9), BOX), right3, calib)
    st = res.stats
    lost_before_bc = sum(st.failed[k] for k in ('temporal', 'fb', 'stereo', 'dc', 'disparity',
                                                'lr'))
    assert st.loss == lost_before_bc > 0
    assert st.maxtrack == 2
    assert st.delta_d_px == pytest.approx(0.23 * st.loss / 2 + 5.0)


@pytest.mark.parametrize('variant', TRACKER_VARIANTS)
def test_variants_switch_checks(variant):
    checks = CheckSet.for_variant(variant)
    calib = rectified_calib()
    tracker = StereoTracker(config(variant=variant), BucketingConfig())
    tracker.track(*pair(M1), calib)
    left2, right2 = pair(M2)
    right2 = patch(right2, render((M2[0] - DISPARITY, M2[1] + 4.0)), BOX)
    st = tracker.track(left2, right2, calib).stats
    assert (st.failed['dc'] > 0) == checks.disparity_constraint
    assert (st.pass_points['bicircular'] > 0) == checks.bicircular
    assert np.isnan(st.delta_d_px) != checks.bicircular
    if variant in ('bc', 'db'):
        assert st.delta_d_px == 5.0
    if variant == 'full':
        assert st.delta_d_px == pytest.approx(0.23 * st.loss / st.maxtrack + 5.0)
    assert [v for v in TRACKER_VARIANTS if CheckSet.for_variant(v) == checks] == [variant]


def test_configuration_changes_apply_without_reset():
    calib = rectified_calib()
    tracker = StereoTracker(config(variant='baseline'))
    tracker.track(*pair(M1), calib)
    tracker.cfg = config(variant='full')  # as a pipeline applying run-time parameters does
    st = tracker.track(*pair(M2), calib).stats
    assert not st.initialized and st.pass_points['bicircular'] > 0
    tracker.configure(config(variant='dc', bc_threshold_px=1.0), BucketingConfig())
    st = tracker.track(*pair(M3), calib).stats
    assert not st.initialized and st.pass_points['bicircular'] == 0


def test_bad_configuration_is_rejected():
    with pytest.raises(ConfigError, match='variant'):
        StereoTracker(config(variant='vins'), BucketingConfig())
    with pytest.raises(ConfigError, match='bicircular_mode'):
        StereoTracker(config(bicircular_mode='both'), BucketingConfig())


# -- robustness ------------------------------------------------------------------------
def test_black_and_flat_images_give_empty_output():
    calib = rectified_calib()
    tracker = StereoTracker(config(), BucketingConfig())
    black = np.zeros((H, W), np.uint8)
    for img in (black, np.full((H, W), 128, np.uint8)):
        res = tracker.track(img, img, calib)
        assert len(res.correspondences) == 0 and res.stats.n_features == 0
        assert_finite(res)
    tracker.track(*pair(M1), calib)
    res = tracker.track(black, black, calib)  # every feature lost
    assert len(res.correspondences) == 0 and res.stats.n_features == 0
    assert res.stats.failed['temporal'] + res.stats.failed['fb'] == res.stats.n_previous > 0
    assert_finite(res)
    res = tracker.track(*pair(M2), calib)  # recovers by detecting again
    assert len(res.correspondences) == 0 and res.stats.n_features > 100


def test_new_image_size_reinitialises():
    tracker = StereoTracker(config(), BucketingConfig())
    tracker.track(*pair(M1), rectified_calib())
    small = (320, 240)
    res = tracker.track(*pair(M2, size=small), rectified_calib(small))
    assert res.stats.initialized and len(res.correspondences) == 0
    assert_finite(res)
    res = tracker.track(*pair(M3, size=small), rectified_calib(small))
    assert len(res.correspondences) > 50
    with pytest.raises(ImageError, match='calibration size'):
        tracker.track(*pair(M3), rectified_calib(small))


def test_reset_and_input_validation():
    calib = rectified_calib()
    tracker = StereoTracker(config(), BucketingConfig())
    tracker.track(*pair(M1), calib)
    tracker.reset()
    assert tracker.num_features == 0
    assert tracker.track(*pair(M2), calib).stats.initialized
    left, right = pair(M3)
    with pytest.raises(ImageError, match='grey'):
        tracker.track(np.dstack([left] * 3), right, calib)
    with pytest.raises(ImageError, match='uint8 or uint16'):
        tracker.track(left.astype(np.float32), right, calib)
    with pytest.raises(ImageError, match='differ'):
        tracker.track(left, right[:-2], calib)


def test_uint16_input_matches_uint8():
    calib = rectified_calib()
    ref, t16 = StereoTracker(), StereoTracker()
    results = []
    for tracker, scale in ((ref, None), (t16, 4095.0 / 255.0)):
        for m in (M1, M2):
            left, right = pair(m)
            if scale:  # 12-bit data in a 16-bit container
                left, right = (np.round(i * scale).astype(np.uint16) for i in (left, right))
            res = tracker.track(left, right, calib)
        results.append(res.correspondences)
    assert len(results[1]) > 0.9 * len(results[0])
    common, i0, i1 = np.intersect1d(results[0].ids, results[1].ids, return_indices=True)
    assert len(common) > 0.9 * len(results[0])
    np.testing.assert_allclose(results[0].cur_right[i0], results[1].cur_right[i1], atol=0.05)


def test_grey_pair_gives_the_images_track_sees():
    """Tracking grey_pair's images tracks the same as tracking the uint16 images themselves."""
    calib = rectified_calib()
    direct, converted = StereoTracker(), StereoTracker()
    out = []
    for tracker, first in ((direct, False), (converted, True)):
        for peak, m in ((1023, M1), (4095, M2)):  # the second pair raises the bit depth
            left, right = (np.round(i * (peak / 255.0)).astype(np.uint16) for i in pair(m))
            if first:
                left, right = tracker.grey_pair(left, right)
                assert left.dtype == right.dtype == np.uint8
            res = tracker.track(left, right, calib)
        out.append((res.correspondences, tracker.last_pair()))
    (a, pair_a), (b, pair_b) = out
    assert len(a) > 100
    assert np.array_equal(a.cur_right, b.cur_right) and np.array_equal(a.ids, b.ids)
    assert all(np.array_equal(x, y) for x, y in zip(pair_a, pair_b))
    with pytest.raises(ImageError, match='differ'):
        converted.grey_pair(left, right[:-2])


@pytest.mark.parametrize('threads', [1, 2])
def test_after_checks_runs_once_behind_the_pairs_helper_work(threads):
    """
    ``track_async``'s ``after_checks`` runs once per pair, behind the aperture checks.

    Work it queues on the helper thread runs after them; on a first pair it runs at once. Its
    return value comes back in ``PendingTrack.after_checks``; the tracking is unchanged.
    """
    calib = rectified_calib()
    workers = Workers(threads, set_opencv=False, kind='thread')
    tracker, plain = StereoTracker(config(), workers=workers), StereoTracker(config())
    queued = []  # the helper's work of each pair, in the order it was queued
    submit_local = workers.submit_local

    def recorded(fn, *args):
        queued.append(fn.__name__)
        return submit_local(fn, *args)
    workers.submit_local = recorded
    try:
        for i, m in enumerate((M1, M2, M3)):
            queued.clear()
            left, right = pair(m)
            track = tracker.track_async(left, right, calib,
                                        after_checks=lambda: queued.append('after') or i)
            assert track.after_checks == i and queued.count('after') == 1
            if i == 0:
                assert queued == ['after']
            else:
                assert queued.index('aperture_checks') < queued.index('after')
            expected = plain.track(left, right, calib).correspondences
            got = track.result().correspondences
            assert np.array_equal(got.cur_right, expected.cur_right)
            assert np.array_equal(got.ids, expected.ids)
        assert len(got) > 100
        assert tracker.track_async(left, right, calib).after_checks is None
    finally:
        workers.close()


def test_caller_reusing_image_buffers_does_not_corrupt_tracking():
    calib = rectified_calib()
    tracker = StereoTracker(config())
    left, right = pair(M1)
    tracker.track(left, right, calib)
    left2, right2 = pair(M2)
    left[:], right[:] = left2, right2  # the caller reuses its buffers in place
    res = tracker.track(left, right, calib)
    assert len(res.correspondences) > 100
    assert np.abs(res.correspondences.cur_left - res.correspondences.prev_left
                  - np.array(M2)).max() < 0.1


# -- raw (distorted, unrectified) input ----------------------------------------------------
ROT_Y = 0.6  # degrees between the cameras


def distorted_calib() -> StereoCalibration:
    """Raw calibration: radial-tangential distortion, right camera rotated by ROT_Y."""
    a = np.radians(ROT_Y)
    R_rl = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    K = np.array([[FOCAL, 0, W / 2 + 3], [0, FOCAL * 1.01, H / 2 - 2], [0, 0, 1.0]])
    K_rect = np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]])
    P0 = np.hstack([K_rect, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -FOCAL * BASELINE
    left = CameraModel(K=K, D=np.array([-0.12, 0.02, 0.001, -0.0005, 0.0]), R=np.eye(3),
                       P=P0, width=W, height=H)
    right = CameraModel(K=K.copy(), D=np.array([-0.10, 0.015, -0.001, 0.0004, 0.0]),
                        R=R_rl.T, P=P1, width=W, height=H)
    return StereoCalibration.from_models(left, right, 'raw')


def plane_homography(calib: StereoCalibration) -> np.ndarray:
    """Left ideal -> right ideal pixels for the fronto-parallel plane of the scene."""
    depth = FOCAL * BASELINE / DISPARITY
    n = np.array([0.0, 0.0, 1.0])
    M = calib.R_right_left + np.outer(calib.t_right_left, n) / depth
    return calib.K_right @ M @ np.linalg.inv(calib.K_left)


def render_raw(calib: StereoCalibration, motion: tuple[float, float], right: bool
               ) -> np.ndarray:
    """Raw (distorted) image of the plane moved by ``motion`` in the left ideal image."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    raw = np.stack([xs.ravel(), ys.ravel()], axis=1)
    ideal = calib.undistort_right(raw) if right else calib.undistort_left(raw)
    if right:  # right ideal -> left ideal through the plane
        ideal = cv2.perspectiveTransform(ideal[None], np.linalg.inv(plane_homography(calib)))[0]
    v = texture(ideal[:, 0] - motion[0], ideal[:, 1] - motion[1], seed=5)
    return np.clip(np.round(v), 0, 255).astype(np.uint8).reshape(H, W)


def test_raw_input_outputs_undistorted_quadruples():
    calib = distorted_calib()
    Hm = plane_homography(calib)
    frames = [(render_raw(calib, m, False), render_raw(calib, m, True)) for m in (M1, M2)]
    delta = np.array(M2) - np.array(M1)

    def prior(prev_left, prev_right):  # exact prediction in ideal pixels
        cur = prev_left + delta
        return cur, cv2.perspectiveTransform(cur[None], Hm)[0]

    for use_prior in (False, True):
        tracker = StereoTracker(config(variant='full'), BucketingConfig())
        tracker.track(*frames[0], calib)
        res = tracker.track(*frames[1], calib, prior if use_prior else None)
        c = res.correspondences
        assert len(c) > 80
        assert res.stats.failed['dc'] == 0
        want_prev_right = cv2.perspectiveTransform(c.prev_left[None], Hm)[0]
        want_cur_right = cv2.perspectiveTransform((c.prev_left + delta)[None], Hm)[0]
        assert np.abs(c.cur_left - (c.prev_left + delta)).max() < 0.1
        # Different distortion and the rotation between the cameras shear the right patch
        # against the left one near the image edges: translational KLT is biased there.
        for got, want in ((c.prev_right, want_prev_right), (c.cur_right, want_cur_right)):
            err = np.linalg.norm(got - want, axis=1)
            assert np.percentile(err, 95) < 0.1
            assert err.max() < 0.25
        # Raw positions are the distorted ones.
        np.testing.assert_allclose(calib.undistort_left(res.raw.cur_left), c.cur_left,
                                   atol=1e-6)
        assert np.abs(res.raw.cur_left - c.cur_left).max() > 1.0
        assert_finite(res)


# -- real KITTI clips ------------------------------------------------------------------
def load_kitti(data: Path, name: str):
    """Images, rectified calibration and T_world_cam poses of a KITTI-layout clip."""
    folder = data / name
    if not (folder / 'calib.txt').exists():
        pytest.skip(f'KITTI clip {folder} is absent')
    proj = {}
    for line in (folder / 'calib.txt').read_text().splitlines():
        key, _, values = line.partition(':')
        if values.strip():
            proj[key.strip()] = np.array(values.split(), np.float64).reshape(3, 4)
    rows = np.loadtxt(folder / 'poses.txt').reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3] = rows
    left = [cv2.imread(str(folder / 'image_0' / f'{i:06d}.png'), cv2.IMREAD_UNCHANGED)
            for i in range(len(poses))]
    right = [cv2.imread(str(folder / 'image_1' / f'{i:06d}.png'), cv2.IMREAD_UNCHANGED)
             for i in range(len(poses))]
    calib = StereoCalibration.from_projections(proj['P0'], proj['P1'], left[0].shape[1],
                                               left[0].shape[0])
    return left, right, calib, poses


def reprojection_errors(calib, corr, T_prev_cur):
    """Left and right errors (pixels) of quadruples moved with the relative pose."""
    K, B = calib.K_left, calib.baseline_m
    disp = np.maximum(corr.prev_left[:, 0] - corr.prev_right[:, 0], 1e-3)
    z = K[0, 0] * B / disp
    X = np.stack([(corr.prev_left[:, 0] - K[0, 2]) * z / K[0, 0],
                  (corr.prev_left[:, 1] - K[1, 2]) * z / K[1, 1], z], axis=1)
    T = np.linalg.inv(T_prev_cur)
    Xh = np.hstack([X @ T[:3, :3].T + T[:3, 3], np.ones((len(X), 1))])
    errs = []
    for P, x in ((calib.projection_left(), corr.cur_left),
                 (calib.projection_right(), corr.cur_right)):
        p = Xh @ P.T
        errs.append(np.linalg.norm(p[:, :2] / p[:, 2:3] - x, axis=1))
    return errs


@pytest.mark.parametrize('name, limit_px', [
    ('kitti06_f0000-0050', 1.0),
    # The GPS/INS ground truth of this highway clip disagrees with image-based motion by
    # ~0.1 m per frame (see its README): a looser bound; the PnP check below is the tight one.
    ('kitti01_f0000-0050', 1.5)])
def test_kitti_quadruples_consistent_with_ground_truth(shared_data, name, limit_px):
    left, right, calib, poses = load_kitti(shared_data, name)
    tracker = StereoTracker()  # default configuration
    err_l, err_r, fit, counts = [], [], [], []
    for i in range(len(left)):
        res = tracker.track(left[i], right[i], calib)
        if i == 0:
            continue
        c = res.correspondences
        counts.append(len(c))
        el, er = reprojection_errors(calib, c, np.linalg.inv(poses[i - 1]) @ poses[i])
        err_l.append(el)
        err_r.append(er)
        # Ground-truth-free consistency: residuals of a robust PnP fit of the frame.
        K, B = calib.K_left, calib.baseline_m
        z = K[0, 0] * B / np.maximum(c.prev_left[:, 0] - c.prev_right[:, 0], 1e-3)
        X = np.stack([(c.prev_left[:, 0] - K[0, 2]) * z / K[0, 0],
                      (c.prev_left[:, 1] - K[1, 2]) * z / K[1, 1], z], axis=1)
        ok, rvec, tvec, _ = cv2.solvePnPRansac(X, c.cur_left, K, None, reprojectionError=1.0,
                                               iterationsCount=200)
        assert ok
        proj, _ = cv2.projectPoints(X, rvec, tvec, K, None)
        fit.append(np.linalg.norm(proj.reshape(-1, 2) - c.cur_left, axis=1))
        assert np.all(np.isfinite(c.cur_left)) and np.all(np.isfinite(c.cur_right))
    err_l, err_r, fit = map(np.concatenate, (err_l, err_r, fit))
    assert np.median(counts) > 80
    assert np.median(err_l) < limit_px
    assert np.median(err_r) < limit_px
    assert np.median(fit) < 0.5
    assert np.mean(fit < 1.0) > 0.65


def test_config_dataclass_is_not_mutated():
    cfg = config()
    before = dataclasses.asdict(cfg)
    tracker = StereoTracker(cfg, BucketingConfig())
    tracker.track(*pair(M1), rectified_calib())
    assert dataclasses.asdict(cfg) == before


def stripes(shift: tuple[float, float], modulation: float = 4.0) -> np.ndarray:
    """uint8 image of vertical stripes with a faint vertical modulation (edges, no corners)."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = xs - shift[0], ys - shift[1]
    v = 128 + 90 * np.sin(2 * np.pi * x / 23.0) * np.sin(2 * np.pi * x / 61.0) + \
        modulation * np.sin(2 * np.pi * y / 37.0)
    return np.clip(np.round(v), 0, 255).astype(np.uint8)


def test_eigen_ratio_separates_edges_from_corners():
    pts = np.array([[100.0, 100.0], [200.0, 150.0], [300.0, 200.0]])
    edges = eigen_ratio(stripes((0.0, 0.0)), pts, 21)
    corners = eigen_ratio(render((0.0, 0.0)), pts, 21)
    assert np.all(edges < 0.01) and np.all(corners > 0.1)
    assert eigen_ratio(np.full((H, W), 77, np.uint8), pts, 21).tolist() == [0.0] * 3
    assert eigen_ratio(render((0.0, 0.0)), np.zeros((0, 2)), 21).shape == (0,)


def test_aperture_check_drops_edge_features():
    calib = rectified_calib()

    def stripe_pair(motion):
        return stripes(motion), stripes((motion[0] - DISPARITY, motion[1]))

    # Without the check the stripes give features (their vertical flow rests on a 4 grey-level
    # modulation); with it none is detected, while a textured scene keeps its features.
    off = StereoTracker(config(min_eigen_ratio=0.0), BucketingConfig())
    assert off.track(*stripe_pair((0.0, 0.0)), calib).stats.n_features > 50
    on = StereoTracker(config(min_eigen_ratio=0.1), BucketingConfig())
    assert on.track(*stripe_pair((0.0, 0.0)), calib).stats.n_features == 0
    textured = StereoTracker(config(min_eigen_ratio=0.1), BucketingConfig())
    textured.track(*pair((0.0, 0.0)), calib)
    res = textured.track(*pair((2.0, 1.0)), calib)
    assert res.stats.failed['aperture'] < 0.1 * res.stats.n_previous
    assert res.stats.n_tracked > 100
    # Switched on at run time, the check drops the stripe features before the temporal pass.
    off.cfg = config(min_eigen_ratio=0.1)
    res = off.track(*stripe_pair((0.0, 3.0)), calib)
    assert res.stats.failed['aperture'] == res.stats.n_previous > 50
    assert res.stats.n_tracked == 0 and res.stats.pass_points['temporal_fwd'] == 0


def test_aperture_checks_test_every_point_on_its_own():
    img = render((0.0, 0.0))
    rng = np.random.default_rng(4)
    pts = rng.uniform([20, 20], [W - 20, H - 20], (40, 2))
    flow = rng.normal(0.0, 5.0, (40, 2))
    eigen_ok, flow_ok = aperture_checks(img, pts, flow, 21, 15, 0.3, 0.5)
    np.testing.assert_array_equal(eigen_ok, eigen_ratio(img, pts, 21) >= 0.3)
    np.testing.assert_array_equal(flow_ok, flow_edge_ratio(img, pts, flow, 15) >= 0.5)
    some = eigen_ok.nonzero()[0]  # the same values on a subset
    np.testing.assert_array_equal(aperture_checks(img, pts[some], flow[some], 21, 15, 0.3,
                                                  0.5)[1], flow_ok[some])
    assert 0 < eigen_ok.sum() < 40 and 0 < flow_ok.sum() < 40
    # Off (threshold 0, or no flow): every point passes.
    for args in ((flow, 0.0, 0.0), (None, 0.0, 0.5)):
        out = aperture_checks(img, pts, args[0], 21, 15, args[1], args[2])
        assert all(o.all() and o.shape == (40,) for o in out)


def test_aperture_checks_next_to_the_klt_pass_change_nothing():
    """With a helper thread the checks run next to the temporal pass: the same features."""
    calib = rectified_calib()
    cfg = config(min_eigen_ratio=0.3, min_flow_edge_ratio_tracked=0.5)
    helper = Workers(2, set_opencv=False, kind='thread')
    try:
        assert helper.overlaps and not inline().overlaps
        alone, beside = StereoTracker(cfg, BucketingConfig()), \
            StereoTracker(cfg, BucketingConfig(), helper)
        flow = np.array([3.0, 1.0])

        def prior(left, right):
            return left + flow, right + flow

        for k, motion in enumerate(((0.0, 0.0), (3.0, 1.0), (6.0, 2.0))):
            a = alone.track(*pair(motion), calib, prior if k else None)
            b = beside.track(*pair(motion), calib, prior if k else None)
            for x, y in zip(dataclasses.astuple(a.correspondences),
                            dataclasses.astuple(b.correspondences)):
                np.testing.assert_array_equal(x, y)
            assert a.stats.failed == b.stats.failed
            assert a.stats.pass_points == b.stats.pass_points
        assert a.stats.failed['aperture'] + a.stats.failed['flow_aperture'] > 0
    finally:
        helper.close()


def _alone_and_beside(first, second, calib, notes: list, prior=None):
    """
    Track two pairs with a tracker alone and with one that has a helper thread.

    Returns both trackers' outputs of the second pair. ``notes`` gets a list per tracker, for
    what a patched function notes while the tracker tracks the second pair: append to
    ``notes[-1]`` when it is not None.
    """
    helper = Workers(2, set_opencv=False, kind='thread')
    outs = []
    try:
        for workers in (inline(), helper):
            tracker = StereoTracker(config(), BucketingConfig(), workers)
            notes.append(None)
            tracker.track(*first, calib)
            notes[-1] = []
            outs.append(tracker.track(*second, calib, prior))
    finally:
        helper.close()
    return outs


def _assert_same_output(a, b) -> None:
    """Assert that the two trackers' outputs of a pair are the same, bit for bit."""
    for x, y in zip(dataclasses.astuple(a.correspondences) + dataclasses.astuple(a.raw),
                    dataclasses.astuple(b.correspondences) + dataclasses.astuple(b.raw)):
        np.testing.assert_array_equal(x, y)
    for key in ('features_left_raw', 'features_right_raw', 'feature_ids', 'feature_ages'):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert a.stats.failed == b.stats.failed
    assert len(a.correspondences) > 100


def test_gradient_matrix_sobel_is_opencv_sobel():
    img = noise(3)
    pts = np.array([[50.0, 40.0], [160.3, 170.6], [1.0, 2.0]])
    a, b, c, ok = gradient_matrix(img, pts[:2], 13, sobel=True)
    f = img.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    box = [cv2.boxFilter(g, -1, (13, 13), normalize=False) for g in (gx * gx, gx * gy, gy * gy)]
    x, y = np.round(pts[:2]).astype(int).T
    for got, want in zip((a, b, c), box):
        np.testing.assert_allclose(got, want[y, x], rtol=1e-4)
    assert ok.all()
    # Without Sobel: the central differences of eigen_ratio (trace larger on pixel noise).
    plain = gradient_matrix(img, pts[:2], 13)
    assert np.all(plain[0] + plain[2] > a + c)


def test_flow_edge_ratio_follows_the_flow_direction():
    pts = np.array([[100.0, 100.0], [200.0, 150.0], [300.0, 200.0]])
    edges = stripes((0.0, 0.0))  # vertical edges
    along = flow_edge_ratio(edges, pts, np.tile([0.0, 5.0], (3, 1)), 13)
    across = flow_edge_ratio(edges, pts, np.tile([-5.0, 0.0], (3, 1)), 13)
    assert np.all(along < 0.02) and np.all(across > 50.0)
    # Inverse of each other for opposite directions; a corner is near 1 either way.
    np.testing.assert_allclose(along * across, 1.0, rtol=1e-9)
    corner = flow_edge_ratio(render((0.0, 0.0)), pts, np.tile([3.0, 4.0], (3, 1)), 13)
    assert np.all((corner > 0.2) & (corner < 5.0))
    # No expected motion or no direction: the point passes any threshold.
    still = flow_edge_ratio(edges, pts, np.array([[0.0, 0.5], [np.nan, 1.0], [0.0, 1.0]]), 13)
    assert still[:2].tolist() == [np.inf, np.inf] and still[2] < 0.02
    assert flow_edge_ratio(np.full((H, W), 77, np.uint8), pts, np.ones((3, 2)), 13).tolist() \
        == [0.0] * 3
    assert flow_edge_ratio(edges, np.zeros((0, 2)), np.zeros((0, 2)), 13).shape == (0,)


def half_striped_pair(motion: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Rectified pair: texture left of x = W / 2, vertical stripes right of it, both moved."""
    left_half = np.arange(W) < W // 2

    def view(shift):  # stripes modulated enough to hold corners next to the texture
        return np.where(left_half[None, :], render(shift), stripes(shift, modulation=12.0))
    return view(motion), view((motion[0] - DISPARITY, motion[1]))


def test_flow_aperture_checks_drop_features_on_edges_along_the_flow():
    calib = rectified_calib()
    margin = 15.0
    # min_eigen_ratio 0: the isotropic aperture check would drop the stripes in any direction.
    on = config(min_eigen_ratio=0.0)
    off = config(min_eigen_ratio=0.0, min_flow_edge_ratio=0.0, min_flow_edge_ratio_tracked=0.0)
    striped = {}
    for name, cfg in (('on', on), ('off', off)):
        tracker = StereoTracker(cfg, BucketingConfig())
        # First pair: no prior, so no flow check at detection; both halves get features.
        first = tracker.track(*half_striped_pair((0.0, 0.0)), calib)
        n_striped = int(np.sum(first.features_left_raw[:, 0] > W / 2 + margin))
        n_textured = int(np.sum(first.features_left_raw[:, 0] < W / 2 - margin))
        assert n_striped > 10 and n_textured > 30
        # Vertical motion, along the stripes, predicted by the prior.
        res = tracker.track(*half_striped_pair((0.0, 2.0)), calib, prior=shift_prior((0.0, 2.0)))
        assert res.stats.used_prior
        kept = res.correspondences.prev_left
        striped[name] = (n_striped, res.stats.failed['flow_aperture'],
                         int(np.sum(kept[:, 0] > W / 2 + margin)),
                         int(np.sum(res.features_left_raw[:, 0] > W / 2 + margin)))
        assert np.sum(kept[:, 0] < W / 2 - margin) >= 0.9 * n_textured
    n_striped, failed, tracked, after = striped['on']
    # Every stripe feature is dropped before the temporal pass, and none is detected again.
    assert failed >= n_striped and tracked == 0 and after == 0
    n_striped, failed, tracked, after = striped['off']
    assert failed == 0 and tracked > 0.5 * n_striped and after >= tracked

    # Motion across the stripes: the same features pass.
    tracker = StereoTracker(on, BucketingConfig())
    tracker.track(*half_striped_pair((0.0, 0.0)), calib)
    res = tracker.track(*half_striped_pair((2.0, 0.0)), calib, prior=shift_prior((2.0, 0.0)))
    assert res.stats.failed['flow_aperture'] == 0
    assert np.sum(res.correspondences.prev_left[:, 0] > W / 2 + margin) > 10


def occluder_pair(boundary: int, far: float, near: float) -> tuple[np.ndarray, np.ndarray]:
    """Rectified pair: a textured band (rows above ``boundary``) in front of a textured plane."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)

    def view(shift_far: float, shift_near: float) -> np.ndarray:
        v = np.where(ys < boundary, texture(xs - shift_near, ys, seed=2),
                     texture(xs - shift_far, ys, seed=1))
        return np.clip(np.round(v), 0, 255).astype(np.uint8)
    return view(0.0, 0.0), view(-far, -near)


def test_smaller_stereo_refinement_window_near_an_occluding_edge():
    # Corners of the far plane (disparity 8 px) up to 10 rows below a nearer band (10 px): the
    # windows that reach into the band take some of its disparity. The stereo refinement's
    # own, smaller window (tracker.affine_stereo_win_size_px) takes less of it; corners away
    # from the edge are exact either way.
    calib = rectified_calib()
    boundary, far = 150, 8.0
    left, right = occluder_pair(boundary, far, 10.0)
    error = {}
    for win in (21, 15):
        tracker = StereoTracker(config(affine_stereo_win_size_px=win, max_features=400,
                                       min_distance_px=6.0), BucketingConfig())
        tracker.track(left, right, calib)
        q = tracker.track(left, right, calib).correspondences  # the same pair again
        disparity = q.cur_left[:, 0] - q.cur_right[:, 0]
        rows = q.cur_left[:, 1]
        near_edge = (rows > boundary + 1) & (rows < boundary + 11)
        away = rows > boundary + 15
        assert near_edge.sum() >= 8 and away.sum() >= 50
        assert np.abs(disparity[away] - far).max() < 0.05
        error[win] = float(np.mean(disparity[near_edge] - far))
    assert error[21] > 0.3  # measured 0.46 px
    assert 0.0 < error[15] < 0.85 * error[21]  # measured 0.34 px


# -- photometric compensation ---------------------------------------------------------------
def exposed(img: np.ndarray, gain: float, offset: float, vignetting: float = 0.0,
            centre: tuple[float, float] | None = None) -> np.ndarray:
    """
    Return an image with a camera gain, offset (grey levels) and radial vignetting.

    Returns
    -------
    np.ndarray
        (H, W) uint8: ``gain * img * V + offset``, ``V = 1 - vignetting * (r / r_corner)^2``.

    """
    h, w = img.shape
    cx, cy = centre if centre is not None else ((w - 1) / 2, (h - 1) / 2)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    v = gain * img.astype(np.float64) * (1.0 - vignetting * r2) + offset
    return np.clip(np.round(v), 0, 255).astype(np.uint8)


#: (gain, offset) of prev left, prev right, cur left, cur right: every pair of images of the
#: two frames differs by up to a third in gain.
EXPOSURES = ((1.0, 0.0), (1.25, -4.0), (0.75, 5.0), (1.2, 3.0))


@pytest.mark.parametrize('vignetting, use_prior', [(0.0, False), (0.3, False), (0.3, True)])
def test_independent_exposure_jumps_of_the_cameras_keep_tracking(vignetting, use_prior):
    """Gains 0.75-1.25, offsets and vignetting differing between cameras: tracks survive."""
    calib = rectified_calib()
    delta = (M2[0] - M1[0], M2[1] - M1[1])
    images = [*pair(M1), *pair(M2)]
    centres = (None, (W / 2 + 30, H / 2 + 10), None, (W / 2 + 30, H / 2 + 10))
    strength = (vignetting, 1.1 * vignetting, vignetting, 1.1 * vignetting)
    changed = [exposed(img, g, o, s, c) for img, (g, o), s, c in
               zip(images, EXPOSURES, strength, centres)]
    counts = {}
    for label, imgs, comp in (('clean', images, True), ('exposed', changed, True),
                              ('uncompensated', changed, False)):
        tracker = StereoTracker(config(photometric_compensation=comp), BucketingConfig())
        first = tracker.track(imgs[0], imgs[1], calib)
        res = tracker.track(imgs[2], imgs[3], calib, shift_prior(delta) if use_prior else None)
        assert res.stats.used_prior == use_prior
        c = res.correspondences
        counts[label] = (first.stats.n_features, len(c))
        if label != 'uncompensated':
            for err in shift_errors(c, delta):
                assert np.median(err) < 0.03, label
                assert np.percentile(err, 95) < 0.1, label
    assert counts['exposed'][0] > 0.9 * counts['clean'][0]
    assert counts['exposed'][1] > 0.9 * counts['clean'][1]
    # Without the compensation KLT (squared differences) drifts and the checks drop the
    # features (measured: 139 and 82 of 186 kept, mostly by the left-right check).
    assert counts['uncompensated'][1] < 0.8 * counts['exposed'][1]


def test_brightness_maps_made_ahead_on_a_helper_change_nothing(monkeypatch):
    """With a helper the stereo and bi-circular passes' images are mapped ahead: same output."""
    calib = rectified_calib()
    delta = (M2[0] - M1[0], M2[1] - M1[1])
    # Every image of the two pairs differs from the others in gain: all three maps apply.
    exposures = ((1.0, 0.0), (1.25, -4.0), (0.75, 5.0), (0.95, 3.0))
    changed = [exposed(img, g, o) for img, (g, o) in zip([*pair(M1), *pair(M2)], exposures)]
    real = photometric.apply_transfer
    made: list = []  # per tracker: (made in the caller's thread, changed the image)

    def recorded(img, *args):
        out = real(img, *args)
        if made[-1] is not None:
            made[-1].append((threading.current_thread() is threading.main_thread(),
                             out is not img))
        return out
    monkeypatch.setattr(photometric, 'apply_transfer', recorded)
    a, b = _alone_and_beside(changed[:2], changed[2:], calib, made, shift_prior(delta))
    made = [sorted(run) for run in made]
    # Alone: temporal, stereo and bi-circular maps in the caller. With the helper: the temporal
    # one in the caller, the two others on the helper, each made once.
    assert made[0] == [(True, True)] * 3
    assert made[1] == [(False, True), (False, True), (True, True)]
    _assert_same_output(a, b)


def test_photometric_map_is_not_applied_to_matching_images():
    """Equal exposures: the tracker sees the images as given (same output as switched off)."""
    calib = rectified_calib()
    outs = []
    for comp in (True, False):
        tracker = StereoTracker(config(photometric_compensation=comp), BucketingConfig())
        tracker.track(*pair(M1), calib)
        outs.append(tracker.track(*pair(M2), calib).correspondences)
    np.testing.assert_array_equal(outs[0].cur_right, outs[1].cur_right)
    np.testing.assert_array_equal(outs[0].cur_left, outs[1].cur_left)


def test_brightness_transfer_recovers_gain_and_offset():
    """Histogram quantiles give the gain and offset of an exposure change; saturation ignored."""
    from stereo_vo_ros.tracking.photometric import apply_transfer, brightness_transfer, histogram
    img = render((0.0, 0.0), seed=3)
    brighter = exposed(img, 1.3, -6.0)  # saturates the brightest pixels
    gain, offset = brightness_transfer(histogram(img), histogram(brighter))
    assert gain == pytest.approx(1.3, abs=0.02)
    assert offset == pytest.approx(-6.0, abs=2.0)
    back = apply_transfer(brighter, *brightness_transfer(histogram(brighter), histogram(img)))
    ok = brighter < 250
    assert np.abs(back[ok].astype(float) - img[ok]).mean() < 1.0
    assert apply_transfer(img, 1.001, 0.1) is img


def test_window_transfer_from_predicted_positions():
    """Window statistics at roughly known positions give gain and offset despite the motion."""
    from stereo_vo_ros.tracking.photometric import window_transfer
    a = render((0.0, 0.0), seed=5)
    b = exposed(render((3.0, -2.0), seed=5), 0.8, 7.0)
    rng = np.random.default_rng(0)
    pts = rng.uniform([30, 30], [W - 30, H - 30], (150, 2))
    # positions in b off by up to a pixel from the truth (a prediction)
    fit = window_transfer(a, pts, b, pts + (3.0, -2.0) + rng.uniform(-1, 1, (150, 2)))
    assert fit is not None
    assert fit[0] == pytest.approx(0.8, abs=0.01)
    assert fit[1] == pytest.approx(7.0, abs=1.5)
    assert window_transfer(a, pts[:5], b, pts[:5]) is None  # too few windows


def test_window_stats_match_the_sampled_windows():
    """Mean, std and usability of each window: as computed directly from its samples."""
    from stereo_vo_ros.tracking.photometric import (MAX_WINDOWS, MIN_WINDOW_STD_GREY,
                                                    SATURATED_GREY, WINDOW_STEP_PX, window_stats)
    rng = np.random.default_rng(4)
    img = render((0.0, 0.0), seed=2)
    other = exposed(img, 1.2, 10.0)
    other[:40] = 255  # a saturated band
    other[-40:, :60] = 90  # a flat corner
    half = 6
    n = MAX_WINDOWS + 9  # more than are used: rows spread over them are taken
    pts = [rng.uniform([-5, -5], [W + 5, H + 5], (n, 2)) for _ in range(2)]
    pts[0][3] = np.nan
    pts[1][:5] = [(30.0, 10.0), (W - half - 0.6, 60.0), (20.0, H - 10.0), (half, half),
                  (W - 1 - half, H - 1 - half)]
    mean, std, ok = window_stats((img, other), tuple(pts), half)
    rows = np.linspace(0, n - 1, MAX_WINDOWS).astype(int)
    assert mean.shape == std.shape == ok.shape == (2, MAX_WINDOWS)
    assert mean.dtype == std.dtype == np.float32
    r = np.arange(-half, half + 1, WINDOW_STEP_PX)
    usable = 0
    for m, (image, p) in enumerate(zip((img, other), pts)):
        for j, row in enumerate(rows):
            x, y = p[row]
            inside = np.isfinite(x) and np.isfinite(y) and half <= round(x) < W - half and \
                half <= round(y) < H - half
            if not inside:
                assert not ok[m, j]
                continue
            win = image[int(np.rint(y)) + r][:, int(np.rint(x)) + r].astype(np.float64)
            assert mean[m, j] == pytest.approx(win.mean(), abs=1e-4)
            assert std[m, j] == pytest.approx(win.std(), abs=1e-3)
            expected = (win.std() > MIN_WINDOW_STD_GREY and win.max() < 255 - SATURATED_GREY
                        and win.min() > SATURATED_GREY)
            assert ok[m, j] == expected
            usable += expected
    assert 0 < usable < 2 * MAX_WINDOWS
    assert window_stats((img,), (np.zeros((0, 2)),)) is None
    tiny = img[:2 * half, :50]  # no window of half side 6 fits
    assert window_stats((tiny,), (np.array([[25.0, 6.0]]),), half) is None


def test_check_helpers_agree_with_their_numpy_forms():
    """The checks' written-out forms give NumPy's values, NaN rows fail, no warning raised."""
    rng = np.random.default_rng(3)
    a = rng.uniform(-20.0, 700.0, (300, 2))
    b = a + rng.normal(0.0, 3.0, a.shape)
    a[::7, 0], a[::11, 1], b[::13] = np.nan, np.inf, -np.inf
    with np.errstate(invalid='ignore'):  # inf - inf: NaN, as before
        norm = np.linalg.norm(a - b, axis=1)
        assert np.array_equal(round_trip_error(a, b), np.where(np.isfinite(norm), norm, np.inf))
    assert np.array_equal(finite_rows(a), np.all(np.isfinite(a), axis=1))
    assert not finite_rows(a).all() and finite_rows(a).any()
    # The borders are inclusive: exactly on them is inside, the next float out is not.
    edges = np.array([[10.0, 100.0], [np.nextafter(10.0, 0.0), 100.0], [629.0, 100.0],
                      [np.nextafter(629.0, 1e9), 100.0], [100.0, 10.0],
                      [100.0, np.nextafter(10.0, 0.0)], [100.0, 469.0],
                      [100.0, np.nextafter(469.0, 1e9)]])
    with np.errstate(all='raise'):  # comparisons with NaN must not warn
        assert inside_image(edges, (640, 480), 10.0).tolist() == [True, False] * 4
        inside = inside_image(a, (640, 480), 10.0)
    with np.errstate(invalid='ignore'):
        expected = (np.all(np.isfinite(a), axis=1) & (a[:, 0] >= 10) & (a[:, 1] >= 10)
                    & (a[:, 0] <= 629) & (a[:, 1] <= 469))
    assert np.array_equal(inside, expected) and inside.any() and not inside.all()
    # Buckets of 80 x 120 pixels (exact in binary): the index by whole divisions, points on
    # every edge and just below it, outside on every side.
    cfg = dataclasses.replace(BucketingConfig(), cols=8, rows=4, roi_margin_px=0)
    xs = np.concatenate([np.arange(0.0, 641.0, 80.0), np.nextafter(np.arange(0.0, 641.0, 80.0),
                                                                   -1.0), [-1e-9, 700.0]])
    ys = np.concatenate([np.arange(0.0, 481.0, 120.0),
                         np.nextafter(np.arange(0.0, 481.0, 120.0), -1.0), [-1e-9, 500.0]])
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < 640) & (pts[:, 1] >= 0) & (pts[:, 1] < 480)
    brute = (pts[:, 1] // 120).astype(int) * 8 + (pts[:, 0] // 80).astype(int)
    got = bucketing.bucket_index(pts, (640, 480), cfg)
    assert np.array_equal(got, np.where(inside, brute, -1))
    assert set(got[inside].tolist()) == set(range(32)) and (got == -1).any()


def _transfer_from_stats_sorted(mean_from, std_from, ok_from, mean_to, std_to, ok_to):
    """``photometric.transfer_from_stats`` as it was written first (whole sorts)."""
    ok = ok_from & ok_to
    if np.count_nonzero(ok) < photometric.MIN_WINDOWS:
        return None
    log_ratio = np.sort(np.log(std_to[ok] / std_from[ok]))
    q = len(log_ratio) // 4
    if log_ratio[len(log_ratio) - 1 - q] - log_ratio[q] > photometric.MAX_LOG_SPREAD:
        return None
    gain = photometric._middle_mean(std_to[ok] / std_from[ok])
    if not photometric.GAIN_RANGE[0] <= gain <= photometric.GAIN_RANGE[1]:
        return None
    return gain, photometric._middle_mean(mean_to[ok] - gain * mean_from[ok])


def test_transfer_from_stats_takes_the_quartiles_of_the_logarithms():
    """Selected quartiles give the sorted ones' map, also at the spread's limit in float32."""
    rng = np.random.default_rng(5)
    seen = set()
    for case in range(600):
        n = int(rng.integers(8, 150))
        std_from = rng.uniform(3.0, 60.0, n).astype(np.float32)
        spread = rng.choice([0.05, 0.19, 0.2, 0.21, 0.4]) * rng.uniform(0.9, 1.1)
        std_to = (std_from * np.float32(rng.uniform(0.5, 2.0))
                  * np.exp(rng.uniform(-spread, spread, n)).astype(np.float32))
        mean_from = rng.uniform(20.0, 200.0, n).astype(np.float32)
        mean_to = (mean_from * 1.1 + 5.0).astype(np.float32)
        ok_from, ok_to = rng.random(n) > 0.1, rng.random(n) > 0.1
        args = (mean_from, std_from, ok_from, mean_to, std_to, ok_to)
        want = _transfer_from_stats_sorted(*args)
        assert photometric.transfer_from_stats(*args) == want, case
        seen.add(want is None)
    assert seen == {True, False}


def test_same_as_sees_either_camera_change():
    """A calibration is the same as itself and its copy, not as one with another distortion."""
    import copy
    calib = distorted_calib()
    assert calib.same_as(calib) and calib.same_as(copy.deepcopy(calib))
    for side in ('left', 'right'):
        other = copy.deepcopy(calib)
        getattr(other, side).D[0] += 1e-3
        assert not calib.same_as(other) and not other.same_as(calib), side
