"""
Robustness matrix of the ROS 2 node: bad input, faults and long runs, with nothing lost.

Every case runs against the real ``StereoVONode`` composed in-process (real rclpy, real
publishers on real topics, DDS on loopback, a namespace per case) and checks that

* the problem is named in a log line (read back from /rosout) and in the node's diagnostics
  status (level WARN or ERROR, message or values);
* every odometry message ever received is finite with symmetric positive semi-definite
  covariances, and the executor never stopped (no escaping exception);
* good pairs afterwards produce odometry again (recovery).

docs/robustness.md lists the cases with the behaviour they check.
"""

from __future__ import annotations

import itertools
import os
import time
import tracemalloc

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from ros_harness import composed_node, domain_id, Harness, stamp_ns, values
from sensor_msgs.msg import CameraInfo, Image
from stereo_vo_ros.ros import conversions as conv
from stereo_vo_ros.synthetic import render_sequence, SequenceSpec

N_FRAMES = 40
TOPICS = ('left/image_rect', 'right/image_rect', 'left/camera_info', 'right/camera_info')
WARN, ERROR = Log.WARN, Log.ERROR
_CASES = itertools.count()


# -- fixtures -----------------------------------------------------------------------------
@pytest.fixture(scope='module')
def sequence():
    """Render the demo city preset (620x188 px, 10 Hz, tracks OK throughout) once."""
    spec = SequenceSpec.preset('demo', n_frames=N_FRAMES, start_time_s=100.0)
    return spec, list(render_sequence(spec))


@pytest.fixture(scope='module')
def harness():
    """One context on this module's own ROS domain for every case."""
    h = Harness(odom_topic=None, domain=domain_id(1), diagnostics=False)
    yield h
    h.close()


