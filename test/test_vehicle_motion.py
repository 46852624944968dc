"""The rolling-vehicle prior: its constraint on true vehicle motion, its fusion, the pipeline."""

import math

import numpy as np
import pytest

from stereo_vo_ros.config import Config, ConfigError
from stereo_vo_ros.estimation.estimator import MotionEstimator
from stereo_vo_ros.estimation.motion import rotation_from_rates, velocity_from_transform
from stereo_vo_ros.pipeline import StereoOdometry
from stereo_vo_ros.road.vehicle_motion import lateral_constraint
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer, Trajectory

DT = 0.1


def arc_motion(speed, yaw_rate, lever, dt=DT, slide=0.0):
    """T_prev_cur of a camera ``lever`` m ahead of a point driving a circle arc (+ a slide)."""
    psi = yaw_rate * dt
    s = speed * dt
    chord = np.array([2.0 * s / psi * math.sin(psi / 2) ** 2, 0.0, s / psi * math.sin(psi)]) \
        if psi else np.array([0.0, 0.0, s])
    R = np.array([[math.cos(psi), 0.0, math.sin(psi)], [0.0, 1.0, 0.0],
                  [-math.sin(psi), 0.0, math.cos(psi)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = chord + R @ [0.0, 0.0, lever] - [0.0, 0.0, lever] + [slide * dt, 0.0, 0.0]
    return T


@pytest.mark.parametrize('lever', [0.0, 1.6, -0.5])
@pytest.mark.parametrize('yaw_rate_deg', [0.0, 3.0, -20.0, 60.0])
def test_arc_motion_satisfies_the_constraint(lever, yaw_rate_deg):
    """A camera on a vehicle driving a circle: c = 0; a sideways slide shows one-for-one."""
    for speed in (2.0, 25.0):
        T = arc_motion(speed, np.radians(yaw_rate_deg), lever)
        y = velocity_from_transform(T, DT)
        value, _ = lateral_constraint(y, DT, lever)
        assert abs(value) < 1e-9
        slid = velocity_from_transform(arc_motion(speed, np.radians(yaw_rate_deg), lever,
                                                  slide=0.3), DT)
        assert lateral_constraint(slid, DT, lever)[0] == pytest.approx(0.3, abs=0.02)
    if yaw_rate_deg and lever:  # the lever arm matters when turning
        T = arc_motion(10.0, np.radians(yaw_rate_deg), lever)
        assert abs(lateral_constraint(velocity_from_transform(T, DT), DT, 0.0)[0]) > 0.01


def test_gradient_matches_finite_differences():
    y = np.array([0.3, 0.1, 20.0, 0.01, 0.2, -0.02])
    for lever in (0.0, 1.5):
        _, grad = lateral_constraint(y, DT, lever)
        num = [(lateral_constraint(y + e * 1e-6, DT, lever)[0]
                - lateral_constraint(y - e * 1e-6, DT, lever)[0]) / 2e-6 for e in np.eye(6)]
        np.testing.assert_allclose(grad, num, atol=1e-7)


def test_renderer_paths_roll_along_their_heading():
    """The synthetic sequences' drives (turns, lane changes) obey the prior to 0.02 m/s."""
    traj = Trajectory(400.0, np.array([(60.0, 25.0, np.pi / 2), (180.0, 25.0, -np.pi / 2)]),
                      np.array([(300.0, 40.0, 3.5)]), 10.0, 7.5, np.random.default_rng(0),
                      1.65, 0.0)
    poses = traj.poses(np.arange(0.0, traj.duration_s - DT, DT))
    lateral, worst = [], 0.0
    for a, b in zip(poses[:-1], poses[1:]):
        y = velocity_from_transform(np.linalg.inv(a) @ b, DT)
        lateral.append(abs(y[0]))
        worst = max(worst, abs(lateral_constraint(y, DT)[0]))
    assert max(lateral) > 0.2  # the turns move the camera sideways ...
    assert worst < 0.02  # ... as their yaw says


def estimator_with(mean, cov):
    est = MotionEstimator(Config())
    est.mean, est.cov = np.asarray(mean, float), np.asarray(cov, float)
    return est


def test_fusion_ties_lateral_speed_to_yaw_and_gates_a_slide():
    # 25 m/s straight ahead, but the estimate has drifted into a lateral speed and no yaw.
    cov = np.diag([0.2, 0.2, 0.2, 0.01, 0.01, 0.01]) ** 2
    est = estimator_with([0.1, 0.0, 25.0, 0.0, 0.0, 0.0], cov)
    value, row = lateral_constraint(est.mean, DT)
    assert est.fuse_linear(row[None], [-value], [[0.05 ** 2]], 10.8)
    after, _ = lateral_constraint(est.mean, DT)
    assert abs(after) < 0.2 * abs(value)
    assert est.mean[4] > 0  # part of it went into a yaw towards the slide
    assert np.trace(est.cov) < np.trace(cov)
    assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    # A clear slide (1 m/s sideways, tightly known) is rejected: the state stays.
    tight = np.diag([0.01, 0.2, 0.2, 0.001, 0.001, 0.001]) ** 2
    est = estimator_with([1.0, 0.0, 25.0, 0.0, 0.0, 0.0], tight)
    value, row = lateral_constraint(est.mean, DT)
    assert not est.fuse_linear(row[None], [-value], [[0.05 ** 2]], 10.8)
    np.testing.assert_array_equal(est.mean, [1.0, 0.0, 25.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(est.cov, tight)


def test_fuse_by_components_is_a_linear_fusion():
    cov = np.diag([0.3, 0.2, 0.5, 0.01, 0.02, 0.01]) ** 2
    a = estimator_with([0.0, 0.1, 20.0, 0.0, 0.0, 0.0], cov)
    b = estimator_with([0.0, 0.1, 20.0, 0.0, 0.0, 0.0], cov)
    meas = np.array([0.0, 0.0, 20.4, 0.0, 0.0, 0.0])
    R = np.diag([1.0, 1.0, 0.1, 1.0, 1.0, 1.0]) ** 2
    assert a.fuse(meas, R, 10.8, components=[2])
    assert b.fuse_linear(np.eye(6)[[2]], [meas[2] - 20.0], [[0.01]], 10.8)
    np.testing.assert_allclose(a.mean, b.mean)
    np.testing.assert_allclose(a.cov, b.cov)


def test_config_ranges():
    with pytest.raises(ConfigError):
        Config().replace(**{'vehicle.lateral_speed_std': 0.0})
    assert not Config().vehicle.nonholonomic


@pytest.fixture(scope='module')
def highway_frames():
    """24 rendered highway pairs at half the KITTI size (25 m/s, with vehicles)."""
    spec = SequenceSpec.preset('highway', seed=1, width=620, height=188, n_frames=24)
    renderer = StereoRenderer(spec)
    frames = [renderer.render(i) for i in range(len(renderer))]
    return [f.stereo_frame(renderer.calibration) for f in frames]


def test_pipeline_fuses_the_prior_only_when_asked(highway_frames):
    frames = highway_frames
    runs = {}
    for on in (False, True):
        vo = StereoOdometry(Config().replace(**{'vehicle.nonholonomic': on}))
        results = [vo.process(f) for f in frames]
        assert all(np.all(np.isfinite(r.T_world_cam)) for r in results)
        fused = [r.vehicle_fused for r in results]
        assert not fused[0]
        runs[on] = results, fused
    assert not any(runs[False][1])
    assert sum(runs[True][1]) >= 0.8 * (len(frames) - 1)

    # With the prior every fused pair's velocity obeys it far more closely than the tracking
    # alone does; the truth obeys it (the renderer's drive rolls along its heading).
    def residual(results):
        out = []
        for r in results[2:]:
            # The reported velocity is in the current frame; c is defined in the previous
            # one, which the pair's rotation (about the angular velocity) turns it back to.
            R = rotation_from_rates(r.velocity[3:], DT)
            y = np.concatenate([R @ r.velocity[:3], r.velocity[3:]])
            out.append(abs(lateral_constraint(y, DT)[0]))
        return np.median(out)
    assert residual(runs[True][0]) < 0.5 * residual(runs[False][0])


def test_prior_switches_at_run_time(highway_frames):
    """``vehicle.nonholonomic`` is settable at run time (the node's parameter callback)."""
    frames = highway_frames
    vo = StereoOdometry(Config())
    before = [vo.process(f).vehicle_fused for f in frames[:8]]
    vo.update_config(Config().replace(**{'vehicle.nonholonomic': True}))
    after = [vo.process(f).vehicle_fused for f in frames[8:16]]
    assert not any(before) and sum(after) >= 6
