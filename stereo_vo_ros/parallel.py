"""
The pipeline's worker threads: independent pieces of one stereo pair run at the same time.

OpenCV and NumPy release the GIL in their heavy calls (KLT, corner detection, remap, array
arithmetic), so Python threads overlap them on several cores. ``Workers(threads)`` is a small
pool owned by one ``StereoOdometry`` (no module state: several pipelines in one process each
have their own); with ``threads == 1`` everything runs inline in the caller's thread, as before
threads existed.

Every use splits work whose pieces do not depend on each other and joins the results in a fixed
order, so the results are the same at any thread count.

``Workers`` also sets OpenCV's own thread count (``cv2.setNumThreads``), which parallelises the
points of one KLT call. OpenCV has one such setting per process: the last pipeline created or
reconfigured in a process sets it.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
import os
from typing import Any, Callable, Iterable, Sequence

import cv2
import numpy as np

#: ``pipeline.threads: 0`` uses the machine's cores, at most this many.
MAX_AUTO_THREADS = 4
#: A split gives every thread at least this many points (smaller pieces cost more to hand
#: over than they save).
MIN_POINTS_PER_THREAD = 32


def auto_threads(requested: int) -> int:
    """Return the thread count for ``pipeline.threads`` (0: the cores, at most four)."""
    if requested > 0:
        return int(requested)
    return max(1, min(os.cpu_count() or 1, MAX_AUTO_THREADS))


class _Done:
    """A finished result with the interface of ``concurrent.futures.Future.result``."""

    def __init__(self, fn: Callable[..., Any], args: tuple) -> None:
        self._value = fn(*args)

    def result(self) -> Any:
        return self._value


class Workers:
    """
    A pool of ``threads - 1`` worker threads plus the calling thread.

    Parameters
    ----------
    threads : int
        Threads to use, the caller's included (0: ``auto_threads``).
    set_opencv : bool
        Also set OpenCV's thread count to the same number (process-wide).

    """

    def __init__(self, threads: int = 1, set_opencv: bool = True) -> None:
        self.threads = auto_threads(threads)
        self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix='stereo_vo') \
            if self.threads > 1 else None
        if set_opencv:
            cv2.setNumThreads(self.threads)

    def close(self) -> None:
        """Stop the worker threads (the object then runs everything inline)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.threads = 1

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future | _Done:
        """Start ``fn(*args)`` on a worker (inline with one thread); ``.result()`` joins it."""
        if self._pool is None:
            return _Done(fn, args)
        return self._pool.submit(fn, *args)

    def each(self, fn: Callable[..., Any], items: Iterable[Any]) -> list[Any]:
        """
        Return ``[fn(item) for item in items]``, the items dealt out over the threads.

        Thread ``k`` takes items ``k, k + threads, ...`` (the caller's thread the first share),
        so many small items of uneven size spread evenly.
        """
        items = list(items)
        if self._pool is None or len(items) < 2:
            return [fn(item) for item in items]
        shares = [items[k::self.threads] for k in range(min(self.threads, len(items)))]
        futures = [self._pool.submit(lambda share: [fn(x) for x in share], share)
                   for share in shares[1:]]
        done = [[fn(x) for x in shares[0]]] + [f.result() for f in futures]
        out: list[Any] = [None] * len(items)
        for k, results in enumerate(done):
            out[k::self.threads] = results
        return out

    def chunks(self, n: int) -> list[slice]:
        """
        Split ``range(n)`` into at most ``threads`` contiguous slices of similar size.

        Every slice but the last starts and ends at a multiple of ``MIN_POINTS_PER_THREAD``:
        NumPy's matrix products (OpenBLAS) round the same rows the same way only when the
        rows keep their position modulo the kernel's block, so the pieces then give exactly
        what one call over all rows gives.
        """
        block = MIN_POINTS_PER_THREAD
        parts = max(1, min(self.threads, n // block))
        edges = [int(round(n * k / parts / block)) * block for k in range(parts)] + [n]
        return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a] or [slice(0, n)]

    def split_points(self, fn: Callable[[slice], Sequence[np.ndarray]], n: int
                     ) -> tuple[np.ndarray, ...]:
        """
        Run ``fn(rows)`` on slices of ``n`` points and concatenate each returned array.

        ``fn`` returns a tuple of arrays whose first axis runs over the rows of its slice.
        """
        parts = self.each(fn, self.chunks(n))
        if len(parts) == 1:
            return tuple(parts[0])
        return tuple(np.concatenate(arrays) for arrays in zip(*parts))


#: Inline workers (one thread) for components used without a pipeline.
def inline() -> Workers:
    """Return workers that run everything in the caller's thread and leave OpenCV alone."""
    return Workers(1, set_opencv=False)