class Rig:
    """
    One node under test in its own namespace, publishers for its inputs, a watch on its odometry.

    Parameters
    ----------
    h : Harness
        The module's harness (context, executor, /rosout collector).
    sequence : tuple
        (SequenceSpec, rendered frames).
    **params
        Parameter overrides of the node (dotted names).

    """

    def __init__(self, h: Harness, sequence, **params) -> None:
        self.h = h
        self.spec, self.frames = sequence
        self.name = f'case{next(_CASES)}'
        self.node = composed_node(h, namespace='/' + self.name, **params)
        self.logger = f'{self.name}.stereo_vo'
        self.pubs = {t: h.node.create_publisher(Image if 'image' in t else CameraInfo,
                                                f'/{self.name}/{t}', 10) for t in TOPICS}
        self.odom = h.watch_odometry(f'/{self.name}/odom')
        assert h.wait_for(lambda: all(p.get_subscription_count() >= 1
                                      for p in self.pubs.values()) and
                          self.odom.subscription.get_publisher_count() >= 1, 15.0)
        self.P0, self.P1 = self.spec.projections()
        self.height, self.width = self.frames[0].left.shape

    # -- inputs ----------------------------------------------------------------------
    def stamp(self, i: int) -> int:
        """Stamp (ns) of frame ``i`` of the sequence."""
        return int(round(self.frames[i].stamp_s * 1e9))

    def camera_info(self, P0=None, P1=None, width=None, height=None, sides='lr') -> None:
        """
        Publish the calibration (default: the sequence's) on the sides named in ``sides``.

        Returns once the node holds them, so that the images published next are paired
        with them (camera_info and images travel on different topics).
        """
        w, h = width or self.width, height or self.height
        sent = {}
        for side, P in (('left', self.P0 if P0 is None else P0),
                        ('right', self.P1 if P1 is None else P1)):
            if side[0] in sides:
                sent[side] = conv.camera_info_from_matrices(P, w, h)
                self.pubs[f'{side}/camera_info'].publish(sent[side])
        # The node keeps the latest message per side (StereoVONode._info).
        assert self.h.wait_for(lambda: all(
            self.node._info[side] is not None and
            np.array_equal(self.node._info[side].p, msg.p, equal_nan=True)
            for side, msg in sent.items()), 10.0), 'camera_info not received'

    def image(self, pixels: np.ndarray, ns: int, frame_id: str = 'camera_left') -> Image:
        """Return a mono8 (or mono16) Image message of an array."""
        encoding = 'mono16' if pixels.dtype == np.uint16 else 'mono8'
        return conv.image_from_numpy(pixels, encoding, conv.time_from_nanoseconds(ns),
                                     frame_id)

    def send(self, left, right, ns: int, right_ns: int | None = None) -> None:
        """Publish a stereo pair (arrays or Image messages) stamped ``ns`` (right: right_ns)."""
        right_ns = ns if right_ns is None else right_ns
        for topic, img, t in (('left/image_rect', left, ns), ('right/image_rect', right,
                                                              right_ns)):
            msg = img if isinstance(img, Image) else self.image(img, t)
            self.pubs[topic].publish(msg)

    def send_frame(self, i: int, ns: int | None = None) -> None:
        """Publish frame ``i`` of the sequence (stamped with its own stamp by default)."""
        f = self.frames[i]
        self.send(f.left, f.right, self.stamp(i) if ns is None else ns)

    def good_run(self, indices, offset_ns: int = 0, timeout_s: float = 10.0) -> None:
        """Publish frames one at a time; each must give one odometry message."""
        for i in indices:
            before = self.odom.count
            self.send_frame(i, self.stamp(i) + offset_ns)
            assert self.odom.wait_count(before + 1, timeout_s), \
                f'no odometry for frame {i}: {self.status()}'

    # -- outputs ---------------------------------------------------------------------
    def diag(self) -> DiagnosticStatus:
        """Return the node's current diagnostic status."""
        return self.node.diagnostics()

    def value(self, key: str) -> str:
        """Return one diagnostics value."""
        return values(self.diag())[key]

    def count(self, key: str) -> int:
        """Return one integer diagnostics value."""
        return int(self.value(key))

    def status(self) -> str:
        """Describe the diagnostics (for assertion messages)."""
        d = self.diag()
        return f'level {d.level!r}: {d.message!r} {values(d)}'

    def wait_count(self, key: str, at_least: int, timeout_s: float = 10.0) -> None:
        """Wait until an integer diagnostics value reaches ``at_least``."""
        assert self.h.wait_for(lambda: self.count(key) >= at_least, timeout_s), self.status()

    def logged(self, text: str, min_level: int = WARN) -> bool:
        """Return True once a log line of the node at ``min_level`` or above contains text."""
        return any(text in line for line in self.h.log_lines(self.logger, min_level))

    def assert_logged(self, text: str, min_level: int = WARN, timeout_s: float = 5.0) -> None:
        """Wait for a log line of the node (from /rosout) containing ``text``."""
        assert self.h.wait_for(lambda: self.logged(text, min_level), timeout_s), \
            f'no log line with {text!r}; got {self.h.log_lines(self.logger)}'

    def assert_diagnosed(self, text: str, level: bytes = DiagnosticStatus.WARN) -> None:
        """Check the diagnostics level (at least ``level``) and that its text names ``text``."""
        d = self.diag()
        assert d.level >= level, self.status()
        named = d.message + ' ' + values(d)['last_error'] + ' ' + values(d)['last_warning']
        assert text in named, self.status()

    def recover(self, first: int, n: int = 6, offset_ns: int = 0) -> None:
        """Good frames ``first``.. must each give odometry, and tracking must be OK again."""
        self.good_run(range(first, first + n), offset_ns)
        assert self.value('tracking_state') == 'ok', self.status()

    def assert_healthy(self) -> None:
        """No bad odometry was ever received and the executor still spins."""
        assert self.odom.problems == [], self.odom.problems[:5]
        assert self.h.spinning

    def close(self) -> None:
        """Destroy the node and the test's publishers and subscription."""
        self.h.remove(self.node)
        self.h.destroy(*self.pubs.values(), self.odom.subscription)


@pytest.fixture
def make_rig(harness, sequence):
    """Return a factory of Rigs; every rig is closed after the test."""
    rigs = []

    def make(**params) -> Rig:
        rigs.append(Rig(harness, sequence, **params))
        return rigs[-1]
    yield make
    for rig in rigs:
        rig.close()


def _position(msg) -> np.ndarray:
    p = msg.pose.pose.position
    return np.array([p.x, p.y, p.z])


# -- images: rejected (ImageError) ---------------------------------------------------------
def _encoding(rig, i):
    msg = rig.image(rig.frames[i].left, rig.stamp(i))
    msg.encoding = 'yuv422'
    return msg, rig.frames[i].right


def _step_short(rig, i):
    msg = rig.image(rig.frames[i].left, rig.stamp(i))
    msg.step = msg.width - 1
    return msg, rig.frames[i].right


