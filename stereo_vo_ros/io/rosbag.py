"""
rosbag2 stereo bags (sqlite3 or mcap) read and written with ``rosbags`` (no rclpy).

A stereo bag holds ``sensor_msgs/Image`` and ``sensor_msgs/CameraInfo`` for the left and the
right camera and optionally the ground truth as ``nav_msgs/Odometry`` (pose of the left camera
optical frame in ``world``, the first left camera frame). Left and right images pair up when
their header stamps are equal. Images may pad their rows: ``step`` is always honoured.
Recorded robot bags often hold ``sensor_msgs/CompressedImage`` instead (image_transport
``compressed``: topic ``<image topic>/compressed``, jpeg or png); the reader takes those when
asked to (``transport='compressed'``) or when the raw image topics are absent.
"""

from __future__ import annotations

from contextlib import contextmanager
import dataclasses
from dataclasses import dataclass
import logging
from pathlib import Path
import struct
from typing import Any, Iterable, Iterator

import cv2
import numpy as np
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.typesys import get_typestore, Stores
from scipy.spatial.transform import Rotation

from .compressed import compress_grey, grey_from_compressed
from ..errors import CalibrationError, DatasetError, ImageError
from ..estimation.camera import StereoCalibration
from ..records import StereoFrame

logger = logging.getLogger(__name__)

IMAGE_TYPE = 'sensor_msgs/msg/Image'
COMPRESSED_TYPE = 'sensor_msgs/msg/CompressedImage'
#: Suffix of image_transport's compressed topic.
COMPRESSED_SUFFIX = '/compressed'
INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
ODOM_TYPE = 'nav_msgs/msg/Odometry'

#: encoding -> (dtype, channels, cv2 conversion to grey or None)
ENCODINGS: dict[str, tuple[type, int, int | None]] = {
    'mono8': (np.uint8, 1, None),
    '8UC1': (np.uint8, 1, None),
    'mono16': (np.uint16, 1, None),
    '16UC1': (np.uint16, 1, None),
    'rgb8': (np.uint8, 3, cv2.COLOR_RGB2GRAY),
    'bgr8': (np.uint8, 3, cv2.COLOR_BGR2GRAY),
    'rgba8': (np.uint8, 4, cv2.COLOR_RGBA2GRAY),
    'bgra8': (np.uint8, 4, cv2.COLOR_BGRA2GRAY),
}
STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}


@dataclass(frozen=True)
class BagTopics:
    """Topic names of a stereo bag."""

    left_image: str = '/left/image_rect'
    right_image: str = '/right/image_rect'
    left_info: str = '/left/camera_info'
    right_info: str = '/right/camera_info'
    odometry: str = '/ground_truth/odom'
    #: ``raw`` (sensor_msgs/Image on the image topics) or ``compressed``
    #: (sensor_msgs/CompressedImage on ``<image topic>/compressed``).
    transport: str = 'raw'

    @classmethod
    def from_config(cls, ros: Any) -> 'BagTopics':
        """Take the image and camera_info topics and the transport from a ``RosConfig``."""
        return cls(left_image=ros.left_image_topic, right_image=ros.right_image_topic,
                   left_info=ros.left_info_topic, right_info=ros.right_info_topic,
                   transport=ros.image_transport)

    def compressed(self) -> 'BagTopics':
        """Return the same topics, read as compressed images."""
        return dataclasses.replace(self, transport='compressed')

    @property
    def images(self) -> tuple[str, str]:
        """Left and right image topics as stored for this transport."""
        suffix = COMPRESSED_SUFFIX if self.transport == 'compressed' else ''
        return self.left_image + suffix, self.right_image + suffix

    @property
    def image_type(self) -> str:
        """Message type of the image topics for this transport."""
        return COMPRESSED_TYPE if self.transport == 'compressed' else IMAGE_TYPE


