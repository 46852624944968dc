"""Tests of the scale-aligned KITTI metric (one scale factor per trajectory)."""

import numpy as np
import pytest

from stereo_vo_ros.evaluation import metrics


def straight(n: int, step_m: float) -> np.ndarray:
    """
    Return a straight trajectory along z with a slow turn.

    Returns
    -------
    np.ndarray
        (n, 4, 4) float64 ``T_world_cam`` (metres).

    """
    poses = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.linspace(0.0, 0.3, n)
    poses[:, 0, 0] = poses[:, 2, 2] = np.cos(yaw)
    poses[:, 0, 2] = np.sin(yaw)
    poses[:, 2, 0] = -np.sin(yaw)
    heading = np.stack([np.sin(yaw), np.zeros(n), np.cos(yaw)], 1)
    poses[:, :3, 3] = np.cumsum(heading * step_m, axis=0) - heading[0] * step_m
    return poses


def test_scale_alignment_removes_a_pure_scale_error() -> None:
    """An estimate 0.5 % too long has t_rel 0.5 % raw and 0 after the scale alignment."""
    gt = straight(400, 1.0)
    est = metrics.scaled_trajectory(gt, 1.005)
    before = est.copy()
    t_rel, _, _ = metrics.kitti_odometry_error(gt, est)
    assert t_rel == pytest.approx(0.5, rel=0.02)
    assert metrics.scale_from_steps(gt, est) == pytest.approx(1.0 / 1.005)
    t_s, r_s, n, scale = metrics.kitti_odometry_error_scale_aligned(gt, est)
    # The rotation error is the devkit's arccos of (trace - 1) / 2, whose smallest non-zero
    # value (one rounding step of the trace below 3) is 2.1e-8 rad: 1.2e-6 deg over a 100 m
    # segment, the shortest. A mean of segments at most two such steps off stays below twice that.
    floor = np.degrees(np.arccos(1.0 - 2.0 ** -52))  # deg per 100 m on a 100 m segment
    assert n > 0 and t_s < 1e-9 and r_s < 2 * floor and scale == pytest.approx(1.0 / 1.005)
    np.testing.assert_array_equal(est, before)


def test_scale_of_a_standing_estimate_is_nan() -> None:
    """An estimate that never moves has no scale."""
    gt = straight(20, 1.0)
    est = np.tile(np.eye(4), (20, 1, 1))
    assert np.isnan(metrics.scale_from_steps(gt, est))
    assert np.isnan(metrics.kitti_odometry_error_scale_aligned(gt, est)[0])
