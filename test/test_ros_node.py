"""
Tests of the ROS 2 node with real rclpy and DDS on loopback.

A rendered synthetic sequence is written to a rosbag2 with rosbags; the bag player replays it
(publishing /clock) into the node started as a separate process through its entry point, or
composed in-process with another node in one executor. Every test module uses its own
ROS_DOMAIN_ID (from the pid) so parallel runs do not talk to each other.
"""

import contextlib
import os
from pathlib import Path
import py_compile
import tempfile
import time
from xml.etree import ElementTree

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from ros_harness import composed_node, domain_id, Harness, NODE_START_S
from ros_harness import stamp_ns as _stamp_ns, values as _values
from rosbags.rosbag2 import Writer
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import Trigger
from stereo_vo_ros.config import Config, to_yaml
from stereo_vo_ros.errors import ConfigError
from stereo_vo_ros.evaluation.metrics import end_point_drift
from stereo_vo_ros.io.rosbag import RosbagSequence, write_stereo_bag
from stereo_vo_ros.pipeline import StereoOdometry
from stereo_vo_ros.ros import conversions as conv
from stereo_vo_ros.ros.node import MAX_SPIN_FAILURES, spin, StereoVONode
from stereo_vo_ros.ros.player import BagPlayer
from stereo_vo_ros.ros.process import node_process as node_subprocess, with_pythonpath
from stereo_vo_ros.synthetic import render_sequence, SequenceSpec
from tf2_msgs.msg import TFMessage

REPO_ROOT = Path(__file__).resolve().parent.parent
DOMAIN_ID = domain_id()
N_FRAMES = 40
SPLIT = 22  # frame at which the reset test restarts the odometry
JITTER_NS = 2_000_000  # right stamps of the jittered bag are 2 ms late
IMAGE_TOPICS = ('/left/image_rect', '/right/image_rect')
INFO_TOPICS = ('/left/camera_info', '/right/camera_info')
#: Sanity bound on the end-point drift against the ground truth; the exact check is that the
#: node reproduces the offline pipeline on the pairs it received.
DRIFT_BOUND_PERCENT = 10.0
T_BASE_CAM = conv.transform_from_xyz_rpy([0, 0, 0], [-90, 0, -90])  # the node's default


# -- fixtures -----------------------------------------------------------------------------
@pytest.fixture(scope='module')
def sequence():
    """Render the demo city preset (620x188 px, 10 Hz) once for the module."""
    spec = SequenceSpec.preset('demo', n_frames=N_FRAMES, start_time_s=100.0)
    frames = list(render_sequence(spec))
    return spec, frames


def _write_jittered_bag(path: Path, spec, frames, right_offset_ns: int) -> None:
    """Write images and camera_info with the right stamps shifted (rosbags, rclpy CDR)."""
    P0, P1 = spec.projections()
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9) as writer:
        conns = {t: writer.add_connection(t, m, typestore=typestore) for t, m in (
            (INFO_TOPICS[0], 'sensor_msgs/msg/CameraInfo'),
            (INFO_TOPICS[1], 'sensor_msgs/msg/CameraInfo'),
            (IMAGE_TOPICS[0], 'sensor_msgs/msg/Image'),
            (IMAGE_TOPICS[1], 'sensor_msgs/msg/Image'))}
        for f in frames:
            ns = int(round(f.stamp_s * 1e9))
            right_ns = ns + right_offset_ns
            left_stamp = conv.time_from_nanoseconds(ns)
            right_stamp = conv.time_from_nanoseconds(right_ns)
            h, w = f.left.shape
            for topic, t, msg in (
                    (INFO_TOPICS[0], ns, conv.camera_info_from_matrices(
                        P0, w, h, stamp=left_stamp, frame_id='camera_left')),
                    (INFO_TOPICS[1], right_ns, conv.camera_info_from_matrices(
                        P1, w, h, stamp=right_stamp, frame_id='camera_right')),
                    (IMAGE_TOPICS[0], ns, conv.image_from_numpy(
                        f.left, 'mono8', left_stamp, 'camera_left')),
                    (IMAGE_TOPICS[1], right_ns, conv.image_from_numpy(
                        f.right, 'mono8', right_stamp, 'camera_right'))):
                writer.write(conns[topic], t, serialize_message(msg))


