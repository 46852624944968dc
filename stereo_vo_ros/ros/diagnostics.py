"""
How the node reports its health: problem log, input monitors, diagnostic status.

* ``ProblemLog``: the node's warnings and errors as log lines throttled per problem (a new
  problem at once, a repeat every ``LOG_THROTTLE_S`` seconds with a count), plus the last
  warning and error and when they came, which hold the status at WARN or ERROR for a while.
* ``LibraryLogBridge``: forwards the warnings the core library logs (``logging``) in the
  node's worker thread to its ``ProblemLog``.
* ``PartnerMonitor`` and ``unmatched_message``: the images that arrived without their stereo
  partner over the last ``PARTNER_WINDOW_S`` seconds, and what to tell about them (stamps that
  miss the pairing rule, or images lost in transport, with the fixes).
* ``exposure_problem``: an over- or under-exposed image (it is still processed).
* ``NodeHealth``: the counts, input rate, pair arrival gaps and timings the node records, and
  the diagnostic_msgs/DiagnosticStatus built from them (published on ``/diagnostics``);
  ``rig_values`` adds the online rig refinement's.

Every time kept here is wall time (``time.monotonic``, seconds), not ROS time. In the status
values, durations are in milliseconds (``*_ms``), rates in hertz, offsets in pixels and angles
in degrees, as their names say; the rig values are those of ``RigEstimate``.
"""

from __future__ import annotations

import collections
import logging
import re
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np

from . import conversions as conv
from . import dds
from ..config import RosConfig
from ..records import OdometryResult, RigEstimate, TrackingStatus

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
#: Seconds (wall) over which images arriving without their partner are counted.
PARTNER_WINDOW_S = 10.0
#: Seconds between repetitions of a throttled log line (per problem, not per call site).
LOG_THROTTLE_S = 5.0
#: Problems remembered for throttling; older ones are forgotten beyond this many.
LOG_THROTTLE_KEYS = 256
#: Share of the pixels at the darkest or the brightest grey level above which an image is
#: reported as under- or over-exposed (a warning; it is still processed).
EXPOSURE_WARN_FRACTION = 0.5
_NUMBER = re.compile(r'[-+]?\d+(\.\d+)?(e[-+]?\d+)?')

_LEVEL = {TrackingStatus.OK: DiagnosticStatus.OK,
          TrackingStatus.INITIALIZING: DiagnosticStatus.OK,
          TrackingStatus.DEGENERATE: DiagnosticStatus.WARN,
          TrackingStatus.TOO_FEW_INLIERS: DiagnosticStatus.WARN,
          TrackingStatus.LOST: DiagnosticStatus.ERROR}


class ProblemLog:
    """
    A node's problems: log lines throttled per problem; the last warning and error, counted.

    Parameters
    ----------
    logger
        The node's logger (``Node.get_logger()``).

    """

    def __init__(self, logger: Any) -> None:
        self._logger = logger
        self._state: dict[str, list] = {}
        self._lock = threading.Lock()
        #: Text of the last warning and its wall time (``time.monotonic``, s).
        self.last_warning = ''
        self.last_warning_wall = -np.inf
        #: Text of the last error (may span lines: a trace) and its wall time.
        self.last_error = ''
        self.last_error_wall = -np.inf
        #: Warnings and errors reported so far (throttled or not).
        self.warnings = 0
        self.errors = 0

    def _should_log(self, text: str, key: str | None) -> str | None:
        """
        Throttle per problem: return the text to log (with a repeat count), or None.

        The problem is ``key``, by default the first line of ``text`` with its numbers
        blanked, so that a new problem is logged at once and a repeated one every
        ``LOG_THROTTLE_S`` seconds.
        """
        key = key if key is not None else _NUMBER.sub('#', text.split('\n', 1)[0])
        now = time.monotonic()
        with self._lock:
            state = self._state.get(key)
            if state is not None and now - state[0] < LOG_THROTTLE_S:
                state[1] += 1
                return None
            if len(self._state) >= LOG_THROTTLE_KEYS:
                self._state = {k: v for k, v in self._state.items()
                               if now - v[0] < LOG_THROTTLE_S}
            self._state[key] = [now, 0]
        if state is not None and state[1]:
            text += f' [{state[1]} more like this in the last {now - state[0]:.0f} s]'
        return text

    def log(self, severity: str, text: str, key: str | None = None) -> None:
        """Log a line (``error``, ``warning`` or else info), throttled per problem."""
        line = self._should_log(text, key)
        if line is None:
            return
        # One call site per severity: rclpy refuses a severity change at a call site.
        if severity == 'error':
            self._logger.error(line)
        elif severity == 'warning':
            self._logger.warning(line)
        else:
            self._logger.info(line)

    def warn(self, text: str, key: str | None = None) -> None:
        """Log a warning (throttled per problem) and hold the diagnostics at WARN."""
        self.last_warning = text
        self.last_warning_wall = time.monotonic()
        self.warnings += 1
        self.log('warning', text, key)

    def error(self, text: str, key: str | None = None) -> None:
        """Log an error, throttled per problem, and hold the diagnostics at ERROR."""
        self.last_error = text
        self.last_error_wall = time.monotonic()
        self.errors += 1
        self.log('error', text, key)