def _data_short(rig, i):
    msg = rig.image(rig.frames[i].left, rig.stamp(i))
    msg.data = bytes(msg.data)[:-rig.width]
    return msg, rig.frames[i].right


def _data_long(rig, i):
    msg = rig.image(rig.frames[i].left, rig.stamp(i))
    msg.data = bytes(msg.data) + bytes(7)
    return msg, rig.frames[i].right


def _height_too_large(rig, i):
    msg = rig.image(rig.frames[i].left, rig.stamp(i))
    msg.height = 2 * msg.height
    return msg, rig.frames[i].right


def _size_swapped(rig, i):
    msg = rig.image(rig.frames[i].left, rig.stamp(i))
    msg.width, msg.height, msg.step = msg.height, msg.width, msg.height
    return msg, msg


def _sides_differ(rig, i):
    return rig.frames[i].left, rig.frames[i].right[:, :-20]


def _zero_size(rig, i):
    msg = Image(encoding='mono8', width=0, height=0, step=0)
    msg.header.stamp = conv.time_from_nanoseconds(rig.stamp(i))
    return msg, rig.frames[i].right


def _size_vs_camera_info(rig, i):
    f = rig.frames[i]
    return f.left[::2, ::2].copy(), f.right[::2, ::2].copy()


@pytest.mark.parametrize('build, problem', [
    (_encoding, "unsupported image encoding 'yuv422'"),
    (_step_short, 'image step 619 is shorter than a row'),
    (_data_short, 'image data has 115940 bytes, expected step*height'),
    (_data_long, 'image data has 116567 bytes, expected step*height'),
    (_height_too_large, 'expected step*height = 620*376'),
    (_size_swapped, 'image size 188x620 does not match the calibration 620x188'),
    (_sides_differ, 'left and right images differ in size: (620, 188) vs (600, 188)'),
    (_zero_size, 'image size must be positive, got 0x0'),
    (_size_vs_camera_info, 'image size 310x94 does not match the calibration 620x188'),
], ids=['unsupported_encoding', 'step_shorter_than_row', 'data_too_short', 'data_too_long',
        'height_larger_than_data', 'width_height_swapped', 'left_right_sizes_differ',
        'zero_size', 'size_differs_from_camera_info'])
def test_bad_image_is_rejected_named_and_the_node_recovers(make_rig, build, problem):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(3))
    published = rig.odom.count
    for i in (3, 4):  # twice: a repeated problem is still reported (throttled log)
        rig.send(*build(rig, i), rig.stamp(i))
        rig.wait_count('errors', i - 2)
    assert rig.odom.count == published  # nothing published for a rejected pair
    rig.assert_diagnosed(problem, DiagnosticStatus.ERROR)
    rig.assert_logged(problem, ERROR)
    rig.recover(5)
    rig.assert_healthy()


# -- images: accepted, no motion estimate ---------------------------------------------------
def _black(f, rng):
    return np.zeros_like(f.left), np.zeros_like(f.right)


def _white(f, rng):
    return np.full_like(f.left, 255), np.full_like(f.right, 255)


def _saturated(f, rng):
    return [np.clip(img.astype(np.int32) * 6, 0, 255).astype(np.uint8)
            for img in (f.left, f.right)]


def _noise(f, rng):
    # A broken sensor: nothing but noise, independent in both cameras and in time.
    return [np.clip(rng.normal(128.0, 60.0, img.shape), 0, 255).astype(np.uint8)
            for img in (f.left, f.right)]


def _occlusion(f, rng):
    # Something dark right in front of both lenses: a dim, almost flat, slightly noisy blur.
    return [np.clip(12 + rng.normal(0.0, 1.0, f.left.shape), 0, 255).astype(np.uint8)
            for _ in range(2)]


