"""
The pipeline's workers: work handed to a thread or a process comes back, errors included.

The speed they buy is measured by ``benchmarks/bench_speed.py``, not here: these tests check
that submitted work returns (from a real worker process over shared memory, or a thread), that
errors and lost workers end in the caller, and what the results depend on: with a worker the
replenishment starts before the later checks, so two or more threads agree bit for bit with each
other and closely with one thread.
"""

from __future__ import annotations

import copy
import logging
import os
from pathlib import Path
import pickle
import resource
import signal
import subprocess
import sys
import threading
import time
import types
import weakref

import numpy as np
import pytest

from stereo_vo_ros import Config, parallel, StereoOdometry
from stereo_vo_ros.config import ConfigError
from stereo_vo_ros.estimation.camera import StereoCalibration
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
        # The helper thread of short overlaps (any kind of worker).
        assert workers.overlaps
        helper = workers.submit_local(lambda: threading.current_thread().name).result()
        assert helper.startswith('stereo_vo_helper')
        with pytest.raises(ValueError):
            workers.submit_local(_fail, 'boom').result()
    finally:
        workers.close()
    assert workers.threads == 1 and workers.kind == 'inline' and not workers.overlaps
    assert workers.submit_local(lambda: threading.current_thread().name).result() == \
        threading.current_thread().name
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


@needs_process
def test_hung_worker_process_is_stopped_and_the_caller_goes_on(caplog, monkeypatch):
    # The first job may wait for the start-up, far longer than for a job once running.
    monkeypatch.setattr(parallel, 'RESULT_TIMEOUT_S', 0.001)
    workers = Workers(2, set_opencv=False)
    try:
        assert workers.submit(os.getpid).result() != os.getpid()
        monkeypatch.setattr(parallel, 'RESULT_TIMEOUT_S', 0.5)
        image = np.ones((376, 1241), np.uint8)  # through shared memory
        assert workers.submit(np.sum, image).result() == image.size
        block = Path(parallel.SHM_DIR) / workers._process._shm.name
        assert block.exists()
        proc = workers._process._proc
        os.kill(proc.pid, signal.SIGSTOP)  # alive, but it never answers
        with caplog.at_level(logging.WARNING, logger='stereo_vo_ros.parallel'):
            assert workers.submit(np.add, 2, 3).result() == 5
        assert 'did not answer within 0.5 s' in caplog.text
        assert proc.poll() == -signal.SIGKILL  # killed and reaped
        assert not block.exists()  # its shared block freed
        assert workers.submit(os.getpid).result() == os.getpid()
    finally:
        workers.close()


def test_auto_threads_and_config_range():
    assert auto_threads(3) == 3
    assert auto_threads(0) == max(1, min(parallel.usable_cpus(), 4))
    assert 1 <= parallel.usable_cpus() <= len(os.sched_getaffinity(0))
    with pytest.raises(ConfigError):
        Config().replace(**{'pipeline.threads': -1})
    with pytest.raises(ConfigError):
        Config().replace(**{'pipeline.worker': 'gpu'})


def _cgroup(tmp_path, lines, files):
    """Write a fake ``/sys/fs/cgroup`` tree and ``/proc/self/cgroup``; return their paths."""
    root = tmp_path / 'cgroup'
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    proc = tmp_path / 'proc_cgroup'
    proc.write_text(''.join(line + '\n' for line in lines))
    return str(root), str(proc)


