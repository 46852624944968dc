"""
A small TF listener: the transforms of ``/tf_static`` and ``/tf`` kept as a tree of frames.

The node needs one lookup, once: the pose of the camera in the robot's base frame (the
camera's mounting, normally a static transform from robot_state_publisher or
static_transform_publisher). ``tf2_ros`` is not on PyPI, so instead of its buffer the node
subscribes to the two topics with ``tf2_msgs/TFMessage`` (generated into the venv by
``scripts/build_tf2_msgs.sh`` where no ROS install provides it) and answers the lookup from
the newest transform of every edge. This is enough for a chain of fixed or slowly changing
transforms; it does not interpolate in time as tf2 does.

``TransformTree`` imports no ROS and is tested on its own; ``TransformListener`` wires it to a
node.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from . import conversions as conv


class TransformTree:
    """
    Frames connected by transforms; look up the transform between any two connected frames.

    Each edge is stored as ``T_parent_child`` (4, 4) float64 (metres), the newest one given.
    Thread-safe: the subscription callbacks add, the node's worker looks up.
    """

    def __init__(self) -> None:
        self._parent: dict[str, tuple[str, np.ndarray]] = {}
        self._lock = threading.Lock()

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        """Set (or replace) the transform of ``child`` in ``parent``."""
        parent, child = parent.lstrip('/'), child.lstrip('/')
        if not parent or not child or parent == child:
            return
        T = np.asarray(T_parent_child, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return
        with self._lock:
            self._parent[child] = (parent, T.copy())

    def __len__(self) -> int:
        return len(self._parent)

    def _up(self, frame: str) -> dict[str, np.ndarray]:
        """{ancestor: T_ancestor_frame} from ``frame`` (identity) up to its root, in order."""
        up = {frame: np.eye(4)}
        T_anc_frame = np.eye(4)
        while frame in self._parent:
            parent, T_parent_frame = self._parent[frame]
            if parent in up:  # a cycle: stop
                break
            T_anc_frame = T_parent_frame @ T_anc_frame
            up[parent] = T_anc_frame
            frame = parent
        return up

    def lookup(self, target: str, source: str) -> np.ndarray:
        """
        Return ``T_target_source`` (4, 4): takes points in ``source`` coordinates to ``target``.

        Raises
        ------
        LookupError
            The frames are not connected (yet); the message names the known frames.

        """
        target, source = target.lstrip('/'), source.lstrip('/')
        with self._lock:
            up_source = self._up(source)
            up_target = self._up(target)
            known = sorted(set(self._parent) | {p for p, _ in self._parent.values()})
        for frame, T_frame_target in up_target.items():  # lowest common ancestor first
            if frame in up_source:
                return np.linalg.inv(T_frame_target) @ up_source[frame]
        raise LookupError(f'no transform between {target!r} and {source!r}; known frames: '
                          f'{known[:20]}')


class TransformListener:
    """
    Fill a TransformTree from ``/tf_static`` (transient local) and ``/tf`` on a node.

    Parameters
    ----------
    node : rclpy.node.Node
        Node that owns the two subscriptions.
    message_type : type
        ``tf2_msgs.msg.TFMessage``.

    """

    def __init__(self, node: Any, message_type: type) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        self.tree = TransformTree()
        static = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        dynamic = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self._subs = [node.create_subscription(message_type, '/tf_static', self._on_tf, static),
                      node.create_subscription(message_type, '/tf', self._on_tf, dynamic)]

    def _on_tf(self, msg: Any) -> None:
        for tf in msg.transforms:
            tr, ro = tf.transform.translation, tf.transform.rotation
            try:
                T = conv.transform_from_pose(tr, ro)
            except ValueError:  # a zero quaternion: not a transform
                continue
            self.tree.add(tf.header.frame_id, tf.child_frame_id, T)
