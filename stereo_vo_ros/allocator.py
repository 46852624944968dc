"""
How the C allocator hands freed memory back to the system (glibc, Linux).

Every stereo pair allocates and frees the same few megabytes: OpenCV's image pyramids and
derivative images in each KLT pass, NumPy's image-sized temporaries. With glibc's defaults the
heap grows by about 4 MB within a 1241x376 pair and shrinks back at its end (``M_TRIM_THRESHOLD``
follows the largest block freed so far), so the next pair touches fresh pages again: about 800
page faults, 1 ms of kernel time per pair on a KITTI clip. ``keep_freed_memory`` raises both of
glibc's thresholds, so that the process keeps that memory and reuses it.

Both are needed: setting either turns glibc's dynamic thresholds off, and with only the trim
threshold raised every block above the fixed 128 kB mmap threshold is mapped and unmapped on
each allocation (about 4000 page faults per pair).

The setting is process-wide and stays for the life of the process (other code in the process
allocates under it too). Where there is no glibc (macOS, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import logging
import os

logger = logging.getLogger(__name__)

#: ``mallopt`` parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: The largest mmap threshold glibc accepts on a 64-bit system (bytes; 16 MB on 32-bit).
MAX_THRESHOLD_MB = 32


def keep_freed_memory(limit_mb: int) -> bool:
    """
    Keep up to ``limit_mb`` MB of freed memory in the process instead of returning it.

    Allocations below ``limit_mb`` come from the heap (``M_MMAP_THRESHOLD``), and the heap is
    not trimmed until ``limit_mb`` of it is free at its top (``M_TRIM_THRESHOLD``). Returns
    True when glibc took both, False otherwise (``limit_mb`` <= 0, no glibc, or a value glibc
    refuses: above 32 on 64-bit systems, 16 on 32-bit ones).
    """
    if limit_mb <= 0:
        return False
    if not _glibc():
        logger.debug('not glibc: the allocator is left as it is')
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    size = int(limit_mb) << 20
    if not mallopt(M_MMAP_THRESHOLD, size):
        logger.warning('glibc refused an mmap threshold of %d MB: the allocator is left as '
                       'it is', limit_mb)
        return False
    # The mmap threshold took: the trim threshold has no upper bound.
    return bool(mallopt(M_TRIM_THRESHOLD, size))


def _glibc() -> bool:
    """Return True in a process linked with glibc."""
    try:
        return (os.confstr('CS_GNU_LIBC_VERSION') or '').startswith('glibc')
    except (ValueError, OSError, AttributeError):  # not a GNU system, or no confstr at all
        return False
