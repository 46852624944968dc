"""
Shared test harness for the tests that run the real ROS 2 node (real rclpy, DDS on loopback).

A ``Harness`` owns a Context on its own ROS domain, a test node that collects the odometry,
the diagnostics and the log lines (/rosout) of the nodes under test, and an executor thread.
``composed_node`` adds a ``StereoVONode`` to the same executor with parameter overrides.
Every received odometry message can be checked as it arrives (``OdometryWatch``), so long runs
need not keep the messages.
"""

from __future__ import annotations

import collections
import contextlib
import os
import threading
import time
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import Log
import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from stereo_vo_ros.jit import COMPILE_S
from stereo_vo_ros.ros import conversions as conv
from stereo_vo_ros.ros.node import StereoVONode


def domain_id(salt: int = 0) -> int:
    """
    Return a ROS_DOMAIN_ID derived from the pid, so that parallel test runs do not talk.

    Parameters
    ----------
    salt : int
        Distinguishes the modules of one pytest process (0 keeps the historical id).

    Returns
    -------
    int
        A domain id in [1, 200].

    """
    return 1 + (os.getpid() * 7 + 3 + 37 * salt) % 200


#: Seconds a node process may take to subscribe: its start, and the first compile of the
#: kernels when their cache is cold (a fresh checkout on a loaded two-core machine).
NODE_START_S = 30.0 + COMPILE_S[1]

#: QoS of /rosout (rcl publishes it reliable and transient local).
ROSOUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


def stamp_ns(msg: Any) -> int:
    """Return the header stamp of a message in integer nanoseconds."""
    return conv.nanoseconds_from_time(msg.header.stamp)


def values(status: DiagnosticStatus) -> dict:
    """Return the key/value pairs of a DiagnosticStatus as a dict of strings."""
    return {kv.key: kv.value for kv in status.values}


def odometry_problems(msg: Odometry) -> list[str]:
    """
    Check one odometry message: every number finite, covariances symmetric PSD.

    Returns
    -------
    list of str
        What is wrong with the message (empty when nothing is).

    """
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    tw = msg.twist.twist
    numbers = np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w, tw.linear.x, tw.linear.y,
                        tw.linear.z, tw.angular.x, tw.angular.y, tw.angular.z,
                        *msg.pose.covariance, *msg.twist.covariance], np.float64)
    if not np.all(np.isfinite(numbers)):
        return [f'non-finite values at {stamp_ns(msg)} ns']
    problems = []
    if abs(np.linalg.norm([q.x, q.y, q.z, q.w]) - 1.0) > 1e-6:
        problems.append(f'quaternion not unit at {stamp_ns(msg)} ns')
    for name, cov in (('pose', msg.pose.covariance), ('twist', msg.twist.covariance)):
        cov = np.asarray(cov, np.float64).reshape(6, 6)
        scale = max(1.0, float(np.abs(cov).max()))
        if np.abs(cov - cov.T).max() > 1e-9 * scale:
            problems.append(f'{name} covariance not symmetric at {stamp_ns(msg)} ns')
        elif np.linalg.eigvalsh(cov).min() < -1e-9 * scale:
            problems.append(f'{name} covariance not positive semi-definite at '
                            f'{stamp_ns(msg)} ns')
    return problems


class OdometryWatch:
    """
    Check every odometry message of one topic on arrival; keep the newest ones.

    Attributes
    ----------
    count : int
        Messages received.
    problems : list of str
        Every failed check (see ``odometry_problems``), in arrival order.
    messages : collections.deque
        The newest ``keep`` messages.

    """

    def __init__(self, keep: int | None = None) -> None:
        self.count = 0
        self.problems: list[str] = []
        self.messages: collections.deque = collections.deque(maxlen=keep)
        self._changed = threading.Condition()

    def __call__(self, msg: Odometry) -> None:
        problems = odometry_problems(msg)
        with self._changed:
            self.count += 1
            self.problems += problems
            self.messages.append(msg)
            self._changed.notify_all()

    def wait_count(self, count: int, timeout_s: float) -> bool:
        """Wait until ``count`` messages have arrived; return False on timeout."""
        with self._changed:
            return self._changed.wait_for(lambda: self.count >= count, timeout_s)

    @property
    def last(self) -> Odometry | None:
        """Return the newest message (None before the first)."""
        return self.messages[-1] if self.messages else None