# ---------------------------------------------------------------------------------------------
# Image conversions
# ---------------------------------------------------------------------------------------------
def grey_from_buffer(encoding: str, width: int, height: int, step: int, data: Any,
                     is_bigendian: bool = False) -> np.ndarray:
    """
    Convert the fields of a ``sensor_msgs/Image`` to a grey image.

    Returns
    -------
    np.ndarray
        (height, width) uint8 grey, or uint16 for mono16 / 16UC1.

    Raises
    ------
    ImageError
        Unsupported encoding, ``step`` shorter than a row, or too little data.

    """
    if encoding not in ENCODINGS:
        raise ImageError(f'unsupported image encoding {encoding!r}; supported: '
                         f'{sorted(ENCODINGS)}')
    dtype, channels, code = ENCODINGS[encoding]
    row_bytes = width * channels * np.dtype(dtype).itemsize
    if width <= 0 or height <= 0:
        raise ImageError(f'image size must be positive, got {width}x{height}')
    if step < row_bytes:
        raise ImageError(f'image step {step} is shorter than a {encoding} row of {width} '
                         f'pixels ({row_bytes} bytes)')
    buf = np.frombuffer(memoryview(data).cast('B'), np.uint8) if not isinstance(
        data, np.ndarray) else data.reshape(-1).view(np.uint8)
    if buf.size < step * height:
        raise ImageError(f'image data has {buf.size} bytes, {step} x {height} = '
                         f'{step * height} expected')
    rows = np.ascontiguousarray(buf[:step * height].reshape(height, step)[:, :row_bytes])
    order = '>' if is_bigendian else '<'
    img = rows.view(np.dtype(dtype).newbyteorder(order)).reshape(height, width, channels)
    img = img.astype(dtype, copy=False)
    if code is None:
        return np.ascontiguousarray(img[:, :, 0])
    return cv2.cvtColor(img, code)


def buffer_from_grey(img: np.ndarray, encoding: str, row_padding: int = 0
                     ) -> tuple[np.ndarray, int]:
    """
    Encode a grey image as ``sensor_msgs/Image`` data; return (data uint8 (step*H,), step).

    uint8 images written as mono16 are scaled by 257; colour encodings replicate the grey
    value (alpha 255). ``row_padding`` extra bytes end every row.
    """
    if encoding not in ENCODINGS:
        raise ImageError(f'unsupported image encoding {encoding!r}; supported: '
                         f'{sorted(ENCODINGS)}')
    dtype, channels, _ = ENCODINGS[encoding]
    img = np.asarray(img)
    if img.ndim != 2:
        raise ImageError(f'expected a grey (H, W) image, got shape {img.shape}')
    if dtype is np.uint16:
        px = img.astype(np.uint16) * 257 if img.dtype == np.uint8 else img.astype(np.uint16)
        px = px.astype('<u2')[:, :, None]
    else:
        if img.dtype != np.uint8:
            raise ImageError(f'{encoding} needs a uint8 image, got {img.dtype}')
        px = np.repeat(img[:, :, None], channels, axis=2)
        if channels == 4:
            px[:, :, 3] = 255
    h, w = img.shape
    raw = px.reshape(h, -1).view(np.uint8)
    step = raw.shape[1] + int(row_padding)
    out = np.zeros((h, step), np.uint8)
    out[:, :raw.shape[1]] = raw
    return out.reshape(-1), step


# ---------------------------------------------------------------------------------------------
# Writer
# ---------------------------------------------------------------------------------------------
def _stamp(typestore: Any, stamp_s: float) -> Any:
    ns = int(round(float(stamp_s) * 1e9))
    if ns < 0:
        raise DatasetError(f'stamps must not be negative, got {stamp_s!r} s')
    return typestore.types['builtin_interfaces/msg/Time'](sec=ns // 1_000_000_000,
                                                          nanosec=ns % 1_000_000_000)


