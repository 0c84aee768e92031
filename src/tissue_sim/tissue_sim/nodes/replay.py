"""`replay` node: plays an MCAP file (or a split run folder) back on its original topics.

    replay runs/2026-11-22T04-00-00/run.mcap                # original timing
    replay run.mcap --rate 0.5 --loop --start 2.0 --topics /tissue/state /tissue/topology

Messages are published as the recorded bytes, on their recorded topics and types, spaced by their
recorded log times / ``rate``. /clock is published from the recorded sim time (the header stamp of
/tissue/state, else of /clock when recorded) so nodes with use_sim_time follow the replay. Topics
recorded once (/tissue/topology) are published transient-local. Read with the project's reader:
a recording cut short by a killed recorder plays up to its last complete chunk.
"""
from __future__ import annotations

import argparse
import time

from rclpy.node import Node

from ..core import mcapio
from ..core.cdr import CdrReader
from ..errors import ArgumentParser
from ..ros.common import TOPIC_CLOCK, TOPIC_MARKERS, TOPIC_TOPOLOGY, OwnParticipant, qos_latched, qos_stream
from ..ros.common import main as node_main


def build_parser():
    p = ArgumentParser(prog='replay', description=__doc__.split('\n')[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split('\n', 2)[2])
    p.add_argument('input', help='.mcap file or a folder of split .mcap files')
    p.add_argument('--rate', type=float, default=1.0, help='playback speed (default 1 = original timing)')
    p.add_argument('--loop', action='store_true', help='start again at the end')
    p.add_argument('--start', type=float, default=0.0, help='skip the first START seconds of the recording')
    p.add_argument('--topics', nargs='*', default=None, help='only these topics')
    p.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    p.add_argument('--wait-subscribers', type=float, default=0.0,
                   help='wait up to N s for a subscriber on each replayed topic (/clock not counted) before playing')
    return p


def stamp_of(data) -> int | None:
    """Header stamp [ns] of a message that starts with std_msgs/Header (or a Clock), else None."""
    try:
        r = CdrReader(data)
        sec, nsec = r.int32(), r.uint32()
        return sec * 1_000_000_000 + nsec
    except Exception:
        return None


class Replay(Node):
    """Publishes a recording's messages on their topics; ``run()`` plays it (instead of spinning)."""

    def __init__(self, args):
        from rosgraph_msgs.msg import Clock
        from ..ros.common import get_message
        if not (0.0 < args.rate <= 1000.0):
            raise ValueError(f'--rate {args.rate}: must be in (0, 1000]')
        if args.start < 0:
            raise ValueError('--start must not be negative')
        self.a = args
        summary = mcapio.scan(args.input)
        if summary.truncated:
            print(f'replay: {args.input} was cut short (recorder killed?): playing up to its last complete chunk',
                  flush=True)
        topics = summary.topics if args.topics is None else {t: summary.topics[t] for t in args.topics if t in summary.topics}
        missing = set(args.topics or ()) - set(topics)
        if missing:
            raise ValueError(f'{args.input}: no topic {", ".join(sorted(missing))}; it has {", ".join(sorted(summary.topics))}')
        if not summary.counts:
            raise ValueError(f'{args.input}: no messages')
        super().__init__('replay')
        self.pubs = {}
        # the full-mesh markers from a participant of their own, as the simulator sends them (ros.common.OwnParticipant)
        self.markers_participant = OwnParticipant(self, 'markers') if TOPIC_MARKERS in topics else None
        for t, typ in topics.items():
            if t == TOPIC_CLOCK and not args.no_clock:
                continue
            by = self.markers_participant if t == TOPIC_MARKERS else self
            self.pubs[t] = by.create_publisher(get_message(typ), t, self._replay_qos(summary, t))
        self.Clock = Clock
        self.pub_clock = None if args.no_clock else self.create_publisher(Clock, TOPIC_CLOCK, qos_stream(1))
        self.start_ns = summary.start_ns
        self.clock_source = '/tissue/state' if '/tissue/state' in summary.counts else (
            TOPIC_CLOCK if TOPIC_CLOCK in summary.counts else None)
        self.published = 0
        print(f'replay: {sum(summary.counts.values())} messages on {len(self.pubs)} topics, '
              f'{(summary.end_ns - summary.start_ns) * 1e-9:.2f} s', flush=True)

    @staticmethod
    def _replay_qos(summary, topic):
        """Offer what the recording's publishers offered (its channel's ``offered_qos_profiles``, as
        ``ros2 bag play`` does): transient local when every recorded publisher was, so late
        subscribers still get the topology, /tf_static, /robot_description; else a reliable stream.
        A recording without that metadata: the topology latched, the rest streamed."""
        meta = summary.channel_metadata.get(topic, {})
        try:
            offered = mcapio.parse_qos_yaml(meta.get('offered_qos_profiles', ''))
        except mcapio.McapIOError:
            offered = []
        if offered:
            latched = all(q.durability == 'transient_local' for q in offered)
        else:
            latched = topic == TOPIC_TOPOLOGY
        return qos_latched() if latched else qos_stream(100)

    def destroy_node(self):
        if self.markers_participant is not None:
            self.markers_participant.close()
        return super().destroy_node()

    def wait(self, timeout):
        """Up to timeout s until every replayed topic has a subscriber. Not /clock, which the replay derives: a node
        without use_sim_time never subscribes to it, and one with it follows from the next tick."""
        import rclpy
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if all(p.get_subscription_count() > 0 for p in self.pubs.values()):
                return
            rclpy.spin_once(self, timeout_sec=0.05)

    def play_once(self):
        import rclpy
        a = self.a
        skip_until = self.start_ns + int(a.start * 1e9)
        wall0 = None
        for m in mcapio.iter_messages(a.input, list(self.pubs) + ([TOPIC_CLOCK] if self.clock_source == TOPIC_CLOCK else [])):
            if m.log_time < skip_until and m.topic != TOPIC_TOPOLOGY:
                continue
            if wall0 is None:
                wall0, log0 = time.monotonic(), max(m.log_time, skip_until)
            due = wall0 + (m.log_time - log0) * 1e-9 / a.rate
            while True:
                left = due - time.monotonic()
                if left <= 0:
                    break
                rclpy.spin_once(self, timeout_sec=min(left, 0.05))
                if not rclpy.ok():
                    return False
            if m.topic == self.clock_source and self.pub_clock is not None:
                ns = stamp_of(m.data)
                if ns is not None:
                    c = self.Clock()
                    c.clock.sec, c.clock.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
                    self.pub_clock.publish(c)
            pub = self.pubs.get(m.topic)
            if pub is not None:
                pub.publish(m.data)
                self.published += 1
        return True

    def run(self):
        if self.a.wait_subscribers > 0:
            self.wait(self.a.wait_subscribers)
        while self.play_once() and self.a.loop:
            pass
        print(f'replay: published {self.published} messages', flush=True)
        time.sleep(0.5)            # let reliable publishers deliver the tail


def main(argv=None):
    return node_main(Replay, build_parser(), argv)


if __name__ == '__main__':
    raise SystemExit(main())
