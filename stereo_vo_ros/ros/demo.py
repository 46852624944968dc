"""
The main job end to end: synthetic stereo bag -> ROS 2 node -> trajectory, metrics and plot.

``stereo_vo demo --out DIR``:

1. renders the ``demo`` preset of the synthetic renderer into a rosbag2 (``DIR/bag``);
2. starts ``stereo_vo_node`` as a separate process (its installed entry point, or
   ``python -m stereo_vo_ros.ros.node``) with ``use_sim_time`` on a private ROS domain;
3. replays the bag into it with the bag player (real rclpy publishers, ``/clock``), one stereo
   pair at a time: the next pair is published once the odometry of the previous one arrived
   (or after a timeout), so no pair is dropped however slow the machine is;
4. collects ``odom``, converts it back to the left camera frame and writes ``DIR/poses.txt``
   (KITTI), ``DIR/poses_tum.txt`` (TUM), ``DIR/ground_truth.txt``, ``DIR/metrics.json`` and
   ``DIR/trajectory.png``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
import shutil
import threading
import time
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..config import Config, to_yaml
from ..errors import DatasetError
from ..jit import COMPILE_S

NODE_NAME = 'stereo_vo_node'
#: How long the first start of the node after an install takes, compiling the pipeline's
#: kernels before it subscribes (s).
FIRST_START_S = COMPILE_S
#: How long to wait for the node to subscribe, once started (s); a node that exits ends the
#: wait at once.
NODE_START_TIMEOUT_S = 180.0

LOG = logging.getLogger(__name__)


def run_demo(out: Path, frames: int | None = None, preset: str = 'demo',
             config: Config | None = None, timeout_s: float = 110.0,
             per_frame_timeout_s: float = 5.0) -> dict[str, Any]:
    """
    Run the demo and return a JSON-ready summary (``ok``, paths, metrics, counts, wall time).

    Parameters
    ----------
    out : Path
        Output folder (created; its previous demo files are replaced).
    frames : int, optional
        Frames to render (default: the preset's).
    preset : str
        Synthetic preset name.
    config : Config, optional
        Node configuration (default: the defaults).
    timeout_s : float
        Wall-time budget of the replay (s), from when the node has subscribed (its start,
        which compiles the pipeline's kernels the first time, has a budget of its own:
        ``NODE_START_TIMEOUT_S``).
    per_frame_timeout_s : float
        How long to wait for the odometry of one pair before publishing the next (s).

    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from nav_msgs.msg import Odometry

    from ..io import render_to_bag
    from ..io.rosbag import RosbagSequence
    from ..evaluation.metrics import evaluate
    from ..evaluation.plotting import save_report
    from ..synthetic import SequenceSpec
    from ..evaluation.trajectory import write_kitti, write_tum
    from .conversions import (camera_pose_from_base_pose, nanoseconds_from_time,
                              transform_from_xyz_rpy)
    from .player import BagPlayer
    from .process import node_process, spinning

    t_start = time.monotonic()
    config = config or Config()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = SequenceSpec.preset(preset, **({'n_frames': int(frames)} if frames else {}))
    bag = out / 'bag'
    if bag.exists():
        shutil.rmtree(bag)
    render_to_bag(spec, bag)
    t_rendered = time.monotonic()
    seq = RosbagSequence(bag)
    gt = seq.ground_truth
    params = out / 'params.yaml'
    params.write_text(to_yaml(config, node=NODE_NAME))
    ros = config.ros
    image_topics = [ros.left_image_topic, ros.right_image_topic]
    topics = image_topics + [ros.left_info_topic, ros.right_info_topic]

    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
    os.environ['ROS_DOMAIN_ID'] = env['ROS_DOMAIN_ID']
    log_path = out / 'node.log'
    ros_args = ['--params-file', str(params), '-p', 'use_sim_time:=true']
    with open(log_path, 'w') as log, node_process(ros_args, env=env, stdout=log) as proc:
        rclpy.init()
        received: dict[int, Any] = {}
        got = threading.Condition()
        try:
            node = rclpy.create_node('stereo_vo_demo')

            def on_odom(msg: Odometry) -> None:
                with got:
                    received[nanoseconds_from_time(msg.header.stamp)] = msg
                    got.notify_all()
            reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
            node.create_subscription(Odometry, 'odom', on_odom, reliable)
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            with spinning(executor):
                player = BagPlayer(node, bag, topics=topics, rate=None, publish_clock=True)
                LOG.info('waiting for the node to subscribe (its first start after an install '
                         'compiles the kernels of the pipeline: %.0f-%.0f s)', *FIRST_START_S)
                if not player.wait_for_subscribers(NODE_START_TIMEOUT_S, topics=image_topics,
                                                   alive=lambda: proc.poll() is None):
                    if proc.poll() is not None:
                        raise DatasetError(f'the node exited (code {proc.returncode}) before it '
                                           f'subscribed to {image_topics}; see {log_path}')
                    raise DatasetError(f'the node did not subscribe to {image_topics} within '
                                       f'{NODE_START_TIMEOUT_S:.0f} s; see {log_path}')
                # ros.qos auto: the node subscribes reliably once it has seen the player's
                # reliable writers (within a second); replaying before would lose images.
                deadline_qos = time.monotonic() + 10.0
                while time.monotonic() < deadline_qos and not all(
                        info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                        for t in image_topics for info in node.get_subscriptions_info_by_topic(t)):
                    time.sleep(0.05)
                time.sleep(0.5)  # let the node see the publishers (discovery both ways)
                published: dict[int, int] = {}
                deadline = time.monotonic() + timeout_s
                stop = threading.Event()

                def pace(topic: str, stamp_ns: int, msg: Any) -> None:
                    if topic not in image_topics:
                        return
                    key = nanoseconds_from_time(msg.header.stamp)
                    published[key] = published.get(key, 0) + 1
                    if published[key] < 2:
                        return
                    wait_until = min(time.monotonic() + per_frame_timeout_s, deadline)
                    with got:
                        while key not in received and time.monotonic() < wait_until:
                            got.wait(0.05)
                    if time.monotonic() >= deadline:
                        stop.set()
                stats = player.play(stop=stop, on_message=pace)
                with got:  # the last odometry may still be on its way
                    end = time.monotonic() + per_frame_timeout_s
                    while len(received) < len(published) and time.monotonic() < end:
                        got.wait(0.05)
            executor.shutdown(timeout_sec=1.0)
            node.destroy_node()
        finally:
            rclpy.try_shutdown()

    stamps_ns = sorted(received)
    T_base_cam = transform_from_xyz_rpy(ros.base_from_camera_xyz, ros.base_from_camera_rpy_deg)
    poses = []
    for ns in stamps_ns:
        p = received[ns].pose.pose
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([p.orientation.x, p.orientation.y, p.orientation.z,
                                        p.orientation.w]).as_matrix()
        T[:3, 3] = [p.position.x, p.position.y, p.position.z]
        poses.append(camera_pose_from_base_pose(T, None, T_base_cam)[0])
    poses = np.asarray(poses).reshape(-1, 4, 4)
    stamps = np.asarray(stamps_ns, np.float64) * 1e-9
    summary: dict[str, Any] = {
        'ok': False, 'preset': preset, 'frames_rendered': int(spec.n_frames),
        'pairs_published': len([k for k, v in published.items() if v >= 2]),
        'odometry_received': len(poses), 'messages_replayed': stats.messages,
        'node_exit_code': proc.returncode, 'node_log': str(log_path), 'bag': str(bag)}
    if len(poses) >= 2:
        write_kitti(out / 'poses.txt', poses)
        write_tum(out / 'poses_tum.txt', stamps, poses)
        summary['poses'] = str(out / 'poses.txt')
        summary['poses_tum'] = str(out / 'poses_tum.txt')
        if gt is not None:
            gt_stamps = np.asarray(seq.stamps, np.float64)
            idx = np.searchsorted(gt_stamps, stamps - 1e-6)
            idx = np.clip(idx, 0, len(gt) - 1)
            gt_sel = np.asarray(gt)[idx]
            # Both in the frame of the FIRST received camera pose.
            gt_sel = np.linalg.inv(gt_sel[0]) @ gt_sel
            poses_rel = np.linalg.inv(poses[0]) @ poses
            write_kitti(out / 'ground_truth.txt', gt_sel)
            metrics = evaluate(gt_sel, poses_rel)
            summary['metrics'] = metrics
            summary['ground_truth'] = str(out / 'ground_truth.txt')
            (out / 'metrics.json').write_text(_json(metrics))
            summary['metrics_json'] = str(out / 'metrics.json')
            summary['plot'] = str(save_report(out / 'trajectory.png', gt_sel, poses_rel,
                                              title=f'stereo_vo demo ({preset})'))
        summary['ok'] = summary['odometry_received'] >= 0.9 * summary['pairs_published']
    summary['wall_s'] = round(time.monotonic() - t_start, 2)
    summary['render_s'] = round(t_rendered - t_start, 2)
    return summary


def _json(data: dict) -> str:
    import json
    clean = {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
             for k, v in data.items()}
    return json.dumps(clean, indent=2) + '\n'