@pytest.mark.parametrize('make_bad, n_bad, problem, diagnosed, keeps_tracking', [
    (_black, 12, 'left image is uniform (every pixel 0)', 'left image is uniform', False),
    (_white, 4, 'right image is uniform (every pixel 255)', 'image is uniform', False),
    (_saturated, 4, 'left image over-exposed: 9',
     'image over-exposed', True),
    (_noise, 4, 'tracking ', 'tracking ', False),
    (_occlusion, 12, 'tracking lost: no motion estimate for', 'tracking lost', False),
], ids=['all_black', 'all_white', 'saturated', 'heavy_noise', 'sudden_full_occlusion'])
def test_images_without_usable_features_coast_and_recover(make_rig, make_bad, n_bad, problem,
                                                          diagnosed, keeps_tracking):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(4))
    rng = np.random.default_rng(7)
    before = rig.odom.count
    for k in range(n_bad):
        i = 4 + k
        rig.send(*make_bad(rig.frames[i], rng), rig.stamp(i))
        assert rig.h.wait_for(lambda: rig.odom.count > before + k, 10.0), rig.status()
    # The pose is still published (coasting when nothing can be tracked) and is flagged.
    assert rig.odom.count == before + n_bad
    rig.assert_diagnosed(diagnosed, DiagnosticStatus.WARN)
    rig.assert_logged(problem, WARN)
    last = rig.odom.last
    if not keeps_tracking:
        assert rig.value('tracking_state') != 'ok'
        assert np.array(last.pose.covariance).reshape(6, 6)[0, 0] > 1e-3
    if n_bad > 10:  # longer than pipeline.max_lost_time_s: LOST, ERROR, large covariance
        assert rig.diag().level == DiagnosticStatus.ERROR
        assert rig.value('tracking_state') == 'lost'
        assert np.linalg.eigvalsh(np.array(last.twist.covariance).reshape(6, 6)).min() >= 1e3
    rig.recover(4 + n_bad)
    rig.assert_healthy()


def test_stationary_camera_identical_frames_do_not_drift(make_rig):
    rig = make_rig()
    rig.camera_info()
    f = rig.frames[5]
    for k in range(20):
        before = rig.odom.count
        rig.send(f.left, f.right, rig.stamp(0) + k * 100_000_000)
        assert rig.h.wait_for(lambda: rig.odom.count > before, 10.0), rig.status()
    positions = np.array([_position(m) for m in rig.odom.messages])
    assert len(positions) == 20
    assert np.abs(positions - positions[0]).max() < 0.01  # m
    speeds = [np.linalg.norm([m.twist.twist.linear.x, m.twist.twist.linear.y,
                              m.twist.twist.linear.z]) for m in rig.odom.messages]
    assert max(speeds[1:]) < 0.05  # m/s
    d = rig.diag()
    assert d.level == DiagnosticStatus.OK and d.message == 'tracking', rig.status()
    assert rig.value('tracking_state') == 'ok'
    rig.assert_healthy()


def test_teleport_to_another_place_keeps_publishing_and_reports(make_rig):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(8))
    jump_from = _position(rig.odom.last)
    # Frames 28.. are ~20 m further along the route (after a turn), stamped as 8...
    for k, i in enumerate(range(28, 36)):
        before = rig.odom.count
        rig.send_frame(i, rig.stamp(8 + k))
        assert rig.h.wait_for(lambda: rig.odom.count > before, 10.0), rig.status()
    rig.assert_logged('tracking ', WARN)  # the jump itself is not trackable
    assert int(rig.value('pairs_processed')) == 16
    positions = np.array([_position(m) for m in rig.odom.messages])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert steps.max() < 6.0  # never more than max_speed * dt: no jump in the output
    assert np.linalg.norm(positions[8] - jump_from) < 6.0
    assert rig.value('tracking_state') == 'ok'  # tracking resumed at the new place
    rig.assert_healthy()


# -- calibration -----------------------------------------------------------------------
def test_missing_camera_info_waits_says_so_and_uses_the_newest_pair(make_rig):
    rig = make_rig()
    for i in range(3):
        rig.send_frame(i)
    rig.wait_count('pairs_without_camera_info', 1)
    both = f'waiting for camera_info on /{rig.name}/left/camera_info, ' \
        f'/{rig.name}/right/camera_info'
    assert rig.h.wait_for(lambda: rig.diag().message == both, 5.0), rig.status()
    rig.assert_diagnosed(both, DiagnosticStatus.WARN)
    rig.assert_logged(both, WARN)
    rig.camera_info(sides='l')
    rig.send_frame(3)
    assert rig.h.wait_for(lambda: rig.diag().message == f'waiting for camera_info on '
                          f'/{rig.name}/right/camera_info', 5.0), rig.status()
    assert rig.odom.count == 0
    # Pair 3 is waiting once the three before it are dropped (replaced in the waiting slot or
    # in the mailbox); the right camera_info must not arrive before it does.
    rig.wait_count('dropped_pairs', 3)
    rig.camera_info(sides='r')
    # Only the newest waiting pair is processed once both camera_info exist; the ones it
    # replaced are counted as dropped.
    assert rig.h.wait_for(lambda: rig.odom.count == 1, 5.0), rig.status()
    assert stamp_ns(rig.odom.last) == rig.stamp(3)
    assert rig.count('dropped_pairs') == 3
    rig.recover(4)
    rig.assert_healthy()


