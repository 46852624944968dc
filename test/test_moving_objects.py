"""Vehicles that move with the camera: ground-plane weights, outlier streaks, uninformed prior."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from stereo_vo_ros.config import Config, load
from stereo_vo_ros.estimation.camera import StereoCalibration
from stereo_vo_ros.estimation.estimator import MotionEstimator
from stereo_vo_ros.estimation.motion import TransferModel, transform_from_velocity
from stereo_vo_ros.pipeline import StereoOdometry
from stereo_vo_ros.records import Correspondences, TrackingStatus
from stereo_vo_ros.road.ground_plane import (
    fit_ground_plane, ground_mask, ROAD_BLUR_PX, road_pixels_seen, road_speed, triangulate)
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer

from test_estimator_core import kitti_calibration, observe, raw_rig

REPO = Path(__file__).resolve().parents[1]

CAMERA_HEIGHT_M = 1.65
#: How far the road speed search's speed at a first pair may lie from the truth (fraction of
#: it): it measures over the features' ground plane (its height off by -6 to +4 % over rendered
#: highways, and the speed with it) on a 1 m/s grid. The tested scenes give up to -6.7 %
#: (highway_photometric 53 on OpenCV 4's render: 25 m/s for 26.8); the failures they guard
#: took the vehicles' motion or no speed at all, off by about the whole speed.
SEARCH_ERROR = 0.1
#: Forward motion at 25 m/s (camera optical frame: z forward).
HIGHWAY = np.array([0.0, 0.0, 25.0, 0.0, 0.0, 0.0])
DT = 0.1


def road_points(rng, n, tilt_deg=0.0):
    """Points on a road plane CAMERA_HEIGHT_M below the camera, pitched by tilt_deg."""
    x, z = rng.uniform(-6, 6, n), rng.uniform(6, 40, n)
    y = CAMERA_HEIGHT_M + np.tan(np.radians(tilt_deg)) * (z - 10.0)
    return np.column_stack([x, y, z])


def box_points(rng, n, z0=12.0):
    """Points on the rear of a vehicle ahead (a vertical face, above the road)."""
    return np.column_stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-1.5, 1.2, n),
                            z0 + rng.uniform(0, 0.2, n)])


def far_points(rng, n):
    """Distant background: fits almost any forward speed within the inlier threshold."""
    return np.column_stack([rng.uniform(-40, 40, n), rng.uniform(-20, -5, n),
                            rng.uniform(400, 600, n)])


def config(**dotted):
    base = {'bucketing.enabled': False, 'filter.threshold_velocity': 1e-3,
            'filter.threshold_angular_deg': 1e-3}
    base.update(dotted)
    return Config().replace(**base)


def test_ground_plane_is_found_among_walls_and_vehicles():
    rng = np.random.default_rng(1)
    road = road_points(rng, 60, tilt_deg=3.0)
    other = np.vstack([box_points(rng, 40), np.column_stack(
        [np.full(30, 7.0), rng.uniform(-3, 1.5, 30), rng.uniform(8, 40, 30)])])  # a wall
    cfg = Config().ransac
    plane = fit_ground_plane(np.vstack([road, other]), cfg, np.random.default_rng(0))
    assert plane is not None
    normal, d = plane
    true_normal = np.array([0.0, np.cos(np.radians(3.0)), -np.sin(np.radians(3.0))])
    assert np.degrees(np.arccos(np.clip(normal @ true_normal, -1, 1))) < 0.5
    assert abs(d - (road[0] @ true_normal)) < 0.02
    # From pixels: exactly the road points are on the ground.
    calib = kitti_calibration()
    pts = np.vstack([road, other])
    pl, pr, _, _ = observe(calib, pts, np.eye(4))
    np.testing.assert_allclose(triangulate(calib, pl, pr), pts, atol=1e-6)
    mask = ground_mask(triangulate(calib, pl, pr), cfg, np.random.default_rng(0))
    np.testing.assert_array_equal(mask, np.arange(len(pts)) < len(road))
    # The estimator's transfer model triangulates the same points.
    model = TransferModel(calib, pl, pr, DT)
    np.testing.assert_allclose(model.points(), pts, atol=1e-6)
    np.testing.assert_array_equal(ground_mask(model.points(), cfg, np.random.default_rng(0)),
                                  mask)


def test_triangulation_of_a_raw_rig_with_a_rotated_right_camera():
    raw, K1, K2, R_rl, t_rl = raw_rig()
    rng = np.random.default_rng(7)
    X = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-2, 2, 50), rng.uniform(2, 30, 50)])
    left = (X @ K1.T)[:, :2] / X[:, 2:]
    Xr = X @ R_rl.T + t_rl
    right = (Xr @ K2.T)[:, :2] / Xr[:, 2:]
    np.testing.assert_allclose(triangulate(raw, left, right), X, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(TransferModel(raw, left, right, DT).points(), X, rtol=1e-6,
                               atol=1e-6)
    # Parallel rays (zero disparity) meet nowhere: NaN, also on a rectified rig.
    kitti = kitti_calibration()
    same = np.array([[600.0, 200.0], [300.0, 250.0]])
    assert np.isnan(triangulate(kitti, same, same)).all()
    assert np.isnan(TransferModel(kitti, same, same, DT).points()).all()
    # Negative disparity: behind the camera.
    assert np.isnan(TransferModel(kitti, same, same + [5.0, 0.0], DT).points()).all()
    far = triangulate(kitti, np.array([[600.0, 200.0]]), np.array([[599.0, 200.0]]))
    assert far[0, 2] == pytest.approx(kitti.K_left[0, 0] * kitti.baseline_m)
    # Behind the camera, or not finite: NaN.
    out = triangulate(raw, np.array([[np.nan, 1.0], [300.0, 200.0]]),
                      np.array([[1.0, 1.0], [400.0, 200.0]]))
    assert np.isnan(out).all()


@pytest.mark.parametrize('scene', ['wall only', 'ground too steep', 'camera too high'])
def test_no_ground_plane_without_an_admissible_road(scene):
    rng = np.random.default_rng(2)
    if scene == 'wall only':
        pts = np.column_stack([np.full(50, 5.0), rng.uniform(0.2, 3, 50), rng.uniform(5, 30, 50)])
    elif scene == 'ground too steep':
        pts = road_points(rng, 50, tilt_deg=30.0)
    else:
        pts = road_points(rng, 50) + np.array([0.0, 6.0, 0.0])
    cfg = Config().ransac
    assert fit_ground_plane(pts, cfg, np.random.default_rng(0)) is None
    calib = kitti_calibration()
    pl, pr, _, _ = observe(calib, pts, np.eye(4))
    assert not ground_mask(triangulate(calib, pl, pr), cfg, np.random.default_rng(0)).any()


def co_moving_scene(rng):
    """Return a bus ahead at the camera's speed (35 points), the road (25) and far points (10)."""
    calib = kitti_calibration()
    T = transform_from_velocity(HIGHWAY, DT)
    road, far, bus = road_points(rng, 25), far_points(rng, 10), box_points(rng, 35)
    pl, pr, cl, cr = observe(calib, np.vstack([road, far]), T)
    bl, br, _, _ = observe(calib, bus, np.eye(4))  # moves with the camera: pixels stay
    noise = 0.1
    corr = Correspondences(np.vstack([pl, bl]), np.vstack([pr, br]),
                           np.vstack([cl, bl]) + rng.normal(0, noise, (70, 2)),
                           np.vstack([cr, br]) + rng.normal(0, noise, (70, 2)))
    return calib, corr