class LibraryLogBridge(logging.Handler):
    """Forward warnings the core library logs in one thread to a node (log line + status)."""

    def __init__(self, problems: ProblemLog, thread: threading.Thread) -> None:
        super().__init__(logging.WARNING)
        self._problems = problems
        self._thread = thread

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self._thread.ident:
            return
        try:
            text = record.getMessage()
        except Exception:  # a malformed record must not break the caller
            return
        if record.levelno >= logging.ERROR:
            self._problems.error(text)
        else:
            self._problems.warn(text)


class PartnerMonitor:
    """Images that arrived without their partner, and the pairs, over ``PARTNER_WINDOW_S``."""

    def __init__(self) -> None:
        self._events: collections.deque = collections.deque()  # (wall, side, n)
        self._pair_walls: collections.deque = collections.deque()  # pairs of the last window

    def note_pair(self, now: float) -> None:
        """Count a pair formed at wall time ``now`` (s)."""
        self._pair_walls.append(now)

    def note_unmatched(self, now: float, lost: dict[str, int]) -> None:
        """Count the images of each side (``lost``) dropped without a partner at ``now``."""
        for side, n in lost.items():
            if n:
                self._events.append((now, side, n))

    def loss(self) -> dict[str, Any]:
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
        while self._events and now - self._events[0][0] > PARTNER_WINDOW_S:
            self._events.popleft()
        while self._pair_walls and now - self._pair_walls[0] > PARTNER_WINDOW_S:
            self._pair_walls.popleft()
        counts = {'left': 0, 'right': 0}
        for _, side, n in self._events:
            counts[side] += n
        lost = counts['left'] + counts['right']
        received = lost + 2 * len(self._pair_walls)
        return {**counts, 'rate_hz': lost / PARTNER_WINDOW_S,
                'share': lost / received if received else 0.0, 'window_s': PARTNER_WINDOW_S}


def unmatched_message(loss: dict[str, Any], recent: dict[str, np.ndarray], cfg: RosConfig,
                      image_reliability: str) -> str:
    """
    Say what images are lost without a partner, why, and the fixes.

    Parameters
    ----------
    loss : dict
        ``PartnerMonitor.loss()``.
    recent : dict
        The recent stamps (ns, int64) of the ``left`` and ``right`` images.
    cfg : RosConfig
        The node's ``ros`` section (sync rule, QoS).
    image_reliability : str
        Reliability of the image subscriptions in force.

    Returns
    -------
    str
        One warning.

    """
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
               f'{image_reliability} (ros.qos: {cfg.qos}). Fixes: with a reliable '
               'image publisher, ros.qos auto or reliable (a resend instead of a loss); '
               'with Fast DDS, start the publishing process with '
               f'FASTRTPS_DEFAULT_PROFILES_FILE={dds.config_path(dds.PUBLISHER_PROFILE)} '
               '(its 512 kB shared-memory segment does not hold two large images), or '
               f'start this node with {dds.config_path(dds.NODE_PROFILE)}')
    return f'{what}: {why}'


