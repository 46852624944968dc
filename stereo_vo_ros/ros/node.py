"""
The ROS 2 node: stereo images in, REP-105 odometry out.

Interface (names relative to the node's namespace, all remappable):

* Subscribes ``left/image_rect``, ``right/image_rect`` (sensor_msgs/Image; with
  ``ros.image_transport: compressed`` sensor_msgs/CompressedImage on ``<topic>/compressed``)
  and ``left/camera_info``, ``right/camera_info`` (sensor_msgs/CameraInfo). ``ros.qos: auto``
  (default) subscribes to the images reliably when every publisher offers reliable, best
  effort otherwise, and re-checks every second as publishers come and go; ``sensor_data`` and
  ``reliable`` fix it. Images are paired by stamp (``ros.sync``: exact, or approximate within
  ``ros.sync_slop_s``); the latest camera_info of each side is used. ``~/set_pose``
  (geometry_msgs/PoseWithCovarianceStamped): pose of the base frame in the odom frame
  (header.frame_id empty or the odom frame) to continue from.
* Publishes ``odom`` (nav_msgs/Odometry, odom frame -> base frame, stamped with the left image
  stamp, twist in the base frame), ``path`` (nav_msgs/Path, at most ``ros.path_max_length``
  poses, sent only while subscribed), ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, 1 Hz
  wall time), ``~/debug_image`` (bgr8, drawn only while subscribed) and, when
  ``ros.publish_tf`` is true, the odom -> base transform on /tf (tf2_msgs/TFMessage, as
  tf2_ros's broadcaster sends it). The camera's mounting (base <- camera optical frame) is
  looked up once in /tf_static and /tf (``tf_tree.py``), else taken from the parameters.
* Services: ``~/reset`` (std_srvs/Trigger) restarts the odometry at the identity.
* Parameters: every field of ``Config`` as ``section.name`` (read-only unless marked dynamic),
  initial values from the parameter overrides (``--params-file``) else the defaults.

Processing never queues: the image callbacks only pair messages and keep the newest pair in a
one-slot mailbox; a worker thread owned by the node processes it and publishes the results, so
any executor keeps receiving images while a pair is processed. A pair overwritten before it
was processed is counted as dropped (newest wins). ``destroy_node`` stops the worker.

Bad input never stops the node (see docs/robustness.md): every problem gets a log line
(repeats of the same problem are throttled, a different problem is logged at once), holds the
diagnostics at WARN or ERROR for a few seconds and is counted there; nothing non-finite is
published; the next good pair produces odometry again. Warnings of the core library
(``logging``) raised while this node's worker processes a pair are forwarded to the node's
logger and diagnostics.
"""

from __future__ import annotations

import array
import collections
import dataclasses
import logging
import pathlib
import re
import sys
import threading
import time
import traceback
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
import numpy as np
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import Trigger
import yaml

from . import conversions as conv
from . import dds
from .sync import StereoPair, StereoSynchronizer
from .tf_tree import TransformListener
from ..config import Config, from_flat
from ..io.compressed import grey_from_compressed
from ..errors import CalibrationError, ConfigError, ImageError
from ..pipeline import RESTART_JUMP_S, StereoOdometry
from ..records import OdometryResult, RigEstimate, StereoFrame, TrackingStatus

try:  # a ROS install has it; a pip install gets it from scripts/build_tf2_msgs.sh
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the install
    TFMessage = None

#: Queue length of the stereo synchroniser per side (messages).
SYNC_QUEUE_SIZE = 10
#: Seconds (wall) during which the last error keeps the diagnostics at ERROR.
ERROR_HOLD_S = 5.0
#: Seconds (wall) during which the last warning keeps the diagnostics at least at WARN.
WARN_HOLD_S = 5.0
#: Mean gap (ms) between the arrivals of the two images of a pair above which the node points
#: at the image transport once. Fast DDS: two large images overflow its default shared-memory
#: segment, and the first of a pair arrives about 10 ms late, for about half of the pairs.
PAIR_GAP_HINT_MS = 5.0
#: Pairs over which that mean is taken.
PAIR_GAP_WINDOW = 30
#: Seconds (wall) without a pair after which the diagnostics report stale input.
STALE_INPUT_S = 3.0
#: Seconds (wall) between two looks at the image publishers' QoS (``ros.qos: auto``).
QOS_CHECK_PERIOD_S = 1.0
#: Seconds (wall) over which images arriving without their partner are counted.
PARTNER_WINDOW_S = 10.0
#: Seconds between repetitions of a throttled log line (per problem, not per call site).
LOG_THROTTLE_S = 5.0
#: Share of the pixels at the darkest or the brightest grey level above which an image is
#: reported as under- or over-exposed (a warning; it is still processed).
EXPOSURE_WARN_FRACTION = 0.5
#: Problems remembered for throttling; older ones are forgotten beyond this many.
LOG_THROTTLE_KEYS = 256
_NUMBER = re.compile(r'[-+]?\d+(\.\d+)?(e[-+]?\d+)?')

_LEVEL = {TrackingStatus.OK: DiagnosticStatus.OK,
          TrackingStatus.INITIALIZING: DiagnosticStatus.OK,
          TrackingStatus.DEGENERATE: DiagnosticStatus.WARN,
          TrackingStatus.TOO_FEW_INLIERS: DiagnosticStatus.WARN,
          TrackingStatus.LOST: DiagnosticStatus.ERROR}


