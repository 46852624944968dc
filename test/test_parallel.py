"""
The pipeline's worker threads: order, splits, and results that do not depend on the count.

The speed they buy is measured by ``benchmarks/bench_speed.py``, not here: these tests check
that work handed to the threads comes back complete, in order, and bit-identical.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from stereo_vo_ros import Config, StereoOdometry
from stereo_vo_ros.config import ConfigError
from stereo_vo_ros.parallel import auto_threads, MIN_POINTS_PER_THREAD, Workers
from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence


@pytest.fixture(scope='module')
def urban_frames():
    """Thirty pairs of the rendered urban preset at KITTI size (exact ground truth)."""
    return list(SyntheticSequence(SequenceSpec.preset('urban', n_frames=30, seed=3)))


def test_each_keeps_the_order_and_uses_the_threads():
    workers = Workers(3, set_opencv=False)
    try:
        names = set()

        def work(x: int) -> int:
            names.add(threading.current_thread().name)
            return x * x
        assert workers.each(work, range(17)) == [x * x for x in range(17)]
        assert workers.each(work, []) == []
        assert len(names) >= 2  # the caller and at least one worker took items
    finally:
        workers.close()
    assert workers.threads == 1
    assert workers.each(lambda x: -x, [1, 2]) == [-1, -2]  # closed: inline


def test_chunks_cover_every_row_once_at_block_multiples():
    workers = Workers(2, set_opencv=False)
    try:
        for n in (0, 1, 31, 32, 63, 64, 65, 97, 200, 1001):
            parts = workers.chunks(n)
            assert np.array_equal(np.concatenate([np.arange(n)[s] for s in parts]),
                                  np.arange(n))
            assert len(parts) <= workers.threads
            assert all(s.start % MIN_POINTS_PER_THREAD == 0 for s in parts)
        out = workers.split_points(lambda rows: (np.arange(200)[rows] * 2,), 200)
        assert np.array_equal(out[0], np.arange(200) * 2)
    finally:
        workers.close()


def test_auto_threads_and_config_range():
    assert auto_threads(3) == 3
    assert 1 <= auto_threads(0) <= 4
    with pytest.raises(ConfigError):
        Config().replace(**{'pipeline.threads': -1})


def test_results_are_identical_at_any_thread_count(urban_frames):
    """One, two and three threads give bit-identical poses and tracker statistics."""
    runs = {}
    for threads in (1, 2, 3):
        odometry = StereoOdometry(Config().replace(**{'pipeline.threads': threads}))
        try:
            results = [odometry.process(frame) for frame in urban_frames]
        finally:
            odometry.close()
        runs[threads] = results
        assert odometry.workers.threads == 1  # closed
    reference = runs[1]
    assert sum(r.status.name == 'OK' for r in reference) >= len(urban_frames) - 2
    for threads in (2, 3):
        for a, b in zip(reference, runs[threads]):
            assert np.array_equal(a.T_world_cam, b.T_world_cam), threads
            assert a.n_tracked == b.n_tracked and a.n_inliers == b.n_inliers