def exposure_problem(grey: np.ndarray) -> tuple[str, int] | None:
    """
    Tell whether a grey image is over- or under-exposed (``EXPOSURE_WARN_FRACTION``).

    Returns
    -------
    tuple of str and int, or None
        What is wrong (the share of the pixels at the brightest or darkest level) and that
        grey level; None for a well exposed image.

    """
    top = np.iinfo(grey.dtype).max
    for value, what in ((top, f'over-exposed: {{:.0%}} of the pixels saturated at {top}'),
                        (0, 'under-exposed: {:.0%} of the pixels at 0')):
        share = np.count_nonzero(grey == value) / grey.size
        if share > EXPOSURE_WARN_FRACTION:
            return what.format(share), value
    return None


def processing_ms(res: OdometryResult) -> float:
    """
    Return a pair's processing time (ms): to its pose, and its work after the pose once run.

    (``timings_ms`` ``total`` and ``after_pose``, see ``StereoOdometry.settle``.)
    """
    t = res.timings_ms
    return float(t.get('total', np.nan)) + float(t.get('after_pose', 0.0))


def rig_values(rig: RigEstimate | None) -> dict[str, Any]:
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


class NodeHealth:
    """
    What a node's diagnostics report: counts, input timing, images without partner, problems.

    The node's callbacks record into it (``counts``, ``note_pair``, ``note_arrival_gap``,
    ``latency_ms``, ``decode_ms``); ``status`` builds the diagnostic status from it.

    Parameters
    ----------
    problems : ProblemLog
        The node's problems: the last warning and error hold the status at WARN or ERROR.

    """

    def __init__(self, problems: ProblemLog) -> None:
        self.problems = problems
        #: Events by name: pairs, processed, published, dropped, without_camera_info,
        #: ignored, non_finite, restarts, resets, calibrations.
        self.counts = collections.Counter()
        self.partner = PartnerMonitor()
        #: Wall time (s) of the last stereo pair; None before the first.
        self.last_pair_wall: float | None = None
        #: Arrival to publication of the last published pair, and decoding of its images (ms).
        self.latency_ms = float('nan')
        self.decode_ms = float('nan')
        self._arrivals: collections.deque = collections.deque(maxlen=30)
        self._pair_gaps_ms: collections.deque = collections.deque(maxlen=PAIR_GAP_WINDOW)
        self._gap_hinted = False

    def note_pair(self, now: float) -> None:
        """Count a stereo pair formed at wall time ``now`` (s)."""
        self._arrivals.append(now)
        self.partner.note_pair(now)
        self.last_pair_wall = now
        self.counts['pairs'] += 1

    def note_arrival_gap(self, gap_s: float) -> str:
        """
        Record how far apart (s) the two images of a pair arrived.

        Returns
        -------
        str
            Once, when the mean gap of ``PAIR_GAP_WINDOW`` pairs exceeds ``PAIR_GAP_HINT_MS``:
            the likely cause and its fix, to log; else ``''``.

        """
        self._pair_gaps_ms.append(gap_s * 1e3)
        if len(self._pair_gaps_ms) == PAIR_GAP_WINDOW and not self._gap_hinted:
            gap = float(np.mean(self._pair_gaps_ms))
            if gap > PAIR_GAP_HINT_MS:
                self._gap_hinted = True
                return (f'the two images of a pair arrive {gap:.1f} ms apart (mean of '
                        f'{PAIR_GAP_WINDOW} pairs), and each pair waits for the later one. If '
                        'the images come over Fast DDS, its default 512 kB shared-memory '
                        'segment is too small for two of them: start the image publisher with '
                        'FASTRTPS_DEFAULT_PROFILES_FILE=<share>/stereo_vo_ros/config/'
                        'fastdds_large_images.xml (docs/ros_interface.md)')
        return ''

    def _level(self, now: float, result: OdometryResult | None, waiting_for: str
               ) -> tuple[int, str]:
        """Level and message of the status: input, tracking, then held warnings and errors."""
        level, message = DiagnosticStatus.OK, 'tracking'
        last_pair_wall = self.last_pair_wall
        if last_pair_wall is None:
            level, message = DiagnosticStatus.WARN, 'no synchronized stereo pair received yet'
        elif now - last_pair_wall > STALE_INPUT_S:
            level, message = DiagnosticStatus.STALE, 'no stereo pair for ' \
                f'{now - last_pair_wall:.1f} s'
        if waiting_for:
            level, message = DiagnosticStatus.WARN, f'waiting for {waiting_for}'
        if result is not None and last_pair_wall is not None and \
                now - last_pair_wall <= STALE_INPUT_S:
            lvl = _LEVEL[result.status]
            if lvl != DiagnosticStatus.OK:
                level, message = lvl, f'tracking {result.status.value}: {result.message}'
            elif result.status is TrackingStatus.INITIALIZING:
                message = 'initializing'
        problems = self.problems
        if now - problems.last_warning_wall < WARN_HOLD_S:
            if level == DiagnosticStatus.OK:
                level, message = DiagnosticStatus.WARN, problems.last_warning
            elif problems.last_warning not in message:
                message = f'{message} (last warning: {problems.last_warning})'
        if now - problems.last_error_wall < ERROR_HOLD_S:
            level, message = DiagnosticStatus.ERROR, problems.last_error.splitlines()[0]
        return level, message

    def status(self, name: str, hardware_id: str, result: OdometryResult | None,
               waiting_for: str, *, image_transport: str, input_qos: str,
               unsynchronized_inputs: int, calibration: str, tf_broadcast: bool,
               path_length: int) -> DiagnosticStatus:
        """
        Build the diagnostic status of the odometry.

        Parameters
        ----------
        name, hardware_id : str
            Of the status.
        result : OdometryResult or None
            The last result of the pipeline.
        waiting_for : str
            What the node waits for (e.g. camera_info), ``''`` if nothing.
        image_transport, input_qos, unsynchronized_inputs, calibration, tf_broadcast
            The node's settings and state, reported as given.
        path_length
            Likewise.

        Returns
        -------
        diagnostic_msgs.msg.DiagnosticStatus
            Level and message with every value, in a fixed order.

        """
        now = time.monotonic()
        res = result
        level, message = self._level(now, res, waiting_for)
        rate = 0.0
        if len(self._arrivals) >= 2 and self._arrivals[-1] > self._arrivals[0]:
            rate = (len(self._arrivals) - 1) / (self._arrivals[-1] - self._arrivals[0])
        loss = self.partner.loss()
        counts, problems = self.counts, self.problems
        values = {
            'tracking_state': res.status.value if res is not None else 'none',
            'features': res.n_tracked if res is not None else 0,
            'inliers': res.n_inliers if res is not None else 0,
            'iterations': res.iterations if res is not None else 0,
            'road_fused': bool(res.road_fused) if res is not None else False,
            'vehicle_fused': bool(res.vehicle_fused) if res is not None else False,
            'processing_ms': processing_ms(res) if res is not None else float('nan'),
            'latency_ms': self.latency_ms,
            'input_rate_hz': rate,
            'pair_arrival_gap_ms': float(np.mean(self._pair_gaps_ms)) if self._pair_gaps_ms
            else float('nan'),
            'image_transport': image_transport,
            'image_decode_ms': self.decode_ms,
            'input_qos': input_qos,
            'images_without_partner_left': loss['left'],
            'images_without_partner_right': loss['right'],
            'images_without_partner_pct': 100.0 * loss['share'],
            'pairs_received': counts['pairs'],
            'pairs_processed': counts['processed'],
            'dropped_pairs': counts['dropped'],
            'unsynchronized_inputs': unsynchronized_inputs,
            'pairs_without_camera_info': counts['without_camera_info'],
            'frames_ignored': counts['ignored'],
            'non_finite_skipped': counts['non_finite'],
            'restarts': counts['restarts'],
            'resets': counts['resets'],
            'calibration': calibration,
            'calibration_changes': max(counts['calibrations'] - 1, 0),
            'tf_broadcast': tf_broadcast,
            **rig_values(res.rig if res is not None else None),
            'path_length': path_length,
            'warnings': problems.warnings,
            'last_warning': problems.last_warning,
            'errors': problems.errors,
            'last_error': problems.last_error.splitlines()[0] if problems.last_error else '',
        }
        return conv.diagnostic_status(level, name, message, values, hardware_id=hardware_id)
