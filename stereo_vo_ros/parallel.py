"""
The pipeline's workers: what of one stereo pair runs next to the caller, and where.

The tracker's replenishment (detection of new corners, their stereo matches and refinement,
``tracking.replenish``) needs nothing of the motion estimate, so it runs while the caller
estimates the motion. Where it runs is ``pipeline.worker``:

* ``process`` (default): a worker process of its own (``serve`` in a new interpreter),
  fed through a socket with the images in shared memory. Only a process overlaps for real: the
  estimate and the replenishment are NumPy on small arrays and Python between OpenCV calls,
  which hold the GIL, so in one process they take turns.
* ``thread``: a background thread (no extra process; measured to overlap little).

Short work that overlaps a call of the caller that releases the GIL (a KLT pass, an OpenCV
call) goes to a helper thread instead (``submit_local``; with two or more threads, whatever the
kind), so NumPy in the helper runs next to it without copying images to another process. The
tracker runs its aperture checks there while it tracks the features, then the brightness maps of
its later passes, and the temporal affine refinement (a compiled kernel, which releases the GIL
too) while its forward-backward check runs.

With one thread (``pipeline.threads: 1``) everything runs inline in the caller's thread, in the
same order; the results are the same either way. ``Workers`` belongs to one ``StereoOdometry``
(no module state: several pipelines in one process each have their own worker). OpenCV's
thread count is per process: the last pipeline created or reconfigured sets it.

Linux is where the process worker runs (it maps the images from ``/dev/shm``); elsewhere, or
when the worker cannot start, dies or hangs (no answer within ``RESULT_TIMEOUT_S``), the work
runs in the caller's thread (logged once).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
import importlib
import json
import logging
import math
import mmap
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
import os
from pathlib import Path
import pickle
import signal
import socket
import subprocess
import sys
from typing import Any, Callable

import cv2
import numpy as np

logger = logging.getLogger(__name__)

#: ``pipeline.threads: 0`` uses the CPUs the process can use (``usable_cpus``), at most this many.
MAX_AUTO_THREADS = 4
#: Where the control groups' files are (Linux), and the file naming the process's groups.
CGROUP_ROOT = '/sys/fs/cgroup'
PROC_CGROUP = '/proc/self/cgroup'
#: Arrays of at least this many bytes travel to the worker process in shared memory.
SHARED_MIN_BYTES = 1 << 16
#: Where POSIX shared memory shows as files (Linux).
SHM_DIR = '/dev/shm'
#: Kinds of worker (``pipeline.worker``).
WORKER_KINDS = ('process', 'thread')
#: A worker process that has not answered a job after this long (seconds) is taken as hung:
#: it is killed and the job runs in the caller. A replenishment takes milliseconds.
RESULT_TIMEOUT_S = 5.0
#: The same for its first job, which also waits for the process to start and import its modules.
STARTUP_TIMEOUT_S = 60.0


def auto_threads(requested: int) -> int:
    """
    Return the thread count for ``pipeline.threads``.

    0: the CPUs this process may use (``usable_cpus``), 1 to 4. The replenishment is one job
    per pair, so two threads (the caller and one worker) take what it offers; more only give
    OpenCV's own calls in the caller more threads.
    """
    if requested > 0:
        return int(requested)
    return max(1, min(usable_cpus(), MAX_AUTO_THREADS))


def usable_cpus(cgroup_root: str = CGROUP_ROOT, proc_cgroup: str = PROC_CGROUP) -> int:
    """
    Return how many CPUs this process can keep busy (at least 1).

    The CPUs it may run on (its affinity: ``taskset``, a cpuset, a container's
    ``--cpuset-cpus``), capped by the CPU time its control groups allow (``cpu.max`` of cgroup
    v2 or ``cpu.cfs_quota_us`` of v1, for the process's group and every group above it: a
    container's ``--cpus``), rounded to the nearest whole CPU. ``os.cpu_count()`` counts the
    machine's CPUs, which a confined process cannot use; threads beyond what it can use only
    take turns.
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cpus = os.cpu_count() or 1
    quota = cgroup_cpu_limit(cgroup_root, proc_cgroup)
    if quota is not None:
        cpus = min(cpus, int(math.floor(quota + 0.5)))
    return max(1, cpus)


def cgroup_cpu_limit(cgroup_root: str = CGROUP_ROOT, proc_cgroup: str = PROC_CGROUP
                     ) -> float | None:
    """
    Return the CPU time the process's control groups allow, in CPUs, or None if unlimited.

    Reads the groups listed in ``proc_cgroup`` (``/proc/self/cgroup``) under ``cgroup_root``
    (``/sys/fs/cgroup``), from the process's own group up to the root; the smallest limit
    wins. Missing or unreadable files count as no limit.
    """
    try:
        with open(proc_cgroup) as fh:
            lines = fh.read().splitlines()
    except OSError:
        return None
    root = Path(cgroup_root)
    limits = []
    for line in lines:
        parts = line.split(':', 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == '':  # cgroup v2: the unified hierarchy
            quota_file, period_file = 'cpu.max', None
            base = root
        elif 'cpu' in controllers.split(','):  # cgroup v1: the cpu controller's hierarchy
            quota_file, period_file = 'cpu.cfs_quota_us', 'cpu.cfs_period_us'
            base = next((root / name for name in (controllers, 'cpu,cpuacct', 'cpu')
                         if (root / name).is_dir()), None)
            if base is None:
                continue
        else:
            continue
        path = path.strip() or '/'
        if not path.startswith('/') or '..' in Path(path).parts:
            continue  # outside this namespace's view of the groups
        group = Path(path)
        for folder in [group, *group.parents]:
            limit = _cpu_limit(base / folder.relative_to('/'), quota_file, period_file)
            if limit is not None:
                limits.append(limit)
    return min(limits) if limits else None


def _cpu_limit(folder: Path, quota_file: str, period_file: str | None) -> float | None:
    """One group's CPU limit (CPUs) from cgroup v2 ``cpu.max`` or v1's two files, or None."""
    try:
        if period_file is None:
            quota, period = (folder / quota_file).read_text().split()[:2]
        else:
            quota = (folder / quota_file).read_text().strip()
            period = (folder / period_file).read_text().strip()
        if quota in ('max', '-1'):
            return None
        value = float(quota) / float(period)
    except (OSError, ValueError):
        return None
    return value if value > 0 and math.isfinite(value) else None


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


class _Shared:
    """Placeholder of an array sent through shared memory: where it lies in the block."""

    def __init__(self, offset: int, shape: tuple, dtype: str) -> None:
        self.offset, self.shape, self.dtype = offset, shape, dtype


class _ProcessJob:
    """The result of one job on the worker process (``result`` waits for it, once)."""

    def __init__(self, worker: 'ProcessWorker', fn: Callable[..., Any], args: tuple) -> None:
        self._worker, self._fn, self._args = worker, fn, args
        self._done: _Done | None = None

    def result(self) -> Any:
        if self._done is None:
            self._done = self._worker._receive(self._fn, self._args)
        return self._done.result()


class ProcessWorker:
    """
    One worker process that runs submitted functions, one at a time, in submission order.

    ``preload`` names what the process does as it starts, so that the first job does not wait:
    modules to import (``package.module``) and functions to call (``package.module:function``,
    or ``package.module:function=JSON`` with one argument). The process sees the caller's
    ``sys.path``. ``submit(fn, *args)`` sends ``fn`` (a module-level function, pickled by name)
    and its arguments; plain NumPy arrays of ``SHARED_MIN_BYTES`` or more are copied into a
    shared-memory block instead of pickled. The next ``submit`` waits for the last job.
    Whatever cannot go (arguments that do not pickle here or unpickle there, no room for the
    shared block) or does not come back (a result that does not pickle, the process died, hung
    for ``RESULT_TIMEOUT_S`` (``STARTUP_TIMEOUT_S`` for the first job) or the wait was
    interrupted) runs inline.
    """

    def __init__(self, preload: tuple[str, ...] = ()) -> None:
        self._preload = tuple(preload)
        self._conn: Connection | None = None
        self._proc: subprocess.Popen | None = None
        self._shm: SharedMemory | None = None
        self._pending: _ProcessJob | None = None
        self._broken = False
        self._answered = False  # the first answer also waits for the start-up
        self._start()

    @staticmethod
    def available() -> bool:
        """Return True where the worker process can map shared memory (Linux)."""
        return os.path.isdir(SHM_DIR) and sys.platform.startswith('linux')

    def _start(self) -> None:
        parent, child = socket.socketpair()
        # The caller's import path, in its order (not the working directory first, as
        # ``python -m`` would put it): the worker runs the caller's code.
        paths = [p or os.getcwd() for p in sys.path]
        try:
            self._proc = subprocess.Popen(
                [sys.executable, '-c', _CHILD_MAIN, json.dumps(paths), str(child.fileno()),
                 *self._preload],
                pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL)
        except OSError as exc:
            logger.warning('cannot start the worker process (%s); working in one thread', exc)
            parent.close()
            self._broken = True
            return
        finally:
            child.close()
        self._conn = Connection(parent.detach())

    @property
    def alive(self) -> bool:
        """Return True while the process takes work."""
        return not self._broken and self._proc is not None

    def submit(self, fn: Callable[..., Any], *args: Any) -> _ProcessJob | _Done:
        """Start ``fn(*args)`` in the process; ``.result()`` returns or raises its outcome."""
        if self._pending is not None:
            try:  # a job nobody collected: its outcome is its owner's, not this job's
                self._pending.result()
            except Exception:  # noqa: BLE001
                pass
        if not self.alive:
            return _Done(fn, args)
        try:
            packed = self._pack(args)
        except (OSError, ValueError) as exc:
            logger.warning('no shared memory for the worker process (%s); working in one '
                           'thread from now on', exc)
            self.close()
            return _Done(fn, args)
        try:
            message = pickle.dumps((fn, packed), protocol=pickle.HIGHEST_PROTOCOL)
        except (pickle.PicklingError, TypeError, AttributeError) as exc:
            logger.debug('job does not pickle (%s); run inline', exc)
            return _Done(fn, args)
        try:
            self._conn.send_bytes(message)
        except OSError as exc:
            self._lost(exc)
            return _Done(fn, args)
        self._pending = _ProcessJob(self, fn, args)
        return self._pending

    def _pack(self, args: tuple) -> tuple:
        """Copy the large arrays of ``args`` into the shared block; return the arguments sent."""
        large = {}
        for arg in args:
            if type(arg) is np.ndarray and arg.nbytes >= SHARED_MIN_BYTES \
                    and not arg.dtype.hasobject:
                large.setdefault(id(arg), arg)
        offsets, size = {}, 0
        for key, arr in large.items():
            offsets[key] = size
            size += -(-arr.nbytes // 64) * 64
        if size and (self._shm is None or self._shm.size < size):
            self._release_block()
            self._shm = SharedMemory(create=True, size=size)
            # Reserve the pages now: a full /dev/shm then fails here (OSError), not with a
            # SIGBUS on the first write.
            fd = os.open(_shm_path(self._shm.name), os.O_RDWR)
            try:
                os.posix_fallocate(fd, 0, size)
            finally:
                os.close(fd)
        sent = []
        for arg in args:
            if id(arg) in offsets and large[id(arg)] is arg:
                offset = offsets[id(arg)]
                view = np.ndarray(arg.shape, arg.dtype, buffer=self._shm.buf, offset=offset)
                view[...] = arg
                del view
                sent.append(_Shared(offset, arg.shape, arg.dtype))
            else:
                sent.append(arg)
        return (self._shm.name if large else None, tuple(sent))

    def _receive(self, fn: Callable[..., Any], args: tuple) -> _Done:
        self._pending = None
        if self._conn is None:  # closed meanwhile
            return _Done(fn, args)
        try:
            timeout = RESULT_TIMEOUT_S if self._answered else STARTUP_TIMEOUT_S
            if not self._conn.poll(timeout):
                self._hung(timeout)
                return _Done(fn, args)
            status, value = self._conn.recv()
            self._answered = True
        except (EOFError, OSError) as exc:
            self._lost(exc)
            return _Done(fn, args)
        except BaseException:
            # Interrupted while waiting: the reply may still come, so the socket can no
            # longer pair replies with jobs.
            self._lost('interrupted while waiting for a result')
            raise
        if status == 'ok':
            return _Done(lambda: value, ())
        if status == 'inline':
            logger.debug('job could not run in the worker process (%s); run inline', value)
            return _Done(fn, args)
        return _Done(_raise, (value,))

    def cpu_seconds(self) -> float:
        """Return the CPU time the process has used so far (user + system, seconds; 0 if gone)."""
        if self._proc is None:
            return 0.0
        try:
            with open(f'/proc/{self._proc.pid}/stat') as stat:
                fields = stat.read().rsplit(')', 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
        except (OSError, ValueError, IndexError):
            return 0.0

    def _lost(self, why: object) -> None:
        logger.warning('worker process lost (%s); working in one thread from now on', why)
        self.close()

    def _hung(self, timeout: float) -> None:
        logger.warning('worker process did not answer within %.1f s; stopped, working in one '
                       'thread from now on', timeout)
        if self._proc is not None:
            self._proc.kill()  # also when it is stopped; close() then reaps it at once
        self.close()

    def _release_block(self) -> None:
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    def close(self) -> None:
        """Stop the process and free the shared block (later work runs inline)."""
        self._pending = None
        self._broken = True
        if self._conn is not None:
            try:
                self._conn.send_bytes(b'')
            except OSError:
                pass
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            self._proc = None
        self._release_block()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


def _raise(exc: Exception) -> None:
    raise exc


class Workers:
    """
    Where ``submit``-ted work runs next to the caller, and OpenCV's thread count.

    Parameters
    ----------
    threads : int
        Threads to use, the caller's included (0: ``auto_threads``). With more than one, a
        worker (``kind``) takes ``submit``-ted work and OpenCV uses ``threads - 1`` threads in
        the caller's process.
    set_opencv : bool
        Set OpenCV's thread count (process-wide).
    kind : str
        ``process`` (a worker process; a thread where no process can run) or ``thread``.
    preload : tuple of str
        Modules a worker process imports as it starts.

    """

    def __init__(self, threads: int = 1, set_opencv: bool = True, kind: str = 'process',
                 preload: tuple[str, ...] = ()) -> None:
        if kind not in WORKER_KINDS:
            raise ValueError(f'worker kind must be one of {WORKER_KINDS}, got {kind!r}')
        self.threads = auto_threads(threads)
        #: The kind asked for; ``kind`` is the one running (``inline`` with one thread).
        self.requested = kind
        self._pool: ThreadPoolExecutor | None = None
        self._process: ProcessWorker | None = None
        #: The helper thread of ``submit_local`` (None with one thread).
        self._helper: ThreadPoolExecutor | None = None
        if self.threads > 1:
            self._helper = ThreadPoolExecutor(1, thread_name_prefix='stereo_vo_helper')
            if kind == 'process' and ProcessWorker.available():
                self._process = ProcessWorker(preload)
            else:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix='stereo_vo')
        self.kind = 'process' if self._process is not None else (
            'thread' if self._pool is not None else 'inline')
        if set_opencv:
            cv2.setNumThreads(max(1, self.threads - 1))

    def close(self) -> None:
        """Stop the worker (the object then runs everything inline)."""
        if self._helper is not None:
            self._helper.shutdown(wait=True)
            self._helper = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._process is not None:
            self._process.close()
            self._process = None
        self.threads = 1
        self.kind = 'inline'

    def wait_ready(self) -> None:
        """Return once a worker process has started and imported its modules (benchmarks)."""
        if self._process is not None:
            self._process.submit(os.getpid).result()

    def worker_cpu_seconds(self) -> float:
        """Return the CPU time of the worker process so far (seconds; 0 without one)."""
        return 0.0 if self._process is None else self._process.cpu_seconds()

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future | _ProcessJob | _Done:
        """
        Start ``fn(*args)`` on the worker and return at once; ``.result()`` joins it.

        Inline (one thread), ``fn`` runs before this returns; its exception, if any, is raised
        by ``.result()`` either way. On a process, ``fn`` must be a module-level function;
        arguments that do not pickle make the call run inline.
        """
        if self._process is not None:
            return self._process.submit(fn, *args)
        if self._pool is None:
            return _Done(fn, args)
        return self._pool.submit(fn, *args)

    @property
    def overlaps(self) -> bool:
        """Whether ``submit_local`` runs next to the caller (else inline, before it returns)."""
        return self._helper is not None

    def submit_local(self, fn: Callable[..., Any], *args: Any) -> Future | _Done:
        """
        Start ``fn(*args)`` on the helper thread of this process; ``.result()`` joins it.

        For short work next to a call of the caller that releases the GIL (a KLT pass): the
        arguments are shared, not copied, and must not change until the result is taken.
        Inline (one thread), ``fn`` runs before this returns.
        """
        if self._helper is None:
            return _Done(fn, args)
        return self._helper.submit(fn, *args)


def inline() -> Workers:
    """Return workers that run everything in the caller's thread and leave OpenCV alone."""
    return Workers(1, set_opencv=False)


def _shm_path(name: str) -> str:
    """Return the file of the POSIX shared-memory block ``name``."""
    return os.path.join(SHM_DIR, name.lstrip('/'))


def _attach(name: str) -> mmap.mmap:
    """Map the whole shared block ``name`` (created by the caller) into this process."""
    fd = os.open(_shm_path(name), os.O_RDWR)
    try:
        return mmap.mmap(fd, 0)
    finally:
        os.close(fd)


def serve(conn: Connection, preload: tuple[str, ...] = ()) -> None:
    """
    Run jobs from ``conn`` until it closes or sends an empty message (the worker's loop).

    ``preload``: modules to import first, or ``module:function`` to call, or
    ``module:function=JSON`` to call with one argument.
    """
    # Ctrl-C in a terminal reaches the whole process group: the caller decides when this
    # process ends (an empty message, or the end of the socket when the caller is gone).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)
    for item in preload:
        name, _, call = item.partition(':')
        function, _, arg = call.partition('=')
        module = importlib.import_module(name)
        if function:
            getattr(module, function)(*([json.loads(arg)] if arg else []))
    block: tuple[str, mmap.mmap] | None = None
    while True:
        try:
            message = conn.recv_bytes()
        except (EOFError, OSError):
            break
        if not message:
            break
        try:
            fn, (name, packed) = pickle.loads(message)
        except Exception as exc:  # noqa: BLE001 - e.g. a class only the caller's __main__ has
            reply = ('inline', f'{type(exc).__name__}: {exc}')
        else:
            if name is not None and (block is None or block[0] != name):
                if block is not None:
                    block[1].close()
                block = (name, _attach(name))
            args = [np.ndarray(arg.shape, arg.dtype, buffer=block[1], offset=arg.offset)
                    if isinstance(arg, _Shared) else arg for arg in packed]
            del packed
            try:
                reply = ('ok', fn(*args))
            except Exception as exc:  # noqa: BLE001 - raised in the caller by result()
                reply = ('error', exc)
            del args
        try:
            try:
                conn.send(reply)
            except (pickle.PicklingError, TypeError, AttributeError) as exc:
                # A result or error that does not pickle: the caller runs the job itself.
                conn.send(('inline', f'{type(exc).__name__}: {exc}'))
        except OSError:  # the caller is gone or closed the socket
            break
        reply = None  # no view of the shared block outlives the job
    if block is not None:
        block[1].close()
    conn.close()


#: The worker process's entry: the caller's import path, then ``serve`` on the inherited socket.
_CHILD_MAIN = (
    'import json, sys\n'
    'sys.path[:] = json.loads(sys.argv[1])\n'
    'from multiprocessing.connection import Connection\n'
    'from stereo_vo_ros.parallel import serve\n'
    'serve(Connection(int(sys.argv[2])), tuple(sys.argv[3:]))\n')