def test_ground_weight_prefers_the_road_to_a_bus_at_the_same_speed():
    calib, corr = co_moving_scene(np.random.default_rng(3))
    # Kitt et al.'s plain count: the bus and the far points (45) outvote the road and the far
    # points (35), and the camera seems to stand still.
    plain = MotionEstimator(config(**{'ransac.ground_weight': 1.0})).estimate(corr, calib, DT)
    assert plain.status is TrackingStatus.OK
    assert np.linalg.norm(plain.velocity[:3]) < 2.0
    assert plain.inliers[35:].all()
    # Road inliers counted 4 times: the true motion wins and the bus is an outlier.
    res = MotionEstimator(config()).estimate(corr, calib, DT)
    assert res.status is TrackingStatus.OK
    np.testing.assert_allclose(res.velocity[:3], HIGHWAY[:3], atol=0.3)
    assert not res.inliers[35:].any()
    assert res.inliers[:25].sum() >= 23


def test_features_that_keep_failing_are_left_out_until_they_fit():
    rng = np.random.default_rng(4)
    calib = kitti_calibration()
    static, vehicle = rng.uniform([-15, -3, 6], [15, 1, 50], (40, 3)), box_points(rng, 60, 20.0)
    ids = np.arange(100)
    y = np.array([0.2, 0.0, 10.0, 0.0, 0.05, 0.0])
    T = transform_from_velocity(y, DT)

    def frame(vehicle_offsets):
        pl, pr, cl, cr = observe(calib, np.vstack([static, vehicle]), T)
        cl, cr = cl.copy(), cr.copy()
        cl[40:] += vehicle_offsets
        cr[40:] += vehicle_offsets
        return Correspondences(pl, pr, cl, cr, ids, np.ones(100, np.int64))

    def co_moving():  # the vehicle's pixels stay where they were
        pl, pr, _, _ = observe(calib, vehicle, np.eye(4))
        c = frame(np.zeros((60, 2)))
        c.cur_left[40:], c.cur_right[40:] = pl, pr
        return c

    def run(streak):
        draw = np.random.default_rng(5)  # the same history for both runs
        # 60 % outliers: enough samples to draw a clean one (ransac.outlier_ratio).
        est = MotionEstimator(config(**{'ransac.ground_weight': 1.0,
                                        'ransac.outlier_ratio': 0.7,
                                        'ransac.max_outlier_streak': streak}))
        est.reset(velocity=y)
        est.cov = np.diag([0.5 ** 2] * 3 + [np.radians(3.0) ** 2] * 3)
        for _ in range(3):  # the vehicle's features do not agree with each other
            offsets = draw.uniform(15, 30, (60, 2)) * draw.choice([-1, 1], (60, 2))
            res = est.estimate(frame(offsets), calib, DT)
            assert res.status is TrackingStatus.OK
            assert res.inliers[:40].all() and not res.inliers[40:].any()
        return est, est.estimate(co_moving(), calib, DT)

    est, res = run(streak=3)
    assert all(est.outlier_streak.get(i, 0) >= 3 for i in range(40, 100))
    assert not any(est.outlier_streak.get(i, 0) for i in range(40))
    np.testing.assert_allclose(res.velocity[:3], y[:3], atol=0.3)
    assert not res.inliers[40:].any()
    # Without the streaks the vehicle, now consistent and in the majority, pulls the motion
    # away (the tight prior keeps it from a standstill).
    _, bad = run(streak=0)
    assert np.abs(bad.velocity[:3] - y[:3]).max() > 1.0
    # A left-out feature that fits the accepted motion again is taken back.
    est.estimate(frame(np.zeros((60, 2))), calib, DT)
    assert not any(est.outlier_streak.get(i, 0) for i in range(100))
    res = est.estimate(frame(np.zeros((60, 2))), calib, DT)
    assert res.inliers[40:].sum() >= 55
    # Never so many left out that fewer than pipeline.min_features remain: then all are used.
    est.outlier_streak = dict.fromkeys(range(100), 10)
    res = est.estimate(frame(np.zeros((60, 2))), calib, DT)
    assert res.status is TrackingStatus.OK and res.inliers.sum() >= 95
    assert est.outlier_streak == {}
    # A reset forgets the streaks.
    est.outlier_streak[7] = 5
    est.reset()
    assert est.outlier_streak == {}


