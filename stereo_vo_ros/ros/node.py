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
  looked up once in /tf_static and /tf, else taken from the parameters (``frames.py``).
* Services: ``~/reset`` (std_srvs/Trigger) restarts the odometry at the identity.
* Parameters (``parameters.py``): every field of ``Config`` as ``section.name`` (read-only
  unless dynamic), initial values from the overrides (``--params-file``) else the defaults.

Processing never queues: the image callbacks only pair messages and keep the newest pair in a
one-slot mailbox; a worker thread owned by the node processes it and publishes the results, so
any executor keeps receiving images while a pair is processed. A pair overwritten before it
was processed is counted as dropped (newest wins). ``destroy_node`` stops the worker.

Bad input never stops the node (docs/robustness.md; ``diagnostics.py``): every problem gets a log
line (repeats of the same problem are throttled, a different problem is logged at once), holds the
diagnostics at WARN or ERROR for a few seconds and is counted there; nothing non-finite is
published; the next good pair produces odometry again. Warnings of the core library (``logging``)
raised while this node's worker processes a pair are forwarded to the node's logger and
diagnostics.
"""

from __future__ import annotations

import collections
import logging
import sys
import threading
import time
import traceback
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
import numpy as np
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import Trigger

from . import conversions as conv
from . import dds
from .diagnostics import (  # noqa: F401 (constants re-exported)
    ERROR_HOLD_S, exposure_problem, EXPOSURE_WARN_FRACTION, LibraryLogBridge, LOG_THROTTLE_KEYS,
    LOG_THROTTLE_S, NodeHealth, PAIR_GAP_HINT_MS, PAIR_GAP_WINDOW, PARTNER_WINDOW_S, ProblemLog,
    processing_ms, STALE_INPUT_S, unmatched_message, WARN_HOLD_S)
from .frames import (base_pose_from_msg, camera_pose_from_base, CameraMount, path_msg, tf_msg,
                     TFMessage)
from .parameters import (  # noqa: F401 (parameter_descriptor re-exported)
    check_params_files, config_updates, declare_config, parameter_descriptor)
from .sync import StereoPair, StereoSynchronizer
from .tf_tree import TransformListener
from .. import jit
from ..config import Config
from ..errors import CalibrationError, ConfigError, ImageError
from ..io.compressed import grey_from_compressed
from ..pipeline import RESTART_JUMP_S, StereoOdometry
from ..records import OdometryResult, StereoFrame, TrackingStatus

#: Queue length of the stereo synchroniser per side (messages).
SYNC_QUEUE_SIZE = 10
#: Seconds (wall) between two looks at the image publishers' QoS (``ros.qos: auto``).
QOS_CHECK_PERIOD_S = 1.0
#: History depth of the image subscriptions (messages per side). The callbacks only pair
#: images, but the worker thread's Python holds the GIL for stretches: on a loaded two-core
#: machine the executor took images off the DDS queue late, and with the sensor-data depth of
#: 5 it lost 1-10 of 40 pairs sent at 10 Hz, with either publisher QoS. 20 holds two seconds
#: at 10 Hz; it costs memory only while the executor is behind.
IMAGE_QUEUE_DEPTH = 20


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
        self._config, self._fields = declare_config(self)
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
        self._path: collections.deque = collections.deque(maxlen=cfg.path_max_length)
        self._problems = ProblemLog(self.get_logger())
        self._health = NodeHealth(self._problems)  # counts, timings, images without partner
        self._last_stamp_ns: int | None = None  # of the last pair the pipeline accepted
        self._waiting_for = ''
        self._last_result: OdometryResult | None = None
        self._warned: set[str] = set()
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
        self._log_bridge = LibraryLogBridge(self._problems, self._worker)
        logging.getLogger('stereo_vo_ros').addHandler(self._log_bridge)
        self._worker.start()
        self.get_logger().info(
            f'stereo VO ready: {self._image_topics[0]} + {self._image_topics[1]} '
            f'({cfg.image_transport}, {cfg.sync} sync, {cfg.qos} QoS, '
            f'{self._config.pipeline.input_kind} input, filter {self._config.filter.type}) -> '
            f'{self.resolve_topic_name("odom")}')
        compiled = jit.compile_note()
        if compiled:
            self.get_logger().info(compiled)

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
        qos = QoSProfile(depth=IMAGE_QUEUE_DEPTH, reliability=reliability)
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
            self._problems.warn('ros.qos is reliable but an image publisher offers best '
                                'effort: nothing is received from it; set ros.qos to auto or '
                                'sensor_data', key='qos-incompatible')

    # -- parameters --------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        updates, refusal = config_updates(self._fields, params)
        if refusal:
            return SetParametersResult(successful=False, reason=refusal)
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
        self._mount = CameraMount(self._tf_listener, self.get_logger())
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
        return self._mount.base_from_camera(camera_frame, self._config.ros)

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
            self._problems.warn(f'{side} image stamp {stamp_ns * 1e-9:.9f} s is '
                                f'{(previous - stamp_ns) * 1e-9:.3f} s before the previous '
                                'one: the input restarted (looping bag?); stereo pairing '
                                'starts afresh', key='sync-restart')
        elif after[1] > before[1]:
            self._problems.warn(f'{side} image dropped: stamp {stamp_ns * 1e-9:.9f} s is not '
                                'after the last stereo pair (duplicate or out-of-order stamp)',
                                key='sync-late')
        lost = {s: after[2][s] - before[2][s] for s in ('left', 'right')}
        if any(lost.values()):  # only the image callbacks append to _recent_ns
            self._on_unmatched(lost, {s: np.array(self._recent_ns[s], np.int64)
                                      for s in ('left', 'right')})
        for pair in pairs:
            hint = self._health.note_arrival_gap(pair.arrival_gap_s)
            if hint:
                self.get_logger().info(hint)
            self._on_pair(pair)

    def partner_loss(self) -> dict[str, Any]:
        """
        Images that arrived without their partner over the last ``PARTNER_WINDOW_S`` seconds.

        The dict of ``PartnerMonitor.loss``: ``left``/``right`` counts, ``rate_hz``, ``share``
        of the images received (0..1), ``window_s``.
        """
        return self._health.partner.loss()

    def _on_unmatched(self, lost: dict[str, int], recent: dict[str, np.ndarray]) -> None:
        """Images dropped without a partner: say what is lost, why, and the fixes (throttled)."""
        self._health.partner.note_unmatched(time.monotonic(), lost)
        self._problems.warn(unmatched_message(self.partner_loss(), recent, self._config.ros,
                                              self.image_reliability), key='sync-unmatched')

    def _on_pair(self, pair: StereoPair) -> None:
        self._health.note_pair(time.monotonic())
        with self._slot_lock:
            dropped = self._slot is not None
            if dropped:
                self._health.counts['dropped'] += 1
            self._slot = (pair, time.perf_counter())
            self._slot_lock.notify()
        if dropped:
            res = self._last_result
            busy = f'{processing_ms(res):.1f} ms' if res else 'unknown'
            self._problems.log('warning', 'stereo pair dropped: pairs arrive faster than they '
                               f'are processed (last processing time {busy}); the newest pair '
                               'is processed', key='dropped')

    # -- processing --------------------------------------------------------------------
    def _calibration(self, left: CameraInfo, right: CameraInfo):
        key = (conv.camera_info_key(left), conv.camera_info_key(right),
               self._config.pipeline.input_kind)
        if key != self._calib_key:
            self._calib = conv.calibration_from_camera_info(left, right,
                                                            self._config.pipeline.input_kind)
            self._calib_key = key
            self._health.counts['calibrations'] += 1
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
        problem = exposure_problem(grey)
        if problem is not None:
            what, value = problem
            self._problems.warn(f'{side} image {what}', key=f'exposure {side} {value}')
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
                self._problems.error(f'{type(exc).__name__} while processing a pair: {exc}; '
                                     'the odometry restarts at the identity with the next '
                                     f'pair\n{traceback.format_exc()}')

    def destroy_node(self) -> None:
        """Stop the worker thread and the pipeline's threads, then destroy the node."""
        with self._slot_lock:
            self._stopping = True
            self._slot_lock.notify()
        if self._worker.is_alive() and self._worker is not threading.current_thread():
            self._worker.join(timeout=10.0)
        if not self._worker.is_alive():
            self._pipeline.close()  # its worker threads (pipeline.threads)
        logging.getLogger('stereo_vo_ros').removeHandler(self._log_bridge)
        super().destroy_node()

    def _process(self, pair: StereoPair, t_arrival: float) -> None:
        left_info, right_info = self._info['left'], self._info['right']
        if left_info is None or right_info is None:
            missing = [self.resolve_topic_name(f'{s}/camera_info')
                       for s in ('left', 'right') if self._info[s] is None]
            self._waiting_for = 'camera_info on ' + ', '.join(missing)
            self._health.counts['without_camera_info'] += 1
            with self._slot_lock:
                if self._waiting_pair is not None:
                    self._health.counts['dropped'] += 1  # only the newest pair waits
                self._waiting_pair = (pair, t_arrival)
            self._release_waiting_pair()  # in case it arrived meanwhile
            self._problems.log('warning', f'waiting for {self._waiting_for}')
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
            self._health.decode_ms = (time.perf_counter() - t0) * 1e3
            with self._pipeline_lock:
                restart = self._last_stamp_ns is not None and \
                    pair.stamp_ns < self._last_stamp_ns - int(RESTART_JUMP_S * 1e9)
                result = self._pipeline.process(frame)
                if result.accepted:
                    self._last_stamp_ns = pair.stamp_ns
                    if restart:  # the pipeline restarted at the identity: so does the path
                        self._path.clear()
                        self._health.counts['restarts'] += 1
        except (ImageError, CalibrationError) as exc:
            self._problems.error(f'{type(exc).__name__}: {exc}')
            return
        if not result.accepted:
            self._health.counts['ignored'] += 1
            self._problems.warn(f'frame ignored: {result.message}')
            return
        self._publish(pair, result, frame.left)
        self._health.latency_ms = (time.perf_counter() - t_arrival) * 1e3
        with self._pipeline_lock:  # the pair's work its pose did not need, while idle
            self._pipeline.settle()

    def _publish(self, pair: StereoPair, result: OdometryResult, left: np.ndarray) -> None:
        cfg = self._config.ros
        camera_frame = cfg.camera_frame or pair.left.header.frame_id
        odom = conv.base_odometry_from_result(result, self._base_from_camera(camera_frame))
        self._last_result = result
        self._health.counts['processed'] += 1
        if not odom.is_finite():
            self._health.counts['non_finite'] += 1
            self._restart_odometry()
            self._problems.error(f'non-finite odometry at {pair.stamp_ns * 1e-9:.9f} s '
                                 f'({result.status.value}): not published; the odometry '
                                 'restarts at the identity with the next pair')
            return
        if result.status is not TrackingStatus.OK and \
                result.status is not TrackingStatus.INITIALIZING:
            self._problems.log('warning', f'tracking {result.status.value}: {result.message}')
        stamp = pair.left.header.stamp
        self._odom_pub.publish(conv.odometry_msg(odom, stamp, cfg.odom_frame, cfg.base_frame))
        self._health.counts['published'] += 1
        self._path.append(conv.pose_stamped_msg(odom.T_odom_base, stamp, cfg.odom_frame))
        if self._path_pub.get_subscription_count() > 0:
            self._path_pub.publish(path_msg(self._path, stamp, cfg.odom_frame))
        if self._tf_pub is not None:
            self._tf_pub.publish(tf_msg(odom.T_odom_base, stamp, cfg))
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
        self._health.counts['resets'] += 1

    def report_executor_failure(self, exc: Exception) -> None:
        """Log a failed turn of the executor (``spin``) with its trace; hold ERROR."""
        trace = ''.join(traceback.format_exception(exc)).rstrip()
        self._problems.error(f'the executor failed ({type(exc).__name__}: {_one_line(exc)}); '
                             f'a message it was taking may be lost\n{trace}',
                             key='executor failure')

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self._restart_odometry(drop_pending=True)
        self.get_logger().info('odometry reset: the next pair starts at the identity')
        response.success = True
        response.message = 'odometry reset; the next stereo pair starts at the identity pose'
        return response

    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        cfg = self._config.ros
        try:
            T_odom_base, cov = base_pose_from_msg(msg, cfg.odom_frame)
            T_world_cam, cov_world = camera_pose_from_base(
                T_odom_base, cov, self._base_from_camera(cfg.camera_frame))
        except ValueError as exc:
            self.get_logger().error(f'~/set_pose ignored: {exc}')
            return
        with self._pipeline_lock:
            self._pipeline.set_pose(T_world_cam, cov_world)
        self.get_logger().info(f'pose set to {T_odom_base[:3, 3].tolist()} m in '
                               f'{cfg.odom_frame}')

    # -- diagnostics -------------------------------------------------------------------
    def diagnostics(self) -> DiagnosticStatus:
        """Return the current diagnostic status of the odometry (also published at 1 Hz)."""
        cfg = self._config.ros
        return self._health.status(
            f'{self.get_name()}: stereo odometry', cfg.camera_frame or 'stereo_camera',
            self._last_result, self._waiting_for, image_transport=cfg.image_transport,
            input_qos=f'{self.image_reliability} (ros.qos {cfg.qos})',
            unsynchronized_inputs=self._sync.stats.unsynchronized,
            calibration=self._calib_summary(), tf_broadcast=self._tf_pub is not None,
            path_length=len(self._path))

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostics()]
        self._diag_pub.publish(msg)


