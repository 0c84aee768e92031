"""`recorder` node: records topics to MCAP exactly as received (raw CDR, no re-encoding).

    recorder -o runs/today/run.mcap                       # the tissue topics
    recorder -o run.mcap --topics /tissue/markers /tf     # plus any topics named
    recorder -o run.mcap --split-size 500 --split-duration 60
    recorder -o run.mcap --topics /tissue/markers --max-rate /tissue/markers=10   # markers at <= 10 Hz

Default topics: /tissue/state, /tissue/topology, /tissue/activation, /joint_states, /diagnostics
(/tissue/markers only when named: ~7 MB/s). The topics of tissue_sim's nodes (ros.common.TOPIC_TYPES)
and those given as ``/topic:pkg/msg/Type`` are subscribed at start-up, before their publishers
appear: creating a subscription takes 5-200 ms (measured) in the node's one thread, which would
delay, and so gap the log times of, the topics already flowing. Other topics' types are discovered
from the ROS graph. Files: profile ros2, ros2msg schemas, cdr, zstd chunks, a ``tissue_sim``
metadata record (model, parameters, versions, topics); rosbag2 and Foxglove open them. Log times
are the receive time (wall clock, ns), publish times the publisher's DDS source timestamp (as rosbag2
records them: a frame's publish time says when the node sent it, its log time when it arrived here).
SIGINT/SIGTERM finish the file; after SIGKILL the file is
readable up to the last flushed chunk (``--flush`` seconds) by tissue_sim.core.mcapio.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time

from ..core import mcapio
from rclpy.node import Node

from ..errors import ArgumentParser
from ..ros.common import (TISSUE_TOPICS, TOPIC_BONE_MARKERS, TOPIC_MUSCLES, TOPIC_ROBOT_DESCRIPTION, TOPIC_TF_STATIC,
                          TOPIC_TOPOLOGY, TOPIC_TYPES,
                          qos_latched, qos_stream)
from ..ros.common import main as node_main

# published once, transient local
LATCHED = (TOPIC_TOPOLOGY, TOPIC_MUSCLES, TOPIC_TF_STATIC, TOPIC_ROBOT_DESCRIPTION, TOPIC_BONE_MARKERS)


def build_parser():
    p = ArgumentParser(prog='recorder', description=__doc__.split('\n')[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split('\n', 2)[2])
    p.add_argument('-o', '--output', required=True, help='output .mcap path (parent folders are created)')
    p.add_argument('--topics', nargs='*', default=[], help='extra topics (optionally /topic:pkg/msg/Type)')
    p.add_argument('--only', action='store_true', help='record only --topics, not the tissue topics')
    p.add_argument('--chunk-size', type=int, default=1 << 20, help='chunk size [bytes] (default 1 MiB)')
    p.add_argument('--flush', type=float, default=0.5, help='flush a chunk at least every FLUSH s (default 0.5)')
    p.add_argument('--split-size', type=float, default=0.0, help='start a new file every N MB (0 = never)')
    p.add_argument('--split-duration', type=float, default=0.0, help='start a new file every N s (0 = never)')
    p.add_argument('--compression', choices=('zstd', 'lz4', 'none'), default='zstd')
    p.add_argument('--meta', nargs='*', default=[], metavar='KEY=VALUE', help='extra metadata entries')
    p.add_argument('--max-rate', nargs='*', default=[], metavar='TOPIC=HZ',
                   help='keep at most HZ messages per second (receive time) of TOPIC, e.g. /tissue/markers=10 '
                        '(the full-mesh markers are ~5 MB/s compressed at 34 Hz)')
    return p


class Recorder(Node):
    """Subscribes (raw) to the wanted topics as they appear and writes what arrives; ``on_shutdown``
    (SIGINT/SIGTERM, a callback racing them) finishes the file."""

    def __init__(self, args):
        super().__init__('recorder')
        self.a = args
        self.wanted = {}               # topic -> explicit type or None
        for t in ([] if args.only else list(TISSUE_TOPICS)) + list(args.topics):
            name, _, typ = t.partition(':')
            self.wanted[name] = typ or TOPIC_TYPES.get(name)
        meta = {'recorder_topics': json.dumps(sorted(self.wanted)), 'versions': json.dumps(mcapio.versions()),
                'command': ' '.join(sys.argv), 'started_wall_ns': str(time.time_ns())}
        for kv in args.meta:
            k, _, v = kv.partition('=')
            meta[k] = v
        self.meta = meta
        self.min_gap_ns = {}           # topic -> least receive-time gap kept [ns] (--max-rate)
        for kv in args.max_rate:
            topic, _, hz = kv.partition('=')
            try:
                rate = float(hz)
            except ValueError:
                rate = float('nan')
            if not topic.startswith('/') or not rate > 0:
                raise ValueError(f'--max-rate {kv!r}: expected /topic=HZ with HZ > 0')
            self.min_gap_ns[topic] = int(1e9 / rate)
        self.last_kept_ns = {}
        self.writer = mcapio.McapWriter(args.output, chunk_size=args.chunk_size, compression=args.compression,
                                        split_bytes=int(args.split_size * 1e6), split_seconds=args.split_duration,
                                        flush_seconds=args.flush, metadata=meta)
        self.subs = {}
        self.types = {}                # topic -> type of a subscribed topic
        self.unrecordable = set()      # topics whose channel could not be written (logged once)
        self.counts = {}               # topic -> messages written (present once its channel is written)
        self.closed = False
        for topic, typ in self.wanted.items():
            if typ is not None:
                self.subscribe(topic, typ)
        self.create_timer(0.5, self.discover)
        self.create_timer(max(args.flush, 0.05), self.writer.flush)
        self.discover()
        print(f'recorder: writing {args.output}', flush=True)

    def discover(self):
        types = dict(self.get_topic_names_and_types())
        for topic, typ in self.wanted.items():
            if topic in self.subs:
                continue
            if typ is None:
                ts = types.get(topic)
                if not ts:
                    continue
                typ = ts[0]
            self.subscribe(topic, typ)

    def subscribe(self, topic, typ):
        """Subscribe to ``topic`` (raw CDR). Transient-local for the topics tissue_sim publishes latched
        (/tissue/topology, /tf_static, /robot_description) and for any whose publishers all offer it, as
        rosbag2 does, so a message sent before the subscription is still caught. The channel is written
        at the first message (:meth:`add_channel`), with the QoS its publishers offer then."""
        from ..ros.common import get_message
        try:
            cls = get_message(typ)
            mcapio.full_type_name(typ)
        except (ValueError, AttributeError, ModuleNotFoundError, mcapio.McapIOError) as e:
            self.get_logger().error(f'cannot record {topic} ({typ}): {e}')
            self.subs[topic] = None
            return
        self.types[topic] = typ
        offered = self.offered(topic)
        latched = topic in LATCHED or (offered and all(q.durability == 'transient_local' for q in offered))
        qos = qos_latched() if latched else qos_stream(100)
        self.subs[topic] = self.create_subscription(cls, topic, lambda data, info, t=topic: self.on_message(t, data, info),
                                                    qos, raw=True)
        self.get_logger().info(f'subscribed to {topic} [{typ}]')

    def offered(self, topic) -> list:
        """The QoS profiles the topic's publishers offer now (rosbag2's ``offered_qos_profiles``); none
        when the graph cannot be asked (at shutdown, after the context is gone)."""
        try:
            infos = self.get_publishers_info_by_topic(topic)
        except Exception:
            return []
        return [mcapio.Qos.from_profile(i.qos_profile) for i in infos]

    def add_channel(self, topic):
        """Write the topic's channel: the QoS its publishers offer (what ``ros2 bag play`` offers again),
        or, with no publisher seen, what tissue_sim's nodes offer for it."""
        offered = self.offered(topic) or [mcapio.QOS_LATCHED if topic in LATCHED else mcapio.qos_stream()]
        try:
            self.writer.add_channel(topic, self.types[topic], qos=offered)
        except mcapio.McapIOError as e:
            self.get_logger().error(f'cannot record {topic}: {e}')
            return False
        return True

    def on_message(self, topic, data, info=None):
        """``info``: rclpy's message info; its ``source_timestamp`` (the publisher's clock, ns) is the
        message's publish time, the receive time (now) its log time."""
        if self.closed:
            return
        now = time.time_ns()
        sent = (info or {}).get('source_timestamp') or now
        gap = self.min_gap_ns.get(topic)
        if gap is not None:
            # keep a message when a whole period has passed since the last kept one (small slack for jitter)
            if now - self.last_kept_ns.get(topic, -gap) < gap * 0.9:
                return
            self.last_kept_ns[topic] = now
        if topic not in self.counts:
            if topic in self.unrecordable or not self.add_channel(topic):
                self.unrecordable.add(topic)
                return
        self.writer.write(topic, data, now, sent)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        if self.counts[topic] == 1:
            self.get_logger().info(f'recording {topic}: first message received')
            if topic == TOPIC_TOPOLOGY:
                self.note_model(data)

    def note_model(self, data):
        """Model name, hash and parameters of the run (from the topology) as a metadata record."""
        try:
            from ..core.tissue_cdr import decode_topology
            topo = decode_topology(data)
        except Exception as e:
            self.get_logger().warning(f'could not decode {TOPIC_TOPOLOGY}: {e}')
            return
        self.writer.add_metadata('tissue_sim_model', {'model': topo.name, 'model_hash': topo.meta['model_hash'],
                                                      'parameters_yaml': topo.meta['parameters_yaml'],
                                                      'n_vertices': str(topo.n_vertices)})

    def on_shutdown(self):
        if self.closed:
            return
        self.closed = True
        # a second SIGINT/SIGTERM (`ros2 launch` forwards the Ctrl-C its process group already got)
        # must not interrupt the summary and footer half written: ignored from here on
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
        try:
            for topic in self.types:         # the subscribed topics that never spoke: their channels too (as rosbag2)
                if topic not in self.counts and topic not in self.unrecordable:
                    self.add_channel(topic)
        finally:
            self.writer.close()
        total = sum(self.counts.values())
        print(f'recorder: {total} messages in {", ".join(str(f) for f in self.writer.files)} '
              f'({", ".join(f"{k}: {v}" for k, v in sorted(self.counts.items()))})', flush=True)


def main(argv=None):
    return node_main(Recorder, build_parser(), argv)


if __name__ == '__main__':
    raise SystemExit(main())
