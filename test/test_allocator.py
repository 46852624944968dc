"""The allocator setting: a pipeline keeps its freed memory; the worker process takes it too."""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from stereo_vo_ros import Config, StereoOdometry
from stereo_vo_ros.allocator import _glibc, keep_freed_memory
from stereo_vo_ros.parallel import ProcessWorker, Workers

ROOT = Path(__file__).resolve().parents[1]

needs_glibc = pytest.mark.skipif(not _glibc(), reason='mallopt is glibc only')

#: Fresh interpreters (the setting is process-wide and cannot be undone).
#: 1. A pair's worth of image-sized blocks allocated and freed, round after round: the page
#:    faults of each round.
BURST = """
import json, resource, sys
import numpy as np
from stereo_vo_ros.allocator import keep_freed_memory
kept = keep_freed_memory(int(sys.argv[1]))
faults = []
for _ in range(12):
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    blocks = [np.ones(400_000, np.uint8) for _ in range(10)]
    del blocks
    faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
print(json.dumps([kept, faults]))
"""
#: 2. The page faults of the caller's thread in each ``process`` call of a rendered city drive.
PIPELINE = """
import json, resource, sys
from stereo_vo_ros import Config, StereoOdometry
from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence
frames = list(SyntheticSequence(SequenceSpec.preset('urban', n_frames=14, seed=3)))
vo = StereoOdometry(Config().replace(**{'pipeline.threads': 1}))
faults = []
for frame in frames:
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    vo.process(frame)
    faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
vo.close()
print(json.dumps(faults))
"""


def _run(script: str, *args: str):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + sys.path))
    out = subprocess.run([sys.executable, '-c', script, *args], capture_output=True, text=True,
                         timeout=300, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@needs_glibc
def test_kept_memory_is_reused_instead_of_faulted_in_again():
    # glibc's defaults give the freed blocks back: every round faults about 1000 pages in.
    kept, default = _run(BURST, '0')
    assert kept is False
    assert min(default[1:]) > 500, default
    kept, faults = _run(BURST, '32')
    assert kept is True
    assert sum(faults[1:]) < 20, faults  # the first round grows the heap once


@needs_glibc
def test_pipeline_pairs_reuse_their_memory():
    # The default keeps the memory of one pair for the next (with only the trim threshold
    # raised, every image-sized block would be mapped and unmapped: thousands of faults a pair).
    faults = _run(PIPELINE)
    assert len(faults) == 14
    assert np.median(faults[6:]) <= 10, faults


def test_keep_freed_memory_arguments():
    assert keep_freed_memory(0) is False  # left alone
    assert keep_freed_memory(-1) is False
    if _glibc():
        assert keep_freed_memory(Config().pipeline.keep_freed_memory_mb) is True


@pytest.mark.skipif(not ProcessWorker.available(), reason='the worker process needs /dev/shm')
def test_worker_process_calls_its_preload_with_an_argument_and_the_pipeline_sends_the_setting():
    workers = Workers(2, set_opencv=False, preload=('os:chdir="/"',))
    try:
        assert workers.kind == 'process'
        assert workers.submit(os.getcwd).result() == '/'
    finally:
        workers.close()
    vo = StereoOdometry(Config().replace(**{'pipeline.threads': 2}))
    try:
        if vo.workers.kind == 'process':
            assert 'stereo_vo_ros.allocator:keep_freed_memory=32' in vo.workers._process._preload
    finally:
        vo.close()
    vo = StereoOdometry(Config().replace(**{'pipeline.threads': 2,
                                            'pipeline.keep_freed_memory_mb': 0}))
    try:
        if vo.workers.kind == 'process':
            assert not any('allocator' in item for item in vo.workers._process._preload)
    finally:
        vo.close()