def _nan_focal(P0, P1):
    P0[0, 0] = np.nan
    return P0, P1, 'invalid camera_info: left P has non-finite values'


def _zero_focal(P0, P1):
    P1[0, 0] = 0.0
    return P0, P1, 'invalid camera_info: right P focal length must be positive, got fx='


def _zero_baseline(P0, P1):
    P1[0, 3] = 0.0
    return P0, P1, 'invalid camera_info: stereo baseline must be positive, got 0.0 m'


def _negative_baseline(P0, P1):
    P1[0, 3] = -P1[0, 3]
    return P0, P1, 'invalid camera_info: right camera must be to the right of the left one'


@pytest.mark.parametrize('corrupt', [_nan_focal, _zero_focal, _zero_baseline,
                                     _negative_baseline],
                         ids=['nan_focal_length', 'zero_focal_length', 'zero_baseline',
                              'negative_baseline'])
@pytest.mark.parametrize('when', ['at_start', 'mid_run'])
def test_invalid_camera_info_is_rejected_named_and_the_node_recovers(make_rig, corrupt, when):
    rig = make_rig()
    start = 0
    if when == 'mid_run':
        rig.camera_info()
        rig.good_run(range(3))
        start = 3
    P0, P1, problem = corrupt(rig.P0.copy(), rig.P1.copy())
    rig.camera_info(P0, P1)
    published = rig.odom.count
    for k in range(2):
        rig.send_frame(start + k)
        rig.wait_count('errors', k + 1)
    assert rig.odom.count == published
    rig.assert_diagnosed(problem, DiagnosticStatus.ERROR)
    rig.assert_logged(problem, ERROR)
    rig.camera_info()  # a valid calibration again
    rig.recover(start + 2)
    rig.assert_healthy()


def test_camera_info_changing_mid_run_uses_the_new_calibration(make_rig):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(8))
    P1 = rig.P1.copy()
    P1[0, 3] *= 2.0  # the baseline doubles: metric motion estimates double too
    rig.camera_info(P1=P1)
    rig.good_run(range(8, 16))
    baseline = rig.spec.baseline_m * 2
    rig.assert_logged(f'stereo calibration: 620x188 px, fx {rig.P0[0, 0]:.6g} px, baseline '
                      f'{baseline:.6g} m', min_level=Log.INFO)
    assert f'baseline {baseline:.6g} m' in rig.value('calibration')
    assert rig.count('calibration_changes') == 1
    msgs = list(rig.odom.messages)
    truth = np.array([f.T_world_cam[:3, 3] for f in rig.frames[:16]])
    true_speed = np.linalg.norm(np.diff(truth, axis=0), axis=1) / 0.1
    est_speed = np.array([np.linalg.norm([m.twist.twist.linear.x, m.twist.twist.linear.y,
                                          m.twist.twist.linear.z]) for m in msgs])
    before = est_speed[3:8] / true_speed[2:7]
    after = est_speed[11:16] / true_speed[10:15]  # re-detection at 8, filter settles
    assert np.all(np.abs(before - 1.0) < 0.2), before
    assert np.all(np.abs(after - 2.0) < 0.4), after
    rig.assert_healthy()


# -- time --------------------------------------------------------------------------------
@pytest.mark.parametrize('stamp_of', [lambda rig: rig.stamp(3), lambda rig: rig.stamp(4)],
                         ids=['out_of_order_stamp', 'duplicate_stamp'])
def test_out_of_order_and_duplicate_stamps_are_dropped_and_counted(make_rig, stamp_of):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(5))
    rig.send_frame(5, stamp_of(rig))
    rig.wait_count('unsynchronized_inputs', 2)
    problem = 'is not after the last stereo pair (duplicate or out-of-order stamp)'
    rig.assert_diagnosed(problem, DiagnosticStatus.WARN)
    rig.assert_logged(problem, WARN)
    assert rig.odom.count == 5 and rig.count('pairs_received') == 5
    rig.recover(5)
    stamps = [stamp_ns(m) for m in rig.odom.messages]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    rig.assert_healthy()