def test_cgroup_cpu_limits_v2_v1_nested_and_unlimited(tmp_path):
    """A container's ``--cpus`` (cgroup v2 or v1), the smallest of nested limits, no limit."""
    limit = parallel.cgroup_cpu_limit
    v2 = _cgroup(tmp_path / 'v2', ['0::/robot/vo'], {
        'cpu.max': 'max 100000\n', 'robot/cpu.max': '150000 100000\n',
        'robot/vo/cpu.max': '300000 100000\n'})
    assert limit(*v2) == pytest.approx(1.5)  # the parent's limit is the smaller
    unlimited = _cgroup(tmp_path / 'none', ['0::/'], {'cpu.max': 'max 100000\n'})
    assert limit(*unlimited) is None
    v1 = _cgroup(tmp_path / 'v1', ['4:memory:/x', '2:cpu,cpuacct:/docker/abc', '0::/'], {
        'cpu,cpuacct/cpu.cfs_quota_us': '50000\n', 'cpu,cpuacct/cpu.cfs_period_us': '100000\n',
        'cpu,cpuacct/docker/abc/cpu.cfs_quota_us': '-1\n',
        'cpu,cpuacct/docker/abc/cpu.cfs_period_us': '100000\n'})
    assert limit(*v1) == pytest.approx(0.5)
    # Garbage, missing files and no /proc/self/cgroup count as no limit.
    broken = _cgroup(tmp_path / 'broken', ['0::/a', 'nonsense', '0::relative', '0::/../../x'],
                     {'a/cpu.max': 'lots\n'})
    assert limit(*broken) is None
    assert limit(str(tmp_path), str(tmp_path / 'missing')) is None
    # The count rounds the limit to the nearest CPU, at least one, at most the affinity.
    cpus = len(os.sched_getaffinity(0))
    assert parallel.usable_cpus(*v1) == 1
    assert parallel.usable_cpus(*v2) == min(cpus, 2)
    assert parallel.usable_cpus(*unlimited) == cpus


