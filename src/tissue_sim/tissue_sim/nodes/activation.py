"""`activation` node: publishes tissue_msgs/MuscleActivation profiles on /tissue/activation.

Examples::

    activation --profile paper                       # hamstrings contract from t = 0, others passive
    activation --profile ramp_hold --muscles hamstrings --level 0.8 --rise 0.5 --hold 2 --fall 0.5
    activation --profile sine --muscles quadriceps --frequency 0.5
    activation --profile timeline --timeline config/activation_timeline.yaml
    activation --set biceps_femoris_long=0.7 semitendinosus=0.3     # one message, then exit

Time is simulated time from /clock (use_sim_time is on by default), so a profile is reproducible
whatever the simulator's real-time rate. Muscle and group names come from /tissue/topology
(transient-local) when a profile needs them (groups, 'all', the paper experiment).
"""
from __future__ import annotations

import argparse
import time

from ..ros import profiles
from ..ros.common import TOPIC_ACTIVATION, TOPIC_TOPOLOGY, _is_rcl_error, main_wrapper, parse_args, qos_latched, qos_stream


def build_parser():
    p = argparse.ArgumentParser(prog='activation', description=__doc__.split('\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--profile', choices=profiles.PROFILES, default=None,
                   help='activation profile (default: paper, or set when --set is given)')
    p.add_argument('--muscles', nargs='+', default=None,
                   help="muscle names, group names (e.g. hamstrings) or 'all' (default: hamstrings)")
    p.add_argument('--others', type=float, default=None,
                   help='activation published for every other muscle (paper: 0 = passive; default: not published)')
    p.add_argument('--level', type=float, default=1.0, help='peak activation in [0, 1] (default 1)')
    p.add_argument('--start', type=float, default=0.0, help='start time [s of sim time] (default 0)')
    p.add_argument('--duration', type=float, default=0.0, help='step/paper: length [s], 0 = forever')
    p.add_argument('--rise', type=float, default=1.0, help='ramp, ramp_hold: rise time [s]')
    p.add_argument('--hold', type=float, default=1.0, help='ramp_hold: hold time [s]')
    p.add_argument('--fall', type=float, default=1.0, help='ramp_hold: fall time [s]')
    p.add_argument('--frequency', type=float, default=0.5, help='sine: frequency [Hz]')
    p.add_argument('--timeline', default=None, help='timeline: YAML file of per-muscle knots')
    p.add_argument('--set', nargs='+', default=None, metavar='NAME=VALUE',
                   help='publish these values once and exit')
    p.add_argument('--rate', type=float, default=50.0, help='publish rate [Hz of wall time] (default 50)')
    p.add_argument('--wall-time', action='store_true', help='profile time from the wall clock, not /clock')
    p.add_argument('--topology-timeout', type=float, default=30.0,
                   help='seconds to wait for /tissue/topology when names must be resolved')
    return p


def check_args(a):
    if a.profile is None:
        a.profile = 'set' if a.set else 'paper'
    if a.profile == 'set' and not a.set:
        raise profiles.ProfileError('--profile set needs --set NAME=VALUE ...')
    if not (0.0 <= a.level <= 1.0):
        raise profiles.ProfileError(f'--level {a.level}: must be in [0, 1]')
    if a.others is not None and not (0.0 <= a.others <= 1.0):
        raise profiles.ProfileError(f'--others {a.others}: must be in [0, 1]')
    if a.profile == 'paper' and a.others is None:
        a.others = 0.0
    if a.rate <= 0 or a.rate > 1000:
        raise profiles.ProfileError(f'--rate {a.rate}: must be in (0, 1000] Hz')
    for k in ('rise', 'hold', 'fall', 'duration', 'frequency'):
        if getattr(a, k) < 0:
            raise profiles.ProfileError(f'--{k}: must not be negative')
    if a.profile == 'timeline' and not a.timeline:
        raise profiles.ProfileError('--profile timeline needs --timeline FILE.yaml')
    return a


class ActivationNode:
    """Holds the rclpy node, the resolved muscle list and the profile function."""

    def __init__(self, args):
        import rclpy
        from rclpy.parameter import Parameter
        from tissue_msgs.msg import MuscleActivation, TissueTopology
        self.a = args
        self.Msg = MuscleActivation
        self.node = rclpy.create_node('activation', parameter_overrides=[
            Parameter('use_sim_time', Parameter.Type.BOOL, not args.wall_time)])
        self.pub = self.node.create_publisher(MuscleActivation, TOPIC_ACTIVATION, qos_stream())
        self.timeline = profiles.load_timeline(args.timeline) if args.profile == 'timeline' else None
        self.set_values = profiles.parse_set(args.set) if args.set else None
        self.topology = None
        self._t0_wall = time.monotonic()
        self.names = None           # resolved muscles, with their per-muscle function
        needs_topology = (args.profile in ('paper',) or args.others is not None
                          or (args.muscles and any(not self._literal(m) for m in args.muscles))
                          or (args.profile == 'timeline'))
        if needs_topology:
            self.node.create_subscription(TissueTopology, TOPIC_TOPOLOGY, self._on_topology, qos_latched())
        else:
            self._resolve(None, None)
        self.timer = self.node.create_timer(1.0 / args.rate, self._tick)

    @staticmethod
    def _literal(m):
        return m != 'all' and ('_' in m or m in profiles.PAPER_MUSCLES)

    def _on_topology(self, msg):
        if self.names is None:
            self._resolve(list(msg.muscle_names), list(msg.muscle_groups))

    def _resolve(self, names, groups):
        a = self.a
        fns = {}
        if a.profile == 'set':
            for n in self.set_values:
                if names is not None and n not in names:
                    raise profiles.ProfileError(f'--set: unknown muscle {n!r}; muscles: {", ".join(names)}')
            fns = {n: (lambda t, v=v: v) for n, v in self.set_values.items()}
        elif a.profile == 'timeline':
            for sel, knots in self.timeline.items():
                for n in (profiles.resolve_muscles([sel], names, groups) if names is not None else [sel]):
                    fns[n] = (lambda t, k=knots: profiles.timeline_value(k, t))
        else:
            if a.muscles:
                chosen = profiles.resolve_muscles(a.muscles, names, groups) if names is not None else list(a.muscles)
            else:
                chosen = profiles.paper_muscles(names, groups) if names is not None else list(profiles.PAPER_MUSCLES)
            kw = dict(level=a.level, start=a.start, duration=a.duration, rise=a.rise, hold=a.hold,
                      fall=a.fall, frequency=a.frequency)
            for n in chosen:
                fns[n] = (lambda t, kind=a.profile: profiles.shape(kind, t, **kw))
        if a.others is not None and names is not None:
            for n in names:
                fns.setdefault(n, (lambda t, v=a.others: v))
        self.fns = fns
        self.names = list(fns)
        self.node.get_logger().info(f'profile {a.profile} on {len(self.names)} muscles: {", ".join(self.names)}')

    def now(self) -> float:
        if self.a.wall_time:
            return time.monotonic() - self._t0_wall
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _tick(self):
        if self.names is None:
            if time.monotonic() - self._t0_wall > self.a.topology_timeout:
                raise profiles.ProfileError(f'no {TOPIC_TOPOLOGY} within {self.a.topology_timeout:.0f} s '
                                            '(is the simulator running in this ROS domain?)')
            return
        if self.a.profile == 'set':
            if self.pub.get_subscription_count() == 0:
                return
            self._publish(0.0)
            self.done = True
            raise SystemExit(0)
        self._publish(self.now())

    def _publish(self, t):
        msg = self.Msg()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.muscle_names = self.names
        msg.activations = [float(min(1.0, max(0.0, f(t)))) for f in (self.fns[n] for n in self.names)]
        self.pub.publish(msg)


@main_wrapper
def main(argv=None):
    args, argv = parse_args(build_parser(), argv)
    check_args(args)
    import rclpy
    from rclpy.executors import ExternalShutdownException
    rclpy.init(args=argv)
    n = ActivationNode(args)
    try:
        rclpy.spin(n.node)
    except (KeyboardInterrupt, ExternalShutdownException, SystemExit):
        pass
    except Exception as e:                  # a timer callback racing SIGINT sees the context already shut down
        if rclpy.ok() or not _is_rcl_error(e):
            raise
    finally:
        if args.profile == 'set':
            time.sleep(0.3)          # let the reliable message reach the subscriber before leaving
        try:
            n.node.destroy_node()
        except Exception as e:
            if not _is_rcl_error(e):
                raise
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