def test_large_gap_reinitialises_the_velocity_and_goes_on(make_rig):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(5))
    gap_ns = 30 * 1_000_000_000
    rig.good_run([5], offset_ns=gap_ns)
    problem = 'gap of 30.100 s: velocity re-initialised'
    rig.assert_diagnosed(problem, DiagnosticStatus.WARN)  # first: the WARN holds 5 s
    rig.assert_logged(problem, WARN)
    cov = np.array(rig.odom.last.pose.covariance).reshape(6, 6)
    assert cov[0, 0] > 1.0  # 30 s without a velocity: the position is very uncertain
    rig.recover(6, offset_ns=gap_ns)
    rig.assert_healthy()


def test_stamps_jumping_back_restart_the_odometry_cleanly(make_rig):
    """A looping bag: the second pass starts at the identity and repeats the first."""
    rig = make_rig(**{'ros.path_max_length': 1000})
    path = []
    sub = rig.h.node.create_subscription(Path, f'/{rig.name}/path', path.append, 10)
    try:
        assert rig.h.wait_for(lambda: sub.get_publisher_count() >= 1, 10.0)
        rig.camera_info()
        rig.good_run(range(15))
        first = list(rig.odom.messages)
        rig.good_run([0])  # back to the first stamp: 1.4 s earlier
        # Checked at once: the warning holds the diagnostics at WARN for WARN_HOLD_S (5 s) of
        # wall time, which nine more frames took on a loaded CI machine (2026-11-23).
        rig.assert_diagnosed('restart', DiagnosticStatus.WARN)
        rig.good_run(range(1, 10))
        second = list(rig.odom.messages)[15:]
        for text in ('is 1.400 s before the previous one: the input restarted (looping bag?)',
                     'stamp jumped back 1.400 s: restarting odometry'):
            rig.assert_logged(text, WARN)
        assert rig.count('restarts') == 1
        assert stamp_ns(second[0]) == rig.stamp(0)
        assert np.linalg.norm(_position(second[0])) < 1e-9
        for a, b in zip(first[:10], second):
            assert np.linalg.norm(_position(a) - _position(b)) < 0.05
        assert rig.h.wait_for(lambda: path and len(path[-1].poses) == 10, 5.0)
        assert stamp_ns(path[-1].poses[0]) == rig.stamp(0)
        assert rig.value('tracking_state') == 'ok'
    finally:
        rig.h.destroy(sub)
    rig.assert_healthy()


def test_images_of_a_pair_arriving_apart_are_measured_and_explained(make_rig):
    """The right image 20 ms after the left one: the gap is reported, with the likely cause."""
    rig = make_rig()
    rig.camera_info()
    order = list(range(N_FRAMES)) + list(range(N_FRAMES - 2, 0, -1))
    for k in range(35):  # more than the 30 pairs of the median
        f = rig.frames[order[k]]
        ns = rig.stamp(0) + k * 100_000_000
        before = rig.odom.count
        rig.pubs['left/image_rect'].publish(rig.image(f.left, ns))
        time.sleep(0.02)
        rig.pubs['right/image_rect'].publish(rig.image(f.right, ns))
        assert rig.odom.wait_count(before + 1, 10.0), rig.status()
    assert float(rig.value('pair_arrival_gap_ms')) >= 15.0, rig.status()
    rig.assert_logged('the two images of a pair arrive', Log.INFO)
    rig.assert_logged('fastdds_large_images.xml', Log.INFO)
    assert rig.value('tracking_state') == 'ok'
    rig.assert_healthy()


@pytest.mark.parametrize('sync, offset_ms, rule', [
    ('approximate', 20, 'within 0.005 s (approximate sync)'),
    ('exact', 1, 'equal (exact sync)'),
])
def test_left_and_right_never_within_the_slop(make_rig, sync, offset_ms, rule):
    rig = make_rig(**{'ros.sync': sync})
    rig.camera_info()
    for i in range(5):
        f = rig.frames[i]
        rig.send(f.left, f.right, rig.stamp(i), rig.stamp(i) + offset_ms * 1_000_000)
    rig.wait_count('unsynchronized_inputs', 3)
    problem = 'without their partner'
    why = f'the left and right stamps are not {rule}'
    rig.assert_diagnosed(why, DiagnosticStatus.WARN)  # first: the WARN holds 5 s
    rig.assert_logged(problem, WARN)
    rig.assert_logged(why, WARN)
    assert rig.diag().message.startswith('no synchronized stereo pair received yet')
    assert rig.count('pairs_received') == 0 and rig.odom.count == 0
    rig.recover(5)
    rig.assert_healthy()