@pytest.fixture(scope='module')
def bag(sequence, tmp_path_factory):
    """Rosbag2 of the sequence (equal left and right stamps) with its ground truth."""
    spec, frames = sequence
    path = tmp_path_factory.mktemp('bags') / 'stereo'
    calib = spec.calibration()
    write_stereo_bag(path, [f.stereo_frame(calib) for f in frames], calib,
                     [f.T_world_cam for f in frames])
    return path


@pytest.fixture(scope='module')
def jitter_bag(sequence, tmp_path_factory):
    """Rosbag2 of the sequence whose right stamps are JITTER_NS late."""
    path = tmp_path_factory.mktemp('bags') / 'jitter'
    _write_jittered_bag(path, *sequence, right_offset_ns=JITTER_NS)
    return path


@pytest.fixture
def harness():
    """Yield a fresh Harness and close it afterwards."""
    h = Harness()
    yield h
    h.close()


@contextlib.contextmanager
def node_process(*ros_args: str, env_extra: dict | None = None):
    """Run the node as a separate process; yields a dict that receives its output."""
    env = with_pythonpath(dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1',
                               **(env_extra or {})), REPO_ROOT)
    result = {'output': '', 'returncode': None}
    with tempfile.TemporaryFile('w+') as log:
        with node_subprocess(ros_args, env=env, stdout=log, text=True) as proc:
            yield result
        log.seek(0)
        result['output'], result['returncode'] = log.read(), proc.returncode


def _camera_poses(odoms) -> np.ndarray:
    """(N, 4, 4) T_world_cam recovered from odometry messages (the node's default T_base_cam)."""
    poses = []
    for m in odoms:
        T_odom_base = conv.transform_from_pose(m.pose.pose.position, m.pose.pose.orientation)
        poses.append(conv.camera_pose_from_base_pose(T_odom_base, None, T_BASE_CAM)[0])
    return np.array(poses)


def _check_odometry(odoms, frames, odom_frame='odom', base_frame='base_link') -> None:
    """Frames, stamps, finite values and positive definite covariances of every message."""
    bag_stamps = {int(round(f.stamp_s * 1e9)) for f in frames}
    stamps = [_stamp_ns(m) for m in odoms]
    assert set(stamps) <= bag_stamps
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    for m in odoms:
        assert (m.header.frame_id, m.child_frame_id) == (odom_frame, base_frame)
        p, q = m.pose.pose.position, m.pose.pose.orientation
        tw = m.twist.twist
        values = np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w, tw.linear.x, tw.linear.y,
                           tw.linear.z, tw.angular.x, tw.angular.y, tw.angular.z,
                           *m.pose.covariance, *m.twist.covariance])
        assert np.all(np.isfinite(values))
        for cov in (m.pose.covariance, m.twist.covariance):
            cov = np.array(cov).reshape(6, 6)
            np.testing.assert_allclose(cov, cov.T, atol=1e-12)
            assert np.linalg.eigvalsh(cov).min() > 0


def _drift(odoms, stamps_s, ground_truth) -> float:
    """End-point drift (% of distance) against the ground truth, from the first message."""
    by_stamp = {int(round(t * 1e9)): T for t, T in zip(stamps_s, ground_truth)}
    T0_inv = np.linalg.inv(by_stamp[_stamp_ns(odoms[0])])
    gt = np.array([T0_inv @ by_stamp[_stamp_ns(m)] for m in odoms])
    return end_point_drift(gt, _camera_poses(odoms))


def _assert_reproduces_offline(segments, spec, frames) -> None:
    """
    Check that the odometry equals the offline pipeline run on the same pairs.

    ``segments`` are lists of odometry messages with a ``reset()`` of the pipeline between
    them, as the node's ~/reset service does.
    """
    calib = spec.calibration()
    vo = StereoOdometry(Config())
    expected = {}
    for k, odoms in enumerate(segments):
        if k:
            vo.reset()
        stamps = {_stamp_ns(m) for m in odoms}
        for f in frames:
            ns = int(round(f.stamp_s * 1e9))
            if ns in stamps:
                result = vo.process(f.stereo_frame(calib))
                expected[ns] = conv.base_odometry_from_result(result, T_BASE_CAM)
    for m in (m for odoms in segments for m in odoms):
        want = expected[_stamp_ns(m)]
        got = conv.transform_from_pose(m.pose.pose.position, m.pose.pose.orientation)
        np.testing.assert_allclose(got, want.T_odom_base, atol=1e-6)
        np.testing.assert_allclose(np.array(m.pose.covariance).reshape(6, 6),
                                   want.pose_covariance, rtol=1e-6, atol=1e-12)


