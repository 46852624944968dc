"""Tests of evaluation/metrics.py on trajectories whose errors are known by construction."""

import copy
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stereo_vo_ros.evaluation.metrics import (align_se3, ate_rmse, end_point_drift, evaluate,
                                              kitti_distances, KITTI_LENGTHS_M,
                                              kitti_odometry_error, kitti_segment_errors,
                                              path_distances, rotation_angle, rpe_frame_to_frame)

REQUIRED_KEYS = {'t_rel_pct', 'r_rel_deg_per_100m', 'ate_rmse_m', 'rpe_trans_rmse_m',
                 'rpe_rot_rmse_deg', 'segments', 'end_drift_pct', 'path_length_m', 'frames'}


def straight(n, step_m=1.0):
    """(n, 4, 4) camera driving along +z with identity rotation, ``step_m`` per frame."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n) * step_m
    return poses


def compose(increments):
    """Chain (n, 4, 4) frame-to-frame motions T_prev_cur into poses starting at identity."""
    poses = np.empty_like(increments)
    poses[0] = np.eye(4)
    for i in range(1, len(increments)):
        poses[i] = poses[i - 1] @ increments[i]
    return poses


def random_drive(n, seed=0, rot_sigma=0.01, step_sigma=0.3):
    """Random smooth-ish drive: about 1 m per frame forward with small turns."""
    rng = np.random.default_rng(seed)
    inc = np.tile(np.eye(4), (n, 1, 1))
    inc[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, rot_sigma, (n, 3))).as_matrix()
    inc[:, :3, 3] = rng.normal([0.0, 0.0, 1.0], step_sigma, (n, 3))
    return compose(inc)


def perturb(poses, seed=1, rot_sigma=0.005, trans_sigma=0.05):
    """Right-multiply every pose by a small random rigid motion."""
    rng = np.random.default_rng(seed)
    noise = np.tile(np.eye(4), (len(poses), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, rot_sigma, (len(poses), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, trans_sigma, (len(poses), 3))
    return poses @ noise


def _noisy_increments(gt, seed):
    """Frame-to-frame motions of gt, each perturbed a little, as a chain of increments."""
    inc = np.empty_like(gt)
    inc[0] = np.eye(4)
    inc[1:] = np.linalg.inv(gt[:-1]) @ gt[1:]
    return perturb(inc, seed=seed, rot_sigma=5e-4, trans_sigma=0.01)


def devkit_reference(gt, est):
    """
    Literal loop transcription of calcSequenceErrors/getStats with float32 where C++ has it.

    Returns (list of (first, last, len, t_err, r_err), t_mean, r_mean).
    """
    f32 = np.float32
    dist = [f32(0.0)]
    for i in range(1, len(gt)):
        dx = f32(gt[i - 1, 0, 3] - gt[i, 0, 3])
        dy = f32(gt[i - 1, 1, 3] - gt[i, 1, 3])
        dz = f32(gt[i - 1, 2, 3] - gt[i, 2, 3])
        sq = f32(f32(f32(dx * dx) + f32(dy * dy)) + f32(dz * dz))
        dist.append(f32(dist[i - 1] + np.sqrt(sq)))
    segs = []
    for first in range(0, len(gt), 10):
        for length in KITTI_LENGTHS_M:
            length = f32(length)
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > f32(dist[first] + length):
                    last = i
                    break
            if last == -1:
                continue
            d_gt = np.linalg.inv(gt[first]) @ gt[last]
            d_est = np.linalg.inv(est[first]) @ est[last]
            err = np.linalg.inv(d_est) @ d_gt
            a, b, c = f32(err[0, 0]), f32(err[1, 1]), f32(err[2, 2])
            d = f32(0.5 * (float(f32(f32(a + b) + c)) - 1.0))
            r = np.arccos(max(min(d, f32(1.0)), f32(-1.0)))
            tx, ty, tz = f32(err[0, 3]), f32(err[1, 3]), f32(err[2, 3])
            t = np.sqrt(f32(f32(f32(tx * tx) + f32(ty * ty)) + f32(tz * tz)))
            segs.append((first, last, float(length), float(f32(t / length)),
                         float(f32(r / length))))
    t_sum, r_sum = f32(0.0), f32(0.0)
    for s in segs:
        t_sum = f32(t_sum + f32(s[3]))
        r_sum = f32(r_sum + f32(s[4]))
    num = f32(len(segs))
    return segs, float(t_sum / num), float(r_sum / num)


# ----------------------------------------------------------------- KITTI devkit metric


def test_hand_counted_segments_and_strict_inequality():
    # 1 m per frame: dist[i] = i exactly (also in float32). A segment of length L starting at
    # f ends at the first frame with dist > f + L, i.e. f + L + 1, and exists when that frame
    # is <= 249. L=100: f = 0, 10, ..., 140 (15 segments); L=200: f = 0, ..., 40 (5); L>=300:
    # none. Total 20.
    gt = straight(250)
    seg = kitti_segment_errors(gt, gt)
    assert len(seg) == 20
    np.testing.assert_array_equal(seg.last_frame, seg.first_frame + seg.length_m + 1)
    assert np.count_nonzero(seg.length_m == 100.0) == 15
    assert np.count_nonzero(seg.length_m == 200.0) == 5
    # devkit order: by first frame, then by length
    assert list(zip(seg.first_frame[:3], seg.length_m[:3])) == [(0, 100.0), (0, 200.0),
                                                                (10, 100.0)]
    # exactly 100 m is not enough (strict '>'), 101 m gives one segment
    _, _, n = kitti_odometry_error(straight(101), straight(101))
    assert n == 0
    _, _, n = kitti_odometry_error(straight(102), straight(102))
    assert n == 1


def test_short_trajectory_gives_nan_and_zero_segments():
    gt = straight(50)
    t_rel, r_rel, n = kitti_odometry_error(gt, gt)
    assert n == 0 and math.isnan(t_rel) and math.isnan(r_rel)
    result = evaluate(gt, gt)
    assert result['segments'] == 0 and math.isnan(result['t_rel_pct'])
    assert result['ate_rmse_m'] == 0.0


def test_scaled_translation_gives_one_percent():
    gt = straight(10000, step_m=0.1)  # 1 km, 0.1 m per frame
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    t_rel, r_rel, n = kitti_odometry_error(gt, est)
    # error = 1 % of the chord, the chord exceeds the nominal length by at most one step
    assert n > 1000
    assert 1.0 <= t_rel <= 1.0 * (1.0 + 0.1 / 100.0) + 1e-9
    assert r_rel == pytest.approx(0.0, abs=1e-9)
    t32, r32, n32 = kitti_odometry_error(gt, est, devkit_float32=True)
    assert n32 == n
    assert t32 == pytest.approx(t_rel, rel=1e-5)
    assert r32 == 0.0


def test_scaled_translation_on_a_curved_drive():
    # Scaling a whole trajectory by s scales every segment's relative translation by s and
    # leaves its rotation alone: t_err = 0.01 |t_dGT| / L.
    gt = random_drive(1200, seed=3, rot_sigma=0.003, step_sigma=0.05)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    seg = kitti_segment_errors(gt, est)
    chord = np.linalg.norm(gt[seg.last_frame, :3, 3] - gt[seg.first_frame, :3, 3], axis=1)
    np.testing.assert_allclose(seg.t_err, 0.01 * chord / seg.length_m, rtol=1e-9)
    np.testing.assert_allclose(seg.r_err, 0.0, atol=1e-9)
    t_rel, _, _ = kitti_odometry_error(gt, est)
    assert 0.9 < t_rel < 1.01


def test_identical_trajectories_give_zeros():
    gt = random_drive(600, seed=2)
    result = evaluate(gt, gt.copy())
    assert set(result) == REQUIRED_KEYS
    assert result['segments'] > 0
    assert result['frames'] == 600
    for key in ('t_rel_pct', 'r_rel_deg_per_100m', 'ate_rmse_m', 'rpe_trans_rmse_m',
                'rpe_rot_rmse_deg', 'end_drift_pct'):
        assert result[key] == pytest.approx(0.0, abs=1e-6), key
    assert result['path_length_m'] == pytest.approx(path_distances(gt)[-1])


def test_constant_yaw_rate_error():
    # Ground truth straight at 1 m/frame; the estimate adds delta rad of yaw (about the camera
    # y axis) every frame. A segment from f to f + L + 1 then has a rotation error of
    # (L + 1) * delta, so r_err = (L + 1) * delta / L.
    delta = 1e-4
    n = 1000
    inc = np.tile(np.eye(4), (n, 1, 1))
    inc[:, :3, :3] = Rotation.from_rotvec([0.0, delta, 0.0]).as_matrix()
    inc[:, 2, 3] = 1.0
    est = compose(inc)
    gt = straight(n)
    expected = []
    for first in range(0, n, 10):
        for length in KITTI_LENGTHS_M:
            if first + length + 1 <= n - 1:
                expected.append((length + 1) * delta / length)
    t_rel, r_rel, segs = kitti_odometry_error(gt, est)
    assert segs == len(expected)
    assert r_rel == pytest.approx(np.degrees(np.mean(expected)) * 100.0, rel=1e-9)
    assert t_rel > 0.0


def test_vectorised_devkit_matches_literal_transcription():
    # Irregular spacing and rotations so that float32 distances and segment ends matter.
    gt = random_drive(700, seed=5, step_sigma=0.4)
    est = perturb(compose(_noisy_increments(gt, seed=6)), seed=7)
    ref_segs, ref_t, ref_r = devkit_reference(gt, est)
    seg = kitti_segment_errors(gt, est, devkit_float32=True)
    assert len(seg) == len(ref_segs) > 50
    np.testing.assert_array_equal(seg.first_frame, [s[0] for s in ref_segs])
    np.testing.assert_array_equal(seg.last_frame, [s[1] for s in ref_segs])
    np.testing.assert_array_equal(seg.length_m, [s[2] for s in ref_segs])
    np.testing.assert_array_equal(seg.t_err, [s[3] for s in ref_segs])
    np.testing.assert_array_equal(seg.r_err, [s[4] for s in ref_segs])
    t_rel, r_rel, _ = kitti_odometry_error(gt, est, devkit_float32=True)
    assert t_rel == pytest.approx(ref_t * 100.0, rel=1e-12)
    assert r_rel == pytest.approx(np.degrees(ref_r) * 100.0, rel=1e-12)
    # the double-precision default differs only by float32 rounding
    t64, r64, _ = kitti_odometry_error(gt, est)
    assert t64 == pytest.approx(t_rel, rel=1e-4)
    assert r64 == pytest.approx(r_rel, rel=1e-3)


def test_kitti_distances_are_float32_and_close_to_double():
    gt = random_drive(300, seed=8)
    d32 = kitti_distances(gt)
    d64 = path_distances(gt)
    assert d32.dtype == np.float32 and d32[0] == 0.0
    np.testing.assert_allclose(d32, d64, rtol=1e-5)


# ----------------------------------------------------------------- ATE, RPE, drift


def random_rigid(seed):
    rng = np.random.default_rng(seed)
    t = np.eye(4)
    t[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    t[:3, 3] = rng.normal(size=3) * 50.0
    return t


def test_align_se3_recovers_a_rigid_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3)) * 10.0
    t = random_rigid(1)
    dst = src @ t[:3, :3].T + t[:3, 3]
    np.testing.assert_allclose(align_se3(src, dst), t, atol=1e-10)


def test_ate_is_invariant_to_a_rigid_transform_of_the_estimate():
    gt = random_drive(300, seed=9)
    est = perturb(gt, seed=10, trans_sigma=0.2)
    ate = ate_rmse(gt, est)
    assert ate > 0.05
    for seed in range(3):
        assert ate_rmse(gt, random_rigid(seed) @ est) == pytest.approx(ate, rel=1e-9)
    # a rigidly moved copy of the ground truth has zero ATE
    assert ate_rmse(gt, random_rigid(5) @ gt) == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=0, max_value=10_000))
def test_ate_invariance_property(seed):
    gt = random_drive(40, seed=seed)
    est = perturb(gt, seed=seed + 1, trans_sigma=0.3)
    expected = ate_rmse(gt, est)
    assert ate_rmse(gt, random_rigid(seed) @ est) == pytest.approx(expected, rel=1e-7, abs=1e-9)


def test_ate_of_a_constant_offset_perpendicular_pattern():
    # gt on a line; est is pushed sideways by +a, -a, -a, +a, ... : the pattern has zero mean
    # and is uncorrelated with the position along the line, so no rigid motion reduces it
    # and ATE = a.
    gt = straight(100)
    est = gt.copy()
    a = 0.3
    est[:, 0, 3] += a * np.where(np.isin(np.arange(100) % 4, [0, 3]), 1.0, -1.0)
    assert ate_rmse(gt, est) == pytest.approx(a, rel=1e-6)


def test_rpe_of_constant_per_frame_errors():
    n = 200
    gt = random_drive(n, seed=11)
    inc = np.empty_like(gt)
    inc[0] = np.eye(4)
    inc[1:] = np.linalg.inv(gt[:-1]) @ gt[1:]
    err = np.eye(4)
    err[:3, :3] = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix()
    err[:3, 3] = [0.03, 0.0, -0.04]
    est = compose(inc @ err)
    trans, rot = rpe_frame_to_frame(gt, est)
    assert trans == pytest.approx(0.05, rel=1e-9)
    assert rot == pytest.approx(np.degrees(np.linalg.norm([0.01, -0.02, 0.005])), rel=1e-9)
    # RPE ignores a rigid transform of the whole estimate
    assert rpe_frame_to_frame(gt, random_rigid(2) @ est) == pytest.approx((trans, rot))


def test_end_point_drift():
    gt = straight(101)  # 100 m
    est = gt.copy()
    est[-1, :3, 3] += [3.0, 0.0, 4.0]
    assert end_point_drift(gt, est) == pytest.approx(5.0)
    assert math.isnan(end_point_drift(np.tile(np.eye(4), (3, 1, 1)),
                                      np.tile(np.eye(4), (3, 1, 1))))


def test_rotation_angle_small_and_large():
    for angle in (0.0, 1e-9, 1e-4, 1.0, 3.0, math.pi - 1e-7):
        r = Rotation.from_rotvec([angle, 0.0, 0.0]).as_matrix()
        assert rotation_angle(r) == pytest.approx(angle, abs=1e-12)


# ----------------------------------------------------------------- contract


def test_length_mismatch_names_both_lengths():
    with pytest.raises(ValueError, match=r'100 poses.*99'):
        evaluate(straight(100), straight(99))
    with pytest.raises(ValueError, match=r'100 poses.*99'):
        ate_rmse(straight(100), straight(99))


def test_inputs_are_not_mutated_and_3x4_is_accepted():
    gt = random_drive(400, seed=12)
    est = perturb(gt, seed=13)
    gt_copy, est_copy = gt.copy(), est.copy()
    gt.flags.writeable = False
    est.flags.writeable = False
    result = evaluate(gt, est)
    kitti_segment_errors(gt, est, devkit_float32=True)
    np.testing.assert_array_equal(gt, gt_copy)
    np.testing.assert_array_equal(est, est_copy)
    result34 = evaluate(gt[:, :3, :], est[:, :3, :])
    assert result34 == pytest.approx(result, nan_ok=True)
    assert all(isinstance(result[k], int) for k in ('segments', 'frames'))


def test_matches_evo_ate_and_rpe():
    evo_metrics = pytest.importorskip('evo.core.metrics',
                                      reason='evo not installed (optional cross-check)')
    from evo.core.trajectory import PosePath3D

    gt = random_drive(250, seed=14)
    est = random_rigid(3) @ perturb(gt, seed=15, rot_sigma=0.01, trans_sigma=0.05)
    ref = PosePath3D(poses_se3=list(gt))
    traj = PosePath3D(poses_se3=list(est))
    aligned = copy.deepcopy(traj)
    aligned.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    assert ate_rmse(gt, est) == pytest.approx(
        ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-9)
    ours = rpe_frame_to_frame(gt, est)
    for value, relation in zip(ours, (evo_metrics.PoseRelation.translation_part,
                                      evo_metrics.PoseRelation.rotation_angle_deg)):
        rpe = evo_metrics.RPE(relation, delta=1, delta_unit=evo_metrics.Unit.frames,
                              all_pairs=False)
        rpe.process_data((ref, traj))
        assert value == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.rmse),
                                      rel=1e-9)
