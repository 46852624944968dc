"""
The node as robots feed it: publisher QoS, large images over Fast DDS, compressed images, TF.

Real rclpy and DDS on loopback. The node runs as a separate process where its transport is
under test (its process chooses its own Fast DDS profile, as ``stereo_vo_node`` does), and
composed in this process elsewhere. Start-up mistakes run the installed entry points as a user
does and check that each gives one line on stderr, a non-zero exit and no traceback.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time

import cv2
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import TransformStamped
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from ros_harness import domain_id, Harness, NODE_START_S, values as _values
from sensor_msgs.msg import Image
from stereo_vo_ros import cli
from stereo_vo_ros.io.rosbag import BagTopics, RosbagSequence, write_stereo_bag
from stereo_vo_ros.ros import conversions as conv
from stereo_vo_ros.ros import dds
from stereo_vo_ros.ros.node import StereoVONode
from stereo_vo_ros.ros.player import BagPlayer, StereoPairPublisher
from stereo_vo_ros.ros.process import node_process, with_pythonpath
from stereo_vo_ros.ros.tf_tree import TransformTree
from stereo_vo_ros.synthetic import render_sequence, SequenceSpec
from tf2_msgs.msg import TFMessage

REPO_ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
#: KITTI's image size: two such mono8 images overflow Fast DDS's 512 kB default segment.
KITTI_SIZE = (1241, 376)
FOCAL_PX, BASELINE_M = 718.856, 0.537
N_PAIRS = 40
#: At most this many pairs (10 Hz) are sent before the counted ones, until one arrives.
WARM_UP_PAIRS = 50
STRICT = bool(os.environ.get('STEREO_VO_STRICT_PACKAGING'))


def _entry_point(name: str) -> Path:
    path = BIN / name
    if not path.exists():
        if STRICT:
            pytest.fail(f'{path} is not installed')
        pytest.skip(f'{path} is not installed (pip install the package to run this test)')
    return path


def _run(cmd: list, env_extra: dict | None = None, timeout_s: float = 120.0):
    env = with_pythonpath(dict(os.environ, ROS_DOMAIN_ID=str(domain_id(31)),
                               **(env_extra or {})), REPO_ROOT)
    return subprocess.run([str(c) for c in cmd], env=env, capture_output=True, text=True,
                          timeout=timeout_s, stdin=subprocess.DEVNULL)


def _one_line_error(proc, *words: str) -> None:
    err = proc.stderr.strip()
    assert proc.returncode != 0, (proc.returncode, proc.stdout, proc.stderr)
    assert 'Traceback' not in proc.stderr + proc.stdout, proc.stderr
    assert len(err.splitlines()) == 1, err
    for word in words:
        assert word in err, (word, err)


# -- start-up mistakes ------------------------------------------------------------------------
@pytest.mark.parametrize('args, words', [
    (['-p', 'tracker.max_features:=-5'], ['tracker.max_features', '[8, 5000]', '-5']),
    (['-p', 'tracker.max_features:=abc'], ['tracker.max_features', 'integer', "'abc'"]),
    (['-p', 'ros.qos:=fast'], ['ros.qos', 'auto', "'fast'"]),
    (['--params-file', '/nonexistent/stereo_vo.yaml'], ['/nonexistent/stereo_vo.yaml',
                                                        'No such file']),
    (['--params-file', 'BAD_YAML'], ['not valid YAML', 'line 3']),
])
def test_node_start_up_mistakes_are_one_line(args, words, tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**:\n  ros__parameters: [\n')
    args = [str(bad) if a == 'BAD_YAML' else a for a in args]
    proc = _run([_entry_point('stereo_vo_node'), '--ros-args', *args])
    _one_line_error(proc, 'stereo_vo_node', *words)


def test_missing_ros_packages_name_the_extra(tmp_path):
    """A pip install without the ROS extra: the node and the demo say what to install."""
    fake = tmp_path / 'no_ros' / 'rclpy'
    fake.mkdir(parents=True)
    (fake / '__init__.py').write_text(
        "raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    env = {'PYTHONPATH': str(fake.parent)}
    for cmd in ([_entry_point('stereo_vo_node')],
                [_entry_point('stereo_vo'), 'demo', '--frames', '3', '--out', tmp_path / 'o']):
        proc = _run(cmd, env)
        _one_line_error(proc, "'rclpy'", 'stereo_vo_ros[ros]', 'ROS 2 Jazzy')
        assert proc.returncode == 2


# -- transport and QoS ------------------------------------------------------------------------
def _textured_pairs(n: int, size: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Blurred noise moving sideways: cheap 1241x376 pairs that KLT can track."""
    w, h = size
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 8 * n + 40)).astype(np.float32),
                            (0, 0), 1.5)
    base = cv2.normalize(base, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return [(base[:, 20 + 4 * i:20 + 4 * i + w].copy(), base[:, 4 * i:4 * i + w].copy())
            for i in range(n)]


def _diag(h: Harness) -> dict:
    ours = [d for d in h.diagnostics if d.status and 'stereo_vo' in d.status[0].name]
    return _values(ours[-1].status[0]) if ours else {}


@pytest.mark.parametrize('reliable', [True, False], ids=['reliable', 'best_effort'])
def test_default_node_receives_every_large_pair_from_either_publisher_qos(reliable):
    """
    Default parameters, a publisher without any DDS profile, 1241x376 pairs at 10 Hz.

    Before ``ros.qos: auto`` and the node's own profile, a best-effort reader lost about a
    quarter of the left images here (Fast DDS's 512 kB shared-memory segment holds one).
    """
    rmem = dds.rmem_max()
    pairs = _textured_pairs(N_PAIRS, KITTI_SIZE)
    h = Harness(domain=domain_id(32))
    try:
        P0 = np.array([[FOCAL_PX, 0, 620.0, 0], [0, FOCAL_PX, 188.0, 0], [0, 0, 1, 0]])
        P1 = P0.copy()
        P1[0, 3] = -FOCAL_PX * BASELINE_M
        pub = StereoPairPublisher(h.node, P0, P1, KITTI_SIZE, depth=10, reliable=reliable)
        env = with_pythonpath(dict(os.environ, ROS_DOMAIN_ID=str(domain_id(32)),
                                   PYTHONUNBUFFERED='1'), REPO_ROOT)
        for var in dds.PROFILE_VARIABLES:  # as on a robot: no profile chosen by the user
            env.pop(var, None)
        log = tempfile.TemporaryFile('w+')
        expected = 'reliable' if reliable else 'best_effort'

        def received() -> int:
            return int(_diag(h).get('pairs_received', 0))

        with node_process([], env=env, stdout=log, text=True):
            assert h.wait_for(pub.connected, NODE_START_S), 'the node did not subscribe'
            # The node's QoS check (every second) re-creates its image readers to match the
            # publisher; then warm-up pairs until one arrives, so that the readers are matched
            # (on a slow machine a fixed 2 s was not always enough: a pair sent before that
            # reaches nobody).
            assert h.wait_for(lambda: _diag(h).get('input_qos') == f'{expected} (ros.qos auto)',
                              10.0), _diag(h)
            for i in range(WARM_UP_PAIRS):
                pub.publish(*pairs[0], 1_000_000_000 + i * 100_000_000)
                if h.wait_for(lambda: received() >= 1, 0.1):
                    break
            assert received() >= 1, 'no warm-up pair reached the node'
            time.sleep(1.2)  # one more diagnostics period: the warm-up counts are final
            before = _diag(h)
            t0 = time.monotonic()
            for i, (left, right) in enumerate(pairs):
                pub.publish(left, right, 1_000_000_000 + (WARM_UP_PAIRS + i) * 100_000_000)
                time.sleep(max(0.0, t0 + (i + 1) * 0.1 - time.monotonic()))
            h.wait_for(lambda: received() >= int(before['pairs_received']) + N_PAIRS, 5.0)
            time.sleep(1.2)  # one more diagnostics period
            values = _diag(h)
    finally:
        h.close()
    log.seek(0)
    out = log.read()
    log.close()
    assert 'Traceback' not in out, out

    def counted(key: str) -> int:  # during the counted pairs, not the warm-up
        return int(values[key]) - int(before[key])

    assert counted('pairs_received') == N_PAIRS, (before, values, out)
    assert counted('images_without_partner_left') + counted('images_without_partner_right') \
        == 0, (before, values)
    assert values['input_qos'] == f'{expected} (ros.qos auto)', values
    if rmem is not None and rmem >= dds.MIN_RMEM_BYTES:
        assert f'Fast DDS profile {dds.config_path(dds.NODE_PROFILE)}' in out, out
    else:  # the kernel caps UDP buffers too low: the defaults are kept, and it says why
        assert 'Fast DDS defaults kept' in out, out


def test_choose_node_profile_respects_the_user_and_the_kernel():
    path, _ = dds.choose_node_profile({}, 16 << 20)
    assert path == str(dds.config_path(dds.NODE_PROFILE)) and Path(path).is_file()
    assert dds.choose_node_profile({'FASTRTPS_DEFAULT_PROFILES_FILE': '/x.xml'}, 16 << 20)[0] \
        is None
    assert dds.choose_node_profile({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}, 16 << 20)[0] \
        is None
    path, reason = dds.choose_node_profile({}, 212992)
    assert path is None and 'net.core.rmem_max' in reason and dds.PUBLISHER_PROFILE in reason
    env = {'FASTRTPS_DEFAULT_PROFILES_FILE': ''}  # the launch file's default dds_profile
    dds.apply_node_profile(env)  # the node's profile, or none at all: never an empty path
    assert env.get('FASTRTPS_DEFAULT_PROFILES_FILE') in (None,
                                                         str(dds.config_path(dds.NODE_PROFILE)))


def _composed(h: Harness, **params) -> StereoVONode:
    overrides = [Parameter('use_sim_time', value=False)]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    return h.add(StereoVONode(context=h.context, parameter_overrides=overrides))


def test_auto_qos_follows_publishers_that_come_later():
    h = Harness(domain=domain_id(33))
    try:
        node = _composed(h)
        assert node.image_reliability == 'best_effort'  # no publisher yet: matches any
        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        best = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        pubs = [h.node.create_publisher(Image, t, reliable)
                for t in ('/left/image_rect', '/right/image_rect')]
        assert h.wait_for(lambda: node.image_reliability == 'reliable', 10.0)
        h.destroy(*pubs)
        pubs = [h.node.create_publisher(Image, t, best)
                for t in ('/left/image_rect', '/right/image_rect')]
        # A best-effort writer: a reliable reader would receive nothing. Back to best effort.
        assert h.wait_for(lambda: node.image_reliability == 'best_effort', 10.0)

        def logged() -> bool:
            logs = ' '.join(h.log_lines('stereo_vo'))
            return 'image subscriptions now reliable' in logs and \
                'image subscriptions now best_effort' in logs
        # /rosout can lag the switch by seconds on a loaded machine (a fresh-clone CI run
        # printed both lines on stderr and had neither on /rosout after 5 s).
        assert h.wait_for(logged, 20.0), h.log_lines('stereo_vo')
    finally:
        h.close()


def test_fixed_reliable_qos_warns_about_a_best_effort_publisher():
    h = Harness(domain=domain_id(34))
    try:
        _composed(h, **{'ros.qos': 'reliable'})
        best = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        h.node.create_publisher(Image, '/left/image_rect', best)
        assert h.wait_for(lambda: any('nothing is received from it' in m for m in
                                      h.log_lines('stereo_vo')), 10.0)
    finally:
        h.close()


def test_images_without_partner_are_explained_once_with_rate_and_fixes():
    """Only right images arrive: one throttled warning saying what, how often and the fixes."""
    h = Harness(domain=domain_id(35))
    try:
        node = _composed(h)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        pub = h.node.create_publisher(Image, '/right/image_rect', qos)
        left_pub = h.node.create_publisher(Image, '/left/image_rect', qos)
        assert h.wait_for(lambda: pub.get_subscription_count() == 1, 10.0)
        img = np.full((48, 64), 100, np.uint8)
        for i in range(12):
            stamp = conv.time_from_nanoseconds(10**9 + i * 10**8)
            pub.publish(conv.image_from_numpy(img, 'mono8', stamp, 'cam_r'))
            if i % 3 == 0:  # a left image now and then: the rights in between lose theirs
                left_pub.publish(conv.image_from_numpy(img, 'mono8', stamp, 'cam_l'))
            time.sleep(0.02)
        assert h.wait_for(lambda: node.partner_loss()['right'] >= 6, 10.0), \
            node.partner_loss()
        warnings = [m for m in h.log_lines('stereo_vo') if 'without their partner' in m]
        assert len(warnings) == 1, warnings  # throttled: one line, not one per image
        text = warnings[0]
        assert 'right images' in text and 'per second' in text and '%' in text, text
        assert 'ros.qos' in text and 'FASTRTPS_DEFAULT_PROFILES_FILE=' in text, text
        assert dds.PUBLISHER_PROFILE in text and dds.NODE_PROFILE in text, text
        values = _values(node.diagnostics())
        assert int(values['images_without_partner_right']) >= 6, values
        assert float(values['images_without_partner_pct']) > 30.0, values
        assert node.diagnostics().level == DiagnosticStatus.WARN
    finally:
        h.close()


# -- compressed images ------------------------------------------------------------------------
@pytest.fixture(scope='module')
def compressed_bag(tmp_path_factory):
    """Write a 30-pair demo render as a jpeg (quality 90) bag, without raw image topics."""
    spec = SequenceSpec.preset('demo', n_frames=30, start_time_s=50.0)
    frames = list(render_sequence(spec))
    calib = spec.calibration()
    path = tmp_path_factory.mktemp('bags') / 'jpeg'
    write_stereo_bag(path, [f.stereo_frame(calib) for f in frames], calib,
                     [f.T_world_cam for f in frames], encoding='jpeg',
                     topics=BagTopics(transport='compressed'))
    return path


def test_offline_run_reads_compressed_topics_and_says_so(compressed_bag, tmp_path, caplog):
    caplog.set_level('INFO')
    out = tmp_path / 'poses.txt'
    assert cli.main(['run', str(compressed_bag), '--poses', str(out), '-q']) == 0
    assert any('reading the compressed ones' in r.getMessage() for r in caplog.records)
    poses = np.loadtxt(out).reshape(-1, 3, 4)
    assert len(poses) == 30 and poses[-1, 2, 3] > 3.0  # 30 poses, drove forward (z)
    seq = RosbagSequence(compressed_bag)
    assert seq.topics.transport == 'compressed' and len(seq) == 30


def test_compressed_bag_replayed_into_the_node(compressed_bag):
    """ros.image_transport compressed: every pair of a jpeg bag becomes odometry."""
    h = Harness(domain=domain_id(36))
    try:
        tfs: list = []
        h.node.create_subscription(TFMessage, '/tf', tfs.append, 100)
        node = _composed(h, **{'ros.image_transport': 'compressed'})
        topics = ('/left/image_rect/compressed', '/right/image_rect/compressed',
                  '/left/camera_info', '/right/camera_info')
        player = BagPlayer(h.node, compressed_bag, topics=topics, rate=None)
        assert player.wait_for_subscribers(20.0)
        # ros.qos auto turns the image subscriptions reliable within a second of seeing the
        # player's writers, re-creating them: replaying before that could lose images.
        assert h.wait_for(lambda: node.image_reliability == 'reliable', 10.0)
        assert player.wait_for_subscribers(20.0)
        time.sleep(0.5)

        def pace(topic, stamp_ns, msg) -> None:  # one pair in flight: no newest-wins drop
            if topic.endswith('right/image_rect/compressed'):
                h.wait_for(lambda: bool(h.odom) and
                           conv.nanoseconds_from_time(h.odom[-1].header.stamp) >= stamp_ns, 10)

        player.play(on_message=pace)
        h.settle(30)
        # Each transform follows its odometry on /tf: wait for the last one before stopping.
        last = conv.nanoseconds_from_time(h.odom[-1].header.stamp)
        assert h.wait_for(lambda: any(conv.nanoseconds_from_time(t.header.stamp) == last
                                      for m in list(tfs) for t in m.transforms), 10.0)
        values = _values(node.diagnostics())
    finally:
        h.close()
    assert len(h.odom) == 30
    assert values['image_transport'] == 'compressed' and float(values['image_decode_ms']) > 0
    assert h.odom[-1].pose.pose.position.x > 3.0  # drove forward (REP-103 x)
    assert {conv.nanoseconds_from_time(t.header.stamp) for m in tfs for t in m.transforms} == \
        {conv.nanoseconds_from_time(o.header.stamp) for o in h.odom}


# -- TF ---------------------------------------------------------------------------------------
def test_transform_tree_looks_up_chains_both_ways():
    tree = TransformTree()
    A = conv.transform_from_xyz_rpy([1, 0, 0.5], [0, 0, 90])
    B = conv.transform_from_xyz_rpy([0, 0.1, 0], [-90, 0, -90])
    C = conv.transform_from_xyz_rpy([0, 0, 1], [0, 10, 0])
    tree.add('base_link', 'camera_link', A)
    tree.add('camera_link', 'camera_optical', B)
    tree.add('/base_link', 'imu', C)
    assert np.allclose(tree.lookup('base_link', 'camera_optical'), A @ B)
    assert np.allclose(tree.lookup('camera_optical', 'base_link'), np.linalg.inv(A @ B))
    assert np.allclose(tree.lookup('imu', 'camera_optical'), np.linalg.inv(C) @ A @ B)
    with pytest.raises(LookupError, match='known frames'):
        tree.lookup('base_link', 'elsewhere')


def test_camera_mounting_comes_from_tf_static():
    """The base <- camera transform published on /tf_static is the one the node uses."""
    h = Harness(domain=domain_id(37))
    try:
        static = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub = h.node.create_publisher(TFMessage, '/tf_static', static)
        T_base_link = conv.transform_from_xyz_rpy([1.2, 0.0, 1.6], [0, 5, 0])
        T_link_opt = conv.transform_from_xyz_rpy([0, 0, 0], [-90, 0, -90])
        msgs = []
        for parent, child, T in (('base_link', 'camera_link', T_base_link),
                                 ('camera_link', 'camera_left_optical', T_link_opt)):
            tf = TransformStamped()
            tf.header.frame_id, tf.child_frame_id = parent, child
            q = conv.quaternion_from_rotation(T[:3, :3])
            tf.transform.translation.x, tf.transform.translation.y, \
                tf.transform.translation.z = (float(v) for v in T[:3, 3])
            (tf.transform.rotation.x, tf.transform.rotation.y, tf.transform.rotation.z,
             tf.transform.rotation.w) = (float(v) for v in q)
            msgs.append(tf)
        pub.publish(TFMessage(transforms=msgs))  # latched: the node gets it when it comes
        node = _composed(h)
        assert h.wait_for(lambda: len(node._tf_listener.tree) == 2, 10.0)
        T = node._base_from_camera('camera_left_optical')
        assert np.allclose(T, T_base_link @ T_link_opt, atol=1e-9)
        assert h.wait_for(lambda: any('from TF' in m for m in h.log_lines('stereo_vo')), 5.0)
    finally:
        h.close()