def test_threads_follow_the_cpus_the_process_may_use():
    """Pinned to one CPU (``taskset``, a cpuset), ``pipeline.threads: 0`` runs inline."""
    script = (
        'import os, sys\n'
        'os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n'
        'from stereo_vo_ros import Config, StereoOdometry\n'
        'import stereo_vo_ros\n'
        'assert stereo_vo_ros.__file__.startswith(os.getcwd()), stereo_vo_ros.__file__\n'
        'from stereo_vo_ros.parallel import auto_threads\n'
        'odometry = StereoOdometry(Config().replace(**{"pipeline.threads": 0}))\n'
        'print(auto_threads(0), odometry.workers.threads, odometry.workers.overlaps)\n'
        'odometry.close()\n')
    out = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                         timeout=300, cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ['1', '1', 'False']


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
    One, two (process or thread worker) and three threads give bit-identical poses and counts.

    The replenishment after every check instead of after the temporal checks (as the pipeline
    ran before it had a worker) differs a little: both end close to the truth and each other.
    """
    frames, truth = urban
    runs = {}
    for threads, worker, start in ((1, 'process', 'temporal'), (2, 'process', 'temporal'),
                                   (2, 'thread', 'temporal'), (3, 'process', 'temporal'),
                                   (1, 'process', 'all'), (2, 'process', 'all')):
        kind, runs[threads, worker, start] = _run(frames, **{
            'pipeline.threads': threads, 'pipeline.worker': worker,
            'tracker.replenish_after': start})
        assert kind == ('inline' if threads == 1 else
                        worker if ProcessWorker.available() else 'thread')
    for start, keys in (('temporal', ((1, 'process'), (2, 'thread'), (3, 'process'))),
                        ('all', ((1, 'process'),))):
        reference = runs[2, 'process', start]
        assert sum(r.status.name == 'OK' for r in reference) >= len(frames) - 2
        for key in keys:
            for a, b in zip(reference, runs[key + (start,)]):
                assert np.array_equal(a.T_world_cam, b.T_world_cam), (key, start)
                assert a.n_tracked == b.n_tracked and a.n_inliers == b.n_inliers
    path = np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))
    end = (np.linalg.inv(truth[0]) @ truth[-1])[:3, 3]  # both start at the identity
    ends = {start: runs[2, 'process', start][-1].T_world_cam[:3, 3]
            for start in ('temporal', 'all')}
    for start, position in ends.items():
        assert np.linalg.norm(position - end) < 0.01 * path, start
    assert np.linalg.norm(ends['temporal'] - ends['all']) < 0.005 * path


def test_road_profile_does_not_depend_on_the_thread_count(urban, monkeypatch):
    """
    The road work on the helper thread gives the poses of one thread.

    The road pyramids are built there next to the tracking, and the road plane of a pair is
    refined there after its pose: whether the caller settles each pair (the plane is refined
    then) or not (the next pair queues it behind its aperture checks, ahead of its pyramids).
    """
    frames, _ = urban
    built = []  # on the caller's thread
    real = StereoOdometry._start_road_images

    def recorded(self, calib, left, right):
        out = real(self, calib, left, right)
        built.append(threading.current_thread() is threading.main_thread()
                     if isinstance(out, parallel._Done) else False)
        return out
    monkeypatch.setattr(StereoOdometry, '_start_road_images', recorded)
    queued = []  # the helper's work, and where it was queued from
    submit_local = Workers.submit_local

    def recorded_local(self, fn, *args):
        queued.append(fn.__name__)
        return submit_local(self, fn, *args)
    monkeypatch.setattr(Workers, 'submit_local', recorded_local)
    profile = {'road.enabled': True, 'vehicle.nonholonomic': True}
    runs = {}
    for threads, settle in ((1, False), (2, False), (2, True)):
        built.clear()
        odometry = StereoOdometry(Config().replace(**profile, **{'pipeline.threads': threads}))
        runs[threads, settle] = []
        try:
            for i, frame in enumerate(frames[:12]):
                queued.clear()
                runs[threads, settle].append(odometry.process(frame))
                in_process = list(queued)
                queued.clear()
                if settle:
                    odometry.settle()
                if threads == 2 and i >= 2:
                    later = in_process if not settle else queued
                    assert later.count('_refine_road_plane') == 1, (settle, i)
                    if not settle:
                        order = [in_process.index(n) for n in (
                            'aperture_checks', '_refine_road_plane', '_prepare_road')]
                        assert order == sorted(order)
        finally:
            odometry.close()
        assert len(built) == 12 and all(built) == (threads == 1)
    reference = runs[1, False]
    assert sum(r.road_fused for r in reference) >= 8
    for key in ((2, False), (2, True)):
        for a, b in zip(reference, runs[key]):
            assert np.array_equal(a.T_world_cam, b.T_world_cam), key
            assert a.road_fused == b.road_fused


def test_reset_after_a_failed_pair_leaves_no_road_work_behind(urban, monkeypatch):
    """
    A pair that raises after its tracking has queued the last pair's road plane on the helper.

    ``reset()`` waits for that plane and drops it: the odometry then starts over as it does
    after a reset between two good pairs (the road pyramids of its first pair are not cut by a
    plane from before).
    """
    frames, _ = urban
    items = {'road.enabled': True, 'vehicle.nonholonomic': True, 'pipeline.threads': 2}
    runs = []
    for fail in (True, False):
        odometry = StereoOdometry(Config().replace(**items))
        try:
            for frame in frames[:4]:
                odometry.process(frame)
            if fail:
                estimate = odometry.estimator.estimate

                def failing(*args, **kwargs):
                    raise RuntimeError('estimator failed')
                monkeypatch.setattr(odometry.estimator, 'estimate', failing)
                with pytest.raises(RuntimeError, match='estimator failed'):
                    odometry.process(frames[4])
                assert odometry._road_plane_job is not None  # queued, not taken
                monkeypatch.setattr(odometry.estimator, 'estimate', estimate)
            odometry.reset()
            assert odometry._road_plane_job is None and odometry._road_plane is None
            runs.append([odometry.process(frame) for frame in frames[5:12]])
        finally:
            odometry.close()
    assert sum(r.road_fused for r in runs[1]) >= 4
    for a, b in zip(*runs):
        assert np.array_equal(a.T_world_cam, b.T_world_cam)


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


@needs_process
def test_process_worker_edge_cases(tmp_path, caplog):
    """The worker process's contract where jobs are unusual (each case once failed a review)."""
    # The worker sees the caller's import path: a module only the caller's sys.path reaches.
    (tmp_path / 'svo_path_probe.py').write_text(
        'import os\n\n\ndef pid():\n    return os.getpid()\n')
    sys.path.append(str(tmp_path))
    try:
        import svo_path_probe
        workers = Workers(2, set_opencv=False)
    finally:
        sys.path.remove(str(tmp_path))
    try:
        assert workers.submit(svo_path_probe.pid).result() != os.getpid()
        # A function that pickles here but does not unpickle there runs inline.
        here_only = types.ModuleType('svo_only_in_this_process')
        exec('import os\n\ndef pid():\n    return os.getpid()\n', here_only.__dict__)
        sys.modules[here_only.__name__] = here_only
        try:
            assert workers.submit(here_only.pid).result() == os.getpid()
        finally:
            del sys.modules[here_only.__name__]
        # A job nobody collected does not fail the next one.
        workers.submit(int, 'boom')
        assert workers.submit(np.add, 1, 2).result() == 3
        # Large arrays keep their dtype; subclasses (a masked array) are pickled whole.
        record = np.zeros(10000, dtype=[('x', '<f4'), ('n', '<i4')])
        record['n'] = np.arange(10000)
        back = workers.submit(np.copy, record).result()
        assert back.dtype == record.dtype and np.array_equal(back, record)
        masked = np.ma.masked_less(np.arange(20000.0), 10000.0)
        assert workers.submit(np.ma.sum, masked).result() == masked.sum()
        # Interrupted while waiting (Ctrl-C in the caller): the socket can no longer pair
        # replies with jobs, so the worker is dropped and later jobs run inline, correctly.
        job = workers.submit(time.sleep, 1.0)

        def interrupt(signum, frame):
            raise KeyboardInterrupt
        previous = signal.signal(signal.SIGALRM, interrupt)
        try:
            signal.setitimer(signal.ITIMER_REAL, 0.2)
            with caplog.at_level(logging.WARNING, logger='stereo_vo_ros.parallel'):
                with pytest.raises(KeyboardInterrupt):
                    job.result()
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
        assert 'interrupted' in caplog.text
        assert workers.submit(np.add, 2, 3).result() == 5
        assert workers.submit(os.getpid).result() == os.getpid()
    finally:
        workers.close()


