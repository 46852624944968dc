"""Tests of evaluation/plotting.py: what is drawn, the report PNG, and import hygiene."""

import os
from pathlib import Path
import subprocess
import sys

from matplotlib.figure import Figure
from matplotlib.image import imread
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stereo_vo_ros.evaluation.plotting import (plot_error_over_distance, plot_timing,
                                               plot_top_view, save_report)

REPO = Path(__file__).resolve().parents[1]


def drive(n=300, yaw_per_frame=0.005, step_m=1.0, scale=1.0):
    """Camera turning at a constant yaw rate, ``step_m * scale`` per frame."""
    inc = np.tile(np.eye(4), (n, 1, 1))
    inc[:, :3, :3] = Rotation.from_rotvec([0.0, yaw_per_frame, 0.0]).as_matrix()
    inc[:, 2, 3] = step_m * scale
    poses = np.empty_like(inc)
    poses[0] = np.eye(4)
    for i in range(1, n):
        poses[i] = poses[i - 1] @ inc[i]
    return poses


def timings(n):
    rng = np.random.default_rng(0)
    out = [{'track': 8.0 + rng.random(), 'estimate': 3.0 + rng.random()} for _ in range(n)]
    for row in out:
        row['total'] = row['track'] + row['estimate'] + 0.5
    return out


def new_axes():
    return Figure().add_subplot()


def test_top_view_draws_x_and_z():
    gt = drive()
    est = drive(scale=1.02)
    gt_copy = gt.copy()
    ax = plot_top_view(new_axes(), gt, est)
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert {'ground truth', 'estimate', 'start'} <= set(lines)
    np.testing.assert_array_equal(lines['ground truth'].get_xdata(), gt[:, 0, 3])
    np.testing.assert_array_equal(lines['ground truth'].get_ydata(), gt[:, 2, 3])
    np.testing.assert_array_equal(lines['estimate'].get_ydata(), est[:, 2, 3])
    assert ax.get_aspect() == 1.0
    assert '[m]' in ax.get_xlabel() and '[m]' in ax.get_ylabel()
    assert 'x' in ax.get_xlabel() and 'z' in ax.get_ylabel()
    assert ax.get_legend() is not None and ax.get_title()
    np.testing.assert_array_equal(gt, gt_copy)


def test_top_view_without_ground_truth():
    est = drive()
    ax = plot_top_view(new_axes(), None, est)
    labels = [line.get_label() for line in ax.get_lines()]
    assert 'ground truth' not in labels and 'estimate' in labels
    with pytest.raises(ValueError):
        plot_top_view(new_axes(), None, None)


def test_error_over_distance_values():
    gt = drive(n=101, yaw_per_frame=0.0)  # straight, 1 m per frame
    est = drive(n=101, yaw_per_frame=0.0, scale=1.01)
    ax = plot_error_over_distance(new_axes(), gt, est)
    line = next(ln for ln in ax.get_lines() if 'p_est' in ln.get_label())
    np.testing.assert_allclose(line.get_xdata(), np.arange(101.0))
    np.testing.assert_allclose(line.get_ydata(), 0.01 * np.arange(101.0), atol=1e-12)
    assert '[m]' in ax.get_xlabel() and '[m]' in ax.get_ylabel()
    with pytest.raises(ValueError, match='101 poses.*100'):
        plot_error_over_distance(new_axes(), gt, est[:100])


def test_timing_total_and_stages():
    stats = timings(50)
    ax = plot_timing(new_axes(), stats)
    lines = {line.get_label().split(' (')[0]: line for line in ax.get_lines()}
    assert set(lines) == {'track', 'estimate', 'total'}
    np.testing.assert_allclose(lines['total'].get_ydata(), [s['total'] for s in stats])
    mean_total = np.mean([s['total'] for s in stats])
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert f'total (mean {mean_total:.1f} ms)' in legend
    assert ax.get_ylabel() == 'time [ms]'


def test_timing_without_total_and_with_gaps():
    stats = [{'track': 2.0}, {'track': 3.0, 'estimate': 1.0}, {'track': 4.0, 'ok': True}]
    ax = plot_timing(new_axes(), stats)
    lines = {line.get_label().split(' (')[0]: line for line in ax.get_lines()}
    assert set(lines) == {'track', 'estimate', 'total'}  # booleans are not timings
    np.testing.assert_allclose(lines['total'].get_ydata(), [2.0, 4.0, 4.0])
    est = lines['estimate'].get_ydata()
    assert np.isnan(est[0]) and est[1] == 1.0 and np.isnan(est[2])
    with pytest.raises(ValueError):
        plot_timing(new_axes(), [])


@pytest.mark.parametrize('with_gt, with_timings, width', [
    (True, True, 1800), (False, True, 1200), (True, False, 1200), (False, False, 600)])
def test_save_report_writes_png(tmp_path, with_gt, with_timings, width):
    gt = drive(n=1200, yaw_per_frame=0.002) if with_gt else None
    est = drive(n=1200, yaw_per_frame=0.0021, scale=1.01)
    path = save_report(tmp_path / 'report.png', gt, est,
                       timings(1200) if with_timings else None, title='test report')
    assert path == tmp_path / 'report.png'
    assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    image = imread(path)
    assert image.shape[:2] == (600, width)
    # not a blank canvas: the curves put plenty of non-white pixels in
    assert np.mean(np.any(image[..., :3] < 0.9, axis=-1)) > 0.01


def test_only_plotting_imports_matplotlib_and_no_pyplot():
    code = ('import sys\n'
            'import stereo_vo_ros.evaluation.metrics, stereo_vo_ros.evaluation.trajectory\n'
            'assert not any(m.startswith("matplotlib") for m in sys.modules), "core"\n'
            'assert not any(m.startswith(("rclpy", "tqdm")) for m in sys.modules)\n'
            'import stereo_vo_ros.evaluation.plotting\n'
            'assert "matplotlib.pyplot" not in sys.modules, "pyplot"\n')
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