class Harness:
    """
    A context, a test node collecting odometry, diagnostics and logs, and an executor.

    Parameters
    ----------
    odom_topic : str or None
        Odometry topic collected into ``odom`` (None: none).
    domain : int, optional
        ROS domain id (default ``domain_id()``).
    diagnostics : bool
        Collect /diagnostics into ``diagnostics``.

    """

    def __init__(self, odom_topic: str | None = '/odom', domain: int | None = None,
                 diagnostics: bool = True) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id() if domain is None else domain)
        self.node = Node('test_harness', context=self.context)
        self.odom: list[Odometry] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.logs: list[Log] = []
        if odom_topic:
            self.node.create_subscription(Odometry, odom_topic, self.odom.append, 100)
        if diagnostics:
            self.node.create_subscription(DiagnosticArray, '/diagnostics',
                                          self.diagnostics.append, 100)
        self.node.create_subscription(Log, '/rosout', self.logs.append, ROSOUT_QOS)
        self.executor = MultiThreadedExecutor(num_threads=3, context=self.context)
        self.executor.add_node(self.node)
        self._gate = threading.Condition()
        self._pauses = 0
        self._in_spin = False
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """Spin until closed, standing still while someone holds ``paused()``."""
        while True:
            with self._gate:
                self._gate.wait_for(lambda: self._stop or not self._pauses)
                if self._stop or not self.context.ok():
                    return
                self._in_spin = True
            try:
                self.executor.spin_once(timeout_sec=0.1)
            finally:
                with self._gate:
                    self._in_spin = False
                    self._gate.notify_all()

    @contextlib.contextmanager
    def paused(self):
        """
        Hold the executor between two waits.

        rclpy's executor builds its wait set from entities that another thread may be
        destroying; destroying them (publishers, subscriptions, clients, nodes) while it
        stands still avoids that race. The callbacks it already handed to its threads (which
        take their message or request there) finish first.
        """
        with self._gate:
            self._pauses += 1
        self.executor.wake()
        try:
            with self._gate:
                self._gate.wait_for(lambda: not self._in_spin)
            # Callbacks the executor handed to its threads (rclpy keeps them in ``_futures``).
            self.wait_for(lambda: all(task.done() for task in
                                      list(getattr(self.executor, '_futures', ()))), 5.0)
            yield
        finally:
            with self._gate:
                self._pauses -= 1
                self._gate.notify_all()

    @property
    def spinning(self) -> bool:
        """Return True while the executor thread runs (an escaping exception stops it)."""
        return self._thread.is_alive()

    def add(self, node: Node) -> Node:
        """Spin another node in the same executor."""
        self.executor.add_node(node)
        return node

    def remove(self, node: Node) -> None:
        """Stop spinning a node added with ``add`` and destroy it."""
        with self.paused():
            self.executor.remove_node(node)
            node.destroy_node()

    def destroy(self, *entities: Any) -> None:
        """Destroy publishers, subscriptions or clients of the test node safely."""
        with self.paused():
            for entity in entities:
                if hasattr(entity, 'publish'):
                    self.node.destroy_publisher(entity)
                elif hasattr(entity, 'call_async'):
                    self.node.destroy_client(entity)
                else:
                    self.node.destroy_subscription(entity)

    def watch_odometry(self, topic: str, keep: int | None = None) -> OdometryWatch:
        """Subscribe to an odometry topic with a checking ``OdometryWatch``."""
        watch = OdometryWatch(keep)
        watch.subscription = self.node.create_subscription(Odometry, topic, watch, 100)
        return watch

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Poll ``predicate`` until it is true or the timeout (s) passes."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.005)
        return predicate()

    def settle(self, count: int, timeout_s: float = 15.0, quiet_s: float = 1.0) -> None:
        """Wait for ``count`` odometry messages, or for the stream to stop growing."""
        deadline = time.monotonic() + timeout_s
        last, since = len(self.odom), time.monotonic()
        while time.monotonic() < deadline and len(self.odom) < count:
            time.sleep(0.05)
            if len(self.odom) != last:
                last, since = len(self.odom), time.monotonic()
            elif time.monotonic() - since > quiet_s + 2.0:
                break

    def log_lines(self, logger: str, min_level: int = 0) -> list[str]:
        """Return the /rosout lines of the logger named ``logger`` at ``min_level`` or above."""
        return [m.msg for m in list(self.logs) if m.name == logger and m.level >= min_level]

    def call(self, srv_type, name: str, request, timeout_s: float = 10.0):
        """Call a service and return the response (None on timeout)."""
        client = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                return None
            future = client.call_async(request)
            self.wait_for(future.done, timeout_s)
            return future.result() if future.done() else None
        finally:
            self.destroy(client)

    def close(self) -> None:
        """Stop the executor thread, destroy the nodes and shut the context down."""
        with self._gate:
            self._stop = True
            self._gate.notify_all()
        self.executor.wake()
        self._thread.join(timeout=10.0)
        self.executor.shutdown(timeout_sec=5.0)
        for node in list(self.executor.get_nodes()):
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def composed_node(h: Harness, namespace: str | None = None, **params: Any) -> StereoVONode:
    """
    Add a StereoVONode to the harness' executor (sim time, reliable QoS, extra parameters).

    ``params`` use the dotted parameter names through keyword unpacking, e.g.
    ``composed_node(h, **{'ros.sync': 'exact'})``.
    """
    overrides = [Parameter('use_sim_time', value=True), Parameter('ros.qos', value='reliable')]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    kwargs = {'namespace': namespace} if namespace else {}
    return h.add(StereoVONode(context=h.context, parameter_overrides=overrides, **kwargs))
