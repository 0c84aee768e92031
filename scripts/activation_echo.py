#!/usr/bin/env python3
"""activation_echo: a minimal real ROS 2 node that checks the transport of tissue_msgs over DDS.

It subscribes to tissue_msgs/MuscleActivation on --input and republishes every message unchanged
on --output, except header.frame_id, which it sets to --tag (so a receiver can tell the message
went through this process). Used by the foundation tests (two processes over DDS) and by the
fallback `make demo`. Needs the workspace environment (`. ./env.sh`). Stop it with Ctrl-C.
"""
import argparse
import sys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='activation_echo', description=__doc__.split('\n\n')[0])
    ap.add_argument('--input', default='activation_in', help='topic to read (default %(default)s)')
    ap.add_argument('--output', default='activation_out', help='topic to write (default %(default)s)')
    ap.add_argument('--tag', default='echo', help='header.frame_id of republished messages')
    ap.add_argument('--count', type=int, default=0, help='exit after echoing this many (0 = run until Ctrl-C)')
    args = ap.parse_args(argv)

    import rclpy
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from tissue_msgs.msg import MuscleActivation

    rclpy.init()
    node = rclpy.create_node('activation_echo')
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(MuscleActivation, args.output, qos)
    echoed = 0

    def on_msg(msg):
        nonlocal echoed
        msg.header.frame_id = args.tag
        echoed += 1          # count first: a SIGINT right after publish() must not lose the count
        pub.publish(msg)

    node.create_subscription(MuscleActivation, args.input, on_msg, qos)
    print(f'activation_echo: ready ({args.input} -> {args.output})', flush=True)
    try:
        while rclpy.ok() and not (args.count and echoed >= args.count):
            rclpy.spin_once(node, timeout_sec=0.1)
        pub.wait_for_all_acked(Duration(seconds=2.0))   # reliable: let the last echoes arrive
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as e:
        # SIGINT can land inside a __del__ (Python prints 'Exception ignored' and drops the
        # KeyboardInterrupt) while rclpy's handler still shuts the context down: the next spin_once
        # then raises RCLError ('the given context is not valid'). That is a stop, not a failure.
        if rclpy.ok() or type(e).__name__ != 'RCLError':
            raise
    finally:
        print(f'activation_echo: echoed {echoed} messages', flush=True)
        try:
            node.destroy_node()
        except Exception as e:
            if type(e).__name__ != 'RCLError':
                raise
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