def write_stereo_bag(path: str | Path, frames: Iterable[StereoFrame],
                     calibration: StereoCalibration | None = None,
                     poses: np.ndarray | Iterable[np.ndarray] | None = None, *,
                     storage: str = 'sqlite3', encoding: str = 'mono8',
                     topics: BagTopics = BagTopics(),
                     frame_ids: tuple[str, str] = ('camera_left_optical', 'camera_right_optical'),
                     world_frame: str = 'world', row_padding: int = 0,
                     jpeg_quality: int = 90) -> int:
    """
    Write stereo frames as a rosbag2 with images, camera infos and optional ground truth.

    Parameters
    ----------
    path : str or Path
        Bag folder to create (must not exist).
    frames : iterable of StereoFrame
        The pairs; header stamps are ``frame.stamp_s`` (s, not negative).
    calibration : StereoCalibration, optional
        Written as CameraInfo; default: each frame's own calibration.
    poses : array_like, optional
        (N, 4, 4) ``T_world_cam`` of the left camera (metres), written as nav_msgs/Odometry
        (frame ``world_frame``, child the left frame id) with the frame's stamp.
    storage : str
        ``sqlite3`` or ``mcap``.
    encoding : str
        One of ``ENCODINGS`` (grey replicated into colour encodings); with
        ``topics.transport == 'compressed'``, ``jpeg`` or ``png`` instead (grey images as
        sensor_msgs/CompressedImage on ``<image topic>/compressed``).
    topics : BagTopics
        Topic names and image transport.
    frame_ids : tuple of str
        Header frame ids of the left and the right camera.
    world_frame : str
        Header frame id of the ground truth.
    row_padding : int
        Extra bytes at the end of every image row (``step`` > width * bytes per pixel).
    jpeg_quality : int
        Quality of compressed jpeg images (1..100).

    Returns
    -------
    int
        Number of stereo pairs written.

    """
    if storage not in STORAGES:
        raise DatasetError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
    compressed = topics.transport == 'compressed'
    known = ('jpeg', 'png') if compressed else tuple(ENCODINGS)
    if encoding not in known:
        raise DatasetError(f'encoding must be one of {sorted(known)} for {topics.transport} '
                           f'images, got {encoding!r}')
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    Header, CameraInfo = T['std_msgs/msg/Header'], T[INFO_TYPE]
    image_type = topics.image_type
    left_topic, right_topic = topics.images
    pose_iter = iter(poses) if poses is not None else None
    count = 0
    try:
        with Writer(Path(path), version=Writer.VERSION_LATEST,
                    storage_plugin=STORAGES[storage]) as writer:
            conns = {name: writer.add_connection(topic, msgtype, typestore=ts) for name, topic,
                     msgtype in (('li', left_topic, image_type),
                                 ('ri', right_topic, image_type),
                                 ('lc', topics.left_info, INFO_TYPE),
                                 ('rc', topics.right_info, INFO_TYPE))}
            if pose_iter is not None:
                conns['gt'] = writer.add_connection(topics.odometry, ODOM_TYPE, typestore=ts)
            for count, frame in enumerate(frames, 1):
                stamp = _stamp(ts, frame.stamp_s)
                ns = stamp.sec * 1_000_000_000 + stamp.nanosec
                calib = calibration or frame.calibration
                for side, img, cam, fid in (('l', frame.left, calib.left, frame_ids[0]),
                                            ('r', frame.right, calib.right, frame_ids[1])):
                    header = Header(stamp=stamp, frame_id=fid)
                    if compressed:
                        fmt, data = compress_grey(img, encoding, jpeg_quality)
                        msg = T[COMPRESSED_TYPE](header=header, format=fmt, data=data)
                    else:
                        data, step = buffer_from_grey(img, encoding, row_padding)
                        msg = T[IMAGE_TYPE](header=header, height=img.shape[0],
                                            width=img.shape[1], encoding=encoding,
                                            is_bigendian=0, step=step, data=data)
                    info = CameraInfo(
                        header=header, height=cam.height, width=cam.width,
                        distortion_model=cam.distortion_model,
                        d=np.asarray(cam.D, np.float64), k=cam.K.astype(np.float64).ravel(),
                        r=cam.R.astype(np.float64).ravel(), p=cam.P.astype(np.float64).ravel(),
                        binning_x=0, binning_y=0,
                        roi=T['sensor_msgs/msg/RegionOfInterest'](
                            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
                    # camera_info first: a player that waits for the odometry of each pair
                    # after its second image must not hold back the calibration it needs.
                    writer.write(conns[side + 'c'], ns, ts.serialize_cdr(info, INFO_TYPE))
                    writer.write(conns[side + 'i'], ns, ts.serialize_cdr(msg, image_type))
                if pose_iter is not None:
                    try:
                        pose = np.asarray(next(pose_iter), np.float64)
                    except StopIteration:
                        raise DatasetError(f'fewer poses than frames ({count - 1})') from None
                    odom = _odometry(ts, Header(stamp=stamp, frame_id=world_frame),
                                     frame_ids[0], pose)
                    writer.write(conns['gt'], ns, ts.serialize_cdr(odom, ODOM_TYPE))
    except WriterError as exc:
        raise DatasetError(f'cannot write bag {str(path)!r}: {exc}') from None
    logger.info('wrote %d stereo pairs to %s (%s, %s %s)', count, path, storage,
                topics.transport, encoding)
    return count


def _odometry(ts: Any, header: Any, child: str, pose: np.ndarray) -> Any:
    T = ts.types
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    geometry = T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=float(pose[0, 3]), y=float(pose[1, 3]),
                                              z=float(pose[2, 3])),
        orientation=T['geometry_msgs/msg/Quaternion'](x=float(qx), y=float(qy), z=float(qz),
                                                      w=float(qw)))
    zero = T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)
    return T[ODOM_TYPE](
        header=header, child_frame_id=child,
        pose=T['geometry_msgs/msg/PoseWithCovariance'](pose=geometry, covariance=np.zeros(36)),
        twist=T['geometry_msgs/msg/TwistWithCovariance'](
            twist=T['geometry_msgs/msg/Twist'](linear=zero, angular=zero),
            covariance=np.zeros(36)))


