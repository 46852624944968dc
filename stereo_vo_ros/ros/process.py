"""
Run ``stereo_vo_node`` as a separate process (the demo, the node tests and the benchmarks).

The node runs as a user runs it: through the installed ``stereo_vo_node`` entry point when
there is one next to the running interpreter or on ``PATH``, else ``python -m
stereo_vo_ros.ros.node``. It is stopped as ``ros2 run`` stops it: SIGINT, then a kill if it
has not exited within the timeout.

The processes that talk to it (the demo, the benchmarks) spin their own executor in a background
thread with :func:`spinning`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import threading
from typing import Any, IO, Iterator, Mapping, Sequence

#: Name of the node's console script.
NODE_EXECUTABLE = 'stereo_vo_node'


def node_command() -> list[str]:
    """Return the command that starts the node (without ``--ros-args``)."""
    here = Path(sys.executable).with_name(NODE_EXECUTABLE)
    if here.exists():
        return [str(here)]
    found = shutil.which(NODE_EXECUTABLE)
    if found:
        return [found]
    return [sys.executable, '-m', 'stereo_vo_ros.ros.node']


def with_pythonpath(env: Mapping[str, str], path: str | Path) -> dict[str, str]:
    """Return a copy of ``env`` with ``path`` first on PYTHONPATH (to run a working tree)."""
    out = dict(env)
    out['PYTHONPATH'] = os.pathsep.join([str(path)] + (
        [out['PYTHONPATH']] if out.get('PYTHONPATH') else []))
    return out


def start_node(ros_args: Sequence[str] = (), env: Mapping[str, str] | None = None,
               stdout: IO | int | None = None, **popen_kwargs) -> subprocess.Popen:
    """
    Start the node with ``--ros-args ROS_ARGS``; stop it with :func:`stop_node`.

    Parameters
    ----------
    ros_args : sequence of str
        Arguments after ``--ros-args`` (``-p name:=value``, ``-r from:=to``, ...).
    env : mapping, optional
        Environment of the process (default: this one), e.g. with its ROS_DOMAIN_ID.
    stdout : file, int or None
        Where the node's output goes (stderr follows it when given).
    **popen_kwargs
        Passed to ``subprocess.Popen``.

    Returns
    -------
    subprocess.Popen
        The running process.

    """
    cmd = node_command() + (['--ros-args', *ros_args] if ros_args else [])
    if stdout is not None:
        popen_kwargs.setdefault('stderr', subprocess.STDOUT)
    popen_kwargs.setdefault('stdin', subprocess.DEVNULL)
    return subprocess.Popen(cmd, env=dict(env if env is not None else os.environ),
                            stdout=stdout, **popen_kwargs)


def stop_node(proc: subprocess.Popen, timeout_s: float = 15.0) -> int:
    """SIGINT the node (Ctrl-C in ``ros2 run``), kill it after ``timeout_s``; return its code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


@contextlib.contextmanager
def node_process(ros_args: Sequence[str] = (), env: Mapping[str, str] | None = None,
                 stdout: IO | int | None = None, timeout_s: float = 15.0,
                 **popen_kwargs) -> Iterator[subprocess.Popen]:
    """
    Run the node for the duration of a ``with`` block (:func:`start_node`, :func:`stop_node`).

    Yields
    ------
    subprocess.Popen
        The running process; its ``returncode`` is set after the block.

    """
    proc = start_node(ros_args, env, stdout, **popen_kwargs)
    try:
        yield proc
    finally:
        stop_node(proc, timeout_s)


@contextlib.contextmanager
def spinning(executor: Any, period_s: float = 0.1) -> Iterator[threading.Thread]:
    """
    Spin an rclpy executor in a background thread for the duration of a ``with`` block.

    The thread calls ``executor.spin_once`` until the block ends, then it is joined, before the
    caller shuts the executor and rclpy down. A free-running ``executor.spin`` thread that is
    still waiting when rclpy shuts down can keep spinning at full CPU and starve the calling
    thread of the GIL: a fresh-clone CI run of the demo test hung that way for minutes,
    waiting for the node process to be reaped.

    Yields
    ------
    threading.Thread
        The spinning thread.

    """
    done = threading.Event()

    def spin() -> None:
        while not done.is_set():
            executor.spin_once(timeout_sec=period_s)

    thread = threading.Thread(target=spin, name='executor_spin', daemon=True)
    thread.start()
    try:
        yield thread
    finally:
        done.set()
        thread.join(timeout=10.0 * period_s + 5.0)
