"""Tests of stereo_vo_ros.synthetic.simulation: ground truth consistency and estimator accuracy."""

import json

import numpy as np
import pytest

from stereo_vo_ros.errors import ConfigError
from stereo_vo_ros.estimation.motion import TransferModel, transform_from_velocity
from stereo_vo_ros.records import TrackingStatus
from stereo_vo_ros.synthetic.simulation import (paper_config, run_simulation,
                                                simulate_and_estimate, simulate_sequence,
                                                SimulationSpec, summarize)

KEYS = ('prev_left', 'prev_right', 'cur_left', 'cur_right')


@pytest.fixture(scope='module')
def clean_seq():
    """Return a noiseless sequence with 20 % outliers of both kinds."""
    return simulate_sequence(SimulationSpec(frames=40, points=40, noise_px=0.0,
                                            outlier_ratio=0.2, seed=3))


def test_clean_correspondences_transfer_exactly_through_true_motion(clean_seq):
    seq = clean_seq
    calib = seq.spec.calibration()
    for k in range(len(seq.data)):
        model = TransferModel(calib, seq.clean['prev_left'][k], seq.clean['prev_right'][k],
                              seq.spec.dt)
        pred = model.predict(seq.velocities[k])
        expected = np.hstack([seq.clean['cur_left'][k], seq.clean['cur_right'][k]])
        np.testing.assert_allclose(pred, expected, atol=1e-6)
    # Without noise the inliers are observed exactly; outliers differ in the current pair only.
    inl = ~seq.outliers
    for key in KEYS:
        np.testing.assert_array_equal(getattr(seq.data, key)[inl], seq.clean[key][inl])
    for key in ('prev_left', 'prev_right'):
        np.testing.assert_array_equal(getattr(seq.data, key), seq.clean[key])
    moved = np.hypot(*(seq.data.cur_left - seq.clean['cur_left']).transpose(2, 0, 1))
    assert np.all(moved[inl] == 0.0)
    assert np.median(moved[seq.outliers]) > 2.0


def test_outliers_are_inconsistent_with_the_true_motion(clean_seq):
    seq = clean_seq
    calib = seq.spec.calibration()
    n_out = seq.outliers.sum(axis=1)
    assert np.all(n_out == 8)  # round(0.2 * 40) in every frame pair
    errors = []
    for k in range(len(seq.data)):
        d = seq.data
        model = TransferModel(calib, d.prev_left[k], d.prev_right[k], seq.spec.dt)
        pred = model.predict(seq.velocities[k])
        z = np.hstack([d.cur_left[k], d.cur_right[k]])
        errors.append(np.abs(pred - z).max(axis=1)[seq.outliers[k]])
    errors = np.concatenate(errors)
    assert np.mean(errors > 1.0) > 0.7  # most outliers are far off (moving ones may be slow)


def test_observations_are_valid_rectified_stereo_inside_the_image(clean_seq):
    seq = clean_seq
    spec = seq.spec
    for key in KEYS:
        p = getattr(seq.data, key)
        assert np.all(p[..., 0] >= spec.border_px - 1e-9)
        assert np.all(p[..., 0] <= spec.width - spec.border_px + 1e-9)
        assert np.all(p[..., 1] >= spec.border_px - 1e-9)
        assert np.all(p[..., 1] <= spec.height - spec.border_px + 1e-9)
    for a, b in (('prev_left', 'prev_right'), ('cur_left', 'cur_right')):
        left, right = getattr(seq.data, a), getattr(seq.data, b)
        np.testing.assert_allclose(left[..., 1], right[..., 1], atol=1e-9)  # same row
        assert np.all(left[..., 0] - right[..., 0] > 0)  # positive disparity
    disparity = seq.clean['prev_left'][..., 0] - seq.clean['prev_right'][..., 0]
    depth = spec.focal_px * spec.baseline / disparity
    assert depth.min() >= spec.min_depth - 1e-6 and depth.max() <= spec.max_depth + 1e-6


def test_ground_truth_poses_chain_the_true_motions(clean_seq):
    seq = clean_seq
    np.testing.assert_allclose(seq.T_prev_cur, transform_from_velocity(seq.velocities,
                                                                       seq.spec.dt))
    np.testing.assert_array_equal(seq.poses[0], np.eye(4))
    for k in range(len(seq.T_prev_cur)):
        np.testing.assert_allclose(seq.poses[k + 1], seq.poses[k] @ seq.T_prev_cur[k],
                                   atol=1e-12)
    np.testing.assert_array_equal(seq.data.gt_poses, seq.poses)


