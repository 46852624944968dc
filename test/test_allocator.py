"""The allocator setting: a pipeline keeps its freed memory; the worker process takes it too."""

from __future__ import annotations

import ctypes
import json
import os
from pathlib import Path
import pickle
import resource
import subprocess
import sys

import numpy as np
import pytest

from stereo_vo_ros import Config, StereoOdometry
from stereo_vo_ros.allocator import (_glibc, keep_freed_memory, M_MMAP_THRESHOLD,
                                     M_TRIM_THRESHOLD, malloc_settings)
from stereo_vo_ros.parallel import ProcessWorker, Workers

ROOT = Path(__file__).resolve().parents[1]

needs_glibc = pytest.mark.skipif(not _glibc(), reason='mallopt is glibc only')
needs_process = pytest.mark.skipif(not ProcessWorker.available(),
                                   reason='the worker process needs /dev/shm (Linux)')

#: The setting is process-wide and cannot be undone: the checks run in fresh interpreters.
#: Their first lines: glibc's thresholds pinned at their start (128 kB), its own adjustment off.
PIN_START = """
import ctypes
from stereo_vo_ros.allocator import M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
libc = ctypes.CDLL(None)
libc.mallopt(M_MMAP_THRESHOLD, 128 << 10)
libc.mallopt(M_TRIM_THRESHOLD, 128 << 10)
"""
#: 1. A pair's worth of image-sized blocks allocated and freed, round after round: the page
#:    faults of each round. glibc's thresholds are set to their start (128 kB) first: left to
#:    itself glibc raises them when a large block is freed, so an import that had freed one left
#:    the blocks in the heap without the setting too (all rounds without a fault, in one run).
BURST = PIN_START + """
import json, sys
from stereo_vo_ros.allocator import keep_freed_memory
sys.path.insert(0, sys.argv[2])
from test_allocator import burst_faults
kept = keep_freed_memory(int(sys.argv[1]))
print(json.dumps([kept, burst_faults()]))
"""
#: 2. The page faults of the caller's thread in each ``process`` call of a rendered city drive
#:    (pickled frames, rendered by the test), in a process whose glibc thresholds are pinned at
#:    their start (128 kB) before anything is allocated: glibc's own adjustment is off, the worst
#:    case of its defaults. Rendered in the same process, the drive left holes in the heap (3 MB
#:    free of 130 MB) that now and then held an image-sized block, and the default run then
#:    faulted nothing.
PIPELINE = PIN_START + """
import json, pickle, resource, sys
from stereo_vo_ros import Config, StereoOdometry
with open(sys.argv[2], 'rb') as stream:
    frames = pickle.load(stream)
vo = StereoOdometry(Config().replace(**{'pipeline.threads': 1,
                                        'pipeline.keep_freed_memory_mb': int(sys.argv[1])}))
faults = []
for frame in frames:
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    vo.process(frame)
    faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
vo.close()
print(json.dumps(faults))
"""


def burst_faults(rounds: int = 12, pin: bool = False) -> tuple[int, list[int]]:
    """
    Return this process's id and the page faults of each round of ten 400 kB blocks.

    ``pin``: set glibc's thresholds to their start first (what the process freed before, e.g.
    while importing, would otherwise have raised them).
    """
    if pin:
        libc = ctypes.CDLL(None)
        libc.mallopt(M_MMAP_THRESHOLD, 128 << 10)
        libc.mallopt(M_TRIM_THRESHOLD, 128 << 10)
    faults = []
    for _ in range(rounds):
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        blocks = [np.ones(400_000, np.uint8) for _ in range(10)]
        del blocks
        faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
    return os.getpid(), faults


def _clean_environment() -> dict[str, str]:
    """Return this environment without the malloc settings, with the repository importable."""
    operator = malloc_settings(os.environ)
    env = {key: value for key, value in os.environ.items() if key not in operator}
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT)] + sys.path)
    return env


