"""`activation` node: publishes tissue_msgs/MuscleActivation profiles on /tissue/activation.

Examples::

    activation                                       # the paper's experiment: the hamstrings contract
                                                     # from t = 0, every other muscle passive
    activation --profile ramp --rise 8               # the model's hamstrings, ramped 0 -> 1 over 8 s
    activation --profile ramp_hold --muscles hamstrings --level 0.8 --rise 0.5 --hold 2 --fall 0.5
    activation --profile sine --muscles quadriceps --frequency 0.5
    activation --profile timeline --timeline config/activation_timeline.yaml
    activation --set biceps_femoris_long_head=0.7 semitendinosus=0.3   # one message, then exit
    activation --profile kick                        # a named motion (knee_flexion, knee_extension, kick,
                                                     # heel_raise, ankle_pump; --level scales, --start shifts it)

Time is simulated time from /clock (use_sim_time is on by default), so a profile is reproducible
whatever the simulator's real-time rate. Muscle names, groups and the default muscles (the
hamstrings of the model) are resolved from /tissue/muscles (transient-local), again whenever a new
model is announced; muscle names with an underscore are published before that. When several
selections name one muscle the most specific sets it (tissue_sim.core.activation).
"""
from __future__ import annotations

import argparse
import time

from rclpy.node import Node

from ..core import activation as act
from ..errors import ArgumentParser
from ..ros.common import TOPIC_ACTIVATION, TOPIC_MUSCLES, qos_latched, qos_stream
from ..ros.common import main as node_main


def build_parser():
    p = ArgumentParser(prog='activation', description=__doc__.split('\n')[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--profile', choices=act.PROFILES, default=None,
                   help='activation profile or named motion (default: paper, or set when --set is given); motions: '
                        + '; '.join(f'{n}: {m.description}' for n, m in act.MOTIONS.items()))
    p.add_argument('--muscles', nargs='+', default=None,
                   help="muscle names, group names (e.g. hamstrings) or 'all' (default: the model's hamstrings)")
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
                   help='seconds to wait for the model\'s muscles (/tissue/muscles) when names must be resolved')
    return p


def check_args(a):
    if a.profile is None:
        a.profile = 'set' if a.set else 'paper'
    if a.profile == 'set' and not a.set:
        raise act.ActivationError('--profile set needs --set NAME=VALUE ...')
    if not (0.0 <= a.level <= 1.0):
        raise act.ActivationError(f'--level {a.level}: must be in [0, 1]')
    if a.others is not None and not (0.0 <= a.others <= 1.0):
        raise act.ActivationError(f'--others {a.others}: must be in [0, 1]')
    if a.profile == 'paper' and a.others is None:
        a.others = 0.0
    if a.rate <= 0 or a.rate > 1000:
        raise act.ActivationError(f'--rate {a.rate}: must be in (0, 1000] Hz')
    for k in ('rise', 'hold', 'fall', 'duration', 'frequency'):
        if getattr(a, k) < 0:
            raise act.ActivationError(f'--{k}: must not be negative')
    if a.profile in act.MOTIONS and a.muscles:
        raise act.ActivationError(f'--profile {a.profile} is a named motion: its muscles are part of it (no --muscles)')
    if a.profile == 'timeline' and not a.timeline:
        raise act.ActivationError('--profile timeline needs --timeline FILE.yaml')
    return a


def literal(selector: str) -> bool:
    """A selector that is taken as a muscle name before the model is known."""
    return selector != 'all' and ('_' in selector or selector in act.PAPER_MUSCLES)


class Activation(Node):
    """Publishes the profile's activations of the muscles it selects at ``--rate`` Hz."""

    def __init__(self, args):
        from rclpy.clock import Clock, ClockType
        from rclpy.parameter import Parameter
        from tissue_msgs.msg import MuscleActivation, MuscleSet
        super().__init__('activation', parameter_overrides=[
            Parameter('use_sim_time', Parameter.Type.BOOL, not args.wall_time)])
        self.a = args
        self.Msg = MuscleActivation
        self.pub = self.create_publisher(MuscleActivation, TOPIC_ACTIVATION, qos_stream())
        self.timeline = act.load_timeline(args.timeline) if args.profile == 'timeline' else None
        self.set_values = act.parse_set(args.set) if args.set else None
        self._t0_wall = time.monotonic()
        self.plan = None            # core.activation.Activations: the muscles published and their a(t)
        self.model = None           # (names, groups) the plan was resolved for
        # the model's muscle names and groups (/tissue/muscles, ~1 kB), not the whole topology (~430 kB: a late reader of
        # a large latched message can hold the simulator's other writes while it is delivered, docs/ros.md)
        self.create_subscription(MuscleSet, TOPIC_MUSCLES, self.on_muscles, qos_latched())
        chosen = list(self.set_values) if args.profile == 'set' else (args.muscles or [])
        if chosen and args.others is None and args.profile != 'timeline' and all(literal(m) for m in chosen):
            self.resolve(None)      # muscle names: published at once, checked when the model's muscles come
        # wall-clock ticks (with use_sim_time the node's own clock stands still while the simulator is paused)
        self.timer = self.create_timer(1.0 / args.rate, self.tick, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def on_muscles(self, msg):
        model = (list(msg.muscle_names), list(msg.muscle_groups))
        if model != self.model:
            self.model = model
            self.resolve(act.Muscles(*model))

    def resolve(self, muscles):
        a = self.a
        entries = act.profile_entries(a.profile, muscles, selectors=a.muscles, others=a.others,
                                      timeline=self.timeline, set_values=self.set_values, level=a.level,
                                      start=a.start, duration=a.duration, rise=a.rise, hold=a.hold, fall=a.fall,
                                      frequency=a.frequency)
        self.plan = act.Activations(entries, muscles)
        self.get_logger().info(f'profile {a.profile} on {len(self.plan.names)} muscles: {", ".join(self.plan.names)}')

    def now(self) -> float:
        if self.a.wall_time:
            return time.monotonic() - self._t0_wall
        return self.get_clock().now().nanoseconds * 1e-9

    def tick(self):
        if self.plan is None:
            if time.monotonic() - self._t0_wall > self.a.topology_timeout:
                raise act.ActivationError(f'no {TOPIC_MUSCLES} within {self.a.topology_timeout:.0f} s '
                                          '(is the simulator running in this ROS domain?)')
            return
        if self.a.profile == 'set':
            if self.pub.get_subscription_count() == 0:
                return
            self.publish(0.0)
            raise SystemExit(0)
        self.publish(self.now())

    def publish(self, t):
        msg = self.Msg()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.muscle_names = self.plan.names
        msg.activations = [float(v) for v in self.plan.values(t)]
        self.pub.publish(msg)

    def on_shutdown(self):
        if self.a.profile == 'set':
            time.sleep(0.3)          # let the reliable message reach the subscriber before leaving


def main(argv=None):
    return node_main(Activation, build_parser(), argv, check=check_args)


if __name__ == '__main__':
    raise SystemExit(main())
