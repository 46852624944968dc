"""
Long-run benchmark of the ROS 2 node: memory stays flat and the path bounded over 20,000 pairs.

The node runs as a separate process (``python -m stereo_vo_ros.ros.node`` on this checkout, or
the installed ``stereo_vo_node`` with ``--installed``) with reliable QoS and
``ros.path_max_length`` set, on its own ROS_DOMAIN_ID. This process publishes rendered
synthetic stereo pairs (the demo city preset at ``--width`` x ``--height``, played forwards
then backwards so the scene never jumps, stamps advancing 0.1 s per pair) with camera_info,
keeping at most ``--window`` pairs in flight, and checks every odometry message (finite
values) and every path message (length).

Prints, every ``--report-every`` pairs: pairs sent, odometry received, pairs/s over the
interval, the node's resident memory (VmRSS, MB), the path length, and the node's dropped
pairs and processing time from /diagnostics. Then a summary: overall pairs/s, the memory
growth over the second half of the run (MB per 1,000 pairs, from a linear fit), the longest
path, and the warnings and errors the node logged.

Usage::

    python benchmarks/bench_long_run.py [--frames 20000] [--width 320 --height 96]
        [--path-max 1000] [--report-every 1000] [--window 2] [--installed]
"""

from __future__ import annotations

import argparse
import collections
import os
from pathlib import Path
import sys
import tempfile
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path as PathMsg
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo_vo_ros.ros.player import StereoPairPublisher  # noqa: E402
from stereo_vo_ros.ros.process import (  # noqa: E402
    spinning, start_node, stop_node, with_pythonpath)
from stereo_vo_ros.synthetic import render_sequence, SequenceSpec  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
DOMAIN_ID = 1 + (os.getpid() * 17 + 11) % 200


