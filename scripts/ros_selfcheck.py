#!/usr/bin/env python3
"""ros_selfcheck: prove the ROS 2 set-up works end to end with two real nodes over DDS.

Starts scripts/activation_echo.py as a separate process, publishes a sweep of
tissue_msgs/MuscleActivation from this process, waits until the echo's subscription has matched
(no blind sleeps), and prints every message that came back through the other process, with the
round-trip latency. Runs in its own ROS_DOMAIN_ID (default: derived from the pid) with
localhost-only discovery. Needs the workspace environment (`. ./env.sh`, done by `make demo`).
Exit status 0 only if every message came back unchanged.
"""
import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='ros_selfcheck', description=__doc__.split('\n\n')[0])
    ap.add_argument('--count', type=int, default=10, help='messages to send (default %(default)s)')
    ap.add_argument('--domain', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: 1 + pid %% 101)')
    ap.add_argument('--timeout', type=float, default=30.0, help='seconds to wait for discovery/replies')
    args = ap.parse_args(argv)
    if args.count < 1:
        ap.error('--count must be at least 1')
    domain = args.domain if args.domain is not None else 1 + os.getpid() % 101
    if not (0 <= domain <= 101 or 215 <= domain <= 232):
        ap.error(f'--domain {domain}: use 0-101 or 215-232')
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    os.environ.pop('ROS_LOCALHOST_ONLY', None)

    try:
        import rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from tissue_msgs.msg import MuscleActivation
    except ImportError as exc:
        print(f'ros_selfcheck: error: {exc}; run `make setup` and `. ./env.sh` first', file=sys.stderr)
        return 2

    echo = subprocess.Popen([sys.executable, str(HERE / 'activation_echo.py'), '--tag', 'via-echo-process'],
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))
    rclpy.init()
    node = rclpy.create_node('ros_selfcheck')
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(MuscleActivation, 'activation_in', qos)
    got = []
    node.create_subscription(MuscleActivation, 'activation_out',
                             lambda m: got.append((time.monotonic(), m)), qos)
    ok = False
    try:
        t0 = time.monotonic()
        print(f'ros_selfcheck: domain {domain}, echo process pid {echo.pid}; waiting for discovery')
        while pub.get_subscription_count() < 1 or node.count_publishers('activation_out') < 1:
            if time.monotonic() - t0 > args.timeout or echo.poll() is not None:
                print('ros_selfcheck: error: the echo node was not discovered', file=sys.stderr)
                return 1
            rclpy.spin_once(node, timeout_sec=0.05)
        print(f'ros_selfcheck: matched after {time.monotonic() - t0:.2f} s')
        names = ['rectus_femoris', 'vastus_lateralis', 'biceps_femoris_lh']
        sent = {}
        for i in range(args.count):
            a = i / max(args.count - 1, 1)
            msg = MuscleActivation(muscle_names=names, activations=[a, 1.0 - a, 0.5 * a])
            msg.header.stamp.sec = i
            sent[i] = (time.monotonic(), list(msg.activations))
            pub.publish(msg)
        t1 = time.monotonic()
        while len(got) < args.count and time.monotonic() - t1 < args.timeout:
            rclpy.spin_once(node, timeout_sec=0.05)
        print(f'{"seq":>4} {"frame_id":>18} {"latency ms":>11}  ' + '  '.join(f'{n:>18}' for n in names))
        bad = 0
        for t, m in got:
            i = m.header.stamp.sec
            ts, acts = sent[i]
            same = all(abs(x - y) < 1e-6 for x, y in zip(acts, m.activations)) and list(m.muscle_names) == names
            bad += not same
            print(f'{i:>4} {m.header.frame_id:>18} {1e3 * (t - ts):>11.2f}  '
                  + '  '.join(f'{x:>18.3f}' for x in m.activations) + ('' if same else '  CHANGED'))
        ok = len(got) == args.count and bad == 0
        print(f'ros_selfcheck: {len(got)}/{args.count} messages came back through the other process'
              + ('' if ok else ' -- FAILED'))
    finally:
        node.destroy_node()
        rclpy.shutdown()
        echo.send_signal(signal.SIGINT)
        try:
            echo.wait(10)
        except subprocess.TimeoutExpired:
            echo.kill()
            echo.wait()
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