def _paced_play(h: Harness, player: BagPlayer, timeout_s: float = 5.0, **kwargs):
    """
    Replay, waiting for the odometry of every pair before the next pair is complete.

    Keeps the tests independent of the machine's load (no pair is dropped because the node is
    still busy); the node's newest-wins dropping is exercised by the benchmark instead. The
    wait happens at the first message of the next frame, so that a camera_info recorded
    after its image is published first.
    """
    pending = []

    def pace(topic: str, stamp_ns: int, msg) -> None:
        if pending and pending[0][1] != stamp_ns:
            left_ns = pending.pop()[0]
            h.wait_for(lambda: bool(h.odom) and _stamp_ns(h.odom[-1]) >= left_ns, timeout_s)
        if topic.endswith('right/image_rect'):
            pending[:] = [(_stamp_ns(msg) - JITTER_NS, stamp_ns)]  # the left stamp or earlier
    return player.play(on_message=pace, **kwargs)


def _wait_for_node(h: Harness, player: BagPlayer, odom_topic: str = '/odom') -> None:
    assert player.wait_for_subscribers(NODE_START_S), \
        'the node did not subscribe to the bag topics'
    assert h.wait_for(lambda: h.node.count_publishers(odom_topic) >= 1, 30.0)
    assert h.wait_for(lambda: h.node.count_subscribers('/clock') >= 1, 10.0)
    # Discovery is not symmetric: give the node's readers time to match the player's writers
    # (volatile QoS: anything published before that is lost).
    time.sleep(1.0)


# -- separate process ---------------------------------------------------------------------
def test_bag_replay_into_node_process_with_sim_time_and_reset(sequence, bag, harness,
                                                              tmp_path):
    spec, frames = sequence
    params = tmp_path / 'params.yaml'
    params.write_text(to_yaml(Config().replace(**{'ros.qos': 'reliable'})))
    player = BagPlayer(harness.node, bag, topics=IMAGE_TOPICS + INFO_TOPICS, rate=1.0)
    split_ns = int(round(frames[SPLIT].stamp_s * 1e9))
    tf_messages = []
    harness.node.create_subscription(TFMessage, '/tf', tf_messages.append, 100)
    with node_process('--params-file', str(params), '-p', 'use_sim_time:=true') as proc:
        _wait_for_node(harness, player)
        stats = _paced_play(harness, player, stop_ns=split_ns)
        assert stats.messages == 4 * SPLIT and stats.clock_messages >= 4 * SPLIT
        harness.settle(SPLIT)
        first = list(harness.odom)
        response = harness.call(Trigger, '/stereo_vo/reset', Trigger.Request())
        assert response is not None and response.success
        _paced_play(harness, player, start_ns=split_ns)
        harness.settle(N_FRAMES)
        second = harness.odom[len(first):]
        # Each transform follows its odometry on /tf: wait for the last one before stopping.
        last = _stamp_ns(harness.odom[-1])
        assert harness.wait_for(lambda: any(_stamp_ns(t) == last for m in list(tf_messages)
                                            for t in m.transforms), 10.0), 'no /tf for the end'
    assert proc['returncode'] == 0, proc['output']
    # Reliable QoS and a paced replay: every pair becomes odometry.
    assert (len(first), len(second)) == (SPLIT, N_FRAMES - SPLIT), proc['output']
    _check_odometry(first + second, frames)
    assert _stamp_ns(first[0]) == int(round(frames[0].stamp_s * 1e9))
    # After the reset the odometry restarts at the identity with the next pair.
    assert _stamp_ns(second[0]) >= split_ns
    p = second[0].pose.pose.position
    assert np.linalg.norm([p.x, p.y, p.z]) < 1e-9
    _assert_reproduces_offline([first, second], spec, frames)
    truth = RosbagSequence(bag)
    assert _drift(first, truth.stamps, truth.ground_truth) < DRIFT_BOUND_PERCENT
    assert _drift(second, truth.stamps, truth.ground_truth) < DRIFT_BOUND_PERCENT
    # The vehicle drove forward: +x in the REP-103 odom frame, no big vertical motion.
    p_end = first[-1].pose.pose.position
    assert p_end.x > 10.0 and abs(p_end.z) < 1.0
    # Diagnostics are stamped with the bag time (use_sim_time + /clock).
    ours = [d for d in harness.diagnostics if d.status and 'stereo_vo' in d.status[0].name]
    assert ours
    sim = [_stamp_ns(d) for d in ours if _stamp_ns(d) > 0]
    assert sim and all(int(spec.start_time_s * 1e9) <= s <= int((spec.start_time_s + 10) * 1e9)
                       for s in sim)
    values = _values(ours[-1].status[0])
    assert values['tracking_state'] == 'ok' and int(values['inliers']) >= 8
    # The online rig refinement reports its estimate and uncertainty (pixels, finite).
    assert values['rig_refinement'].split(',')[0] in ('settled', 'converging'), values
    for key in ('rig_row_offset_px', 'rig_row_offset_std_px', 'rig_disparity_offset_px',
                'rig_disparity_offset_std_px'):
        assert np.isfinite(float(values[key])), (key, values)
    # odom -> base_link on /tf (tf2_msgs/TFMessage, as tf2_ros sends it), one per odometry,
    # stamped like it and with its pose.
    assert 'NOT broadcast on /tf' not in proc['output']
    transforms = {_stamp_ns(t): t for m in tf_messages for t in m.transforms}
    for odom in first + second:
        tf = transforms[_stamp_ns(odom)]
        assert (tf.header.frame_id, tf.child_frame_id) == ('odom', 'base_link')
        p, q, r = odom.pose.pose.position, odom.pose.pose.orientation, tf.transform.rotation
        assert np.allclose([p.x, p.y, p.z], [tf.transform.translation.x,
                                             tf.transform.translation.y,
                                             tf.transform.translation.z], atol=1e-12)
        assert np.allclose([q.x, q.y, q.z, q.w], [r.x, r.y, r.z, r.w], atol=1e-12)
    # No camera mounting on /tf_static here: the parameters' one, said once.
    assert 'ros.base_from_camera_rpy_deg=[-90.0, 0.0, -90.0]' in proc['output']