# ---------------------------------------------------------------------------------------------
# Reader
# ---------------------------------------------------------------------------------------------
def _header_stamp_ns(raw: bytes | memoryview) -> int:
    """Header stamp (ns) of a CDR message whose first field is a std_msgs/Header."""
    little = raw[1] == 1
    sec, nanosec = struct.unpack_from('<iI' if little else '>iI', raw, 4)
    return sec * 1_000_000_000 + nanosec


class RosbagSequence:
    """
    A rosbag2 stereo bag (folder, .db3 or .mcap) as a sequence of StereoFrames.

    Parameters
    ----------
    path : str or Path
        Bag folder (with metadata.yaml) or a single .db3 / .mcap file.
    topics : BagTopics, optional
        Topic names; the odometry topic is optional in the bag.
    kind : str
        Calibration kind passed to ``StereoCalibration.from_camera_info``.

    Attributes
    ----------
    path : Path
        The bag.

    """

    format_name = 'rosbag'

    def __init__(self, path: str | Path, topics: BagTopics | None = None,
                 kind: str = 'rectified') -> None:
        self.path = Path(path)
        self.topics = topics or BagTopics()
        self.kind = kind
        if not self.path.exists():
            raise DatasetError(f'bag {str(self.path)!r} does not exist')
        self._ts = get_typestore(Stores.ROS2_JAZZY)
        self._infos: dict[str, list[tuple[int, Any]]] = {'left': [], 'right': []}
        self._calibs: dict[tuple[int, int], StereoCalibration] = {}
        left: list[int] = []
        right: list[int] = []
        odom: dict[int, np.ndarray] = {}
        with self._open() as reader:
            conns = self._connections(reader)
            tp = self.topics  # the transport may have changed to the one the bag holds
            left_topic, right_topic = tp.images
            for conn, _, raw in reader.messages(connections=[c for c in conns.values() if c]):
                if conn.topic == left_topic:
                    left.append(_header_stamp_ns(raw))
                elif conn.topic == right_topic:
                    right.append(_header_stamp_ns(raw))
                elif conn.topic in (tp.left_info, tp.right_info):
                    side = 'left' if conn.topic == tp.left_info else 'right'
                    msg = self._ts.deserialize_cdr(raw, INFO_TYPE)
                    ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                    infos = self._infos[side]
                    if not infos or not _same_info(infos[-1][1], msg):
                        infos.append((ns, msg))
                else:
                    msg = self._ts.deserialize_cdr(raw, ODOM_TYPE)
                    ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                    odom[ns] = _pose_from_odometry(msg)
        for side in ('left', 'right'):
            self._infos[side].sort(key=lambda item: item[0])
            if not self._infos[side]:
                raise DatasetError(f'bag {str(self.path)!r} has no message on '
                                   f'{getattr(tp, side + "_info")!r}')
        paired = sorted(set(left) & set(right))
        unpaired = len(left) + len(right) - 2 * len(paired)
        if unpaired:
            logger.warning('%s: %d images without a partner of equal stamp skipped', self.path,
                           unpaired)
        if not paired:
            raise DatasetError(f'bag {str(self.path)!r} has no left/right images with equal '
                               f'stamps ({len(left)} left, {len(right)} right)')
        self._pairs = np.array(paired, np.int64)
        self._gt = self._match_ground_truth(odom) if odom else None
        self._calibration = self._calibration_at(int(self._pairs[0]))

    # -- helpers --------------------------------------------------------------------------
    @contextmanager
    def _open(self) -> Iterator[Reader]:
        try:
            reader = Reader(self.path)
            reader.open()
        except (ReaderError, FileNotFoundError, OSError, ValueError, KeyError) as exc:
            raise DatasetError(f'cannot read bag {str(self.path)!r}: {exc}') from None
        try:
            yield reader
        finally:
            reader.close()

    def _connections(self, reader: Reader) -> dict[str, Any]:
        by_topic = {c.topic: c for c in reader.connections}
        found = {c.topic: c.msgtype for c in reader.connections}
        tp = self.topics
        if tp.transport == 'raw' and not set(tp.images) & set(found) and \
                all(found.get(t) == COMPRESSED_TYPE for t in tp.compressed().images):
            logger.info('%s: no raw images on %s; reading the compressed ones on %s',
                        self.path, list(tp.images), list(tp.compressed().images))
            self.topics = tp = tp.compressed()
        wanted = {tp.images[0]: tp.image_type, tp.images[1]: tp.image_type,
                  tp.left_info: INFO_TYPE, tp.right_info: INFO_TYPE}
        missing = [t for t in wanted if t not in by_topic]
        if missing:
            raise DatasetError(f'bag {str(self.path)!r} lacks topic(s) {missing}; it has '
                               f'{found}')
        wrong = {t: found[t] for t, msgtype in wanted.items() if found[t] != msgtype}
        if wrong:
            raise DatasetError(f'bag {str(self.path)!r}: unexpected message types {wrong} '
                               f'(need {tp.image_type} and {INFO_TYPE})')
        conns = {t: by_topic[t] for t in wanted}
        odom = by_topic.get(tp.odometry)
        if odom is not None and odom.msgtype == ODOM_TYPE:
            conns[tp.odometry] = odom
        return conns

    def _match_ground_truth(self, odom: dict[int, np.ndarray]) -> np.ndarray:
        stamps = np.array(sorted(odom), np.int64)
        poses = np.stack([odom[s] for s in stamps])
        j = np.clip(np.searchsorted(stamps, self._pairs), 1, len(stamps) - 1) if len(
            stamps) > 1 else np.zeros(len(self._pairs), np.int64)
        if len(stamps) > 1:
            j = np.where(np.abs(stamps[j - 1] - self._pairs) <= np.abs(stamps[j] - self._pairs),
                         j - 1, j)
        gap = np.abs(stamps[j] - self._pairs)
        out = poses[j].copy()
        far = gap > 5_000_000
        if far.any():
            logger.warning('%s: %d image pairs have no ground truth within 5 ms', self.path,
                           int(far.sum()))
            out[far] = np.nan
        return out

    def _calibration_at(self, ns: int) -> StereoCalibration:
        idx = []
        for side in ('left', 'right'):
            stamps = [s for s, _ in self._infos[side]]
            idx.append(max(0, int(np.searchsorted(stamps, ns, side='right')) - 1))
        key = (idx[0], idx[1])
        if key not in self._calibs:
            try:
                self._calibs[key] = StereoCalibration.from_camera_info(
                    self._infos['left'][idx[0]][1], self._infos['right'][idx[1]][1], self.kind)
            except CalibrationError as exc:
                raise DatasetError(f'bag {str(self.path)!r}: camera_info unusable: {exc}') \
                    from None
        return self._calibs[key]

    # -- sequence protocol ----------------------------------------------------------------
    @property
    def calibration(self) -> StereoCalibration:
        """Calibration from the first camera_info messages."""
        return self._calibration

    @property
    def stamps(self) -> np.ndarray:
        """Stamps of the stereo pairs in stamp order: (N,) float64, seconds."""
        return self._pairs / 1e9

    @property
    def ground_truth(self) -> np.ndarray | None:
        """(N, 4, 4) ``T_world_cam`` from the odometry topic (NaN where none), or None."""
        return None if self._gt is None else self._gt.copy()

    def __len__(self) -> int:
        return len(self._pairs)

    def __iter__(self) -> Iterator[StereoFrame]:
        """Yield the pairs in stamp order (the order of ``stamps`` and ``ground_truth``)."""
        tp = self.topics
        wanted = set(self._pairs.tolist())
        pending: dict[str, dict[int, Any]] = {'l': {}, 'r': {}}
        complete: set[int] = set()
        nxt = 0  # index into self._pairs of the next pair to yield
        with self._open() as reader:
            images = tp.images
            conns = [c for c in reader.connections if c.topic in images]
            for conn, _, raw in reader.messages(connections=conns):
                ns = _header_stamp_ns(raw)
                if ns not in wanted:
                    continue
                side, other = ('l', 'r') if conn.topic == images[0] else ('r', 'l')
                pending[side][ns] = raw
                if ns in pending[other]:
                    complete.add(ns)
                while nxt < len(self._pairs) and int(self._pairs[nxt]) in complete:
                    ns = int(self._pairs[nxt])
                    complete.discard(ns)
                    nxt += 1
                    left = self._decode(pending['l'].pop(ns), images[0])
                    right = self._decode(pending['r'].pop(ns), images[1])
                    yield StereoFrame(left, right, ns / 1e9, self._calibration_at(ns))

    def _decode(self, raw: bytes, topic: str) -> np.ndarray:
        msg = self._ts.deserialize_cdr(raw, self.topics.image_type)
        try:
            if self.topics.transport == 'compressed':
                return grey_from_compressed(msg.format, msg.data)
            return grey_from_buffer(msg.encoding, msg.width, msg.height, msg.step, msg.data,
                                    bool(msg.is_bigendian))
        except ImageError as exc:
            raise ImageError(f'{topic}: {exc}') from None


def _same_info(a: Any, b: Any) -> bool:
    return (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model) \
        and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ('d', 'k', 'r', 'p'))


def _pose_from_odometry(msg: Any) -> np.ndarray:
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = (p.x, p.y, p.z)
    return T
