"""
How the C allocator hands freed memory back to the system (glibc, Linux).

Every stereo pair allocates and frees the same few megabytes: OpenCV's image pyramids and
derivative images in each KLT pass, NumPy's image-sized temporaries. glibc returns freed memory
at the top of its heap to the system once more than its trim threshold is free there, and maps
blocks above its mmap threshold on their own (unmapped again when freed). Both thresholds start
at 128 kB and rise only when glibc unmaps a larger block (the mmap threshold to that block's
size, at most 32 MB, the trim threshold to twice that). So whether a pair's memory survives to
the next pair depends on what the process freed before: in a process that had only loaded the
KITTI clips, the heap grew by about 4 MB within each 1241x376 pair and was trimmed back at its
end, and the next pair faulted those pages in again (up to about 800 page faults, 1.3 ms of
kernel time per pair). ``keep_freed_memory`` sets both thresholds, so that the process keeps
that memory and reuses it whatever it did before.

Both are needed: setting either turns glibc's dynamic thresholds off. With only the trim
threshold raised, in the process above every block over 128 kB was mapped and unmapped on each
allocation (about 4000 page faults per pair).

The setting is process-wide and stays for the life of the process: every library and thread in
it allocates under it (in a process that hosts several ROS nodes, all of them), and each of
glibc's per-thread arenas may keep up to the limit free. The last call wins. Where the
operator set glibc's malloc thresholds in the environment (``MALLOC_*_`` variables,
``GLIBC_TUNABLES=glibc.malloc...``), they are left as set. Where there is no glibc (macOS, musl)
it does nothing; with another allocator preloaded (jemalloc, tcmalloc) the call reaches that
allocator's ``mallopt``, which usually ignores it.
"""

from __future__ import annotations

from collections.abc import Mapping
import ctypes
import logging
import os

logger = logging.getLogger(__name__)

#: ``mallopt`` parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: The largest value taken (MB; the top of ``pipeline.keep_freed_memory_mb``'s range): glibc's
#: own ceiling for the thresholds it raises itself on a 64-bit system. Blocks larger than this
#: are mapped on their own, as glibc would.
MAX_LIMIT_MB = 32
#: Environment variables by which an operator sets glibc's malloc thresholds.
MALLOC_ENVIRONMENT = ('MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_', 'MALLOC_TOP_PAD_',
                      'MALLOC_MMAP_MAX_')


def keep_freed_memory(limit_mb: int) -> bool:
    """
    Keep up to ``limit_mb`` MB of freed memory in the process instead of returning it.

    Allocations below ``limit_mb`` (at most ``MAX_LIMIT_MB``) come from the heap
    (``M_MMAP_THRESHOLD``), and the heap is not trimmed until ``limit_mb`` of it is free at its
    top (``M_TRIM_THRESHOLD``). Returns True when glibc took both, False otherwise:
    ``limit_mb`` <= 0, no glibc, or the operator set the thresholds in the environment.
    """
    if limit_mb <= 0:
        return False
    if not _glibc():
        logger.debug('not glibc: the allocator is left as it is')
        return False
    operator = malloc_settings(os.environ)
    if operator:
        logger.info('glibc malloc thresholds set in the environment (%s): '
                    'pipeline.keep_freed_memory_mb is not applied', ', '.join(operator))
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    size = min(int(limit_mb), MAX_LIMIT_MB) << 20
    if not mallopt(M_MMAP_THRESHOLD, size):
        logger.warning('glibc refused an mmap threshold of %d MB: the allocator is left as '
                       'it is', size >> 20)
        return False
    if not mallopt(M_TRIM_THRESHOLD, size):
        # Half applied: the mmap threshold is fixed now, but the heap is still trimmed.
        logger.warning('glibc refused a trim threshold of %d MB', size >> 20)
        return False
    return True


def malloc_settings(environ: Mapping[str, str]) -> list[str]:
    """Return the names of the variables of ``environ`` that set glibc's malloc thresholds."""
    names = [name for name in MALLOC_ENVIRONMENT if name in environ]
    if 'glibc.malloc.' in environ.get('GLIBC_TUNABLES', ''):
        names.append('GLIBC_TUNABLES')
    return names


def _glibc() -> bool:
    """Return True in a process linked with glibc."""
    try:
        return (os.confstr('CS_GNU_LIBC_VERSION') or '').startswith('glibc')
    except (ValueError, OSError, AttributeError):  # not a GNU system, or no confstr at all
        return False
