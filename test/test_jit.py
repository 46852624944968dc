"""
Tests of the compiled kernels' support (``stereo_vo_ros/jit.py``): the finiteness test, the cache.

The kernels themselves are tested where they are used (``test_affine_klt.py``,
``test_tracker.py``, ``test_rig_calibration.py``, ``test_estimator_fast_paths.py``).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
import subprocess
import sys

import numba
import numpy as np

from stereo_vo_ros import jit


@numba.njit(**{**jit.JIT, 'cache': False})
def _sum_and_its_test(h, a, b, c, d):
    """Return a sum of terms, as the kernels form them, and ``jit.finite`` of it (fast math)."""
    s = h / c  # h = 0.5 of the arguments' type: no float64 constant widens a float32 sum
    g = h * a + b * s * (d - h - h) + b * s * d
    return jit.finite(g), g


def test_finite_sees_non_finite_sums_in_fast_math_kernels():
    """With reassoc and nsz, Numba's isfinite of a sum can cancel to True; ``finite`` does not."""
    for dtype in (np.float64, np.float32):
        values = [0.0, 1.0, -2.5, np.finfo(dtype).max / 4, np.inf, -np.inf, np.nan]
        seen = set()
        for a in values:
            for b in values:
                for c in (0.0, 1.0, np.inf):
                    args = [dtype(v) for v in (0.5, a, b, c, 0.0)]
                    ok, g = _sum_and_its_test(*args)
                    assert ok == np.isfinite(g), (args, g)
                    seen.add(ok)
        assert seen == {True, False}
    # The sums were formed in the arguments' type (float32 ones too).
    assert all(sig.return_type[1] == sig.args[0]
               for sig in _sum_and_its_test.nopython_signatures)
    assert jit.finite(np.finfo(np.float64).max) and not jit.finite(np.float32(np.inf))
    assert jit.finite(np.float32(3.0e38)) and jit.finite(-1e-320)


def test_kernels_work_without_a_place_for_their_cache():
    """No writable cache location (read-only install, no home): compiled uncached, a warning."""
    code = """
import logging
import numba.core.caching as caching
caching.CacheImpl._locator_classes = []  # no location can hold the cache
logging.basicConfig()
import numpy as np
from stereo_vo_ros import jit
from stereo_vo_ros.tracking.affine_klt import refine_affine
img = (np.arange(60 * 80) % 251).astype(np.uint8).reshape(60, 80)
pts = np.array([[40.3, 30.2]])
out, ok = refine_affine(img, img, pts, pts + 0.3)
assert np.all(np.isfinite(out)) and len(jit._UNCACHED) >= 3, jit._UNCACHED
print('uncached', len(jit._UNCACHED))
"""
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1], timeout=600)
    assert done.returncode == 0, done.stderr
    assert 'uncached' in done.stdout
    assert done.stderr.count('compiled kernels are not cached') == 1


def test_a_cache_built_against_another_version_of_the_kernel_options_is_dropped(tmp_path):
    """Kernels call jit.py's helpers and take its options: its change invalidates their cache."""
    from stereo_vo_ros import jit
    (tmp_path / 'kernels_mod.py').write_text('def f():\n    return 1\n')
    cache = tmp_path / '__pycache__'
    cache.mkdir()
    stale = [cache / 'kernels_mod.f-1.py311.nbi', cache / 'kernels_mod.f-1.py311.1.nbc',
             cache / 'kernels_mod.jit-000000000000']
    other = cache / 'other.f-1.py311.nbi'
    for path in stale + [other]:
        path.write_bytes(b'x')
    spec = importlib.util.spec_from_file_location('kernels_mod', tmp_path / 'kernels_mod.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    jit._drop_stale_cache(module.f)
    assert not any(path.exists() for path in stale) and other.exists()
    assert (cache / f'kernels_mod.jit-{jit._STAMP}').exists()
    kept = cache / 'kernels_mod.f-1.py311.nbi'
    kept.write_bytes(b'x')  # built against this version: kept from now on
    jit._CHECKED.discard(tmp_path / 'kernels_mod.py')
    jit._drop_stale_cache(module.f)
    assert kept.exists()


def test_a_cache_built_where_no_bytecode_was_written_is_kept(tmp_path):
    """Without ``__pycache__`` (PYTHONDONTWRITEBYTECODE) the first start marks the new cache."""
    from stereo_vo_ros import jit
    (tmp_path / 'fresh_mod.py').write_text('def f():\n    return 1\n')
    spec = importlib.util.spec_from_file_location('fresh_mod', tmp_path / 'fresh_mod.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    jit._drop_stale_cache(module.f)  # the first start: Numba saves its cache after this
    cache = tmp_path / '__pycache__'
    assert (cache / f'fresh_mod.jit-{jit._STAMP}').exists()
    saved = cache / 'fresh_mod.f-1.py311.nbi'
    saved.write_bytes(b'x')
    jit._CHECKED.discard(tmp_path / 'fresh_mod.py')
    jit._drop_stale_cache(module.f)  # the next start keeps it
    assert saved.exists()


def test_a_process_that_compiles_the_kernels_and_one_that_loads_them_agree(tmp_path):
    """
    The poses do not depend on whether the kernels were compiled here or taken from the cache.

    The first process compiles every kernel into an empty cache (``NUMBA_CACHE_DIR``), the
    second loads them; both run the road vehicle profile (tracker, estimator, rig and road
    kernels) over the same rendered pairs and must give the same poses to the bit. The first
    says, once and as it starts, that it compiles them, and counts them (``jit.compile_note``,
    which the node logs); the second neither.
    """
    code = """
import hashlib
import logging
logging.basicConfig(level=logging.INFO)
import numpy as np
from stereo_vo_ros import jit
from stereo_vo_ros.config import Config
from stereo_vo_ros.pipeline import StereoOdometry
from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence
items = {'road.enabled': True, 'vehicle.nonholonomic': True, 'pipeline.threads': 1}
odometry = StereoOdometry(Config().replace(**items))
poses = [odometry.process(frame).T_world_cam for frame in
         SyntheticSequence(SequenceSpec.preset('urban', n_frames=10, seed=3))]
print(jit.COMPILED['kernels'], jit.compile_note())
print(hashlib.sha1(np.array(poses).tobytes()).hexdigest())
"""
    env = {**os.environ, 'NUMBA_CACHE_DIR': str(tmp_path)}
    digests, compiled, notes = [], [], []
    for _ in range(2):
        done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parents[1], timeout=900, env=env)
        assert done.returncode == 0, done.stderr
        digests.append(done.stdout.split()[-1])
        compiled.append(int(done.stdout.split()[0]))
        notes.append(done.stderr.count('compiling the kernels into'))
        assert any(tmp_path.rglob('*.nbi'))  # compiled into the empty cache, then loaded
    assert digests[0] == digests[1]
    assert compiled[0] >= 10 and compiled[1] == 0, compiled
    assert notes == [1, 0], notes
