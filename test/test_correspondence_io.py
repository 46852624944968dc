"""Tests of stereo_vo_ros.io.correspondences: the .npz format and trajectory estimation."""

import numpy as np
import pytest

from stereo_vo_ros.config import Config
from stereo_vo_ros.errors import DatasetError
from stereo_vo_ros.io.correspondences import (CorrespondenceData, estimate_trajectory,
                                              iter_estimates, load_npz, OPTIONAL_KEYS,
                                              REQUIRED_KEYS, save_npz)
from stereo_vo_ros.synthetic.simulation import paper_config, simulate_sequence, SimulationSpec

KEYS = ('prev_left', 'prev_right', 'cur_left', 'cur_right')


@pytest.fixture(scope='module')
def seq():
    return simulate_sequence(SimulationSpec(frames=12, points=40, noise_px=0.0, seed=11))


@pytest.fixture()
def arrays(seq):
    """Return the archive content of the simulated sequence (fresh copies)."""
    return {k: np.array(v) for k, v in seq.data.arrays().items()}


def write(path, content):
    np.savez(path, **content)
    return path


def test_round_trip_is_exact(tmp_path, seq):
    path = tmp_path / 'corr.npz'
    save_npz(path, seq.data)
    loaded = load_npz(path)
    for key in REQUIRED_KEYS + OPTIONAL_KEYS:
        a, b = getattr(seq.data, key), getattr(loaded, key)
        if a is None:
            assert b is None
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert len(loaded) == 12 and loaded.num_points == 40
    assert loaded.image_size() == (seq.spec.width, seq.spec.height)
    calib = loaded.calibration()
    assert calib.baseline_m == pytest.approx(seq.spec.baseline)
    np.testing.assert_allclose(loaded.time_steps(), 1.0 / seq.spec.rate)
    with np.load(path, allow_pickle=False) as raw:  # plain arrays, no pickles
        assert set(raw.files) == set(REQUIRED_KEYS + OPTIONAL_KEYS) - {'stamps'}
        assert raw['prev_left'].dtype == np.float64


def test_estimate_trajectory_returns_m_plus_one_poses_from_identity(seq):
    poses = estimate_trajectory(seq.data, paper_config(noise_px=0.0))
    assert poses.shape == (13, 4, 4)
    np.testing.assert_array_equal(poses[0], np.eye(4))
    np.testing.assert_allclose(poses[:, 3], np.tile([0, 0, 0, 1.0], (13, 1)))
    # noiseless data: the trajectory is the ground truth (KITTI convention, first frame = I)
    np.testing.assert_allclose(poses[:, :3, 3], seq.poses[:, :3, 3], atol=1e-4)
    for R in poses[:, :3, :3]:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_estimate_from_file_equals_estimate_from_memory(tmp_path, seq):
    path = tmp_path / 'corr.npz'
    save_npz(path, seq.data)
    cfg = paper_config(noise_px=0.0)
    np.testing.assert_array_equal(estimate_trajectory(load_npz(path), cfg),
                                  estimate_trajectory(seq.data, cfg))


def test_nan_rows_are_missing_points(arrays, seq):
    # Drop a different third of the points in every frame pair (any coordinate NaN).
    rng = np.random.default_rng(0)
    for k in range(12):
        rows = rng.choice(40, 13, replace=False)
        arrays[KEYS[k % 4]][k, rows, k % 2] = np.nan
    data = CorrespondenceData(**arrays)
    fes = list(iter_estimates(data, paper_config(noise_px=0.0)))
    assert all(fe.estimate.status.value == 'ok' for fe in fes)
    for k, fe in enumerate(fes):
        missing = ~np.all(np.isfinite(np.hstack([getattr(data, key)[k] for key in KEYS])),
                          axis=1)
        assert missing.sum() == 13
        assert not fe.estimate.inliers[missing].any()
    np.testing.assert_allclose(fes[-1].T_world_cam[:3, 3], seq.poses[-1, :3, 3], atol=1e-4)


def test_stamps_give_the_time_steps(arrays, seq):
    # The same motions over twice the time: velocities halve, poses stay the same.
    arrays['stamps'] = np.arange(13) * 0.2 + 100.0
    data = CorrespondenceData(**arrays)
    np.testing.assert_allclose(data.time_steps(), 0.2)
    poses = estimate_trajectory(data, paper_config(noise_px=0.0))
    np.testing.assert_allclose(poses[:, :3, 3], seq.poses[:, :3, 3], atol=1e-4)