def rss_mb(pid: int) -> float:
    """Return the resident memory (VmRSS) of a process in MB."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


class Feeder(Node):
    """Publishes the pairs; counts and checks the odometry, path and diagnostics."""

    def __init__(self, context: Context, frames, P0, P1) -> None:
        super().__init__('bench_long_run', context=context)
        h, w = frames[0].left.shape
        self.pairs = StereoPairPublisher(self, P0, P1, (w, h))
        self.frames = frames
        self.order = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
        self.odom_count = 0
        self.non_finite = 0
        self.path_len = 0
        self.path_max_seen = 0
        self.diag: dict[str, str] = {}
        self.changed = threading.Condition()
        self.create_subscription(Odometry, 'odom', self._on_odom, 100)
        self.create_subscription(PathMsg, 'path', self._on_path, 2)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def _on_odom(self, msg: Odometry) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        finite = np.all(np.isfinite([p.x, p.y, p.z, q.x, q.y, q.z, q.w,
                                     *msg.pose.covariance, *msg.twist.covariance]))
        with self.changed:
            self.odom_count += 1
            self.non_finite += 0 if finite else 1
            self.changed.notify_all()

    def _on_path(self, msg: PathMsg) -> None:
        self.path_len = len(msg.poses)
        self.path_max_seen = max(self.path_max_seen, self.path_len)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if 'stereo odometry' in status.name:
                self.diag = {kv.key: kv.value for kv in status.values}

    def send(self, k: int) -> None:
        """Publish pair ``k`` (camera_info first)."""
        f = self.frames[self.order[k % len(self.order)]]
        self.pairs.publish(f.left, f.right, 1_000_000_000 + k * 100_000_000)

    def wait_odometry(self, count: int, timeout_s: float) -> bool:
        """Wait until ``count`` odometry messages arrived (False on timeout)."""
        with self.changed:
            return self.changed.wait_for(lambda: self.odom_count >= count, timeout_s)


def main() -> int:
    """Run the benchmark and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--frames', type=int, default=20000)
    parser.add_argument('--width', type=int, default=320)
    parser.add_argument('--height', type=int, default=96)
    parser.add_argument('--path-max', type=int, default=1000)
    parser.add_argument('--report-every', type=int, default=1000)
    parser.add_argument('--window', type=int, default=2)
    parser.add_argument('--installed', action='store_true',
                        help='run the installed stereo_vo_node instead of this checkout')
    args = parser.parse_args()

    spec = SequenceSpec.preset('demo', n_frames=60, width=args.width, height=args.height,
                               turns=False)
    frames = list(render_sequence(spec))
    P0, P1 = spec.projections()
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1')
    if not args.installed:
        env = with_pythonpath(env, REPO_ROOT)
    log = tempfile.NamedTemporaryFile('w+', prefix='bench_long_run_node_', suffix='.log',
                                      delete=False)
    proc = start_node(['-p', 'ros.qos:=reliable', '-p', f'ros.path_max_length:={args.path_max}'],
                      env=env, stdout=log)
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    feeder = Feeder(context, frames, P0, P1)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(feeder)
    spin = spinning(executor)
    spin.__enter__()
    samples = []  # (pairs sent, node RSS MB)
    stalls = 0
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (
                feeder.pairs.connected() and
                feeder.count_publishers('/odom') and feeder.count_publishers('/path')):
            time.sleep(0.05)
        time.sleep(1.0)
        print(f'node: {" ".join(proc.args)} (pid {proc.pid}, ROS_DOMAIN_ID={DOMAIN_ID}, log '
              f'{log.name}); {args.frames} pairs of {args.width}x{args.height} mono8, '
              f'ros.path_max_length={args.path_max}, at most {args.window} in flight')
        print(f'{"pairs":>7} {"odom":>7} {"pairs/s":>8} {"node RSS MB":>12} {"path":>6} '
              f'{"dropped":>8} {"proc ms":>8}')
        t_start = t_last = time.perf_counter()
        for k in range(args.frames):
            feeder.send(k)
            # The node may drop a pair (newest wins) or a message may be lost: after a
            # generous timeout carry on, owing that pair.
            if not feeder.wait_odometry(k + 2 - args.window - stalls, 2.0):
                stalls = k + 2 - args.window - feeder.odom_count
            if (k + 1) % args.report_every == 0 or k == 0:
                now = time.perf_counter()
                rate = f'{args.report_every / (now - t_last):8.1f}' if k else f'{"-":>8}'
                t_last = now
                mem = rss_mb(proc.pid)
                samples.append((k + 1, mem))
                print(f'{k + 1:7d} {feeder.odom_count:7d} {rate} {mem:12.1f} '
                      f'{feeder.path_len:6d} {feeder.diag.get("dropped_pairs", "?"):>8} '
                      f'{feeder.diag.get("processing_ms", "?"):>8}', flush=True)
        feeder.wait_odometry(args.frames - stalls, 10.0)
        elapsed = time.perf_counter() - t_start
        time.sleep(1.5)  # one more /diagnostics message
        second_half = np.array([s for s in samples if s[0] >= args.frames // 2])
        slope = np.polyfit(second_half[:, 0], second_half[:, 1], 1)[0] * 1000 \
            if len(second_half) >= 2 else float('nan')
        print(f'summary: {args.frames} pairs in {elapsed:.1f} s ({args.frames / elapsed:.1f} '
              f'pairs/s); {feeder.odom_count} odometry messages, {feeder.non_finite} '
              f'non-finite; node RSS {samples[0][1]:.1f} MB after the first pair, '
              f'{min(s[1] for s in samples[1:]):.1f}..{max(s[1] for s in samples[1:]):.1f} MB '
              f'from pair {samples[1][0]} on, {samples[-1][1]:.1f} MB at the end; growth over '
              f'the second half {slope:+.3f} MB per 1000 pairs; longest path '
              f'{feeder.path_max_seen} poses (limit {args.path_max})')
        print('node diagnostics at the end: ' + ', '.join(
            f'{key}={feeder.diag.get(key, "?")}' for key in (
                'tracking_state', 'pairs_received', 'pairs_processed', 'dropped_pairs',
                'path_length', 'restarts', 'warnings', 'errors', 'non_finite_skipped')))
    finally:
        spin.__exit__(None, None, None)
        executor.shutdown()
        feeder.destroy_node()
        rclpy.try_shutdown(context=context)
        stop_node(proc)
        log.seek(0)
        lines = [line.rstrip() for line in log if line.startswith(('[WARN]', '[ERROR]'))]
        kinds = collections.Counter(line.split(']: ', 1)[-1][:90] for line in lines)
        print(f'node log: {len(lines)} warning/error lines' + ''.join(
            f'\n  {n:5d} x {text}' for text, n in kinds.most_common(8)))
        log.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