def test_node_process_remapping_exact_sync_and_auto_qos(sequence, bag):
    """Remapped topics, exact sync, default QoS: the reliable player gets a reliable reader."""
    _, frames = sequence
    remaps = {t: '/cam' + t for t in IMAGE_TOPICS + INFO_TOPICS}
    args = ['-p', 'use_sim_time:=true', '-p', 'ros.sync:=exact', '-r', 'odom:=/vo/odom']
    for topic, target in remaps.items():
        args += ['-r', f'{topic[1:]}:={target}']
    h = Harness('/vo/odom')
    try:
        player = BagPlayer(h.node, bag, topics=IMAGE_TOPICS + INFO_TOPICS, rate=1.0,
                           remap=remaps)

        def input_qos() -> str:
            ours = [_values(d.status[0]) for d in h.diagnostics
                    if d.status and 'stereo_vo' in d.status[0].name]
            return ours[-1].get('input_qos', '') if ours else ''

        with node_process(*args) as proc:
            _wait_for_node(h, player, '/vo/odom')
            # The player's writers may be discovered after the node started: auto then
            # subscribes best effort first and switches within a second.
            assert h.wait_for(lambda: input_qos() == 'reliable (ros.qos auto)', 10.0), \
                input_qos()
            assert h.wait_for(lambda: h.node.count_subscribers('/cam/left/image_rect') == 1,
                              5.0)
            assert h.node.count_subscribers('/left/image_rect') == 0
            _paced_play(h, player, timeout_s=5.0, stop_ns=int(round(frames[15].stamp_s * 1e9)))
            h.settle(15)
        assert proc['returncode'] == 0, proc['output']
        # The player publishes reliably, so auto subscribes reliably: every pair arrives.
        assert len(h.odom) == 15, proc['output']
        _check_odometry(h.odom, frames)
        assert 'exact sync, auto QoS' in proc['output']
        assert input_qos() == 'reliable (ros.qos auto)', input_qos()
    finally:
        h.close()