@needs_process
def test_no_room_for_shared_memory_runs_inline(caplog):
    """A shared block that cannot be made (here: a file size limit) leaves the work inline."""
    workers = Workers(2, set_opencv=False)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 16, hard))
        with caplog.at_level(logging.WARNING, logger='stereo_vo_ros.parallel'):
            image = np.ones((376, 1241), np.uint8)
            assert workers.submit(np.sum, image).result() == image.size
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        workers.close()
    assert 'no shared memory' in caplog.text


def test_calibration_copies_stay_copies():
    """Copies of a calibration are new objects outside a worker process."""
    calib = SequenceSpec.preset('urban', n_frames=2).calibration()
    first, second = copy.deepcopy(calib), copy.deepcopy(calib)
    assert first is not second and first is not calib and first.same_as(calib)
    assert copy.copy(calib) is not first
    first.K_left[0, 0] += 1.0
    assert second.K_left[0, 0] == calib.K_left[0, 0]
    assert pickle.loads(pickle.dumps(calib)).same_as(calib)


def test_worker_looks_equal_calibrations_up_by_their_pickled_value(monkeypatch):
    """In a worker, equal calibrations come back as one object; another value as another."""
    from stereo_vo_ros.estimation import camera
    calib = SequenceSpec.preset('urban', n_frames=2).calibration()
    P_right = calib.right.P.copy()
    P_right[0, 3] *= 1.1  # a longer baseline
    other = StereoCalibration.from_projections(calib.left.P, P_right, *calib.size)
    monkeypatch.setattr(camera, '_UNPICKLED', weakref.WeakValueDictionary())
    first = pickle.loads(pickle.dumps(calib))
    assert first is not calib and first.same_as(calib)
    assert pickle.loads(pickle.dumps(copy.deepcopy(calib))) is first
    assert pickle.loads(pickle.dumps((calib, [calib])))[0] is first
    changed = copy.deepcopy(calib)
    changed.K_left[0, 0] += 1.0
    restored = pickle.loads(pickle.dumps(changed))
    assert restored is not first and restored.K_left[0, 0] == calib.K_left[0, 0] + 1.0
    assert pickle.loads(pickle.dumps(other)) is not first
    assert pickle.loads(pickle.dumps(other)).same_as(other)
