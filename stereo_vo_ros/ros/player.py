"""
Replay a rosbag2 into rclpy publishers, publishing ``/clock`` for ``use_sim_time``.

The bag is read with the ``rosbags`` reader (sqlite3 or mcap, no ROS install needed); each
raw CDR message is turned into an rclpy message with
``rclpy.serialization.deserialize_message`` and published unchanged (header stamps as
recorded). ``/clock`` (``rosgraph_msgs/Clock``) carries the bag's log time: before every
message and, between messages, at ``clock_hz``. The rate factor scales the replay speed
(1.0 = recorded speed, 0.5 = half speed, ``None`` or 0 = as fast as possible).

Used by the node tests, the latency benchmark and ``stereo_vo demo``; it owns no node and no
executor: publishing needs no spinning, so ``play`` simply blocks the calling thread.

``StereoPairPublisher`` publishes in-memory stereo pairs (camera_info first, then the images) on
the node's input topics, raw or compressed, reliable or best effort; the node benchmarks and
the transport tests feed it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import importlib
from pathlib import Path
import threading
import time
from typing import Any, Callable, Iterable, Mapping

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from .conversions import camera_info_from_matrices, image_from_numpy, time_from_nanoseconds
from ..errors import DatasetError
from ..io.compressed import compress_grey


class StereoPairPublisher:
    """
    Publish stereo pairs on the node's input topics (relative names).

    Parameters
    ----------
    node : Node
        The node that owns the publishers.
    P0, P1 : np.ndarray
        (3, 4) rectified projection matrices of the left and right camera (pixels).
    size : tuple of int
        (width, height) of the images.
    depth : int
        History depth of the publishers.
    reliable : bool
        Reliable publishers (the ROS default, as most camera drivers), else best effort.
    compressed : bool
        Publish sensor_msgs/CompressedImage (jpeg) on ``<image topic>/compressed`` instead.
    jpeg_quality : int
        JPEG quality of compressed images.

    """

    INFO_TOPICS = ('left/camera_info', 'right/camera_info')
    IMAGE_TOPICS = ('left/image_rect', 'right/image_rect')

    def __init__(self, node: Node, P0: Any, P1: Any, size: tuple[int, int],
                 depth: int = 5, reliable: bool = True, compressed: bool = False,
                 jpeg_quality: int = 90) -> None:
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE if reliable
                         else ReliabilityPolicy.BEST_EFFORT)
        self._compressed = compressed
        self._quality = jpeg_quality
        self._infos = [node.create_publisher(CameraInfo, t, qos) for t in self.INFO_TOPICS]
        self._images = [
            node.create_publisher(CompressedImage, t + '/compressed', qos) if compressed
            else node.create_publisher(Image, t, qos) for t in self.IMAGE_TOPICS]
        w, h = size
        self._info_msgs = (camera_info_from_matrices(P0, w, h, frame_id='camera_left'),
                           camera_info_from_matrices(P1, w, h, frame_id='camera_right'))

    def connected(self) -> bool:
        """Return True once every input topic has a subscriber (the node is listening)."""
        return all(p.get_subscription_count() for p in self._infos + self._images)

    def publish(self, left: Any, right: Any, stamp_ns: int) -> float:
        """
        Publish the camera_info pair, then the mono8 images, all stamped ``stamp_ns``.

        Returns the ``time.perf_counter()`` reading taken just before the images go out.
        """
        stamp = time_from_nanoseconds(stamp_ns)
        if self._compressed:
            images = tuple(self._compress(img, stamp, frame_id) for img, frame_id in
                           ((left, 'camera_left'), (right, 'camera_right')))
        else:
            images = (image_from_numpy(left, 'mono8', stamp, 'camera_left'),
                      image_from_numpy(right, 'mono8', stamp, 'camera_right'))
        for pub, info in zip(self._infos, self._info_msgs):
            info.header.stamp = stamp
            pub.publish(info)
        t = time.perf_counter()
        for pub, image in zip(self._images, images):
            pub.publish(image)
        return t

    def _compress(self, img: Any, stamp: Any, frame_id: str) -> CompressedImage:
        msg = CompressedImage()
        msg.header.stamp, msg.header.frame_id = stamp, frame_id
        fmt, data = compress_grey(img, 'jpeg', self._quality)
        msg.format, msg.data = fmt, data.tobytes()
        return msg


def message_class(msgtype: str) -> type:
    """
    Return the rclpy message class of a type name such as ``sensor_msgs/msg/Image``.

    Raises
    ------
    DatasetError
        The name is malformed or its package is not importable.

    """
    parts = msgtype.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        raise DatasetError(f'message type {msgtype!r} is not of the form pkg/msg/Name')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2])
    except (ImportError, AttributeError):
        raise DatasetError(f'message type {msgtype!r} is not available to rclpy') from None


@dataclass
class PlaybackStats:
    """
    What one ``play`` call did.

    Attributes
    ----------
    messages : int
        Messages published (``/clock`` not counted).
    per_topic : dict
        Messages published per (remapped) topic.
    clock_messages : int
        ``/clock`` messages published.
    first_stamp_ns, last_stamp_ns : int
        Log times (ns) of the first and last message published (-1 if none).
    wall_s : float
        Wall-clock duration of the replay (s).
    stopped : bool
        True if ``stop`` ended the replay early.

    """

    messages: int = 0
    per_topic: dict = field(default_factory=dict)
    clock_messages: int = 0
    first_stamp_ns: int = -1
    last_stamp_ns: int = -1
    wall_s: float = 0.0
    stopped: bool = False


class BagPlayer:
    """
    Publish the messages of a rosbag2 with rclpy at a chosen rate.

    Parameters
    ----------
    node : rclpy.node.Node
        Node that owns the publishers (it should not use sim time itself).
    bag_path : str or Path
        rosbag2 directory (or a .db3 / .mcap file).
    topics : iterable of str, optional
        Topics to replay; default all topics whose message type rclpy can import (others are
        skipped with a warning).
    rate : float or None
        Replay speed factor (> 0); None or 0 replays as fast as possible.
    publish_clock : bool
        Publish ``/clock`` with the bag's log time.
    clock_hz : float
        ``/clock`` rate between messages (Hz, wall time).
    remap : mapping, optional
        Bag topic -> published topic.
    qos_depth : int
        History depth of the reliable publishers.

    Raises
    ------
    DatasetError
        The bag cannot be opened, or a requested topic is missing or has an unknown type.

    """

    def __init__(self, node: Node, bag_path: str | Path, topics: Iterable[str] | None = None,
                 rate: float | None = 1.0, publish_clock: bool = True, clock_hz: float = 40.0,
                 remap: Mapping[str, str] | None = None, qos_depth: int = 10) -> None:
        if rate is not None and rate < 0:
            raise ValueError(f'rate must be positive (or None / 0 for no pacing), got {rate!r}')
        self.node = node
        self.bag_path = Path(bag_path)
        self.rate = rate if rate else None
        self.publish_clock = publish_clock
        self.clock_period_s = 1.0 / clock_hz if clock_hz > 0 else float('inf')
        remap = dict(remap or {})
        try:
            reader = Reader(self.bag_path)
            reader.open()
        except Exception as exc:  # rosbags raises several types
            raise DatasetError(f'cannot open rosbag2 {str(self.bag_path)!r}: {exc}') from None
        try:
            available = {c.topic: c.msgtype for c in reader.connections}
            self.start_ns = int(reader.start_time)
            self.end_ns = int(reader.end_time)
        finally:
            reader.close()
        wanted = list(topics) if topics is not None else sorted(available)
        qos = QoSProfile(depth=qos_depth, reliability=ReliabilityPolicy.RELIABLE)
        self.topics: dict[str, str] = {}
        self._classes: dict[str, type] = {}
        self._publishers: dict[str, Any] = {}
        log = node.get_logger()
        for topic in wanted:
            if topic not in available:
                raise DatasetError(f'topic {topic!r} is not in {str(self.bag_path)!r}; it has '
                                   f'{sorted(available)}')
            try:
                cls = message_class(available[topic])
            except DatasetError as exc:
                if topics is not None:
                    raise
                log.warning(f'skipping {topic}: {exc}')
                continue
            out = remap.get(topic, topic)
            self.topics[topic] = out
            self._classes[topic] = cls
            self._publishers[topic] = node.create_publisher(cls, out, qos)
        self._clock_pub = node.create_publisher(Clock, '/clock', qos) if publish_clock else None

    def publisher(self, topic: str) -> Any:
        """Return the rclpy publisher of a bag topic."""
        return self._publishers[topic]

    def wait_for_subscribers(self, timeout_s: float = 10.0, topics: Iterable[str] | None = None,
                             min_count: int = 1,
                             alive: Callable[[], bool] | None = None) -> bool:
        """
        Block until every publisher (of ``topics``, default all) has ``min_count`` subscribers.

        ``alive``, when given, is asked between polls (e.g. whether the subscribing process
        still runs): once it returns False the wait ends at once.

        Returns
        -------
        bool
            True if they all have, False on timeout (s) or once ``alive`` returned False.

        """
        names = list(topics) if topics is not None else list(self._publishers)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(self._publishers[t].get_subscription_count() >= min_count for t in names):
                return True
            if alive is not None and not alive():
                return False
            time.sleep(0.02)
        return False

    def _clock(self, stamp_ns: int, stats: PlaybackStats) -> None:
        if self._clock_pub is not None:
            self._clock_pub.publish(Clock(clock=time_from_nanoseconds(stamp_ns)))
            stats.clock_messages += 1

    def play(self, stop: threading.Event | None = None,
             on_message: Callable[[str, int, Any], None] | None = None,
             start_ns: int | None = None, stop_ns: int | None = None) -> PlaybackStats:
        """
        Replay the bag once, blocking until done (or until ``stop`` is set).

        Parameters
        ----------
        stop : threading.Event, optional
            Set it from another thread to end the replay early.
        on_message : callable, optional
            Called as ``on_message(topic, log_time_ns, msg)`` right after each publish (topic
            as published, i.e. remapped).
        start_ns, stop_ns : int, optional
            Replay only the messages with log times in ``[start_ns, stop_ns)`` (ns).

        Returns
        -------
        PlaybackStats
            Counters of the replay.

        Raises
        ------
        DatasetError
            A message cannot be deserialised.

        """
        stats = PlaybackStats(per_topic=dict.fromkeys(self.topics.values(), 0))
        wall0 = time.monotonic()
        bag0: int | None = None
        with Reader(self.bag_path) as reader:
            conns = [c for c in reader.connections if c.topic in self.topics]
            messages = reader.messages(connections=conns, start=start_ns, stop=stop_ns)
            for conn, stamp_ns, raw in messages:
                if stop is not None and stop.is_set():
                    stats.stopped = True
                    break
                if bag0 is None:
                    bag0 = stamp_ns
                    stats.first_stamp_ns = stamp_ns
                if self.rate is not None:
                    self._wait_until(wall0, bag0, stamp_ns, stop, stats)
                try:
                    msg = deserialize_message(bytes(raw), self._classes[conn.topic])
                except Exception as exc:  # rclpy raises plain exceptions on bad CDR
                    raise DatasetError(f'cannot deserialise a {conn.msgtype} message on '
                                       f'{conn.topic} at {stamp_ns} ns: {exc}') from None
                self._clock(stamp_ns, stats)
                self._publishers[conn.topic].publish(msg)
                out = self.topics[conn.topic]
                stats.per_topic[out] += 1
                stats.messages += 1
                stats.last_stamp_ns = stamp_ns
                if on_message is not None:
                    on_message(out, stamp_ns, msg)
        stats.wall_s = time.monotonic() - wall0
        return stats

    def _wait_until(self, wall0: float, bag0: int, stamp_ns: int,
                    stop: threading.Event | None, stats: PlaybackStats) -> None:
        """Sleep until the wall time of ``stamp_ns``, publishing /clock meanwhile."""
        target = wall0 + (stamp_ns - bag0) * 1e-9 / self.rate
        while True:
            now = time.monotonic()
            if now >= target or (stop is not None and stop.is_set()):
                return
            time.sleep(min(target - now, self.clock_period_s))
            now = time.monotonic()
            if now < target:
                self._clock(bag0 + int((now - wall0) * self.rate * 1e9), stats)
