"""
Benchmark of the ROS 2 node: image-to-odometry latency and the highest sustained input rate.

The node runs as a separate process (the installed ``stereo_vo_node`` entry point, or
``python -m stereo_vo_ros.ros.node``) with reliable QoS on its own ROS_DOMAIN_ID; this
process publishes 1241x376 stereo pairs (a KITTI clip of the data folder when present,
otherwise a rendered synthetic city sequence) with camera_info and receives the odometry.

1. Latency: pairs published at ``--latency-rate`` Hz (well below capacity); latency is the
   wall time from publishing the left image to receiving the odometry with its stamp (image
   conversion, DDS transport of two 467 kB images, pairing, processing, odometry transport).
   Prints median, p90 and max (ms), and from /diagnostics the node's processing time and its
   own latency (pair complete -> odometry published).
2. Sustained rate: pairs published at increasing rates for ``--seconds`` each; a rate is
   sustained when at least 97 % of the pairs give odometry (the node drops the others, newest
   wins). Prints, per rate, the odometry rate and the dropped pairs; then the highest
   sustained rate.

Stamps advance by the clip's frame period whatever the publish rate, and the frames are
played forwards then backwards (no jump in the scene), so the odometry keeps tracking.

0. Delivery (``--delivery-pairs N``, default 250): N pairs at ``--delivery-rate`` Hz (10) as a
   camera driver sends them; prints how many gave odometry and the largest difference of the
   node's trajectory from the offline pipeline run on the same pairs.

Targets: median latency <= 30 ms, sustained >= 30 Hz, delivery >= 99 % with the node's default
parameters whatever the publisher's QoS.

Transport options. The node's process chooses its own Fast DDS profile unless one is given
(``config/fastdds_node.xml`` where the kernel allows, see ``stereo_vo_ros/ros/dds.py``);
this process, the image publisher, uses Fast DDS's defaults unless one is given:
``--publisher-profile config/fastdds_large_images.xml`` (16 MB shared-memory segment instead of
512 kB, which two 467 kB images overflow), ``--node-profile XML``, ``--fastdds-profile XML``
(both processes). ``--best-effort`` publishes best effort (default reliable, the ROS default);
``--compressed`` publishes jpeg (quality 90) on ``<topic>/compressed`` and starts the node with
``ros.image_transport:=compressed``; the node's decode time per pair is printed.

Usage::

    python benchmarks/bench_node_latency.py [--data ../shared/data] [--frames 40]
        [--rates 10 15 20 30 40 60] [--seconds 4] [--delivery-pairs 250]
        [--best-effort] [--compressed] [--publisher-profile XML] [--render 1280x720]

``--render WxH`` publishes a rendered city sequence of that size instead of the clip.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import threading
import time

import cv2
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.estimation.camera import StereoCalibration  # noqa: E402
from stereo_vo_ros.io.compressed import compress_grey, grey_from_compressed  # noqa: E402
from stereo_vo_ros.pipeline import StereoOdometry  # noqa: E402
from stereo_vo_ros.records import StereoFrame  # noqa: E402
from stereo_vo_ros.ros import conversions as conv  # noqa: E402
from stereo_vo_ros.ros import dds  # noqa: E402
from stereo_vo_ros.ros.player import StereoPairPublisher  # noqa: E402
from stereo_vo_ros.ros.process import (  # noqa: E402
                                       spinning, start_node, stop_node, with_pythonpath)

REPO_ROOT = Path(__file__).resolve().parents[1]
DOMAIN_ID = 1 + (os.getpid() * 13 + 5) % 200
KITTI_CLIP = 'kitti01_f0000-0050'


#: The read-only clips next to the repository (``../shared/data``), as CI lays them out.
SHARED_DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'


def load_frames(data: Path, n: int, render_size: tuple[int, int] | None = None):
    """
    Return (left list, right list, P0, P1, frame period s).

    The KITTI clip (1241x376) when present and no ``render_size`` (width, height) is asked for,
    else a rendered synthetic city sequence of that size (1241x376 by default).
    """
    clip = data / KITTI_CLIP
    if render_size is None and (clip / 'calib.txt').exists():
        calib = {line.split(':')[0]: np.array(line.split()[1:], float).reshape(3, 4)
                 for line in (clip / 'calib.txt').read_text().splitlines() if line.strip()}
        names = sorted((clip / 'image_0').glob('*.png'))[:n]
        left = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in names]
        right = [cv2.imread(str(clip / 'image_1' / p.name), cv2.IMREAD_GRAYSCALE)
                 for p in names]
        print(f'frames: {len(left)} of {clip} ({left[0].shape[1]}x{left[0].shape[0]})')
        return left, right, calib['P0'], calib['P1'], 0.1
    from stereo_vo_ros.synthetic import render_sequence, SequenceSpec
    size = {} if render_size is None else {'width': render_size[0], 'height': render_size[1]}
    spec = SequenceSpec.preset('urban', n_frames=n, **size)
    frames = list(render_sequence(spec))
    P0, P1 = spec.projections()
    why = 'as asked' if render_size else f'{clip} not found'
    print(f'frames: {n} rendered ({spec.width}x{spec.height}; {why})')
    return [f.left for f in frames], [f.right for f in frames], P0, P1, 1.0 / spec.frame_rate_hz


class Bench(Node):
    """Publishes stereo pairs and records when the odometry of each stamp arrives."""

    def __init__(self, context: Context, left, right, P0, P1, period_s: float,
                 reliable: bool = True, compressed: bool = False) -> None:
        super().__init__('bench_node_latency', context=context)
        h, w = left[0].shape
        self.pairs = StereoPairPublisher(self, P0, P1, (w, h), reliable=reliable,
                                         compressed=compressed)
        self.left, self.right, self.period_ns = left, right, int(period_s * 1e9)
        order = list(range(len(left))) + list(range(len(left) - 2, 0, -1))
        self.order = order
        self.k = 0
        self.stamp_ns = 1_000_000_000
        self.sent: dict[int, float] = {}
        self.sent_index: dict[int, int] = {}
        self.received: dict[int, float] = {}
        self.poses: dict[int, np.ndarray] = {}
        self.decode_ms: list[float] = []
        self.values: dict[str, str] = {}
        self.processing_ms: list[float] = []
        self.node_latency_ms: list[float] = []
        self.pair_gap_ms: list[float] = []
        self.lock = threading.Lock()
        self.create_subscription(Odometry, 'odom', self._on_odom, 100)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def _on_odom(self, msg: Odometry) -> None:
        now = time.perf_counter()
        stamp = conv.nanoseconds_from_time(msg.header.stamp)
        with self.lock:
            self.received[stamp] = now
            self.poses[stamp] = conv.transform_from_pose(msg.pose.pose.position,
                                                         msg.pose.pose.orientation)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if 'image_decode_ms' in values:
                self.values = values
                self.decode_ms.append(float(values['image_decode_ms']))
            if 'processing_ms' in values:
                self.processing_ms.append(float(values['processing_ms']))
            if 'latency_ms' in values:
                self.node_latency_ms.append(float(values['latency_ms']))
            if 'pair_arrival_gap_ms' in values:
                self.pair_gap_ms.append(float(values['pair_arrival_gap_ms']))

    def publish_pair(self) -> int:
        """Publish the next pair (images built beforehand are not reused: fresh messages)."""
        i = self.order[self.k % len(self.order)]
        self.k += 1
        self.stamp_ns += self.period_ns
        t = self.pairs.publish(self.left[i], self.right[i], self.stamp_ns)
        with self.lock:
            self.sent[self.stamp_ns] = t
            self.sent_index[self.stamp_ns] = i
        return self.stamp_ns


def publish_at(bench: Bench, rate_hz: float, seconds: float) -> list[int]:
    """Publish pairs at ``rate_hz`` for ``seconds``; return their stamps."""
    stamps = []
    period = 1.0 / rate_hz
    t0 = time.perf_counter()
    n = int(round(rate_hz * seconds))
    for k in range(n):
        target = t0 + k * period
        delay = target - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        stamps.append(bench.publish_pair())
    return stamps


def offline_difference_m(bench: Bench, stamps: list[int], P0, P1, size,
                         compressed: bool = False) -> float:
    """
    Largest position difference (m) of the node's odometry from the offline pipeline.

    The offline run sees the same pairs (jpeg-coded and decoded when ``compressed``); a pair
    the node dropped (newest wins, when it is busy) makes the two runs differ from there on.
    """
    calib = StereoCalibration.from_projections(np.asarray(P0), np.asarray(P1), *size)

    def seen(img: np.ndarray) -> np.ndarray:
        if not compressed:
            return img
        fmt, data = compress_grey(img, 'jpeg', 90)
        return grey_from_compressed(fmt, data)

    vo = StereoOdometry()
    T_base_cam = conv.transform_from_xyz_rpy([0, 0, 0], [-90, 0, -90])  # the node's default
    worst = 0.0
    for s in stamps:
        i = bench.sent_index[s]
        result = vo.process(StereoFrame(seen(bench.left[i]), seen(bench.right[i]), s * 1e-9,
                                        calib))
        if s in bench.poses:
            T_world_cam = conv.camera_pose_from_base_pose(bench.poses[s], None, T_base_cam)[0]
            worst = max(worst, float(np.linalg.norm(T_world_cam[:3, 3] -
                                                    result.T_world_cam[:3, 3])))
    return worst


def main() -> int:
    """Run the benchmark and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--data', type=Path, default=SHARED_DATA)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--delivery-pairs', type=int, default=250)
    parser.add_argument('--delivery-rate', type=float, default=10.0)
    parser.add_argument('--latency-rate', type=float, default=5.0)
    parser.add_argument('--latency-pairs', type=int, default=60)
    parser.add_argument('--rates', type=float, nargs='*', default=[10, 15, 20, 30, 40, 60])
    parser.add_argument('--seconds', type=float, default=4.0)
    parser.add_argument('--fastdds-profile', type=Path, metavar='XML',
                        help='Fast DDS profile of both processes')
    parser.add_argument('--publisher-profile', type=Path, metavar='XML',
                        help='Fast DDS profile of this (publishing) process, e.g. '
                        'config/fastdds_large_images.xml; default: Fast DDS defaults')
    parser.add_argument('--node-profile', type=Path, metavar='XML',
                        help="Fast DDS profile of the node's process; default: its own choice")
    parser.add_argument('--best-effort', action='store_true',
                        help='publish best effort (default: reliable)')
    parser.add_argument('--compressed', action='store_true',
                        help='publish jpeg (quality 90) on <topic>/compressed')
    parser.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                        help='extra node parameter (repeatable), e.g. ros.qos:=reliable')
    parser.add_argument('--render', metavar='WxH',
                        help='publish a rendered city sequence of this size, e.g. 1280x720, '
                        'instead of the KITTI clip')
    args = parser.parse_args()
    render_size = None
    if args.render:
        try:
            render_size = tuple(int(v) for v in args.render.lower().split('x'))
            if len(render_size) != 2:
                raise ValueError(args.render)
        except ValueError:
            parser.error(f'--render wants WxH, got {args.render!r}')

    left, right, P0, P1, period = load_frames(args.data, args.frames, render_size)
    size = (left[0].shape[1], left[0].shape[0])
    pub_profile = args.publisher_profile or args.fastdds_profile
    node_profile = args.node_profile or args.fastdds_profile
    for var in dds.PROFILE_VARIABLES:  # this process: the given profile or the defaults
        os.environ.pop(var, None)
    node_env = with_pythonpath(dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID)), REPO_ROOT)
    if pub_profile:  # before any participant of this process exists
        os.environ[dds.PROFILE_VARIABLES[0]] = str(pub_profile.resolve())
    if node_profile:
        node_env[dds.PROFILE_VARIABLES[0]] = str(node_profile.resolve())
    extra = [arg for p in args.param for arg in ('-p', p)]
    if args.compressed:
        extra += ['-p', 'ros.image_transport:=compressed']
    proc = start_node([*extra, '--log-level', 'error'], env=node_env)
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    bench = Bench(context, left, right, P0, P1, period, reliable=not args.best_effort,
                  compressed=args.compressed)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(bench)
    spin = spinning(executor)
    spin.__enter__()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (
                bench.pairs.connected() and
                bench.count_publishers('/odom')):
            time.sleep(0.05)
        time.sleep(2.0)
        print(f'node: {" ".join(proc.args)} (ROS_DOMAIN_ID={DOMAIN_ID}); DDS profile of the '
              f'node: {node_profile or "its own choice"}; of the publisher: '
              f'{pub_profile or "Fast DDS defaults"}; publisher '
              f'{"best effort" if args.best_effort else "reliable"}, '
              f'{"jpeg q90" if args.compressed else "raw mono8"} {size[0]}x{size[1]}')

        # 0. delivery at a camera's rate, compared with the offline pipeline
        if args.delivery_pairs:
            stamps = publish_at(bench, args.delivery_rate,
                                args.delivery_pairs / args.delivery_rate)
            time.sleep(2.0)
            with bench.lock:
                got = sum(s in bench.received for s in stamps)
            diff = offline_difference_m(bench, stamps, P0, P1, size, args.compressed)
            v = bench.values
            print(f'delivery at {args.delivery_rate:g} Hz: odometry for {got}/{len(stamps)} '
                  f'pairs ({100.0 * got / len(stamps):.1f} %); in the node: '
                  f'{v.get("pairs_received", "?")} pairs complete, '
                  f'{v.get("dropped_pairs", "?")} dropped while busy (newest wins), images '
                  f'without partner {v.get("images_without_partner_left", "?")} left / '
                  f'{v.get("images_without_partner_right", "?")} right; input QoS '
                  f'{v.get("input_qos", "?")}; processing {v.get("processing_ms", "?")} ms; '
                  f'largest position difference from the offline pipeline on the same pairs '
                  f'{diff * 1e3:.3f} mm')

        # 1. latency well below capacity (the first pairs warm the pipeline up)
        if not args.latency_pairs:
            return 0
        publish_at(bench, args.latency_rate, 2.0)
        stamps = publish_at(bench, args.latency_rate, args.latency_pairs / args.latency_rate)
        time.sleep(1.0)
        with bench.lock:
            lat = np.array([(bench.received[s] - bench.sent[s]) * 1e3 for s in stamps
                            if s in bench.received])
        proc_ms = np.array(bench.processing_ms[-5:]) if bench.processing_ms else np.array([])
        # The diagnostics (1 Hz) of the latency phase: the node's own share of the latency.
        n_diag = int(args.latency_pairs / args.latency_rate)
        node_ms = np.array(bench.node_latency_ms[-n_diag:])
        node_ms = node_ms[np.isfinite(node_ms)]
        print(f'latency publish -> odometry at {args.latency_rate:g} Hz, {size[0]}x{size[1]}, '
              f'{len(lat)}/{len(stamps)} pairs: median {np.median(lat):.1f} ms, '
              f'p90 {np.percentile(lat, 90):.1f} ms, max {lat.max():.1f} ms')
        if proc_ms.size:
            print(f'node processing (diagnostics processing_ms, last samples): '
                  f'{np.median(proc_ms):.1f} ms')
        decode = np.array(bench.decode_ms[-n_diag:])
        decode = decode[np.isfinite(decode)]
        if decode.size:
            print(f'image decoding of a pair in the node (diagnostics image_decode_ms): median '
                  f'{np.median(decode):.2f} ms')
        if node_ms.size:
            print(f'inside the node, pair complete -> odometry published (diagnostics '
                  f'latency_ms, {node_ms.size} samples): median {np.median(node_ms):.1f} ms; '
                  f'the rest is transport and the two executors')
        if bench.pair_gap_ms and np.isfinite(bench.pair_gap_ms[-1]):
            print(f'the two images of a pair arrive {bench.pair_gap_ms[-1]:.1f} ms apart in the '
                  f'node (diagnostics pair_arrival_gap_ms, mean of the last 30 pairs)')

        # 2. sustained input rate
        if not args.rates:
            return 0
        sustained = 0.0
        print(f'{"input Hz":>9} {"odom Hz":>8} {"pairs":>6} {"odom":>6} {"dropped":>8} '
              f'{"median latency ms":>18}')
        for rate in args.rates:
            stamps = publish_at(bench, rate, args.seconds)
            time.sleep(1.0)
            with bench.lock:
                got = [s for s in stamps if s in bench.received]
                lat = [(bench.received[s] - bench.sent[s]) * 1e3 for s in got]
                span = bench.received[got[-1]] - bench.received[got[0]] if len(got) > 1 else 0
            odom_hz = (len(got) - 1) / span if span > 0 else 0.0
            ok = len(got) >= 0.97 * len(stamps)
            if ok:
                sustained = max(sustained, rate)
            print(f'{rate:9.1f} {odom_hz:8.1f} {len(stamps):6d} {len(got):6d} '
                  f'{len(stamps) - len(got):8d} {np.median(lat) if lat else float("nan"):18.1f}'
                  f'{"" if ok else "  (not sustained)"}')
        print(f'highest sustained input rate: {sustained:g} Hz (>= 97 % of the pairs give '
              f'odometry)')
    finally:
        spin.__exit__(None, None, None)
        executor.shutdown()
        bench.destroy_node()
        rclpy.try_shutdown(context=context)
        stop_node(proc)
    return 0


if __name__ == '__main__':
    sys.exit(main())