def test_image_size_is_derived_without_width_and_height(arrays):
    del arrays['width'], arrays['height']
    data = CorrespondenceData(**arrays)
    w, h = data.image_size()
    assert (w, h) == (int(np.ceil(2 * arrays['P0'][0, 2])), int(np.ceil(2 * arrays['P0'][1, 2])))
    arrays['cur_left'][0, 0] = [w + 50.3, 10.0]
    assert CorrespondenceData(**arrays).image_size() == (w + 51, h)


def test_frame_keeps_every_row_with_ids(seq):
    corr = seq.data.frame(3)
    assert len(corr) == 40
    np.testing.assert_array_equal(corr.ids, np.arange(40))
    np.testing.assert_array_equal(corr.cur_right, seq.data.cur_right[3])


def _drop(key):
    def edit(a):
        del a[key]
    return edit


def _set(key, value):
    def edit(a):
        a[key] = value(a) if callable(value) else value
    return edit


@pytest.mark.parametrize('edit,message', [
    (_drop('cur_right'), 'missing key'),
    (_drop('P1'), 'missing key'),
    (_drop('rate'), 'missing key'),
    (_set('curr_left', np.zeros((12, 40, 2))), 'unknown key'),
    (_set('prev_left', lambda a: a['prev_left'][0]), 'prev_left must have shape'),
    (_set('cur_left', lambda a: a['cur_left'][..., :1]), 'cur_left must have shape'),
    (_set('prev_right', lambda a: a['prev_right'][:, :30]), 'prev_right has shape'),
    (_set('cur_left', lambda a: np.where(np.arange(40)[:, None] == 3, np.inf, a['cur_left'])),
     'infinite'),
    (_set('cur_left', lambda a: a['cur_left'].astype(str)), 'numeric'),
    (_set('P0', np.eye(3)), 'P0 must be a finite 3x4'),
    (_set('P1', lambda a: np.where(np.eye(3, 4) > 0, np.nan, a['P1'])), 'P1 must be a finite'),
    (_set('P1', lambda a: a['P0']), 'baseline'),
    (_set('rate', 0.0), 'rate must be a positive'),
    (_set('rate', np.array([10.0, 20.0])), 'rate must be a number'),
    (_set('width', -5), 'width must be a positive'),
    (_set('height', 391.5), 'height must be a positive int'),
    (_set('stamps', np.arange(12.0)), 'stamps must have shape'),
    (_set('stamps', np.r_[np.arange(12.0), 5.0]), 'strictly increasing'),
    (_set('gt_poses', np.zeros((12, 4, 4))), 'gt_poses'),
    (lambda a: a.update({k: a[k][:0] for k in KEYS}), 'no frame pairs'),
])
def test_malformed_files_are_rejected(tmp_path, arrays, edit, message):
    edit(arrays)
    path = write(tmp_path / 'bad.npz', arrays)
    with pytest.raises(DatasetError, match=message) as info:
        load_npz(path)
    assert 'bad.npz' in str(info.value)


def test_unreadable_files_are_rejected(tmp_path):
    with pytest.raises(DatasetError, match='does not exist'):
        load_npz(tmp_path / 'absent.npz')
    junk = tmp_path / 'junk.npz'
    junk.write_bytes(b'this is not a zip archive')
    with pytest.raises(DatasetError, match='junk.npz'):
        load_npz(junk)
    pickled = tmp_path / 'pickled.npz'
    np.savez(pickled, prev_left=np.array([{'a': 1}], dtype=object))
    with pytest.raises(DatasetError, match='pickled.npz'):
        load_npz(pickled)


def test_constructor_validates(arrays):
    arrays['rate'] = -1.0
    with pytest.raises(DatasetError, match='rate'):
        CorrespondenceData(**arrays)


def test_save_to_unwritable_path_raises(tmp_path, seq):
    with pytest.raises(DatasetError, match='cannot write'):
        save_npz(tmp_path / 'no' / 'such' / 'dir' / 'x.npz', seq.data)


def test_default_config_runs(seq):
    poses = estimate_trajectory(seq.data)  # Config() defaults, RANSAC on
    assert poses.shape == (13, 4, 4) and np.all(np.isfinite(poses))
    assert Config().ransac.enabled
    err = np.linalg.norm(poses[-1, :3, 3] - seq.poses[-1, :3, 3])
    assert err < 0.01 * np.linalg.norm(seq.T_prev_cur[:, :3, 3], axis=1).sum()