def test_trajectory_is_vehicle_like():
    spec = SimulationSpec(frames=2000, points=4, noise_px=0.0, seed=5)
    seq = simulate_sequence(spec)
    y = seq.velocities
    assert seq.distance_m == pytest.approx(2000.0, rel=0.05)  # 10 m/s at 10 Hz
    assert np.all(y[:, 2] > 0) and abs(y[:, 2].mean() - spec.speed) < 1.0
    assert np.abs(y[:, :2]).max() <= spec.side_velocity + 1e-12
    assert np.degrees(np.abs(y[:, 4])).max() <= spec.yaw_rate_deg + 1e-9
    assert np.degrees(np.abs(y[:, [3, 5]])).max() <= spec.pitch_roll_rate_deg + 1e-9
    assert np.degrees(np.abs(y[:, 4])).max() > 1.0  # it does turn
    # smooth: per-frame change of the forward speed is small
    assert np.abs(np.diff(y[:, 2])).max() < 0.2


def test_simulation_is_deterministic_per_seed():
    a = simulate_sequence(SimulationSpec(frames=5, points=10, seed=7, outlier_ratio=0.3))
    b = simulate_sequence(SimulationSpec(frames=5, points=10, seed=7, outlier_ratio=0.3))
    c = simulate_sequence(SimulationSpec(frames=5, points=10, seed=8, outlier_ratio=0.3))
    for key in KEYS:
        np.testing.assert_array_equal(getattr(a.data, key), getattr(b.data, key))
    np.testing.assert_array_equal(a.outliers, b.outliers)
    assert not np.array_equal(a.data.cur_left, c.data.cur_left)


@pytest.mark.parametrize('field,value', [
    ('frames', 0), ('points', 0), ('noise_px', -0.1), ('outlier_ratio', 0.95),
    ('speed', 0.0), ('rate', -10.0), ('min_depth', 0.5), ('max_depth', 4.0),
    ('outlier_model', 'aliens'), ('noise_px', float('nan'))])
def test_spec_rejects_bad_values(field, value):
    with pytest.raises(ConfigError, match=field):
        SimulationSpec(**{field: value})


def test_paper_config_matches_noise_and_threshold():
    cfg = paper_config('iekf', ransac=False, threshold=1e-5, noise_px=0.7, max_iterations=1000)
    assert cfg.filter.type == 'iekf' and not cfg.ransac.enabled
    assert cfg.filter.pixel_noise_px == 0.7 and cfg.filter.max_iterations == 1000
    assert cfg.filter.threshold_velocity == 1e-5 and cfg.filter.threshold_angular_deg == 1e-5
    assert paper_config(noise_px=0.0).filter.pixel_noise_px > 0
    with pytest.raises(ConfigError):
        paper_config('kalman')


@pytest.mark.parametrize('ransac', [False, True])
def test_ispkf_recovers_noiseless_trajectory(ransac):
    spec = SimulationSpec(frames=60, points=40, noise_px=0.0, seed=2)
    run = simulate_and_estimate(spec, paper_config('ispkf', ransac=ransac, noise_px=0.0))
    res = summarize(run)
    assert res['statuses']['ok'] == spec.frames
    assert res['final_error_percent'] < 0.1  # < 1e-3 of the distance
    dist = res['distance_m']
    drift = np.linalg.norm(run.poses[:, :3, 3] - run.sequence.poses[:, :3, 3], axis=1)
    assert drift.max() < 1e-3 * dist
    np.testing.assert_allclose(run.velocities, run.sequence.velocities, atol=1e-3)
    assert res['mean_iterations'] <= 5


def test_ransac_bounds_the_error_with_outliers():
    spec = SimulationSpec(frames=100, points=40, noise_px=0.7, outlier_ratio=0.2, seed=4)
    seq = simulate_sequence(spec)
    with_ransac = summarize(simulate_and_estimate(spec, paper_config(ransac=True), seq))
    without = summarize(simulate_and_estimate(spec, paper_config(ransac=False), seq))
    assert with_ransac['statuses']['ok'] == spec.frames
    assert with_ransac['final_error_percent'] < 1.5
    assert with_ransac['outliers_accepted_percent'] < 5.0
    assert without['outliers_accepted_percent'] == 100.0
    assert without['final_error_percent'] > 2 * with_ransac['final_error_percent']


def test_run_simulation_returns_json_ready_results():
    spec = SimulationSpec(frames=10, points=40, seed=1, outlier_ratio=0.1)
    res = run_simulation(spec, paper_config('ukf', noise_px=spec.noise_px))
    text = json.dumps(res)
    assert json.loads(text) == res
    assert res['filter'] == 'ukf' and res['frames'] == 10
    assert sum(res['statuses'].values()) == 10
    assert res['statuses'][TrackingStatus.OK.value] == 10
    assert res['spec']['points'] == 40
    assert res['ms_per_frame_median'] > 0
    assert res['final_position_error_m'] == pytest.approx(
        res['final_error_percent'] * res['distance_m'] / 100.0)
