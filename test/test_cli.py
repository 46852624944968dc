"""
Tests of the ``stereo_vo`` command line: run, eval, plot, config and user errors.

The commands run in-process through ``cli.main`` on small rendered sequences written as a
KITTI folder and as a rosbag2 (rosbags); user mistakes must give an exit code of 2 and a
one-line message, never a traceback.
"""

import json
from pathlib import Path
import re

import numpy as np
import pytest
from stereo_vo_ros import cli
from stereo_vo_ros.evaluation.trajectory import read_kitti, read_tum
from stereo_vo_ros.io import write_kitti, write_stereo_bag
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer
import yaml

N_FRAMES = 12


@pytest.fixture(scope='module')
def sources(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Write one rendered sequence (400x120, 10 Hz) as a KITTI folder and as a bag."""
    root = tmp_path_factory.mktemp('cli')
    # 400x120: at 320x96 the detector finds only 10-20 corners a frame, at the edge of
    # pipeline.min_features, and the run below must not lose a frame.
    renderer = StereoRenderer(SequenceSpec.preset('demo', width=400, height=120,
                                                  n_frames=N_FRAMES, turns=False))
    frames = list(renderer.frames())
    write_kitti(root / 'kitti', frames, renderer.poses)
    write_stereo_bag(root / 'bag', frames, renderer.calibration, renderer.poses)
    return {'kitti': root / 'kitti', 'bag': root / 'bag', 'root': root}


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """Run ``stereo_vo ARGV``; return (exit code, stdout, stderr)."""
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exc:  # argparse and the error path exit
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize('kind, fmt', [('kitti', 'kitti'), ('bag', 'tum')])
def test_run_writes_poses_stats_and_ground_truth(sources, tmp_path, capsys, kind, fmt):
    poses, stats, gt = tmp_path / 'est.txt', tmp_path / 'stats.json', tmp_path / 'gt.txt'
    code, _, err = run_cli(capsys, 'run', sources[kind], '--poses', poses, '--stats', stats,
                           '--gt-out', gt, '--format', fmt)
    assert code == 0, err
    read = read_tum if fmt == 'tum' else (lambda p: (None, read_kitti(p)))
    stamps, est = read(poses)
    _, truth = read(gt)
    assert est.shape == truth.shape == (N_FRAMES, 4, 4)
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-12)
    if stamps is not None:
        assert np.all(np.diff(stamps) > 0)
    moved, true_moved = (np.linalg.norm(p[-1, :3, 3] - p[0, :3, 3]) for p in (est, truth))
    assert abs(moved - true_moved) < 0.05 * true_moved  # a working odometry, not a stub
    data = json.loads(stats.read_text())
    assert data['frames'] == N_FRAMES and data['lost_frames'] == 0
    for stage in ('total', 'track', 'estimate'):
        assert set(data['ms'][stage]) == {'mean', 'median', 'p95'}
        assert data['ms'][stage]['median'] > 0


def test_eval_json_and_plot(sources, tmp_path, capsys):
    poses, gt = tmp_path / 'est.txt', tmp_path / 'gt.txt'
    assert run_cli(capsys, 'run', sources['kitti'], '--poses', poses, '--gt-out', gt)[0] == 0
    code, out, err = run_cli(capsys, 'eval', gt, poses, '--json')
    assert code == 0, err
    metrics = json.loads(out)
    for key in ('t_rel_pct', 'r_rel_deg_per_100m', 'ate_rmse_m', 'rpe_trans_rmse_m',
                'rpe_rot_rmse_deg', 'segments'):
        assert key in metrics
    assert metrics['segments'] == 0 and metrics['t_rel_pct'] is None  # path < 100 m
    assert 0 <= metrics['ate_rmse_m'] < 0.5
    code, out, err = run_cli(capsys, 'eval', gt, poses)
    assert code == 0 and 'ate_rmse_m' in out
    png = tmp_path / 'plot.png'
    code, _, err = run_cli(capsys, 'plot', poses, '--gt', gt, '--out', png)
    assert code == 0, err
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 10_000


def test_config_prints_the_validated_yaml(capsys, repo_root):
    shipped = repo_root / 'config' / 'stereo_vo.yaml'
    code, out, _ = run_cli(capsys, 'config', '--config', shipped)
    assert code == 0
    assert yaml.safe_load(out) == yaml.safe_load(shipped.read_text())


def _bad_calibration(sources: dict[str, Path]) -> Path:
    bad = sources['root'] / 'bad_calib'
    if not bad.exists():
        (bad / 'image_0').mkdir(parents=True)
        (bad / 'image_1').mkdir()
        for side in ('image_0', 'image_1'):
            src = sorted((sources['kitti'] / side).glob('*.png'))[0]
            (bad / side / src.name).write_bytes(src.read_bytes())
        (bad / 'calib.txt').write_text('P0: 1 2 3\nP1: not numbers\n')
    return bad


@pytest.mark.parametrize('case, pattern', [
    ('missing folder', 'does not exist'),
    ('bag without the topics', "lacks topic.*'/nope'"),
    ('calibration that cannot be parsed', 'calib'),
    ('unknown option value', 'invalid choice'),
    ('misspelt config key', 'max_featurs'),
])
def test_user_errors_exit_2_with_a_message_and_no_traceback(sources, tmp_path, capsys, case,
                                                            pattern):
    poses = tmp_path / 'est.txt'
    argv = {
        'missing folder': ['run', tmp_path / 'nowhere', '--poses', poses],
        'bag without the topics': ['run', sources['bag'], '--poses', poses,
                                   '--left-topic', '/nope'],
        'calibration that cannot be parsed': ['run', _bad_calibration(sources), '--poses',
                                              poses],
        'unknown option value': ['run', sources['kitti'], '--poses', poses, '--format', 'csv'],
        'misspelt config key': ['run', sources['kitti'], '--poses', poses, '--config',
                                tmp_path / 'typo.yaml'],
    }[case]
    (tmp_path / 'typo.yaml').write_text(
        '/**:\n  ros__parameters:\n    tracker:\n      max_featurs: 100\n')
    code, _, err = run_cli(capsys, *argv)
    assert code == 2
    assert 'Traceback' not in err
    assert err.startswith(('stereo_vo: error:', 'usage:'))
    assert re.search(pattern, err), err
    assert not poses.exists()