def test_node_process_with_the_shipped_road_vehicle_overlay(sequence, bag):
    """The README's command for a road vehicle: both shipped parameter files, in that order."""
    _, frames = sequence
    h = Harness()
    try:
        player = BagPlayer(h.node, bag, topics=IMAGE_TOPICS + INFO_TOPICS, rate=1.0)
        with node_process('--params-file', str(REPO_ROOT / 'config' / 'stereo_vo.yaml'),
                          '--params-file', str(REPO_ROOT / 'config' / 'road_vehicle.yaml'),
                          '-p', 'use_sim_time:=true', '-p', 'ros.qos:=reliable') as proc:
            _wait_for_node(h, player)
            _paced_play(h, player, stop_ns=int(round(frames[12].stamp_s * 1e9)))
            h.settle(12)
            assert h.wait_for(lambda: any(
                _values(d.status[0]).get('vehicle_fused') == 'True' for d in h.diagnostics
                if d.status and 'stereo_vo' in d.status[0].name), 5.0)
        assert proc['returncode'] == 0, proc['output']
        assert len(h.odom) == 12, proc['output']
        _check_odometry(h.odom, frames)
    finally:
        h.close()


def test_fastdds_large_images_profile_is_valid_and_carries_pairs(sequence, bag):
    """The shipped Fast DDS profile: parsed without error, talks to a default participant."""
    _, frames = sequence
    profile = REPO_ROOT / 'config' / 'fastdds_large_images.xml'
    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ElementTree.parse(profile).getroot()
    kinds = {d.findtext('p:transport_id', namespaces=ns): d.findtext('p:type', namespaces=ns)
             for d in root.iterfind('p:transport_descriptors/p:transport_descriptor', ns)}
    assert sorted(kinds.values()) == ['SHM', 'UDPv4']  # other hosts still reachable
    segment = int(root.findtext('.//p:segment_size', namespaces=ns))
    assert segment >= 4 * 2 * 1241 * 376  # a few KITTI-size mono8 pairs in flight
    participant = root.find('p:participant', ns)
    assert participant.get('is_default_profile') == 'true'
    used = [t.text for t in participant.iterfind('p:rtps/p:userTransports/p:transport_id', ns)]
    assert sorted(used) == sorted(kinds)
    # The node with the profile; the test's participant (the bag player) with the defaults.
    h = Harness()
    try:
        player = BagPlayer(h.node, bag, topics=IMAGE_TOPICS + INFO_TOPICS, rate=1.0)
        with node_process('-p', 'use_sim_time:=true', '-p', 'ros.qos:=reliable',
                          env_extra={'FASTRTPS_DEFAULT_PROFILES_FILE': str(profile)}) as proc:
            _wait_for_node(h, player)
            _paced_play(h, player, stop_ns=int(round(frames[10].stamp_s * 1e9)))
            h.settle(10)
        assert proc['returncode'] == 0, proc['output']
        assert ' Error]' not in proc['output'], proc['output']  # Fast DDS: [XMLPARSER Error]
        assert len(h.odom) == 10, proc['output']
        _check_odometry(h.odom, frames)
    finally:
        h.close()