# -- non-finite odometry -------------------------------------------------------------------
def test_absurd_set_pose_never_publishes_non_finite_odometry(make_rig):
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(3))
    pub = rig.h.node.create_publisher(PoseWithCovarianceStamped, f'/{rig.name}/stereo_vo/'
                                      'set_pose', 10)
    try:
        assert rig.h.wait_for(lambda: pub.get_subscription_count() >= 1, 10.0)
        pose = PoseWithCovarianceStamped()
        pose.pose.pose.orientation.w = 1.0
        pose.pose.covariance = (np.eye(6) * 0.01).ravel().tolist()
        pose.pose.pose.position.x = 1e200  # its covariance overflows: refused
        pub.publish(pose)
        rig.assert_logged('~/set_pose ignored: the pose or its covariance overflows', ERROR)
        rig.good_run([3])
        assert _position(rig.odom.last)[0] < 1e3
        # Accepted (a zero covariance stays finite in the camera frame), but the next pair's
        # covariance increment, moved out to 1e308 m, overflows whatever the velocity's
        # uncertainty (1e150 with a 0.01 covariance overflowed only for some).
        pose.pose.pose.position.x = 1e308
        pose.pose.covariance = [0.0] * 36
        pub.publish(pose)
        rig.assert_logged('pose set to [1e+308', Log.INFO)
        rig.send_frame(4)
        rig.wait_count('non_finite_skipped', 1)
    finally:
        rig.h.destroy(pub)
    problem = 'not published; the odometry restarts at the identity with the next pair'
    rig.assert_diagnosed(problem, DiagnosticStatus.ERROR)  # first: the ERROR holds 5 s
    rig.assert_logged(problem, ERROR)
    rig.good_run(range(5, 8))
    assert np.linalg.norm(_position(rig.odom.last)) < 5.0
    assert rig.count('resets') == 1
    rig.assert_healthy()


# -- load ----------------------------------------------------------------------------------
def test_input_at_three_times_the_processing_rate_drops_newest_wins_no_queue(make_rig):
    """
    Flood the node at three times the rate its processing allows: drops, no queue.

    The publisher shares this process (and the GIL) with the composed node, so the flood also
    slows the node's executor down; the end-to-end latency under a real overload, node in its
    own process, is measured by ``benchmarks/bench_node_latency.py``. What is asserted here is
    the design: pairs are dropped and counted, and after the flood only a handful of pairs come
    out, the newest last: nothing queued up.
    """
    rig = make_rig()
    rig.camera_info()
    rig.good_run(range(15))  # warm: the processing time below is the steady one
    period_s = max(float(rig.value('processing_ms')) * 1e-3, 1e-3)
    rate_hz = 3.0 / period_s
    arrivals = {}
    watch = rig.odom

    def on_odom(msg):
        arrivals.setdefault(stamp_ns(msg), time.perf_counter())
    sub = rig.h.node.create_subscription(Odometry, f'/{rig.name}/odom', on_odom, 100)
    try:
        assert rig.h.wait_for(lambda: sub.get_publisher_count() >= 1, 10.0)
        order = list(range(15, N_FRAMES)) + list(range(N_FRAMES - 2, 0, -1))  # ping-pong
        start = time.perf_counter()
        # At least 5 s, and on until the node has published 3 pairs during the flood (at most
        # 30 s): on a loaded CI machine this process got through only 37 sends in 5 s, and the
        # node through 2 pairs (2026-11-23), so a fixed duration asserted the machine's load.
        min_s, max_s = 5.0, 30.0
        k = 0
        while time.perf_counter() - start < min_s or (
                len(arrivals) < 3 and time.perf_counter() - start < max_s):
            i = order[k % len(order)]
            ns = rig.stamp(15) + k * 100_000_000
            rig.send(rig.frames[i].left, rig.frames[i].right, ns)
            k += 1
            # One sleep to the next send time: polling with short sleeps woke this thread
            # ~2000 times a second, and every wake-up took the GIL from the node's worker.
            time.sleep(max(0.0, start + k / rate_hz - time.perf_counter()))
        flood_end, last_ns = time.perf_counter(), ns
        # Newest wins: the last pair comes out, and only a handful after the flood (what the
        # DDS readers and the pairing still hold), not a backlog of the k pairs sent. The time
        # it takes is not asserted: the flooding publisher shares this process's GIL.
        assert rig.h.wait_for(lambda: last_ns in arrivals, 10.0), rig.status()
        late = sum(1 for t in arrivals.values() if t > flood_end)
        assert late <= 6, (late, k, period_s)
    finally:
        rig.h.destroy(sub)
    time.sleep(0.2)  # let the diagnostics counters settle
    dropped = rig.count('dropped_pairs')
    received = rig.count('pairs_received')
    assert dropped > 0 and k > len(arrivals), rig.status()
    assert rig.count('pairs_processed') == received - dropped  # every other one
    assert len(arrivals) >= 3, (len(arrivals), k, period_s)  # still processing while flooded
    # How long the node takes under the flood is the benchmark's to measure
    # (benchmarks/bench_node_latency.py, node in its own process): here the flooding publisher
    # shares the GIL with the node, and any time bound would assert the machine's load.
    rig.assert_logged('stereo pair dropped: pairs arrive faster than they are processed', WARN)
    assert watch.problems == []
    rig.assert_healthy()