def test_tracker_searches_without_a_prior_while_the_velocity_is_unknown():
    calib = kitti_calibration()
    vo = StereoOdometry(Config())
    assert vo.estimator.cov[0, 0] ** 0.5 > vo.config.pipeline.prior_max_velocity_std
    assert vo._prior(calib, calib, DT) is None
    vo.estimator.cov = np.eye(6) * 0.01
    predict = vo._prior(calib, calib, DT)
    assert callable(predict)
    # One coasted pair (no estimate) keeps the prediction; a second one loses it.
    vo.estimator.mean = np.array([0.0, 0.0, 25.0, 0.0, 0.0, 0.0])
    vo.estimator.coast()
    assert callable(vo._prior(calib, calib, DT))
    vo.estimator.coast()
    assert vo._prior(calib, calib, DT) is None


def render_pairs(preset, seed, frames, n_frames=None, depth=False):
    """Render the first ``frames`` pairs of a preset's scene (laid out for ``n_frames``)."""
    extra = {} if n_frames is None else {'n_frames': n_frames}
    renderer = StereoRenderer(SequenceSpec.preset(preset, seed=seed, **extra))
    return renderer.calibration, [renderer.render(i, depth=depth) for i in range(frames)]


def step_ratios(config, calib, frames):
    """
    Run the pipeline over rendered frames.

    Returns the estimated over the true step length of each pair after the first, and the
    status of each of those pairs.
    """
    vo = StereoOdometry(config)
    ratios, statuses, prev = [], [], None
    for fr in frames:
        res = vo.process(fr.stereo_frame(calib))
        if prev is not None:
            true_step = np.linalg.norm(fr.T_world_cam[:3, 3] - prev[1][:3, 3])
            ratios.append(np.linalg.norm(res.T_world_cam[:3, 3] - prev[0][:3, 3]) / true_step)
            statuses.append(res.status)
        prev = (res.T_world_cam.copy(), fr.T_world_cam)
    vo.close()
    return np.asarray(ratios), statuses


