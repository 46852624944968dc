"""
The pipeline's threads: background work joins, and results do not depend on the count.

The speed they buy is measured by ``benchmarks/bench_speed.py``, not here: these tests check
that work handed to the background thread comes back, errors included, and bit-identical.
"""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from stereo_vo_ros import Config, StereoOdometry
from stereo_vo_ros.config import ConfigError
from stereo_vo_ros.parallel import auto_threads, Workers
from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence


@pytest.fixture(scope='module')
def urban_frames():
    """Thirty pairs of the rendered urban preset at KITTI size (exact ground truth)."""
    return list(SyntheticSequence(SequenceSpec.preset('urban', n_frames=30, seed=3)))


def test_submit_runs_in_the_background_and_joins():
    workers = Workers(2, set_opencv=False)
    try:
        names = []
        job = workers.submit(lambda x: names.append(threading.current_thread().name) or x * 2, 21)
        assert job.result() == 42
        assert names and names[0] != threading.current_thread().name

        def fail():
            raise ValueError('boom')
        with pytest.raises(ValueError):
            workers.submit(fail).result()
    finally:
        workers.close()
    assert workers.threads == 1
    # Closed or single-threaded: inline, the error still raised by result(), not by submit.
    assert workers.submit(lambda: threading.current_thread().name).result() == \
        threading.current_thread().name
    late = workers.submit(fail)
    with pytest.raises(ValueError):
        late.result()


def test_auto_threads_and_config_range():
    assert auto_threads(3) == 3
    assert 1 <= auto_threads(0) <= 4
    assert auto_threads(0) <= max(1, (os.cpu_count() or 1) - 1)
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