def _rss_bytes() -> int:
    with open(f'/proc/{os.getpid()}/statm') as f:
        return int(f.read().split()[1]) * os.sysconf('SC_PAGE_SIZE')


def test_long_run_memory_flat_and_path_bounded(harness):
    """
    Many small frames (forwards, then backwards: no jump) through the node.

    The short version of ``benchmarks/bench_long_run.py`` (20,000 pairs, memory growth per
    1,000 pairs): 200 pairs, four times the path's bound, with Python's allocations traced over
    the second half.
    """
    n_pairs, path_max = 200, 50
    spec = SequenceSpec.preset('demo', n_frames=60, width=320, height=96, turns=False,
                               start_time_s=100.0)
    rig = Rig(harness, (spec, list(render_sequence(spec))),
              **{'ros.path_max_length': path_max})
    path_lengths = []
    sub = harness.node.create_subscription(
        Path, f'/{rig.name}/path', lambda m: path_lengths.append(len(m.poses)), 10)
    rig.odom.messages = type(rig.odom.messages)(maxlen=5)  # check on arrival, keep few
    try:
        assert harness.wait_for(lambda: sub.get_publisher_count() >= 1, 10.0)
        rig.camera_info()
        order = list(range(60)) + list(range(58, 0, -1))
        marks = {}
        t_start = time.perf_counter()
        for k in range(n_pairs):
            if k == n_pairs // 5:
                tracemalloc.start()
            if k in (n_pairs // 5, n_pairs // 2, n_pairs - 1):
                marks[k] = (tracemalloc.get_traced_memory()[0] if tracemalloc.is_tracing()
                            else 0, _rss_bytes())
            i = order[k % len(order)]
            rig.send(rig.frames[i].left, rig.frames[i].right, rig.stamp(0) + k * 100_000_000)
            # One pair in flight: the next is sent once this one's odometry arrived, so none is
            # dropped (the newest pair wins while the node is busy) however slow the machine.
            assert rig.odom.wait_count(k + 1, 30.0), rig.status()
        elapsed = time.perf_counter() - t_start
        dropped = rig.count('dropped_pairs')
    finally:
        harness.destroy(sub)
        rig.close()
        # After the node's threads are gone: tracemalloc must not stop while another thread
        # allocates (a race in CPython's tracemalloc that can crash the process).
        tracemalloc.stop()
    mid, end = marks[n_pairs // 2], marks[n_pairs - 1]
    assert rig.odom.count == n_pairs and dropped == 0, (rig.odom.count, dropped)
    assert path_lengths and max(path_lengths) <= path_max and path_lengths[-1] == path_max
    # Second half vs first half: no growth of Python memory, little of the process'.
    assert end[0] - mid[0] < 1_000_000, (mid, end)
    assert end[1] - mid[1] < 20_000_000, (mid, end)
    assert rig.odom.problems == []
    assert harness.spinning
    print(f'long run: {n_pairs} pairs in {elapsed:.1f} s; traced Python memory '
          f'{mid[0] / 1e6:.2f} -> {end[0] / 1e6:.2f} MB, RSS {mid[1] / 1e6:.1f} -> '
          f'{end[1] / 1e6:.1f} MB')