def parameter_descriptor(name: str, field: dataclasses.Field) -> ParameterDescriptor:
    """
    Build the ROS parameter descriptor of one ``Config`` field.

    The description is the field's doc (plus its choices); integer and floating-point ranges
    come from ``lo``/``hi``; the parameter is read-only unless the field is ``dynamic``.
    Floating-point and list fields use dynamic typing so that a params file may write ``1``
    for ``1.0``; ``Config`` then checks and converts the value.
    """
    meta = field.metadata
    default = field.default if field.default is not dataclasses.MISSING else \
        field.default_factory()
    desc = ParameterDescriptor(name=name, description=str(meta.get('doc', '')),
                               read_only=not meta.get('dynamic', False))
    if meta.get('choices'):
        desc.additional_constraints = 'one of: ' + ', '.join(meta['choices'])
    lo, hi = meta.get('lo'), meta.get('hi')
    if isinstance(default, bool):
        pass
    elif isinstance(default, int):
        if lo is not None and hi is not None:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
    elif isinstance(default, float):
        desc.dynamic_typing = True
        if lo is not None and hi is not None:
            desc.floating_point_range = [
                FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    elif isinstance(default, list):
        desc.dynamic_typing = True
    return desc


def _reason(exc: ParameterException) -> str:
    """Return the useful part of an rclpy parameter exception, on one line."""
    text = ' '.join(str(exc).split())
    return text.replace('Invalid parameter value ', '').replace('Trying to set parameter ', '')


def _rig_values(rig: RigEstimate | None) -> dict[str, Any]:
    """Diagnostic values of the online rig refinement (``rig.*``; see ``RigEstimate``)."""
    if rig is None:
        return {'rig_refinement': 'off'}
    d = rig.as_dict()
    return {'rig_refinement': f'{"settled" if rig.settled else "converging"}, last pair '
                              f'{rig.last}',
            'rig_row_offset_px': d['row_offset_px'],
            'rig_row_offset_std_px': d['row_offset_std_px'],
            'rig_disparity_offset_px': d['disparity_offset_px'],
            'rig_disparity_offset_std_px': d['disparity_offset_std_px'],
            'rig_roll_pitch_yaw_deg': [round(d[k], 5)
                                       for k in ('roll_deg', 'pitch_deg', 'yaw_deg')],
            'rig_focal_ratio_pct': d['focal_ratio_pct'],
            'rig_updates': rig.updates, 'rig_rejected': rig.rejected}


def _plain(value: Any) -> Any:
    """Parameter value as Config expects it (arrays -> lists)."""
    if isinstance(value, (array.array, tuple, np.ndarray)):
        return list(value)
    return value


class _LibraryLogBridge(logging.Handler):
    """Forward warnings the core library logs in one thread to a node (log line + status)."""

    def __init__(self, node: 'StereoVONode', thread: threading.Thread) -> None:
        super().__init__(logging.WARNING)
        self._node = node
        self._thread = thread

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self._thread.ident:
            return
        try:
            text = record.getMessage()
        except Exception:  # a malformed record must not break the caller
            return
        if record.levelno >= logging.ERROR:
            self._node._error(text)
        else:
            self._node._warn(text)


class StereoVONode(Node):
    """
    Stereo visual odometry node (see the module docstring for topics, services, parameters).

    Parameters
    ----------
    **kwargs
        Forwarded to ``rclpy.node.Node`` (``node_name`` defaults to ``stereo_vo``; pass
        ``context``, ``parameter_overrides``, ``namespace``, ``cli_args`` to compose or test).

    Raises
    ------
    ConfigError
        A parameter override is not a valid configuration (unknown ``section.name``, wrong
        type or out of range).

    """

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault('node_name', 'stereo_vo')
        super().__init__(**kwargs)
        self._fields: dict[str, dataclasses.Field] = {}
        self._config = self._declare_config()
        cfg = self._config.ros
        self._pipeline = StereoOdometry(self._config)
        self._pipeline_lock = threading.Lock()
        self._slot_lock = threading.Condition()
        self._stopping = False
        self._slot: tuple[StereoPair, float] | None = None
        self._waiting_pair: tuple[StereoPair, float] | None = None
        self._info: dict[str, CameraInfo | None] = {'left': None, 'right': None}
        self._calib_key: tuple | None = None
        self._calib = None
        self._T_base_cam: np.ndarray | None = None
        self._path: collections.deque = collections.deque(maxlen=cfg.path_max_length)
        self._counts = collections.Counter()
        self._arrivals: collections.deque = collections.deque(maxlen=30)
        self._pair_gaps_ms: collections.deque = collections.deque(maxlen=PAIR_GAP_WINDOW)
        self._last_pair_wall: float | None = None
        self._last_error = ''
        self._last_error_wall = -np.inf
        self._last_warning = ''
        self._last_warning_wall = -np.inf
        self._log_state: dict[str, list] = {}
        self._log_lock = threading.Lock()
        self._last_stamp_ns: int | None = None  # of the last pair the pipeline accepted
        self._waiting_for = ''
        self._last_result: OdometryResult | None = None
        self._last_latency_ms = float('nan')
        self._decode_ms = float('nan')
        self._warned: set[str] = set()
        self._partner_events: collections.deque = collections.deque()  # (wall, side, n)
        self._pair_walls: collections.deque = collections.deque()  # pairs of the last window
        #: Recent stamps (ns) of each side: tell a stamp mismatch from a transport loss.
        self._recent_ns = {side: collections.deque(maxlen=20) for side in ('left', 'right')}
        self._image_subs: list = []
        self._image_reliability: ReliabilityPolicy | None = None
        self._image_type = CompressedImage if cfg.image_transport == 'compressed' else Image
        self._image_topics = tuple(
            self.resolve_topic_name(f'{side}/image_rect') +
            ('/compressed' if cfg.image_transport == 'compressed' else '')
            for side in ('left', 'right'))

        self._odom_pub = self.create_publisher(Odometry, 'odom', 10)
        self._path_pub = self.create_publisher(Path, 'path', 1)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._debug_pub = self.create_publisher(Image, '~/debug_image', 1) \
            if cfg.publish_debug_image else None
        self._setup_tf()

        # camera_info: small messages; best effort matches every publisher (reliable only
        # when asked for).
        info_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE) \
            if cfg.qos == 'reliable' else qos_profile_sensor_data
        self.create_subscription(CameraInfo, 'left/camera_info',
                                 lambda m: self._on_info('left', m), info_qos)
        self.create_subscription(CameraInfo, 'right/camera_info',
                                 lambda m: self._on_info('right', m), info_qos)
        # Pairing: the pure-Python synchroniser (message_filters' policies, tested here).
        self._sync = StereoSynchronizer(cfg.sync, cfg.sync_slop_s, SYNC_QUEUE_SIZE,
                                        restart_jump_s=RESTART_JUMP_S)
        self._sync_lock = threading.Lock()
        self._subscribe_images(self._wanted_reliability())
        self.create_timer(QOS_CHECK_PERIOD_S, self._check_publishers,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_subscription(PoseWithCovarianceStamped, '~/set_pose', self._on_set_pose, 10)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_timer(1.0, self._publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._worker = threading.Thread(target=self._work, name='stereo_vo_worker', daemon=True)
        self._log_bridge = _LibraryLogBridge(self, self._worker)
        logging.getLogger('stereo_vo_ros').addHandler(self._log_bridge)
        self._worker.start()
        self.get_logger().info(
            f'stereo VO ready: {self._image_topics[0]} + {self._image_topics[1]} '
            f'({cfg.image_transport}, {cfg.sync} sync, {cfg.qos} QoS, '
            f'{self._config.pipeline.input_kind} input, filter {self._config.filter.type}) -> '
            f'{self.resolve_topic_name("odom")}')

    # -- image subscriptions and their QoS ---------------------------------------------
    def _publisher_reliabilities(self) -> list[ReliabilityPolicy]:
        """Reliability offered by every publisher of the two image topics (graph query)."""
        return [info.qos_profile.reliability for topic in self._image_topics
                for info in self.get_publishers_info_by_topic(topic)]

    def _wanted_reliability(self) -> ReliabilityPolicy:
        """
        Reliability the image subscriptions should have now.

        ``auto``: reliable when there are publishers and every one offers reliable (a reliable
        reader gets a resend where a best-effort one loses an image), best effort otherwise
        (a reliable reader receives nothing from a best-effort writer).
        """
        qos = self._config.ros.qos
        if qos == 'reliable':
            return ReliabilityPolicy.RELIABLE
        if qos == 'sensor_data':
            return ReliabilityPolicy.BEST_EFFORT
        offered = self._publisher_reliabilities()
        if offered and all(r == ReliabilityPolicy.RELIABLE for r in offered):
            return ReliabilityPolicy.RELIABLE
        return ReliabilityPolicy.BEST_EFFORT

    def _subscribe_images(self, reliability: ReliabilityPolicy) -> None:
        """(Re)create the two image subscriptions with the given reliability."""
        for sub in self._image_subs:
            self.destroy_subscription(sub)
        qos = QoSProfile(depth=qos_profile_sensor_data.depth, reliability=reliability)
        self._image_subs = [
            self.create_subscription(self._image_type, topic,
                                     lambda m, side=side: self._on_image(side, m), qos)
            for side, topic in zip(('left', 'right'), self._image_topics)]
        self._image_reliability = reliability

    @property
    def image_reliability(self) -> str:
        """Reliability of the image subscriptions in force: ``reliable`` or ``best_effort``."""
        return 'reliable' if self._image_reliability == ReliabilityPolicy.RELIABLE else \
            'best_effort'

    def _check_publishers(self) -> None:
        """Timer: follow the publishers' QoS (auto); warn when a fixed QoS cannot match."""
        cfg = self._config.ros
        wanted = self._wanted_reliability()
        if wanted != self._image_reliability:
            self._subscribe_images(wanted)
            self.get_logger().info(
                f'image subscriptions now {self.image_reliability}: the publishers of '
                f'{list(self._image_topics)} offer '
                f'{sorted({str(r.name).lower() for r in self._publisher_reliabilities()})}')
        if cfg.qos == 'reliable' and ReliabilityPolicy.BEST_EFFORT in \
                self._publisher_reliabilities():
            self._warn('ros.qos is reliable but an image publisher offers best effort: '
                       'nothing is received from it; set ros.qos to auto or sensor_data',
                       key='qos-incompatible')

    # -- parameters --------------------------------------------------------------------
    def _declare_config(self) -> Config:
        """Declare every Config field as a parameter and build the Config from their values."""
        values = {}
        overrides = getattr(self, '_parameter_overrides', {})  # rclpy keeps them here
        fields = {name: field for name, _, field in Config().items()}
        # Check the overrides first, for messages that name the parameter, its range and type.
        from_flat({n: _plain(p.value) for n, p in overrides.items() if n in fields})
        for name, default, field in Config().items():
            self._fields[name] = field
            try:
                param = self.declare_parameter(name, default, parameter_descriptor(name, field))
            except ParameterException as exc:  # out of range or of the wrong type
                given = overrides[name].value if name in overrides else default
                raise ConfigError(f'parameter {name}: {given!r} rejected ({_reason(exc)}); '
                                  f'default {default!r}: {field.metadata.get("doc", "")}') \
                    from None
            values[name] = _plain(param.value)
        sections = {name.partition('.')[0] for name in self._fields}
        unknown = sorted(n for n in overrides if n.partition('.')[0] in sections and
                         n not in self._fields)
        if unknown:
            raise ConfigError(f'unknown parameter(s) {unknown}; see config/stereo_vo.yaml for '
                              f'the known ones')
        return from_flat(values)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        updates = {}
        for p in params:
            field = self._fields.get(p.name)
            if field is None:
                continue  # use_sim_time and the like
            if not field.metadata.get('dynamic', False):
                return SetParametersResult(
                    successful=False, reason=f'{p.name} cannot change at run time')
            updates[p.name] = _plain(p.value)
        if not updates:
            return SetParametersResult(successful=True)
        try:
            config = self._config.replace(**updates)
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        with self._pipeline_lock:
            self._pipeline.update_config(config)
            self._config = config
            if self._path.maxlen != config.ros.path_max_length:
                self._path = collections.deque(self._path, maxlen=config.ros.path_max_length)
        self.get_logger().info(f'parameters updated: {updates}')
        return SetParametersResult(successful=True)

    @property
    def config(self) -> Config:
        """Return the configuration in force."""
        return self._config

    # -- transforms --------------------------------------------------------------------
    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def _setup_tf(self) -> None:
        """Create the /tf publisher (tf2_ros's broadcaster sends the same) and TF listener."""
        cfg = self._config.ros
        self._tf_pub = None
        self._tf_listener = TransformListener(self, TFMessage) if TFMessage is not None \
            else None
        if not cfg.publish_tf:
            return
        if TFMessage is not None:
            self._tf_pub = self.create_publisher(TFMessage, '/tf', 100)
        else:  # pragma: no cover - scripts/_venv.sh builds tf2_msgs into the test venv
            self._warn_once('tf', 'ros.publish_tf is true but tf2_msgs is not importable: the '
                            'odom -> base transform is NOT broadcast on /tf (the odom topic '
                            'carries the same pose); source a ROS 2 install or run '
                            'scripts/build_tf2_msgs.sh for a pip install')

    def _base_from_camera(self, camera_frame: str) -> np.ndarray:
        """Pose (4, 4) of the left camera optical frame in the base frame (fixed per run)."""
        if self._T_base_cam is not None:
            return self._T_base_cam
        cfg = self._config.ros
        reason = 'tf2_msgs is not importable (no TF listener)'
        if self._tf_listener is not None and camera_frame:
            try:
                self._T_base_cam = self._tf_listener.tree.lookup(cfg.base_frame, camera_frame)
                self.get_logger().info(f'{cfg.base_frame} <- {camera_frame} from TF: '
                                       f'{np.round(self._T_base_cam[:3], 6).tolist()}')
                return self._T_base_cam
            except LookupError as exc:
                reason = f'TF lookup {cfg.base_frame} <- {camera_frame!r} failed: {exc}'
        elif not camera_frame:
            reason = 'the camera frame is unknown (empty frame_id and ros.camera_frame)'
        self._T_base_cam = conv.transform_from_xyz_rpy(cfg.base_from_camera_xyz,
                                                       cfg.base_from_camera_rpy_deg)
        self.get_logger().warning(
            f'{reason}: using the base <- camera transform from the parameters '
            f'ros.base_from_camera_xyz={list(cfg.base_from_camera_xyz)} m and '
            f'ros.base_from_camera_rpy_deg={list(cfg.base_from_camera_rpy_deg)} deg')
        return self._T_base_cam

    # -- inputs ------------------------------------------------------------------------
    def _on_info(self, side: str, msg: CameraInfo) -> None:
        self._info[side] = msg
        if self._waiting_pair is not None:
            self._release_waiting_pair()

    def _release_waiting_pair(self) -> None:
        """Hand a pair that came before the first camera_info to the worker, once both exist."""
        if None in self._info.values():
            return
        with self._slot_lock:
            if self._slot is None and self._waiting_pair is not None:
                self._slot = self._waiting_pair
                self._slot_lock.notify()
            self._waiting_pair = None

    def _on_image(self, side: str, msg: Image) -> None:
        stamp_ns = conv.nanoseconds_from_time(msg.header.stamp)
        with self._sync_lock:
            stats = self._sync.stats
            before = (stats.restarts, stats.late[side], dict(stats.unmatched))
            previous = self._sync.newest(side)
            self._recent_ns[side].append(stamp_ns)
            pairs = self._sync.add(side, stamp_ns, msg)
            stats = self._sync.stats
            after = (stats.restarts, stats.late[side], dict(stats.unmatched))
        if after[0] > before[0]:
            self._warn(f'{side} image stamp {stamp_ns * 1e-9:.9f} s is '
                       f'{(previous - stamp_ns) * 1e-9:.3f} s before the previous one: the '
                       'input restarted (looping bag?); stereo pairing starts afresh',
                       key='sync-restart')
        elif after[1] > before[1]:
            self._warn(f'{side} image dropped: stamp {stamp_ns * 1e-9:.9f} s is not after the '
                       'last stereo pair (duplicate or out-of-order stamp)', key='sync-late')
        lost = {s: after[2][s] - before[2][s] for s in ('left', 'right')}
        if any(lost.values()):  # only the image callbacks append to _recent_ns
            self._on_unmatched(lost, {s: np.array(self._recent_ns[s], np.int64)
                                      for s in ('left', 'right')})
        for pair in pairs:
            self._note_arrival_gap(pair)
            self._on_pair(pair)

    def _note_arrival_gap(self, pair: StereoPair) -> None:
        """Record how far apart the two images of a pair arrived; point at the cause once."""
        self._pair_gaps_ms.append(pair.arrival_gap_s * 1e3)
        if len(self._pair_gaps_ms) == PAIR_GAP_WINDOW and 'pair-gap' not in self._warned:
            gap = float(np.mean(self._pair_gaps_ms))
            if gap > PAIR_GAP_HINT_MS:
                self._warned.add('pair-gap')
                self.get_logger().info(
                    f'the two images of a pair arrive {gap:.1f} ms apart (mean of '
                    f'{PAIR_GAP_WINDOW} pairs), and each pair waits for the later one. If the '
                    'images come over Fast DDS, its default 512 kB shared-memory segment is too '
                    'small for two of them: start the image publisher with '
                    'FASTRTPS_DEFAULT_PROFILES_FILE=<share>/stereo_vo_ros/config/'
                    'fastdds_large_images.xml (docs/ros_interface.md)')

    def partner_loss(self) -> dict[str, Any]:
        """
        Images that arrived without their partner over the last ``PARTNER_WINDOW_S`` seconds.

        Returns
        -------
        dict
            ``left``/``right``: images of that side left without a partner (count),
            ``rate_hz``: such images per second, ``share``: their fraction of the images
            received (0..1), ``window_s``.

        """
        now = time.monotonic()
        while self._partner_events and now - self._partner_events[0][0] > PARTNER_WINDOW_S:
            self._partner_events.popleft()
        while self._pair_walls and now - self._pair_walls[0] > PARTNER_WINDOW_S:
            self._pair_walls.popleft()
        counts = {'left': 0, 'right': 0}
        for _, side, n in self._partner_events:
            counts[side] += n
        lost = counts['left'] + counts['right']
        received = lost + 2 * len(self._pair_walls)
        return {**counts, 'rate_hz': lost / PARTNER_WINDOW_S,
                'share': lost / received if received else 0.0, 'window_s': PARTNER_WINDOW_S}

    def _on_unmatched(self, lost: dict[str, int], recent: dict[str, np.ndarray]) -> None:
        """Images dropped without a partner: say what is lost, why, and the fixes (throttled)."""
        now = time.monotonic()
        for side, n in lost.items():
            if n:
                self._partner_events.append((now, side, n))
        loss = self.partner_loss()
        cfg = self._config.ros
        # The closest left and right stamps of the last images, and the frame period.
        left, right = recent['left'], recent['right']
        gap = float(np.abs(left[:, None] - right[None, :]).min()) * 1e-9 \
            if left.size and right.size else 0.0
        steps = np.concatenate([np.diff(np.sort(left)), np.diff(np.sort(right))])
        steps = steps[steps > 0]
        period = float(np.median(steps)) * 1e-9 if steps.size else np.inf
        rule = 'equal (exact sync)' if cfg.sync == 'exact' else \
            f'within {cfg.sync_slop_s} s (approximate sync)'
        what = (f'{loss["left"]} left and {loss["right"]} right images of the last '
                f'{loss["window_s"]:.0f} s arrived without their partner '
                f'({loss["share"]:.0%} of the images, {loss["rate_hz"]:.1f} per second)')
        # Left and right stamps that are never closer than the rule allows, yet closer than
        # half a frame period, belong to the same exposures: the stamps miss the pairing rule.
        # Where pairs do form, the images without partner lost it in transport.
        slop = 0.0 if cfg.sync == 'exact' else cfg.sync_slop_s
        if slop < gap < 0.5 * period:
            why = (f'the left and right stamps are not {rule} (the closest ones differ by '
                   f"{gap:.6f} s): check the cameras' stamps or ros.sync_slop_s")
        else:
            missing = 'left' if loss['right'] >= loss['left'] else 'right'
            why = (f'{missing} images are lost in transport. The image subscriptions are '
                   f'{self.image_reliability} (ros.qos: {cfg.qos}). Fixes: with a reliable '
                   'image publisher, ros.qos auto or reliable (a resend instead of a loss); '
                   'with Fast DDS, start the publishing process with '
                   f'FASTRTPS_DEFAULT_PROFILES_FILE={dds.config_path(dds.PUBLISHER_PROFILE)} '
                   '(its 512 kB shared-memory segment does not hold two large images), or '
                   f'start this node with {dds.config_path(dds.NODE_PROFILE)}')
        self._warn(f'{what}: {why}', key='sync-unmatched')

    def _on_pair(self, pair: StereoPair) -> None:
        now = time.monotonic()
        self._arrivals.append(now)
        self._pair_walls.append(now)
        self._last_pair_wall = now
        self._counts['pairs'] += 1
        with self._slot_lock:
            dropped = self._slot is not None
            if dropped:
                self._counts['dropped'] += 1
            self._slot = (pair, time.perf_counter())
            self._slot_lock.notify()
        if dropped:
            res = self._last_result
            busy = f'{res.timings_ms.get("total", float("nan")):.1f} ms' if res else 'unknown'
            self._log('warning', f'stereo pair dropped: pairs arrive faster than they are '
                      f'processed (last processing time {busy}); the newest pair is processed',
                      key='dropped')

    # -- logging -----------------------------------------------------------------------
    def _should_log(self, text: str, key: str | None) -> str | None:
        """
        Throttle per problem: return the text to log (with a repeat count), or None.

        The problem is ``key``, by default the first line of ``text`` with its numbers
        blanked, so that a new problem is logged at once and a repeated one every
        ``LOG_THROTTLE_S`` seconds.
        """
        key = key if key is not None else _NUMBER.sub('#', text.split('\n', 1)[0])
        now = time.monotonic()
        with self._log_lock:
            state = self._log_state.get(key)
            if state is not None and now - state[0] < LOG_THROTTLE_S:
                state[1] += 1
                return None
            if len(self._log_state) >= LOG_THROTTLE_KEYS:
                self._log_state = {k: v for k, v in self._log_state.items()
                                   if now - v[0] < LOG_THROTTLE_S}
            self._log_state[key] = [now, 0]
        if state is not None and state[1]:
            text += f' [{state[1]} more like this in the last {now - state[0]:.0f} s]'
        return text

    def _log(self, severity: str, text: str, key: str | None = None) -> None:
        line = self._should_log(text, key)
        if line is None:
            return
        # One call site per severity: rclpy refuses a severity change at a call site.
        if severity == 'error':
            self.get_logger().error(line)
        elif severity == 'warning':
            self.get_logger().warning(line)
        else:
            self.get_logger().info(line)

    def _warn(self, text: str, key: str | None = None) -> None:
        """Log a warning (throttled per problem) and hold the diagnostics at WARN."""
        self._last_warning = text
        self._last_warning_wall = time.monotonic()
        self._counts['warnings'] += 1
        self._log('warning', text, key)

    def _error(self, text: str, key: str | None = None) -> None:
        """Log an error (throttled per problem) and hold the diagnostics at ERROR."""
        self._last_error = text
        self._last_error_wall = time.monotonic()
        self._counts['errors'] += 1
        self._log('error', text, key)

    # -- processing --------------------------------------------------------------------
    def _calibration(self, left: CameraInfo, right: CameraInfo):
        key = (conv.camera_info_key(left), conv.camera_info_key(right),
               self._config.pipeline.input_kind)
        if key != self._calib_key:
            self._calib = conv.calibration_from_camera_info(left, right,
                                                            self._config.pipeline.input_kind)
            self._calib_key = key
            self._counts['calibrations'] += 1
            self.get_logger().info(f'stereo calibration: {self._calib_summary()}')
        return self._calib

    def _calib_summary(self) -> str:
        if self._calib is None:
            return 'none'
        return (f'{self._calib.size[0]}x{self._calib.size[1]} px, fx '
                f'{self._calib.K_left[0, 0]:.6g} px, baseline {self._calib.baseline_m:.6g} m')

    def _grey(self, side: str, msg: Image | CompressedImage) -> np.ndarray:
        """Convert one image, naming the side and topic in the error; warn if badly exposed."""
        try:
            if isinstance(msg, CompressedImage):
                grey = grey_from_compressed(msg.format, msg.data)
            else:
                grey = conv.grey_from_image(msg)
        except ImageError as exc:
            topic = self._image_topics[0 if side == 'left' else 1]
            raise ImageError(f'{side} image ({topic}): {exc}') from None
        top = np.iinfo(grey.dtype).max
        for value, what in ((top, f'over-exposed: {{:.0%}} of the pixels saturated at {top}'),
                            (0, 'under-exposed: {:.0%} of the pixels at 0')):
            share = np.count_nonzero(grey == value) / grey.size
            if share > EXPOSURE_WARN_FRACTION:
                self._warn(f'{side} image {what.format(share)}', key=f'exposure {side} {value}')
                break
        return grey

    def _work(self) -> None:
        """Worker thread: process the newest pair whenever there is one, until destroyed."""
        while True:
            with self._slot_lock:
                while self._slot is None and not self._stopping:
                    self._slot_lock.wait()
                if self._stopping:
                    return
                item, self._slot = self._slot, None
            try:
                self._process(*item)
            except Exception as exc:  # never let a bug stop the worker: log it, report it
                # The odometry state may be what fails: restart it rather than fail forever.
                self._restart_odometry()
                self._error(f'{type(exc).__name__} while processing a pair: {exc}; the '
                            'odometry restarts at the identity with the next pair\n'
                            f'{traceback.format_exc()}')

    def destroy_node(self) -> None:
        """Stop the worker thread, then destroy the node."""
        with self._slot_lock:
            self._stopping = True
            self._slot_lock.notify()
        if self._worker.is_alive() and self._worker is not threading.current_thread():
            self._worker.join(timeout=10.0)
        logging.getLogger('stereo_vo_ros').removeHandler(self._log_bridge)
        super().destroy_node()

    def _process(self, pair: StereoPair, t_arrival: float) -> None:
        left_info, right_info = self._info['left'], self._info['right']
        if left_info is None or right_info is None:
            missing = [self.resolve_topic_name(f'{s}/camera_info')
                       for s in ('left', 'right') if self._info[s] is None]
            self._waiting_for = 'camera_info on ' + ', '.join(missing)
            self._counts['without_camera_info'] += 1
            with self._slot_lock:
                if self._waiting_pair is not None:
                    self._counts['dropped'] += 1  # only the newest pair waits
                self._waiting_pair = (pair, t_arrival)
            self._release_waiting_pair()  # in case it arrived meanwhile
            self._log('warning', f'waiting for {self._waiting_for}')
            return
        self._waiting_for = ''
        try:
            try:
                calib = self._calibration(left_info, right_info)
            except CalibrationError as exc:
                raise CalibrationError(f'invalid camera_info: {exc}') from None
            t0 = time.perf_counter()
            frame = StereoFrame(self._grey('left', pair.left), self._grey('right', pair.right),
                                pair.stamp_ns * 1e-9, calib)
            self._decode_ms = (time.perf_counter() - t0) * 1e3
            with self._pipeline_lock:
                restart = self._last_stamp_ns is not None and \
                    pair.stamp_ns < self._last_stamp_ns - int(RESTART_JUMP_S * 1e9)
                result = self._pipeline.process(frame)
                if result.accepted:
                    self._last_stamp_ns = pair.stamp_ns
                    if restart:  # the pipeline restarted at the identity: so does the path
                        self._path.clear()
                        self._counts['restarts'] += 1
        except (ImageError, CalibrationError) as exc:
            self._error(f'{type(exc).__name__}: {exc}')
            return
        if not result.accepted:
            self._counts['ignored'] += 1
            self._warn(f'frame ignored: {result.message}')
            return
        self._publish(pair, result, frame.left)
        self._last_latency_ms = (time.perf_counter() - t_arrival) * 1e3

    def _publish(self, pair: StereoPair, result: OdometryResult, left: np.ndarray) -> None:
        cfg = self._config.ros
        camera_frame = cfg.camera_frame or pair.left.header.frame_id
        odom = conv.base_odometry_from_result(result, self._base_from_camera(camera_frame))
        self._last_result = result
        self._counts['processed'] += 1
        if not odom.is_finite():
            self._counts['non_finite'] += 1
            self._restart_odometry()
            self._error(f'non-finite odometry at {pair.stamp_ns * 1e-9:.9f} s '
                        f'({result.status.value}): not published; the odometry restarts at the '
                        'identity with the next pair')
            return
        if result.status is not TrackingStatus.OK and \
                result.status is not TrackingStatus.INITIALIZING:
            self._log('warning', f'tracking {result.status.value}: {result.message}')
        stamp = pair.left.header.stamp
        self._odom_pub.publish(conv.odometry_msg(odom, stamp, cfg.odom_frame, cfg.base_frame))
        self._counts['published'] += 1
        self._path.append(conv.pose_stamped_msg(odom.T_odom_base, stamp, cfg.odom_frame))
        if self._path_pub.get_subscription_count() > 0:
            path = Path()
            path.header.stamp = stamp
            path.header.frame_id = cfg.odom_frame
            path.poses = list(self._path)
            self._path_pub.publish(path)
        if self._tf_pub is not None:
            if cfg.invert_tf:
                tf = conv.transform_msg(np.linalg.inv(odom.T_odom_base), stamp, cfg.base_frame,
                                        cfg.odom_frame)
            else:
                tf = conv.transform_msg(odom.T_odom_base, stamp, cfg.odom_frame, cfg.base_frame)
            self._tf_pub.publish(TFMessage(transforms=[tf]))
        if self._debug_pub is not None and self._debug_pub.get_subscription_count() > 0:
            img = conv.debug_image(left, result.features, result.inliers)
            self._debug_pub.publish(conv.image_from_numpy(img, 'bgr8', stamp, camera_frame))

    # -- services ----------------------------------------------------------------------
    def _restart_odometry(self, drop_pending: bool = False) -> None:
        """Restart at the identity (pose, velocity, features, path); count it as a reset."""
        with self._pipeline_lock:
            self._pipeline.reset()
            self._path.clear()
            self._last_stamp_ns = None
            if drop_pending:  # also forget the images not yet paired or processed
                with self._sync_lock:
                    self._sync.reset()
                with self._slot_lock:
                    self._slot = None
        self._counts['resets'] += 1

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self._restart_odometry(drop_pending=True)
        self.get_logger().info('odometry reset: the next pair starts at the identity')
        response.success = True
        response.message = 'odometry reset; the next stereo pair starts at the identity pose'
        return response

    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        cfg = self._config.ros
        if msg.header.frame_id not in ('', cfg.odom_frame):
            self.get_logger().error(f'~/set_pose ignored: frame {msg.header.frame_id!r} is not '
                                    f'the odom frame {cfg.odom_frame!r}')
            return
        try:
            T_odom_base = conv.transform_from_pose(msg.pose.pose.position,
                                                   msg.pose.pose.orientation)
        except ValueError as exc:
            self.get_logger().error(f'~/set_pose ignored: {exc}')
            return
        cov = np.asarray(msg.pose.covariance, np.float64).reshape(6, 6)
        if not np.all(np.isfinite(cov)):
            self.get_logger().error('~/set_pose ignored: non-finite covariance')
            return
        T_base_cam = self._base_from_camera(cfg.camera_frame)
        try:
            with np.errstate(all='ignore'):
                T_world_cam, cov_world = conv.camera_pose_from_base_pose(T_odom_base, cov,
                                                                         T_base_cam)
        except ValueError:  # LinAlgError included
            T_world_cam = cov_world = np.full((4, 4), np.nan)
        if not (np.all(np.isfinite(T_world_cam)) and np.all(np.isfinite(cov_world))):
            self.get_logger().error('~/set_pose ignored: the pose or its covariance overflows '
                                    f'in the camera frame (position {T_odom_base[:3, 3]} m)')
            return
        with self._pipeline_lock:
            self._pipeline.set_pose(T_world_cam, cov_world)
        self.get_logger().info(f'pose set to {T_odom_base[:3, 3].tolist()} m in '
                               f'{cfg.odom_frame}')

    # -- diagnostics -------------------------------------------------------------------
    def diagnostics(self) -> DiagnosticStatus:
        """Return the current diagnostic status of the odometry (also published at 1 Hz)."""
        now = time.monotonic()
        res = self._last_result
        level, message = DiagnosticStatus.OK, 'tracking'
        if self._last_pair_wall is None:
            level, message = DiagnosticStatus.WARN, 'no synchronized stereo pair received yet'
        elif now - self._last_pair_wall > STALE_INPUT_S:
            level, message = DiagnosticStatus.STALE, 'no stereo pair for ' \
                f'{now - self._last_pair_wall:.1f} s'
        if self._waiting_for:
            level, message = DiagnosticStatus.WARN, f'waiting for {self._waiting_for}'
        if res is not None and self._last_pair_wall is not None and \
                now - self._last_pair_wall <= STALE_INPUT_S:
            lvl = _LEVEL[res.status]
            if lvl != DiagnosticStatus.OK:
                level, message = lvl, f'tracking {res.status.value}: {res.message}'
            elif res.status is TrackingStatus.INITIALIZING:
                message = 'initializing'
        if now - self._last_warning_wall < WARN_HOLD_S:
            if level == DiagnosticStatus.OK:
                level, message = DiagnosticStatus.WARN, self._last_warning
            elif self._last_warning not in message:
                message = f'{message} (last warning: {self._last_warning})'
        if now - self._last_error_wall < ERROR_HOLD_S:
            level, message = DiagnosticStatus.ERROR, self._last_error.splitlines()[0]
        rate = 0.0
        if len(self._arrivals) >= 2 and self._arrivals[-1] > self._arrivals[0]:
            rate = (len(self._arrivals) - 1) / (self._arrivals[-1] - self._arrivals[0])
        sync_stats = self._sync.stats
        loss = self.partner_loss()
        values = {
            'tracking_state': res.status.value if res is not None else 'none',
            'features': res.n_tracked if res is not None else 0,
            'inliers': res.n_inliers if res is not None else 0,
            'iterations': res.iterations if res is not None else 0,
            'road_fused': bool(res.road_fused) if res is not None else False,
            'vehicle_fused': bool(res.vehicle_fused) if res is not None else False,
            'processing_ms': float(res.timings_ms.get('total', np.nan)) if res is not None
            else float('nan'),
            'latency_ms': self._last_latency_ms,
            'input_rate_hz': rate,
            'pair_arrival_gap_ms': float(np.mean(self._pair_gaps_ms)) if self._pair_gaps_ms
            else float('nan'),
            'image_transport': self._config.ros.image_transport,
            'image_decode_ms': self._decode_ms,
            'input_qos': f'{self.image_reliability} (ros.qos {self._config.ros.qos})',
            'images_without_partner_left': loss['left'],
            'images_without_partner_right': loss['right'],
            'images_without_partner_pct': 100.0 * loss['share'],
            'pairs_received': self._counts['pairs'],
            'pairs_processed': self._counts['processed'],
            'dropped_pairs': self._counts['dropped'],
            'unsynchronized_inputs': sync_stats.unsynchronized,
            'pairs_without_camera_info': self._counts['without_camera_info'],
            'frames_ignored': self._counts['ignored'],
            'non_finite_skipped': self._counts['non_finite'],
            'restarts': self._counts['restarts'],
            'resets': self._counts['resets'],
            'calibration': self._calib_summary(),
            'calibration_changes': max(self._counts['calibrations'] - 1, 0),
            'tf_broadcast': self._tf_pub is not None,
            **_rig_values(res.rig if res is not None else None),
            'path_length': len(self._path),
            'warnings': self._counts['warnings'],
            'last_warning': self._last_warning,
            'errors': self._counts['errors'],
            'last_error': self._last_error.splitlines()[0] if self._last_error else '',
        }
        return conv.diagnostic_status(level, f'{self.get_name()}: stereo odometry', message,
                                      values, hardware_id=self._config.ros.camera_frame or
                                      'stereo_camera')

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostics()]
        self._diag_pub.publish(msg)


def _one_line(exc: BaseException) -> str:
    """Return an exception as one line: rcl's multi-line errors folded, its trace dropped."""
    text = str(exc).split(', at ')[0]  # rcl appends ", at <file>:<line>"
    return ' '.join(text.split())


def _check_params_files(argv: list[str]) -> None:
    """
    Read every ``--params-file`` of the command line before rcl does, for a one-line error.

    Only readability and YAML syntax are checked here: the file may hold other nodes'
    parameters too; the node checks its own values once rclpy has parsed them.

    Raises
    ------
    ConfigError
        A params file is missing, unreadable or not YAML.

    """
    for flag, path in zip(argv, argv[1:]):
        if flag != '--params-file':
            continue
        try:
            yaml.safe_load(pathlib.Path(path).read_text())
        except OSError as exc:
            raise ConfigError(f'cannot read the params file {path!r}: {exc.strerror}') \
                from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, 'problem_mark', None)
            where = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
            problem = getattr(exc, 'problem', None) or ' '.join(str(exc).split())
            raise ConfigError(f'the params file {path!r} is not valid YAML: {problem}{where}') \
                from None


def main(args: list[str] | None = None) -> int:
    """
    Run the node (``ros2 run stereo_vo_ros stereo_vo_node``) until shut down.

    Before ROS starts, the process chooses its Fast DDS profile (``dds.apply_node_profile``).
    A start-up mistake (a missing or unparsable params file, a parameter out of range or of
    the wrong type) is one line on stderr and exit code 2, never a traceback.

    Returns
    -------
    int
        0 on a normal shutdown, 2 if the node cannot start.

    """
    profile_note = dds.apply_node_profile()
    try:
        _check_params_files(sys.argv if args is None else args)
    except ConfigError as exc:
        print(f'stereo_vo_node: {exc}', file=sys.stderr)
        return 2
    try:
        rclpy.init(args=args)
    except Exception as exc:  # rclpy raises RCLError for bad --ros-args and params files
        print(f'stereo_vo_node: cannot start ROS: {_one_line(exc)}', file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = StereoVONode()
        node.get_logger().info(profile_note)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ConfigError as exc:
        print(f'stereo_vo_node: invalid configuration: {exc}', file=sys.stderr)
        code = 2
    except (NameValidationException, ParameterException) as exc:  # e.g. a bad remapping
        print(f'stereo_vo_node: cannot start: {_one_line(exc)}', file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