def _one_line(exc: BaseException) -> str:
    """Return an exception as one line: rcl's multi-line errors folded, its trace dropped."""
    text = str(exc).split(', at ')[0]  # rcl appends ", at <file>:<line>"
    return ' '.join(text.split())


#: Failed turns of the executor within ``SPIN_FAILURE_WINDOW_S`` after which the node stops: a
#: lost message now and then is survivable, an executor that keeps failing is not.
MAX_SPIN_FAILURES = 50
SPIN_FAILURE_WINDOW_S = 10.0


def spin(executor: Any, report: Any) -> None:
    """
    Spin ``executor`` as ``Executor.spin`` does, surviving a ``RuntimeError`` out of a turn.

    Under load rclpy can fail to convert a message it takes from DDS ("Unable to convert call
    argument '0' to Python object", a ``RuntimeError`` raised by ``spin_once``): that message is
    lost, and ``executor.spin()`` would end the process with it. Here such a failure goes to
    ``report(exc)`` and spinning goes on; ``MAX_SPIN_FAILURES`` of them within
    ``SPIN_FAILURE_WINDOW_S`` raise the last one. Any other exception (a bug in a callback)
    ends the loop at once, as it ends ``spin()``; so do the context's and the executor's
    shutdown.
    """
    failures: collections.deque = collections.deque()
    # ``Executor.spin`` also stops once the executor is shut down (a private flag in Jazzy).
    while executor.context.ok() and not getattr(executor, '_is_shutdown', False):
        try:
            executor.spin_once()
        except RuntimeError as exc:
            now = time.monotonic()
            failures.append(now)
            while failures[0] < now - SPIN_FAILURE_WINDOW_S:
                failures.popleft()
            if len(failures) >= MAX_SPIN_FAILURES:
                raise
            report(exc)


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
        check_params_files(sys.argv if args is None else args)
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
        spin(executor, node.report_executor_failure)
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
