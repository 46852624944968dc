"""The README's main job: synthetic bag -> node process (real rclpy) -> trajectory, metrics."""

import json

import numpy as np
import pytest

pytest.importorskip('rclpy', reason='the demo needs rclpy (pip install ".[ros]")')

from stereo_vo_ros.evaluation.trajectory import read_poses  # noqa: E402
from stereo_vo_ros.ros.demo import run_demo  # noqa: E402


def test_demo_end_to_end(tmp_path):
    summary = run_demo(tmp_path, frames=40, timeout_s=90.0)
    assert summary['ok'], summary
    assert summary['pairs_published'] == 40
    assert summary['odometry_received'] == 40  # camera_info precedes the first pair
    est = read_poses(summary['poses']).poses
    gt = read_poses(summary['ground_truth']).poses
    assert est.shape == gt.shape and np.all(np.isfinite(est))
    metrics = json.loads((tmp_path / 'metrics.json').read_text())
    # About 30 m of urban driving: the end point within 3 % of the distance.
    assert metrics['path_length_m'] > 20.0
    assert metrics['end_drift_pct'] < 3.0
    assert metrics['ate_rmse_m'] < 0.5
    assert (tmp_path / 'trajectory.png').stat().st_size > 10_000
    assert read_poses(summary['poses_tum']).stamps is not None


def test_spinning_delivers_callbacks_and_stops_before_shutdown():
    """The demo's background spinner runs callbacks in the block and is joined at its end."""
    import threading

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from stereo_vo_ros.ros.process import spinning

    context = Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node('spin_test', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        fired = threading.Event()
        node.create_timer(0.01, fired.set)
        with spinning(executor, period_s=0.05) as thread:
            assert fired.wait(5.0)
            assert thread.is_alive()
        assert not thread.is_alive()  # joined before the executor and rclpy shut down
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_demo_reports_a_node_that_exits_before_it_subscribes(tmp_path, monkeypatch):
    """A node that dies at start ends the wait for its subscriptions at once, with its code."""
    import sys

    from stereo_vo_ros.errors import DatasetError
    from stereo_vo_ros.ros import demo, process

    # The wait for a starting node is long (its first start compiles the kernels); a node
    # that exits must not hold the demo for all of it: the error names the exit, not the
    # timeout.
    assert demo.NODE_START_TIMEOUT_S >= 2 * demo.FIRST_START_S[1]
    exiting = [sys.executable, '-c', 'import sys; print("node failed"); sys.exit(3)']
    monkeypatch.setattr(process, 'node_command', lambda: exiting)
    with pytest.raises(DatasetError, match=r'the node exited \(code 3\) before it subscribed'):
        run_demo(tmp_path, frames=3)
    assert 'node failed' in (tmp_path / 'node.log').read_text()