def test_rendered_highway_behind_buses_starts_at_the_true_speed():
    """Highway seed 1 starts behind two buses at the camera's speed (it used to start at 4 %)."""
    calib, frames = render_pairs('highway', 1, 12)
    ratios, statuses = step_ratios(Config(), calib, frames)
    assert all(status is TrackingStatus.OK for status in statuses)
    assert np.median(ratios) > 0.95
    assert min(ratios) > 0.8


@pytest.mark.parametrize('seed', [15, 35])
def test_road_alignment_finds_the_forward_speed_behind_vehicles(seed):
    """Seeds 15 and 35 start behind buses; their first estimate used to take the buses' speed."""
    calib, (f0, f1) = render_pairs('highway', seed, 2)
    cfg = Config()
    vo = StereoOdometry(cfg)
    vo.process(f0.stereo_frame(calib))
    left, right = vo.tracker.feature_points()
    plane = fit_ground_plane(triangulate(calib, left, right), cfg.ransac,
                             np.random.default_rng(0))
    assert plane is not None
    assert plane[1] == pytest.approx(1.65, abs=0.1)  # the renderer's camera height
    true_speed = np.linalg.norm(f1.T_world_cam[:3, 3] - f0.T_world_cam[:3, 3]) / DT
    for prev_right in (None, f0.right):
        found = road_speed(f0.left, f1.left, calib, plane, DT, np.arange(-10.0, 61.0),
                           prev_right)
        assert abs(found.speed - true_speed) <= SEARCH_ERROR * true_speed
        assert found.contrast < 0.8
    # The same image twice: the road is best aligned at rest, and the pipeline adds no prior.
    at_rest = road_speed(f0.left, f0.left, calib, plane, DT, np.arange(-10.0, 61.0))
    assert at_rest.speed == 0.0 and at_rest.contrast == 1.0
    assert vo._road_prior(f0.stereo_frame(calib), calib, DT) is None
    moving = vo._road_prior(f1.stereo_frame(calib), calib, DT)
    assert callable(moving)


def blurred(img):
    return cv2.GaussianBlur(img, (0, 0), ROAD_BLUR_PX).astype(np.float32)


def test_road_pixels_seen_keeps_the_road_and_leaves_out_the_lorry_in_front_of_it():
    """Highway seed 23 (150 frames) starts behind a lorry in the middle of the road region."""
    calib, (pair,) = render_pairs('highway', 23, 1, n_frames=150, depth=True)
    f, cy = calib.K_left[0, 0], calib.K_left[1, 2]
    h, w = pair.left.shape
    ys, xs = (a.ravel().astype(np.float64) for a in np.mgrid[int(cy) + 1:h:4, 0:w:4])
    depth = CAMERA_HEIGHT_M * f / (ys - cy)  # the renderer's flat road
    near = (depth > 2.0) & (depth < 40.0)
    xs, ys, depth = xs[near], ys[near], depth[near]
    seen = road_pixels_seen(blurred(pair.left), blurred(pair.right), xs, ys,
                            f * calib.baseline_m / depth)
    row, col = ys.astype(int), xs.astype(int)
    vehicle = ~pair.static_left[row, col]
    gx, gy = (cv2.Sobel(blurred(pair.left), cv2.CV_32F, *d) for d in ((1, 0), (0, 1)))
    textured = np.hypot(gx, gy)[row, col] > 20.0
    assert np.count_nonzero(vehicle & textured) > 300
    assert seen[~vehicle].mean() > 0.85
    assert seen[vehicle & textured].mean() < 0.5  # 0.36 measured
    # Matches that fall outside the right image are not kept.
    assert not road_pixels_seen(blurred(pair.left), blurred(pair.right), xs[:5], ys[:5],
                                xs[:5] + 1.0).any()