# -- composed in-process ------------------------------------------------------------------
def test_composed_node_approximate_sync_parameters_debug_image_and_set_pose(
        sequence, jitter_bag, harness):
    _, frames = sequence
    node = composed_node(harness, **{'ros.sync': 'approximate', 'ros.sync_slop_s': 0.005})
    debug = []
    harness.node.create_subscription(Image, '/stereo_vo/debug_image', debug.append, 10)
    player = BagPlayer(harness.node, jitter_bag, rate=1.0)
    _wait_for_node(harness, player)
    assert harness.wait_for(lambda: node.count_subscribers('/stereo_vo/debug_image') >= 1, 10)
    _paced_play(harness, player, stop_ns=int(round(frames[12].stamp_s * 1e9)))
    harness.settle(12)
    assert len(harness.odom) == 12, _values(node.diagnostics())
    _check_odometry(harness.odom, frames)  # stamped with the LEFT stamps
    _assert_reproduces_offline([harness.odom], sequence[0], frames)
    assert debug and debug[-1].encoding == 'bgr8'
    assert (debug[-1].width, debug[-1].height) == (frames[0].left.shape[1],
                                                   frames[0].left.shape[0])

    # Run-time parameters: dynamic ones go to the pipeline, the others are refused.
    ok = node.set_parameters([Parameter('ransac.inlier_threshold_px', value=3.0),
                              Parameter('tracker.fb_threshold_px', value=1)])
    assert all(r.successful for r in ok)
    assert node.config.ransac.inlier_threshold_px == 3.0
    assert node.config.tracker.fb_threshold_px == 1.0
    (bad_range,) = node.set_parameters([Parameter('ransac.inlier_threshold_px', value=1e4)])
    assert not bad_range.successful and '100' in bad_range.reason
    (read_only,) = node.set_parameters([Parameter('filter.type', value='ekf')])
    assert not read_only.successful and node.config.filter.type == 'ispkf'
    (bad_type,) = node.set_parameters([Parameter('ransac.inlier_threshold_px', value='x')])
    assert not bad_type.successful and node.config.ransac.inlier_threshold_px == 3.0

    # ~/set_pose: continue from 100 m ahead in odom.
    pose = PoseWithCovarianceStamped()
    pose.header.frame_id = 'odom'
    pose.pose.pose.position.x = 100.0
    pose.pose.pose.orientation.w = 1.0
    pose.pose.covariance = (np.eye(6) * 0.01).ravel().tolist()
    pub = harness.node.create_publisher(PoseWithCovarianceStamped, '/stereo_vo/set_pose', 10)
    assert harness.wait_for(lambda: pub.get_subscription_count() >= 1, 10)
    pub.publish(pose)
    time.sleep(0.5)
    count = len(harness.odom)
    _paced_play(harness, player, start_ns=int(round(frames[12].stamp_s * 1e9)),
                stop_ns=int(round(frames[16].stamp_s * 1e9)))
    harness.settle(count + 4)
    after = harness.odom[count]
    assert 100.0 < after.pose.pose.position.x < 103.0
    assert np.array(after.pose.covariance).reshape(6, 6)[0, 0] >= 0.01


def test_composed_node_exact_sync_refuses_jittered_stamps(sequence, jitter_bag, harness):
    _, frames = sequence
    node = composed_node(harness, **{'ros.sync': 'exact'})
    player = BagPlayer(harness.node, jitter_bag, rate=2.0)
    _wait_for_node(harness, player)
    player.play(stop_ns=int(round(frames[8].stamp_s * 1e9)))
    assert harness.wait_for(lambda: _values(node.diagnostics())['unsynchronized_inputs'] != '0',
                            5.0)
    time.sleep(0.5)
    status = node.diagnostics()
    assert harness.odom == []
    assert status.level == DiagnosticStatus.WARN
    assert int(_values(status)['unsynchronized_inputs']) >= 7
    assert _values(status)['pairs_received'] == '0'


def test_composed_node_survives_bad_input_and_waits_for_camera_info(sequence, harness):
    spec, frames = sequence
    node = composed_node(harness)
    qos = 10
    pubs = {t: harness.node.create_publisher(Image if 'image' in t else CameraInfo, t, qos)
            for t in IMAGE_TOPICS + INFO_TOPICS}
    assert harness.wait_for(lambda: all(p.get_subscription_count() >= 1
                                        for p in pubs.values()), 10)

    def send_pair(i, encoding='mono8'):
        stamp = conv.time_from_nanoseconds(int(round(frames[i].stamp_s * 1e9)))
        for topic, img in zip(IMAGE_TOPICS, (frames[i].left, frames[i].right)):
            msg = conv.image_from_numpy(img, 'mono8', stamp, 'camera_left')
            msg.encoding = encoding
            pubs[topic].publish(msg)

    send_pair(0)
    assert harness.wait_for(lambda: 'camera_info' in node.diagnostics().message, 5)
    assert node.diagnostics().level == DiagnosticStatus.WARN
    P0, P1 = spec.projections()
    h, w = frames[0].left.shape
    pubs[INFO_TOPICS[0]].publish(conv.camera_info_from_matrices(P0, w, h))
    pubs[INFO_TOPICS[1]].publish(conv.camera_info_from_matrices(P1, w, h))
    time.sleep(0.3)
    send_pair(1, encoding='yuv422')
    assert harness.wait_for(lambda: node.diagnostics().level == DiagnosticStatus.ERROR, 5)
    assert 'yuv422' in _values(node.diagnostics())['last_error']
    send_pair(2)
    # Pair 3 only once pair 2's odometry is out: sent while the node is still busy, it would
    # replace pair 2 (newest wins), which a fixed pause did once on a loaded machine.
    assert harness.wait_for(lambda: len(harness.odom) >= 2, 10)
    send_pair(3)
    harness.settle(3, timeout_s=5)
    # The pair that came before the camera_info is processed once it arrives; the bad one is
    # skipped; the node goes on.
    expected = [int(round(frames[i].stamp_s * 1e9)) for i in (0, 2, 3)]
    assert [_stamp_ns(m) for m in harness.odom] == expected


