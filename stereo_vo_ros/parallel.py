"""
The pipeline's threads: what of one stereo pair may run at the same time.

Two kinds of concurrency pay on a small CPU, measured on the KITTI clip (two cores; see
``benchmarks/bench_speed.py`` and docs/benchmarks.md):

* OpenCV's own threads spread the points of one KLT call (``cv2.setNumThreads``);
* the tracker's replenishment (detection of new corners and their stereo matches, mostly
  OpenCV calls that release the GIL) runs on a worker thread while the caller estimates the
  motion (NumPy on small arrays, which holds the GIL most of the time).

Finer splits (the affine refinement's points over two threads, the detection crops) were
measured to cost more CPU than they saved: NumPy on arrays of a few thousand elements holds the
GIL between its short calls, so two such threads take turns instead of overlapping.

``Workers(threads)`` belongs to one ``StereoOdometry`` (no module state: several pipelines in
one process each have their own). With one thread everything runs inline in the caller's
thread, in the same order as with more; the results are the same at any thread count.
OpenCV's thread count is per process: the last pipeline created or reconfigured sets it.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
import os
from typing import Any, Callable

import cv2

#: ``pipeline.threads: 0`` uses the machine's cores but one, at most this many.
MAX_AUTO_THREADS = 4


def auto_threads(requested: int) -> int:
    """
    Return the thread count for ``pipeline.threads``.

    0: the machine's cores but one (left to the camera driver, DDS and the rest of the robot),
    at least one and at most ``MAX_AUTO_THREADS``. On two cores that is one thread: there a
    second bought 5-9 % of the time per pair for 35 % more CPU (OpenCV's idle threads wait
    actively), a bad trade on a CPU the robot shares.
    """
    if requested > 0:
        return int(requested)
    return max(1, min((os.cpu_count() or 1) - 1, MAX_AUTO_THREADS))


class _Done:
    """A result computed inline, with the interface of ``concurrent.futures.Future``."""

    def __init__(self, fn: Callable[..., Any], args: tuple) -> None:
        self._value: Any = None
        self._error: Exception | None = None
        try:
            self._value = fn(*args)
        except Exception as exc:  # raised by result(), as a Future does
            self._error = exc

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value


class Workers:
    """
    One background thread for work that overlaps the caller's, and OpenCV's thread count.

    Parameters
    ----------
    threads : int
        Threads to use, the caller's included (0: ``auto_threads``). With more than one, a
        background thread takes ``submit``-ted work and OpenCV uses ``threads`` threads.
    set_opencv : bool
        Set OpenCV's thread count (process-wide) to ``threads``.

    """

    def __init__(self, threads: int = 1, set_opencv: bool = True) -> None:
        self.threads = auto_threads(threads)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix='stereo_vo') \
            if self.threads > 1 else None
        if set_opencv:
            cv2.setNumThreads(self.threads)

    def close(self) -> None:
        """Stop the background thread (the object then runs everything inline)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.threads = 1

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future | _Done:
        """
        Start ``fn(*args)`` in the background and return at once; ``.result()`` joins it.

        With one thread ``fn`` runs inline before this returns; its exception, if any, is
        raised by ``.result()`` either way.
        """
        if self._pool is None:
            return _Done(fn, args)
        return self._pool.submit(fn, *args)


def inline() -> Workers:
    """Return workers that run everything in the caller's thread and leave OpenCV alone."""
    return Workers(1, set_opencv=False)