def first_pair_search(preset, seed):
    """
    Return what the road speed search of a rendered scene's first pair starts from.

    The calibration, ten rendered pairs of the 150-frame scene, the ground plane of the first
    pair's features and the true speed between the first two pairs (m/s).
    """
    calib, frames = render_pairs(preset, seed, 10, n_frames=150)
    f0, f1 = frames[:2]
    vo = StereoOdometry(Config())
    vo.process(f0.stereo_frame(calib))
    plane = fit_ground_plane(triangulate(calib, *vo.tracker.feature_points()), Config().ransac,
                             np.random.default_rng(0))
    vo.close()
    true_speed = np.linalg.norm(f1.T_world_cam[:3, 3] - f0.T_world_cam[:3, 3]) / DT
    return calib, frames, plane, true_speed


def test_road_speed_search_behind_a_lorry_compares_only_the_road():
    """
    Seed 23: the lorry keeps pace, so its pixels in the road region match best at rest.

    With them in, the minimum at the true speed was not clear enough to use (contrast 0.95)
    and the odometry kept the vehicles' speed for the whole drive (t_rel 101 %).
    """
    calib, frames, plane, true_speed = first_pair_search('highway', 23)
    f0, f1 = frames[:2]
    speeds = np.arange(-10.0, 61.0)
    everything = road_speed(f0.left, f1.left, calib, plane, DT, speeds)
    road_only = road_speed(f0.left, f1.left, calib, plane, DT, speeds, f0.right)
    assert everything.contrast > 0.8  # the failure
    assert abs(road_only.speed - true_speed) <= SEARCH_ERROR * true_speed
    assert road_only.contrast < 0.7
    # The pipeline starts from it and keeps the true speed.
    ratios, _ = step_ratios(Config(), calib, frames)
    assert np.median(ratios) > 0.95 and min(ratios) > 0.8


def test_road_speed_search_through_an_exposure_change():
    """
    The road speed search compares the road after matching the two frames' brightness.

    A camera's automatic exposure changes its gain and offset between frames. The photometric
    highway seed 53 starts with such a change: the grey-level differences then outweighed the
    road's texture, the search scored best at -10 m/s with a contrast of 0.95, no speed was
    taken, and the first pair took the vehicles' motion (a step 0.05 of the true one, and the
    constant-velocity prior held it: t_rel 96 %).
    """
    calib, frames, plane, true_speed = first_pair_search('highway_photometric', 53)
    f0, f1 = frames[:2]
    speeds = np.arange(-10.0, 61.0)
    found = road_speed(f0.left, f1.left, calib, plane, DT, speeds, f0.right)
    assert abs(found.speed - true_speed) <= SEARCH_ERROR * true_speed, (found, true_speed)
    assert found.contrast < 0.8, found
    # The same jump made by hand: the current image at 0.75 of the gain, 6 grey levels lower.
    darker = np.clip(f1.left.astype(np.float64) * 0.75 - 6.0, 0, 255).astype(np.uint8)
    jumped = road_speed(f0.left, darker, calib, plane, DT, speeds, f0.right)
    assert abs(jumped.speed - true_speed) <= SEARCH_ERROR * true_speed, (jumped, true_speed)
    assert jumped.contrast < 0.8, jumped
    # The pipeline starts from the speed found and keeps it.
    ratios, _ = step_ratios(Config(), calib, frames)
    assert np.median(ratios) > 0.95 and min(ratios) > 0.8, ratios


def test_road_speed_search_at_full_hd():
    """1920x1080: more road pixels than one ``cv2.remap`` call takes (it raised an error)."""
    f, width, height, baseline = 1000.0, 1920, 1080, 0.12
    P0 = np.array([[f, 0.0, width / 2, 0.0], [0.0, f, height / 2, 0.0], [0.0, 0.0, 1.0, 0.0]])
    P1 = P0.copy()
    P1[0, 3] = -f * baseline
    calib = StereoCalibration.from_projections(P0, P1, width, height)
    texture = cv2.GaussianBlur(np.random.default_rng(0).uniform(0, 255, (height, width)),
                               (0, 0), 2.0).astype(np.float32)
    # The right image of a flat road CAMERA_HEIGHT_M below: row y shifted by its disparity.
    rows = np.arange(height, dtype=np.float32)[:, None]
    shift = np.maximum(rows - height / 2, 0.0) * baseline / CAMERA_HEIGHT_M
    cols = np.arange(width, dtype=np.float32)[None, :] + shift
    right = cv2.remap(texture, cols, np.broadcast_to(rows, cols.shape).copy(), cv2.INTER_LINEAR)
    left = texture.astype(np.uint8)
    plane = (np.array([0.0, 1.0, 0.0]), CAMERA_HEIGHT_M)
    at_rest = road_speed(left, left, calib, plane, DT, np.arange(-10.0, 61.0),
                         right.astype(np.uint8))
    assert at_rest.speed == 0.0 and at_rest.contrast == 1.0


