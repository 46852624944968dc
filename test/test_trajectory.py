"""Tests of evaluation/trajectory.py: KITTI and TUM files, full precision, malformed input."""

import math
from pathlib import Path
import re

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stereo_vo_ros.errors import DatasetError
from stereo_vo_ros.evaluation.trajectory import (as_poses, read_kitti, read_poses, read_tum,
                                                 Trajectory, write_kitti, write_tum)


def random_poses(n, seed=0, scale=100.0):
    """Return (n, 4, 4) random rigid transforms with translations of size ``scale`` m."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(n, 3)) * scale
    return poses


def test_kitti_round_trip_is_bit_exact(tmp_path):
    poses = random_poses(20)
    poses[3, 0, 3] = 0.1 + 0.2  # 0.30000000000000004: lost by any fixed-point format
    poses[4, 1, 3] = 1e-300
    original = poses.copy()
    path = tmp_path / 'est.txt'
    write_kitti(path, poses)
    np.testing.assert_array_equal(poses, original)  # input untouched
    traj = read_poses(path)
    assert isinstance(traj, Trajectory)
    assert traj.file_format == 'kitti'
    assert traj.stamps is None
    np.testing.assert_array_equal(traj.poses, poses)
    lines = path.read_text().splitlines()
    assert len(lines) == 20
    assert all(len(line.split()) == 12 for line in lines)
    assert '0.30000000000000004' in lines[3].split()


def test_kitti_accepts_3x4_input(tmp_path):
    poses = random_poses(5)
    write_kitti(tmp_path / 'a.txt', poses[:, :3, :])
    np.testing.assert_array_equal(read_kitti(tmp_path / 'a.txt'), poses)


def test_tum_round_trip(tmp_path):
    poses = random_poses(30, seed=1)
    stamps = 1317384506.402 + 0.1 * np.arange(30)
    stamps_in, poses_in = stamps.copy(), poses.copy()
    path = tmp_path / 'est.tum'
    write_tum(path, stamps, poses)
    np.testing.assert_array_equal(stamps, stamps_in)
    np.testing.assert_array_equal(poses, poses_in)
    traj = read_poses(path)
    assert traj.file_format == 'tum'
    np.testing.assert_array_equal(traj.stamps, stamps)
    np.testing.assert_array_equal(traj.poses[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(traj.poses[:, :3, :3], poses[:, :3, :3], atol=1e-14)
    np.testing.assert_array_equal(traj.poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (30, 1)))
    rows = [line.split() for line in path.read_text().splitlines() if not line.startswith('#')]
    assert all(len(r) == 8 for r in rows)
    quat = np.array(rows, dtype=float)[:, 4:]
    assert np.all(quat[:, 3] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-15)
    stamps2, poses2 = read_tum(path)
    np.testing.assert_array_equal(stamps2, stamps)
    np.testing.assert_array_equal(poses2, traj.poses)


def test_tum_quaternion_convention_is_xyzw(tmp_path):
    # 90 deg about z: qx qy qz qw = 0 0 sin(45) cos(45); maps x to y.
    s = math.sqrt(0.5)
    path = tmp_path / 'q.txt'
    path.write_text(f'# stamp x y z qx qy qz qw\n0.5 1 2 3 0 0 {s!r} {s!r}\n')
    stamps, poses = read_tum(path)
    np.testing.assert_array_equal(stamps, [0.5])
    np.testing.assert_allclose(poses[0, :3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                               atol=1e-15)
    np.testing.assert_array_equal(poses[0, :3, 3], [1.0, 2.0, 3.0])


def test_comments_blank_lines_and_commas(tmp_path):
    path = tmp_path / 'k.txt'
    path.write_text('# header\n\n1,0,0,5, 0,1,0,6, 0,0,1,7\n  \n1 0 0 8 0 1 0 9 0 0 1 10\n')
    poses = read_poses(path, 'kitti').poses
    np.testing.assert_array_equal(poses[:, :3, 3], [[5, 6, 7], [8, 9, 10]])


def test_explicit_format_overrides_detection(tmp_path):
    path = tmp_path / 'k.txt'
    write_kitti(path, random_poses(3))
    with pytest.raises(DatasetError, match=r'k\.txt:1: 12 numbers per line.*TUM'):
        read_poses(path, format='tum')
    with pytest.raises(ValueError, match='euroc'):
        read_poses(path, format='euroc')


@pytest.mark.parametrize('text, pattern', [
    ('1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n', r':2: 11 numbers, expected 12'),
    ('# c\n1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 x 0 1 0 0 0 0 1 0\n', r':3: not a number'),
    ('1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n', r':2: non-finite'),
    ('1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n', r':2: the 3x3 block is not a rotation'),
    ('-1 0 0 0 0 1 0 0 0 0 1 0\n', r':1: the 3x3 block is not a rotation'),
    ('1 2 3 4 5\n', r':1: 5 numbers per line; expected 12 \(KITTI\) or 8 \(TUM\)'),
    ('# only a comment\n\n', r'contains no pose'),
    ('0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0.5 1\n', r':2: quaternion norm 1\.11803'),
    ('0 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n', r':3: stamp 1\.0 is before'),
])
def test_malformed_files_name_file_and_line(tmp_path, text, pattern):
    path = tmp_path / 'bad_traj.txt'
    path.write_text(text)
    with pytest.raises(DatasetError) as info:
        read_poses(path)
    message = str(info.value)
    assert 'bad_traj.txt' in message
    assert re.search(pattern, message), message


def test_missing_file_is_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match='nope.txt'):
        read_poses(tmp_path / 'nope.txt')


def test_as_poses_validates_and_copies():
    poses = random_poses(4)
    out = as_poses(poses)
    out[0, 0, 0] = 42.0
    assert poses[0, 0, 0] != 42.0
    with pytest.raises(ValueError, match=r'\(4, 4\)'):
        as_poses(np.eye(4))
    bad = poses.copy()
    bad[2, 3, 0] = 1.0
    with pytest.raises(ValueError, match=r'poses\[2\] last row'):
        as_poses(bad)
    bad = poses.copy()
    bad[1, 0, 3] = np.inf
    with pytest.raises(ValueError, match=r'poses\[1\] has non-finite'):
        as_poses(bad)


def test_write_tum_checks_lengths(tmp_path):
    with pytest.raises(ValueError, match='2 stamps for 3 poses'):
        write_tum(tmp_path / 't.txt', [0.0, 1.0], random_poses(3))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64),
                min_size=3, max_size=3))
def test_any_finite_translation_round_trips(tmp_path_factory, xyz):
    path = tmp_path_factory.mktemp('rt') / 'p.txt'
    poses = np.tile(np.eye(4), (1, 1, 1))
    poses[0, :3, 3] = xyz
    write_kitti(path, poses)
    np.testing.assert_array_equal(read_kitti(path), poses)
    write_tum(path, [xyz[0]], poses)
    stamps, back = read_tum(path)
    np.testing.assert_array_equal(back[0, :3, 3], xyz)
    np.testing.assert_array_equal(stamps, [xyz[0]])


def test_evo_reads_our_files(tmp_path):
    file_interface = pytest.importorskip(
        'evo.tools.file_interface', reason='evo not installed (optional cross-check)')
    poses = random_poses(10, seed=4)
    stamps = np.arange(10) * 0.1
    write_kitti(tmp_path / 'k.txt', poses)
    write_tum(tmp_path / 't.txt', stamps, poses)
    kitti = file_interface.read_kitti_poses_file(str(tmp_path / 'k.txt'))
    tum = file_interface.read_tum_trajectory_file(str(tmp_path / 't.txt'))
    np.testing.assert_array_equal(np.array(kitti.poses_se3), poses)
    np.testing.assert_array_equal(tum.timestamps, stamps)
    np.testing.assert_allclose(np.array(tum.poses_se3), poses, atol=1e-12)


DATA = Path('/work/shared/data')


@pytest.mark.parametrize('clip', ['kitti01_f0000-0050', 'kitti06_f0000-0050'])
def test_reads_real_kitti_ground_truth(tmp_path, clip):
    path = DATA / clip / 'poses.txt'
    if not path.is_file():
        pytest.skip(f'real data not available: {path}')
    traj = read_poses(path)
    assert traj.file_format == 'kitti'
    assert traj.poses.shape == (51, 4, 4)
    np.testing.assert_allclose(traj.poses[0], np.eye(4), atol=1e-6)
    rot = traj.poses[:, :3, :3]
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.tile(np.eye(3), (51, 1, 1)),
                               atol=1e-5)
    steps = np.linalg.norm(np.diff(traj.poses[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.3) & (steps < 4.0))  # 10 Hz car: 3 to 40 m/s
    write_kitti(tmp_path / 'copy.txt', traj.poses)
    np.testing.assert_array_equal(read_kitti(tmp_path / 'copy.txt'), traj.poses)
