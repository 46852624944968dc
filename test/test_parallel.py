"""
The pipeline's workers: work handed to a thread or a process comes back, errors included.

The speed they buy is measured by ``benchmarks/bench_speed.py``, not here: these tests check
that submitted work returns (from a real worker process over shared memory, or a thread), that
errors and lost workers end in the caller, and what the results depend on: with a worker the
replenishment starts before the later checks, so two or more threads agree bit for bit with each
other and closely with one thread.
"""

from __future__ import annotations

import logging
import os
import signal
import threading

import numpy as np
import pytest

from stereo_vo_ros import Config, StereoOdometry
from stereo_vo_ros.config import ConfigError
from stereo_vo_ros.parallel import auto_threads, ProcessWorker, Workers
from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence

needs_process = pytest.mark.skipif(not ProcessWorker.available(),
                                   reason='the worker process needs /dev/shm (Linux)')


@pytest.fixture(scope='module')
def urban():
    """Thirty pairs of the rendered urban preset at KITTI size and their true poses."""
    seq = SyntheticSequence(SequenceSpec.preset('urban', n_frames=30, seed=3))
    return list(seq), seq.ground_truth


def _fail(message: str) -> None:
    raise ValueError(message)


def test_thread_worker_runs_in_the_background_and_joins():
    workers = Workers(2, set_opencv=False, kind='thread')
    assert workers.kind == 'thread'
    try:
        names = []
        job = workers.submit(lambda x: names.append(threading.current_thread().name) or x * 2, 21)
        assert job.result() == 42
        assert names and names[0] != threading.current_thread().name
        with pytest.raises(ValueError):
            workers.submit(_fail, 'boom').result()
    finally:
        workers.close()
    assert workers.threads == 1 and workers.kind == 'inline'
    # Closed or single-threaded: inline, the error still raised by result(), not by submit.
    assert workers.submit(lambda: threading.current_thread().name).result() == \
        threading.current_thread().name
    late = workers.submit(_fail, 'late')
    with pytest.raises(ValueError):
        late.result()


@needs_process
def test_process_worker_runs_jobs_in_another_process():
    workers = Workers(2, set_opencv=False)
    assert workers.kind == 'process'
    try:
        assert workers.submit(os.getpid).result() != os.getpid()
        # Large arrays travel through shared memory, small ones pickled; the same array twice.
        image = np.arange(376 * 1241, dtype=np.uint32).reshape(376, 1241)
        small = np.array([1.0, 2.0])
        assert workers.submit(np.add, image, image).result().sum() == 2 * image.sum()
        assert np.array_equal(workers.submit(np.multiply, small, 3.0).result(), [3.0, 6.0])
        # A larger block later, and results that do not keep views of it.
        bigger = np.ones((720, 1280, 3), np.uint8)
        total = workers.submit(np.sum, bigger)
        assert total.result() == bigger.size
        # The worker's error is raised by result(); the worker goes on.
        with pytest.raises(ValueError, match='boom'):
            workers.submit(int, 'boom').result()
        assert workers.submit(np.negative, small).result().tolist() == [-1.0, -2.0]
        # Ctrl-C (SIGINT to the process group) leaves the worker to its owner.
        os.kill(workers._process._proc.pid, signal.SIGINT)
        assert workers.submit(os.getpid).result() != os.getpid()
        # What does not pickle runs inline, in this process.
        assert workers.submit(lambda: os.getpid()).result() == os.getpid()
        assert workers.worker_cpu_seconds() > 0.0
    finally:
        workers.close()
    assert workers.kind == 'inline'
    assert workers.submit(os.getpid).result() == os.getpid()


@needs_process
def test_lost_worker_process_falls_back_to_the_caller(caplog):
    workers = Workers(2, set_opencv=False)
    try:
        workers._process._proc.kill()
        workers._process._proc.wait()
        with caplog.at_level(logging.WARNING, logger='stereo_vo_ros.parallel'):
            # The job is sent to a dead process: it runs inline instead, once, and says so.
            assert workers.submit(np.add, 2, 3).result() == 5
        assert 'worker process lost' in caplog.text
        assert workers.submit(os.getpid).result() == os.getpid()
    finally:
        workers.close()


def test_auto_threads_and_config_range():
    assert auto_threads(3) == 3
    assert auto_threads(0) == max(1, min(os.cpu_count() or 1, 4))
    with pytest.raises(ConfigError):
        Config().replace(**{'pipeline.threads': -1})
    with pytest.raises(ConfigError):
        Config().replace(**{'pipeline.worker': 'gpu'})


def _run(frames, **items):
    odometry = StereoOdometry(Config().replace(**items))
    kind = odometry.workers.kind
    try:
        results = [odometry.process(frame) for frame in frames]
    finally:
        odometry.close()
    assert odometry.workers.threads == 1  # closed
    return kind, results


def test_results_with_a_worker_do_not_depend_on_its_kind_or_count(urban):
    """
    Two threads (process or thread worker) and three give bit-identical poses and counts.

    One thread differs only in when the replenishment starts (after every check instead of
    after the temporal ones): both end close to the truth and to each other.
    """
    frames, truth = urban
    runs = {}
    for threads, worker in ((1, 'process'), (2, 'process'), (2, 'thread'), (3, 'process')):
        kind, runs[threads, worker] = _run(frames, **{'pipeline.threads': threads,
                                                      'pipeline.worker': worker})
        assert kind == ('inline' if threads == 1 else
                        worker if ProcessWorker.available() else 'thread')
    reference = runs[2, 'process']
    assert sum(r.status.name == 'OK' for r in reference) >= len(frames) - 2
    for key in ((2, 'thread'), (3, 'process')):
        for a, b in zip(reference, runs[key]):
            assert np.array_equal(a.T_world_cam, b.T_world_cam), key
            assert a.n_tracked == b.n_tracked and a.n_inliers == b.n_inliers
    path = np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))
    ends = {}
    for key in ((1, 'process'), (2, 'process')):
        # Both start at the identity; the truth's first pose is the origin of the comparison.
        end = np.linalg.inv(truth[0]) @ truth[-1]
        ends[key] = runs[key][-1].T_world_cam[:3, 3]
        assert np.linalg.norm(ends[key] - end[:3, 3]) < 0.01 * path, key
    assert np.linalg.norm(ends[1, 'process'] - ends[2, 'process']) < 0.005 * path


@needs_process
def test_pipeline_goes_on_identically_when_its_worker_process_dies(urban, caplog):
    """Killing the worker mid-run: a warning, the rest inline, the same poses as one thread."""
    frames, _ = urban
    _, reference = _run(frames[:12], **{'pipeline.threads': 1})
    odometry = StereoOdometry(Config().replace(**{'pipeline.threads': 2}))
    try:
        results = []
        for i, frame in enumerate(frames[:12]):
            if i == 6:
                odometry.workers._process._proc.kill()
            with caplog.at_level(logging.WARNING, logger='stereo_vo_ros.parallel'):
                results.append(odometry.process(frame))
        assert odometry.workers._process is None or not odometry.workers._process.alive
    finally:
        odometry.close()
    assert 'worker process lost' in caplog.text
    for a, b in zip(reference, results):
        assert np.array_equal(a.T_world_cam, b.T_world_cam)