def test_rendered_full_hd_highway_starts_with_the_road():
    """The pipeline on 1920x1080 pairs: the search runs (it raised there) and gives the speed."""
    renderer = StereoRenderer(SequenceSpec.preset('highway', seed=0, n_frames=20, width=1920,
                                                  height=1080))
    frames = [renderer.render(i) for i in range(2)]
    ratios, _ = step_ratios(Config().replace(**{'pipeline.threads': 1}),
                            renderer.calibration, frames)
    assert len(ratios) == 1 and abs(ratios[0] - 1.0) < 0.05


def test_road_alignment_needs_a_road():
    calib = kitti_calibration()
    flat = np.full((calib.size[1], calib.size[0]), 128, np.uint8)
    plane = (np.array([0.0, 1.0, 0.0]), 1.65)
    # A textureless road cannot be aligned better than at rest: no clear minimum.
    found = road_speed(flat, flat, calib, plane, DT, np.arange(-10.0, 61.0))
    assert not found.contrast < 1.0
    # Ground 100 m below the camera: no pixel sees it within 40 m, nothing to compare.
    none = road_speed(flat, flat, calib, (np.array([0.0, 1.0, 0.0]), 100.0), DT,
                      np.arange(0.0, 5.0))
    assert np.isnan(none.speed) and np.isnan(none.contrast)


@pytest.mark.parametrize('search', [True, False])
def test_rendered_highway_behind_buses_at_speed_starts_with_the_road(search):
    """Seed 35: without the road alignment the first estimate took the buses' motion."""
    calib, frames = render_pairs('highway', 35, 10)
    ratios, _ = step_ratios(Config().replace(**{'pipeline.road_speed_search': search}),
                            calib, frames)
    if search:
        assert np.median(ratios) > 0.95 and min(ratios) > 0.8
    else:
        assert np.median(ratios) < 0.5  # the failure the search exists for


def test_road_vehicle_profile_keeps_its_speed_past_vehicles_that_keep_pace():
    """
    Highway seed 10: the profile keeps the speed next to buses that keep pace.

    A bare stretch leaves few static features next to them; tracking at most 100-120 features
    leaves about ten. Within two pairs those said the car had lost most of its 23 m/s; a car's
    acceleration (vehicle.acceleration_std in the profile) does not allow that. The profile
    keeps the speed with either sparse count, through the pairs that have too few inliers there
    (which pairs, if any, hangs on exact tracks: 0-6 of 29 seen; the speed then coasts on the
    prior, within 9.6 % of the truth), and tracks every pair with the default count.
    """
    calib, frames = render_pairs('highway', 10, 30, n_frames=150)
    profile = load(REPO / 'config' / 'road_vehicle.yaml')
    assert profile.vehicle.acceleration_std > 0
    sparse = [profile.replace(**{'tracker.max_features': n}) for n in (100, 120)]
    # The failure the acceleration bound is for (min ratio 0.20). Whether a feature count shows
    # it hangs on exact tracks (with 200 features it showed with OpenCV's KLT, not with this
    # one; 100, 110 and 130 show it with the road alignment's exact bilinear samples, 120 not;
    # on a render whose polygon edges differ by a few pixels 100-120 show it, 130 not): one of
    # two counts has to, and the bound must keep the speed there.
    failing = [config for config in sparse
               if min(step_ratios(config.replace(**{'vehicle.acceleration_std': 0.0}), calib,
                                  frames)[0]) < 0.6]
    assert failing
    for config in sparse:
        ratios, statuses = step_ratios(config, calib, frames)
        assert sum(status is not TrackingStatus.OK for status in statuses) <= len(statuses) // 3
        assert np.all(np.abs(ratios - 1) < 0.15), ratios
    ratios, statuses = step_ratios(profile, calib, frames)
    assert all(status is TrackingStatus.OK for status in statuses)
    assert np.all(np.abs(ratios - 1) < 0.1), ratios