def test_parameters_are_declared_from_the_config_with_descriptors():
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    try:
        node = StereoVONode(context=context, node_name='stereo_vo_params',
                            parameter_overrides=[Parameter('tracker.max_features', value=123),
                                                 Parameter('filter.pixel_noise_px', value=2)])
        try:
            for name, _, field in Config().items():
                desc = node.describe_parameter(name)
                assert desc.description == field.metadata['doc']
                assert desc.read_only == (not field.metadata['dynamic'])
            assert node.config.tracker.max_features == 123
            assert node.config.filter.pixel_noise_px == 2.0
            rng = node.describe_parameter('tracker.max_features').integer_range[0]
            assert (rng.from_value, rng.to_value) == (8, 5000)
        finally:
            node.destroy_node()
        with pytest.raises(ConfigError, match='tracker.max_featurs'):
            StereoVONode(context=context, node_name='stereo_vo_typo',
                         parameter_overrides=[Parameter('tracker.max_featurs', value=3)])
        with pytest.raises(ConfigError, match='one of'):
            StereoVONode(context=context, node_name='stereo_vo_bad',
                         parameter_overrides=[Parameter('ros.sync', value='nearest')])
    finally:
        rclpy.try_shutdown(context=context)


def test_launch_file_compiles(tmp_path):
    launch = REPO_ROOT / 'launch' / 'stereo_vo.launch.py'
    py_compile.compile(str(launch), cfile=str(tmp_path / 'launch.pyc'), doraise=True)
    assert 'def generate_launch_description' in launch.read_text()


def test_spin_survives_failed_turns_and_stops_on_bugs_and_repeated_failures():
    """A turn that fails as rclpy's take does under load is reported; a bug ends the loop."""

    def spin_with(callback, name, reported=None):
        """Spin a node whose 1 ms timer runs ``callback(context, executor)``; return reports."""
        context = Context()
        rclpy.init(context=context, domain_id=DOMAIN_ID)
        reported = [] if reported is None else reported
        try:
            node = rclpy.create_node(name, context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            node.create_timer(0.001, lambda: callback(context, executor))
            try:
                spin(executor, reported.append)
            finally:
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)
        return reported

    calls = []

    def sometimes_fails(context, executor):
        calls.append(1)
        if len(calls) in (2, 3, 5):
            raise RuntimeError('Unable to convert call argument to Python object')
        if len(calls) == 8:
            context.shutdown()

    reported = spin_with(sometimes_fails, 'spin_failures')  # returns at the context's shutdown
    assert len(calls) == 8 and [str(e) for e in reported] == [
        'Unable to convert call argument to Python object'] * 3
    calls.clear()

    def shuts_the_executor(context, executor):
        calls.append(1)
        if len(calls) == 3:
            executor.shutdown(timeout_sec=0)

    assert spin_with(shuts_the_executor, 'spin_shutdown') == [] and len(calls) == 3

    def always_fails(context, executor):
        raise RuntimeError('take failed')

    reported = []
    with pytest.raises(RuntimeError, match='take failed'):
        spin_with(always_fails, 'spin_always_fails', reported)
    assert len(reported) == MAX_SPIN_FAILURES - 1  # within the window: 50 ms here

    def bug(context, executor):
        raise ZeroDivisionError('a bug in a callback')

    with pytest.raises(ZeroDivisionError):  # not survived: it would fail at every message
        spin_with(bug, 'spin_bug')
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    try:
        vo = StereoVONode(context=context, node_name='stereo_vo_spin')
        try:  # the node's report: an error with its trace in the log and the diagnostics
            try:
                raise RuntimeError('Unable to convert call argument to Python object')
            except RuntimeError as exc:
                vo.report_executor_failure(exc)
            assert vo._problems.errors == 1
            assert 'the executor failed (RuntimeError: Unable' in vo._problems.last_error
            assert 'Traceback' in vo._problems.last_error
        finally:
            vo.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
