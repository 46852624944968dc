"""Vehicles that move with the camera: ground-plane weights, outlier streaks, uninformed prior."""

import numpy as np
import pytest

from stereo_vo_ros.config import Config
from stereo_vo_ros.estimation.estimator import MotionEstimator
from stereo_vo_ros.estimation.motion import TransferModel, transform_from_velocity
from stereo_vo_ros.pipeline import StereoOdometry
from stereo_vo_ros.records import Correspondences, TrackingStatus
from stereo_vo_ros.road.ground_plane import fit_ground_plane, ground_mask, road_speed, triangulate
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer

from test_estimator_core import kitti_calibration, observe, raw_rig

CAMERA_HEIGHT_M = 1.65
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


def test_rendered_highway_behind_buses_starts_at_the_true_speed():
    """Highway seed 1 starts behind two buses at the camera's speed (it used to start at 4 %)."""
    spec = SequenceSpec.preset('highway', seed=1)
    renderer = StereoRenderer(spec)
    vo = StereoOdometry(Config())
    ratios, prev = [], None
    for i in range(12):
        fr = renderer.render(i)
        res = vo.process(fr.stereo_frame(renderer.calibration))
        if prev is not None:
            assert res.status is TrackingStatus.OK
            true_step = np.linalg.norm(fr.T_world_cam[:3, 3] - prev[1][:3, 3])
            ratios.append(np.linalg.norm(res.T_world_cam[:3, 3] - prev[0][:3, 3]) / true_step)
        prev = (res.T_world_cam.copy(), fr.T_world_cam)
    assert np.median(ratios) > 0.95
    assert min(ratios) > 0.8


def render_pairs(preset, seed, frames):
    spec = SequenceSpec.preset(preset, seed=seed)
    renderer = StereoRenderer(spec)
    return renderer.calibration, [renderer.render(i) for i in range(frames)]


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
    found = road_speed(f0.left, f1.left, calib, plane, DT, np.arange(-10.0, 61.0))
    assert abs(found.speed - true_speed) <= 1.0
    assert found.contrast < 0.8
    # The same image twice: the road is best aligned at rest, and the pipeline adds no prior.
    at_rest = road_speed(f0.left, f0.left, calib, plane, DT, np.arange(-10.0, 61.0))
    assert at_rest.speed == 0.0 and at_rest.contrast == 1.0
    assert vo._road_prior(f0.stereo_frame(calib), calib, DT) is None
    moving = vo._road_prior(f1.stereo_frame(calib), calib, DT)
    assert callable(moving)


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
    vo = StereoOdometry(Config().replace(**{'pipeline.road_speed_search': search}))
    ratios, prev = [], None
    for fr in frames:
        res = vo.process(fr.stereo_frame(calib))
        if prev is not None:
            true_step = np.linalg.norm(fr.T_world_cam[:3, 3] - prev[1][:3, 3])
            ratios.append(np.linalg.norm(res.T_world_cam[:3, 3] - prev[0][:3, 3]) / true_step)
        prev = (res.T_world_cam.copy(), fr.T_world_cam)
    if search:
        assert np.median(ratios) > 0.95 and min(ratios) > 0.8
    else:
        assert np.median(ratios) < 0.5  # the failure the search exists for
