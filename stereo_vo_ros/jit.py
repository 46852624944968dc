"""
Options and small linear algebra shared by the kernels compiled with Numba.

The package's per-point loops that NumPy would run as many small array operations (the affine
refinement, the KLT gradient matrices of the aperture checks, the rig refinement's row
couplings and bundle adjustment, the road alignment's steps, the estimator's transfer to pixels,
the Shi-Tomasi detection) are compiled with ``kernel`` (``numba.njit`` with ``JIT``). The
kernels the pipeline calls are compiled as their module is imported, for explicit signatures
(compiling takes 20-45 s once on two cores; later imports load the on-disk cache in
``__pycache__``), so no pair, and no job of the worker process, waits for the compiler. They
release the GIL, so a helper thread runs them next to the caller.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import math
from pathlib import Path
import time

import numba
import numpy as np

LOG = logging.getLogger(__name__)

#: Compile options: cached on disk, GIL released, float division by zero gives inf/NaN as in
#: NumPy. Sums may be reordered (SIMD), which is deterministic on a given machine; values are not
#: assumed finite (no ``nnan``/``ninf``), since a non-finite result is how a kernel reports a
#: point that failed.
JIT = {'cache': True, 'nogil': True, 'error_model': 'numpy',
       'fastmath': {'reassoc', 'contract', 'nsz', 'arcp'}}


_UNCACHED = []  # kernels compiled without the on-disk cache (no writable place for it)
#: Kernels this process compiled because the on-disk cache did not hold them (the first start
#: after an install or an update, or no place for the cache), and the seconds that took.
COMPILED = {'kernels': 0, 'seconds': 0.0}
#: How long compiling every kernel takes (s; two cores, from a quiet to a busy machine).
COMPILE_S = (20, 45)
#: This module's source, which every kernel's compiled code depends on (options, helpers).
_STAMP = hashlib.sha1(Path(__file__).read_bytes()).hexdigest()[:12]
_CHECKED: set = set()


def _drop_stale_cache(fn) -> None:
    """
    Delete the cached kernels of ``fn``'s module compiled against another version of this one.

    Numba invalidates a kernel's cache when the kernel's own file changes, not when a function
    it calls from another module, or the options, change. A marker file next to the cache
    (``__pycache__/<module>.jit-<stamp>``) says which version of this module the cache was
    built with. Only the cache next to the sources is checked: a read-only install does not
    change.
    """
    src = Path(inspect.getfile(fn))
    if src in _CHECKED or src == Path(__file__):
        return
    _CHECKED.add(src)
    cache = src.parent / '__pycache__'
    marker = cache / f'{src.stem}.jit-{_STAMP}'
    try:
        if marker.exists():
            return
        if cache.is_dir():
            for old in [*cache.glob(f'{src.stem}.*.nbi'), *cache.glob(f'{src.stem}.*.nbc'),
                        *cache.glob(f'{src.stem}.jit-*')]:
                old.unlink(missing_ok=True)
        else:  # no bytecode written yet (PYTHONDONTWRITEBYTECODE): the kernels' cache goes here
            cache.mkdir()
        marker.touch()
    except OSError:  # not writable: Numba uses the user's cache directory then
        pass


def kernel(signatures=None, exact: bool = False):
    """
    Return ``numba.njit`` with ``JIT`` (eager when ``signatures`` are given) as a decorator.

    With ``exact`` the kernel is compiled without ``JIT``'s fast-math flags: IEEE arithmetic in
    the order written, as NumPy evaluates it, for formulas whose exact zeros mean something (a
    fused multiply-add turns ``a * b - c * d`` of equal products into rounding noise).

    Numba keeps its cache next to the module, else in the user's cache directory; with neither
    writable (a read-only install run by a user without a writable home) the kernel is compiled
    without the cache, at every start, and a warning says so once. A cache built against
    another version of this module is dropped first (``_drop_stale_cache``).
    """
    args = () if signatures is None else (signatures,)
    options = {**JIT, 'fastmath': False} if exact else JIT

    def decorate(fn):
        _drop_stale_cache(fn)
        t0 = time.perf_counter()
        try:
            compiled = numba.njit(*args, **options)(fn)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            if not _UNCACHED:
                LOG.warning('compiled kernels are not cached (%s): each start compiles them '
                            'again, which takes %d-%d s', exc, *COMPILE_S)
            _UNCACHED.append(fn.__qualname__)
            compiled = numba.njit(*args, **{**options, 'cache': False})(fn)
        if signatures is not None:
            _count_compiled(compiled, time.perf_counter() - t0)
        return compiled
    return decorate


def _count_compiled(dispatcher, seconds: float) -> None:
    """Add an eagerly compiled kernel to ``COMPILED`` unless it came from the cache."""
    stats = getattr(dispatcher, 'stats', None)  # Numba's cache hits and misses
    if stats is None or stats.cache_hits:
        return
    if not COMPILED['kernels'] and not _UNCACHED:  # else the warning has said it
        LOG.info('compiling the kernels into %s: the first start after an install or an '
                 'update takes %d-%d s, later starts load them', stats.cache_path, *COMPILE_S)
    COMPILED['kernels'] += 1
    COMPILED['seconds'] += seconds


def compile_note() -> str | None:
    """One line on the kernels this process compiled; None if the cache held them all."""
    if not COMPILED['kernels']:
        return None
    why = ('no place for their cache: every start compiles them' if _UNCACHED else
           'the first start after an install or an update; later starts load them from the '
           'cache')
    kernels, seconds = COMPILED['kernels'], COMPILED['seconds']
    return f'this start compiled {kernels} kernels in {seconds:.0f} s ({why})'


#: The image types the kernels are compiled for (others are converted to float32).
IMAGE_TYPES = (numba.types.uint8, numba.types.float32)


def readonly(dtype, ndim: int):
    """Return the Numba type of a C-contiguous array read by a kernel (writeable ones pass too)."""
    return numba.types.Array(dtype, ndim, 'C', readonly=True)


def kernel_image(img: np.ndarray) -> np.ndarray:
    """Return ``img`` as a C-contiguous array of one of ``IMAGE_TYPES`` (else float32)."""
    img = np.asarray(img)
    return np.ascontiguousarray(img if img.dtype in (np.uint8, np.float32) else
                                img.astype(np.float32))


def image_signatures(make) -> list:
    """Return ``make(image_type)`` for every type of ``IMAGE_TYPES`` (an eager ``njit`` list)."""
    return [make(readonly(t, 2)) for t in IMAGE_TYPES]


#: The largest finite float64: ``finite`` compares magnitudes with it.
_LARGEST = float(np.finfo(np.float64).max)


@kernel()
def finite(x):
    """
    Return whether ``x`` is neither NaN nor infinite, also in kernels compiled with ``JIT``.

    Numba's ``math.isfinite(x)`` and ``np.isfinite(x)`` test ``x - x``: with ``reassoc`` and
    ``nsz`` together, LLVM cancels that difference when ``x`` is a sum of terms, and the test
    of a NaN sum gives True. A comparison of the magnitude has no terms to cancel, and NaN fails
    it (the kernels are compiled without ``nnan``/``ninf``).
    """
    return abs(x) <= _LARGEST


@kernel()
def cholesky(mat, n, out):
    """
    Write the lower Cholesky factor of ``mat[:n, :n]`` (symmetric; lower triangle read) to ``out``.

    A matrix that is not positive definite gives NaN on the diagonal from there on.
    """
    for a in range(n):
        for b in range(a + 1):
            s = mat[a, b]
            for k in range(b):
                s -= out[a, k] * out[b, k]
            if a == b:
                out[a, a] = math.sqrt(s) if s > 0.0 else np.nan
            else:
                out[a, b] = s / out[b, b]


@kernel()
def cholesky_solve(chol, n, rhs, tmp, out):
    """Solve ``L L^T x = rhs`` for the factor ``chol`` (``cholesky``) into ``out[:n]``."""
    for a in range(n):
        s = rhs[a]
        for b in range(a):
            s -= chol[a, b] * tmp[b]
        tmp[a] = s / chol[a, a]
    for a in range(n - 1, -1, -1):
        s = tmp[a]
        for b in range(a + 1, n):
            s -= chol[b, a] * out[b]
        out[a] = s / chol[a, a]