def _run(script: str, *args: str):
    out = subprocess.run([sys.executable, '-c', script, *args], capture_output=True, text=True,
                         timeout=300, env=_clean_environment())
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@needs_glibc
def test_kept_memory_is_reused_instead_of_faulted_in_again():
    # glibc's start thresholds give the freed blocks back: every round faults them in again.
    kept, (_, default) = _run(BURST, '0', str(Path(__file__).parent))
    assert kept is False
    kept, (_, faults) = _run(BURST, '32', str(Path(__file__).parent))
    assert kept is True
    # The first round grows the heap once; after it, no more faults.
    assert sum(default[1:]) > 10 * max(sum(faults[1:]), 50), (default, faults)


@needs_glibc
def test_pipeline_keeps_its_pairs_memory_whatever_the_process_set_before(tmp_path):
    # (Imported here: the worker processes of the other tests import this module.)
    from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence
    frames = tmp_path / 'frames.pickle'
    with open(frames, 'wb') as stream:
        pickle.dump(list(SyntheticSequence(SequenceSpec.preset('urban', n_frames=10, seed=3))),
                    stream)
    default, kept = _run(PIPELINE, '0', str(frames)), _run(PIPELINE, '32', str(frames))
    assert len(default) == len(kept) == 10
    later = slice(4, None)  # the first pairs grow the heap
    assert np.median(kept[later]) <= 10, kept
    assert np.median(default[later]) > 10 * max(np.median(kept[later]), 5), (default, kept)


def test_keep_freed_memory_leaves_the_operators_settings(monkeypatch, caplog):
    assert keep_freed_memory(0) is False  # left alone
    assert keep_freed_memory(-1) is False
    for name in malloc_settings(os.environ):
        monkeypatch.delenv(name)
    monkeypatch.setenv('GLIBC_TUNABLES', 'glibc.malloc.trim_threshold=1000000')
    with caplog.at_level('INFO', logger='stereo_vo_ros.allocator'):
        assert keep_freed_memory(32) is False
    if _glibc():
        assert 'GLIBC_TUNABLES' in caplog.text
    monkeypatch.setenv('GLIBC_TUNABLES', 'glibc.rtld.nns=2')  # not malloc's
    monkeypatch.setenv('MALLOC_TRIM_THRESHOLD_', '1000000')
    assert keep_freed_memory(32) is False
    monkeypatch.delenv('MALLOC_TRIM_THRESHOLD_')
    assert keep_freed_memory(32) is _glibc()


@needs_glibc
@needs_process
def test_worker_process_applies_the_pipelines_setting(monkeypatch):
    for name in malloc_settings(os.environ):
        monkeypatch.delenv(name)
    # A preload item with a JSON argument ('module:function=JSON').
    workers = Workers(2, set_opencv=False, preload=('os:chdir="/"',))
    try:
        assert workers.kind == 'process'
        assert workers.submit(os.getcwd).result() == '/'
        pid, default = workers.submit(burst_faults, 12, True).result()
        assert pid != os.getpid()  # it ran in the worker
    finally:
        workers.close()
    vo = StereoOdometry(Config().replace(**{'pipeline.threads': 2}))
    try:
        assert vo.workers.kind == 'process'
        pid, kept = vo.workers.submit(burst_faults).result()
        assert pid != os.getpid()
        assert sum(default[1:]) > 10 * max(sum(kept[1:]), 50), (default, kept)
        # Changed at run time: the worker process starts over without it. (Not pinned: pinning
        # would hide the setting if it were still there; what the new process freed while
        # starting could then keep the blocks too, which has not been seen.)
        vo.update_config(vo.config.replace(**{'pipeline.keep_freed_memory_mb': 0}))
        assert vo.workers.kind == 'process'
        pid_again, again = vo.workers.submit(burst_faults).result()
        assert pid_again not in (pid, os.getpid())
        assert sum(again[1:]) > 10 * max(sum(kept[1:]), 50), (again, kept)
    finally:
        vo.close()
