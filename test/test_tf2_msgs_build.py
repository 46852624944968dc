"""
tf2_msgs, generated into the venv by ``scripts/build_tf2_msgs.sh`` (it is not on PyPI).

The generated ``tf2_msgs/msg/TFMessage`` must be the one a ROS 2 Jazzy install has: the same
field, the same type hash (RIHS01) as Jazzy's own package advertises and rosbags computes, the
same CDR layout as rosbags' Jazzy typestore (each reads what the other writes), and a real
rclpy publisher on ``/tf`` must reach a real rclpy subscriber through the default RMW.

The tests skip when tf2_msgs does not import (e.g. a plain ``pytest`` in an environment where
the script has not run), except under ``scripts/test.sh``, which sets
``STEREO_VO_STRICT_PACKAGING=1`` after running the script and turns such a skip into a failure.
"""

import os
import time

from geometry_msgs.msg import TransformStamped
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from ros_harness import domain_id
from rosbags.typesys import get_typestore, Stores

#: The type hash Jazzy's own tf2_msgs advertises for TFMessage (its first 8 hex digits).
JAZZY_HASH_PREFIX = 'RIHS01_e369d0f0'
TYPE_NAME = 'tf2_msgs/msg/TFMessage'
RECEIVE_TIMEOUT_S = 10.0


@pytest.fixture(scope='module')
def tf_message_type():
    """
    Return the generated ``tf2_msgs.msg.TFMessage`` class.

    Skips when tf2_msgs does not import, or fails when ``STEREO_VO_STRICT_PACKAGING`` is set.
    """
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        reason = (f'tf2_msgs does not import ({exc}); '
                  'generate it with: bash scripts/build_tf2_msgs.sh')
        if os.environ.get('STEREO_VO_STRICT_PACKAGING'):
            pytest.fail(f'{reason} (STEREO_VO_STRICT_PACKAGING is set)')
        pytest.skip(reason)
    return TFMessage


def _transform(parent: str, child: str, sec: int, nanosec: int,
               xyz: tuple[float, float, float],
               xyzw: tuple[float, float, float, float]) -> TransformStamped:
    """Return a TransformStamped (translation in m, rotation as a unit quaternion x, y, z, w)."""
    t = TransformStamped()
    t.header.stamp.sec, t.header.stamp.nanosec = sec, nanosec
    t.header.frame_id, t.child_frame_id = parent, child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = xyz
    q = t.transform.rotation
    q.x, q.y, q.z, q.w = xyzw
    return t


def _sample(tf_message_type):
    """Return a TFMessage with two transforms of distinct frames, stamps and values."""
    return tf_message_type(transforms=[
        _transform('odom', 'base_link', 1_700_000_123, 456_789_012, (1.25, -2.5, 0.125),
                   (0.0, 0.0, 0.38268343236508984, 0.9238795325112867)),
        _transform('base_link', 'camera_left', 7, 999_999_999, (0.5, 0.25, 1.5),
                   (-0.5, 0.5, -0.5, 0.5)),
    ])


def _as_tuple(t: TransformStamped) -> tuple:
    """Return the frames, stamp (s, ns), translation (m) and rotation (x, y, z, w) of ``t``."""
    tr, q = t.transform.translation, t.transform.rotation
    return (t.header.frame_id, t.child_frame_id, t.header.stamp.sec, t.header.stamp.nanosec,
            tr.x, tr.y, tr.z, q.x, q.y, q.z, q.w)


def test_tf_message_has_the_jazzy_definition(tf_message_type) -> None:
    """The generated TFMessage holds one field, ``transforms``: TransformStamped[]."""
    assert tf_message_type.get_fields_and_field_types() == {
        'transforms': 'sequence<geometry_msgs/TransformStamped>'}
    assert tf_message_type().transforms == []


def test_tf_message_cdr_reads_both_ways_with_rosbags_jazzy(tf_message_type) -> None:
    """The CDR rclpy writes reads back in rosbags' Jazzy typestore, and the other way round."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    sent = _sample(tf_message_type)
    # Padding bytes are not compared: Fast CDR leaves them as it finds them.
    decoded = typestore.deserialize_cdr(serialize_message(sent), TYPE_NAME)
    assert [(t.header.frame_id, t.child_frame_id, t.header.stamp.sec,
             t.header.stamp.nanosec, t.transform.translation.x, t.transform.translation.y,
             t.transform.translation.z, t.transform.rotation.x, t.transform.rotation.y,
             t.transform.rotation.z, t.transform.rotation.w)
            for t in decoded.transforms] == [_as_tuple(t) for t in sent.transforms]
    raw = bytes(typestore.serialize_cdr(decoded, TYPE_NAME))
    back = deserialize_message(raw, tf_message_type)
    assert [_as_tuple(t) for t in back.transforms] == [_as_tuple(t) for t in sent.transforms]


def test_tf_published_on_tf_is_received_with_the_jazzy_type_hash(tf_message_type) -> None:
    """A TFMessage published on /tf reaches a subscriber unchanged; the hash is Jazzy's."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id(7))
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        talker = Node('tf2_msgs_talker', context=context)
        listener = Node('tf2_msgs_listener', context=context)
        nodes += [talker, listener]
        received = []
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        listener.create_subscription(tf_message_type, '/tf', received.append, qos)
        publisher = talker.create_publisher(tf_message_type, '/tf', qos)
        for node in nodes:
            executor.add_node(node)
        sent = _sample(tf_message_type)
        deadline = time.monotonic() + RECEIVE_TIMEOUT_S
        while not received and time.monotonic() < deadline:
            publisher.publish(sent)
            executor.spin_once(timeout_sec=0.05)
        infos = listener.get_publishers_info_by_topic('/tf')
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)

    assert received, f'no TFMessage received on /tf within {RECEIVE_TIMEOUT_S} s'
    assert [_as_tuple(t) for t in received[0].transforms] == \
        [_as_tuple(t) for t in sent.transforms]
    assert [info.topic_type for info in infos] == [TYPE_NAME]
    advertised = str(infos[0].topic_type_hash)
    assert advertised.startswith(JAZZY_HASH_PREFIX), advertised
    assert advertised == get_typestore(Stores.ROS2_JAZZY).hash_rihs01(TYPE_NAME)
