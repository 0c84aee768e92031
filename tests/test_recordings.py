"""Recordings a rosbag2 user trusts: channel QoS and type-hash metadata and the rosbag2 bag metadata
(checked with rosbags' own parsers and its Jazzy type store), `tissue-sim info`, and `tissue-sim
repair` of real files cut short at many offsets (read back by rosbags and by the mcap package)."""
import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml

from tissue_sim import cli
from tissue_sim.core import mcapio, runio
from tissue_sim.core.tissue_cdr import STATE_TYPE, TOPOLOGY_TYPE

from synthetic import bending_run, tube_model

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def tube():
    return tube_model()


def mcap_messages(path):
    """(topic, log time, data) of a file, by the mcap package's indexed reader (needs the summary)."""
    from mcap.reader import make_reader
    with open(path, 'rb') as f:
        r = make_reader(f)
        assert r.get_summary() is not None
        return [(c.topic, m.log_time, m.data) for _, c, m in r.iter_messages(log_time_order=False)]


def rosbags_messages(path):
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)]) as r:
        return [(c.topic, t, d) for c, t, d in r.messages()]


def records(path):
    """(opcode, start, end) of the top-level records of an MCAP file (after the magic)."""
    data = Path(path).read_bytes()
    out, pos = [], 8
    while pos + 9 <= len(data):
        op, n = data[pos], struct.unpack_from('<Q', data, pos + 1)[0]
        out.append((op, pos, pos + 9 + n))
        if op == 0x02:
            break
        pos += 9 + n
    return out


def test_run_channels_carry_rosbag2_qos_and_type_hash(tmp_path, tube):
    """rosbags reads the offered QoS of every channel (topology transient-local, depth 1; state volatile);
    the recorded hash is the RIHS01 rosbags computes from the recorded schema and the one in the built
    interface package."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosHistory, QosReliability
    p = bending_run(tube, tmp_path / 'run.mcap', n_frames=6)
    with AnyReader([p]) as r:
        by_topic = {c.topic: c for c in r.connections}
        topo_q = by_topic[runio.TOPIC_TOPOLOGY].ext.offered_qos_profiles
        state_q = by_topic[runio.TOPIC_STATE].ext.offered_qos_profiles
        computed = {t: r.typestore.hash_rihs01(t) for t in (TOPOLOGY_TYPE, STATE_TYPE)}
    assert len(topo_q) == 1 and len(state_q) == 1
    assert topo_q[0].durability == QosDurability.TRANSIENT_LOCAL and topo_q[0].depth == 1
    assert topo_q[0].reliability == QosReliability.RELIABLE and topo_q[0].history == QosHistory.KEEP_LAST
    assert state_q[0].durability == QosDurability.VOLATILE and state_q[0].depth == 10
    assert topo_q[0].deadline.sec == mcapio.INFINITE_SEC and topo_q[0].deadline.nsec == mcapio.INFINITE_NSEC
    with open(p, 'rb') as f:
        s = make_reader(f).get_summary()
    meta = {c.topic: c.metadata for c in s.channels.values()}
    for topic, typ in ((runio.TOPIC_TOPOLOGY, TOPOLOGY_TYPE), (runio.TOPIC_STATE, STATE_TYPE)):
        h = meta[topic]['topic_type_hash']
        assert h.startswith('RIHS01_') and len(h) == 7 + 64
        assert h == computed[typ]
        pkg, _, name = typ.split('/')
        built = list((ROOT / 'ros_ws' / 'install').glob(f'*/share/{pkg}/msg/{name}.json'))
        if built:
            assert h == json.loads(built[0].read_text())['type_hashes'][0]['hash_string']


def test_standard_types_hash_as_rosbags_jazzy_store(tmp_path):
    from rosbags.typesys import Stores, get_typestore
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    for t in ('visualization_msgs/msg/MarkerArray', 'sensor_msgs/msg/JointState', 'tf2_msgs/msg/TFMessage',
              'rosgraph_msgs/msg/Clock', 'diagnostic_msgs/msg/DiagnosticArray'):
        assert mcapio.type_hash(t) == jazzy.hash_rihs01(t), t
        # the fallback (no built package): computed from the schema text
        assert mcapio.compute_type_hash(t, mcapio.schema_text(t)) == jazzy.hash_rihs01(t), t


def test_bag_metadata_is_what_rosbag2_and_rosbags_read(tmp_path, tube):
    """The rosbag2 metadata record, served to rosbags' rosbag2 directory reader as metadata.yaml: it
    parses (version 9, ros_distro jazzy, counts), its QoS equal the channels' (rosbags pairs the
    connections by them) and AnyReader checks the type_description_hash against the schemas."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader
    p = bending_run(tube, tmp_path / 'run.mcap', n_frames=7)
    with open(p, 'rb') as f:
        r = make_reader(f)
        recs = {m.name: m.metadata for m in r.iter_metadata()}
    doc = yaml.safe_load(recs['rosbag2']['serialized_metadata'])
    assert doc['version'] == 9 and doc['ros_distro'] == 'jazzy' and doc['storage_identifier'] == 'mcap'
    assert doc['message_count'] == 8 and doc['relative_file_paths'] == ['run.mcap']
    bag = tmp_path / 'bag'
    bag.mkdir()
    shutil.copy(p, bag / 'run.mcap')
    (bag / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': doc}))
    with AnyReader([bag]) as ar:
        assert ar.readers[0].ros_distro == 'jazzy'
        assert {c.topic: c.msgcount for c in ar.connections} == {runio.TOPIC_TOPOLOGY: 1, runio.TOPIC_STATE: 7}
        assert all(c.digest.startswith('RIHS01_') for c in ar.connections)
        got = [(c.topic, t, d) for c, t, d in ar.messages()]
    assert got == mcap_messages(p)
    # a wrong hash is caught by the same reader: the check above can fail
    doc['topics_with_message_count'][0]['topic_metadata']['type_description_hash'] = 'RIHS01_' + '0' * 64
    (bag / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': doc}))
    with pytest.raises(Exception, match='hash mismatch'):
        with AnyReader([bag]):
            pass


def test_qos_yaml_round_trips_through_rosbags_parser():
    from rosbags.rosbag2.metadata import parse_qos
    q = [mcapio.Qos(reliability='best_effort', durability='transient_local', depth=3, deadline_ns=1_500_000_000),
         mcapio.QOS_LATCHED]
    text = mcapio.qos_yaml(q)
    assert text.startswith('- history: keep_last\n  depth: 3\n  reliability: best_effort\n')
    parsed = parse_qos(text)
    assert parsed[0].deadline.sec == 1 and parsed[0].deadline.nsec == 500_000_000 and parsed[0].depth == 3
    assert mcapio.parse_qos_yaml(text) == q
    with pytest.raises(mcapio.McapIOError, match='QoS durability'):
        mcapio.Qos(durability='forever')


def test_qos_from_an_rclpy_profile():
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    p = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
    assert mcapio.Qos.from_profile(p) == mcapio.QOS_LATCHED
    p = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT, lifespan=Duration(seconds=2))
    q = mcapio.Qos.from_profile(p)
    assert q.reliability == 'best_effort' and q.depth == 5 and q.lifespan_ns == 2_000_000_000


def test_info_reports_topics_qos_hash_distro_and_model(tmp_path, tube, capsys):
    p = bending_run(tube, tmp_path / 'run.mcap', n_frames=35, rate_hz=34.0)
    assert cli.main(['info', str(p), '--json']) == 0
    info = json.loads(capsys.readouterr().out)
    assert info['ros_distro'] == 'jazzy' and info['messages'] == 36 and not info['truncated']
    assert info['model']['name'] == tube.name and info['model']['hash']
    t = {x['topic']: x for x in info['topics']}
    assert t[runio.TOPIC_STATE]['count'] == 35 and t[runio.TOPIC_STATE]['rate_hz'] == pytest.approx(34.0, rel=1e-3)
    assert t[runio.TOPIC_TOPOLOGY]['qos'] == ['reliable, transient_local, keep_last 1']
    assert t[runio.TOPIC_STATE]['type_hash'].startswith('RIHS01_')
    assert cli.main(['info', str(p)]) == 0
    out = capsys.readouterr().out
    assert 'ROS Distro:        jazzy' in out and 'Topic: /tissue/state | Type: tissue_msgs/msg/TissueState' in out
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(p.read_bytes()[:p.stat().st_size // 2])
    assert cli.main(['info', str(cut), '--json']) == 0
    assert json.loads(capsys.readouterr().out)['truncated'] is True
    (tmp_path / 'x.mcap').write_text('not mcap')
    assert cli.main(['info', str(tmp_path / 'x.mcap')]) == 2
    assert 'not an MCAP file' in capsys.readouterr().err


@pytest.mark.parametrize('chunk_size', [4096, 1 << 20])
def test_repair_of_files_cut_at_many_offsets(tmp_path, tube, capsys, chunk_size):
    """A run written by the real writer, cut inside chunks, between chunks, inside the summary and just
    before the footer: the repaired file is read by rosbags and by the mcap package, its messages are
    a prefix of the original (the very messages the project's reader finds in the cut file), and a cut
    through a large chunk still yields that chunk's complete messages."""
    p = bending_run(tube, tmp_path / 'run.mcap', n_frames=60, chunk_size=chunk_size)
    full = mcap_messages(p)
    data = p.read_bytes()
    recs = records(p)
    chunks = [(s, e) for op, s, e in recs if op == 0x06]
    data_end = next(s for op, s, e in recs if op == 0x0F)
    cuts = {s + 9 + (e - s) // 2 for s, e in chunks} | {s + 20 for s, e in chunks} | {e for s, e in chunks[:-1]}
    cuts |= {data_end, data_end + 5, len(data) - 20, len(data) - 1}
    cuts |= set(np.random.default_rng(3).integers(200, len(data), 5).tolist())
    recovered_from_cut = 0
    for cut in sorted(cuts):
        src = tmp_path / f'cut_{cut}.mcap'
        src.write_bytes(data[:cut])
        baseline = len(list(mcapio.iter_messages(src)))
        out = tmp_path / f'fixed_{cut}.mcap'
        assert cli.main(['repair', str(src), '-o', str(out)]) == 0, cut
        report = capsys.readouterr().out
        assert src.read_bytes() == data[:cut]                           # input untouched
        got = mcap_messages(out)
        assert got == full[:len(got)], cut
        assert len(got) == baseline, cut                # the project's reader sees the same messages
        assert rosbags_messages(out) == got, cut
        if cut >= data_end:
            assert len(got) == len(full), cut
        if 'more complete messages' in report:
            recovered_from_cut += 1
        assert f'kept {len(got)} complete messages' in report
        # the repaired run is a run: the analysis reader takes it, topology first
        if len(got) > 1:
            assert runio.read_topology(out).n_vertices == tube.n_vertices
    if chunk_size > 4096:
        assert recovered_from_cut > 0          # zstd blocks of a 1 MiB chunk decode up to the cut


def test_repair_in_place_and_refusals(tmp_path, tube, capsys):
    p = bending_run(tube, tmp_path / 'run.mcap', n_frames=20, chunk_size=4096)
    full = mcap_messages(p)
    size = p.stat().st_size
    cut = tmp_path / 'rec.mcap'
    cut.write_bytes(p.read_bytes()[:size * 2 // 3])
    # complete input: nothing to do, nothing written
    assert cli.main(['repair', str(p)]) == 0
    assert 'nothing to repair' in capsys.readouterr().out and not (tmp_path / 'run.repaired.mcap').exists()
    # default output beside the input; a second run refuses to overwrite it
    assert cli.main(['repair', str(cut)]) == 0
    out = tmp_path / 'rec.repaired.mcap'
    n = len(mcap_messages(out))
    assert cli.main(['repair', str(cut)]) == 2
    assert 'exists' in capsys.readouterr().err
    # in place: the input becomes the complete file, no temporary file is left
    before = cut.read_bytes()
    assert cli.main(['repair', '--in-place', str(cut)]) == 0
    assert cut.read_bytes() != before and mcap_messages(cut) == full[:n]
    assert sorted(f.name for f in tmp_path.iterdir()) == ['rec.mcap', 'rec.repaired.mcap', 'run.mcap']
    # bad input: one line, exit 2, nothing written
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(b'\x89MCAP0\r\n')
    capsys.readouterr()
    for argv, msg in ((['repair', str(bad)], 'no complete MCAP record'),
                      (['repair', str(tmp_path / 'missing.mcap')], 'no such file'),
                      (['repair', str(tmp_path)], 'a folder'),
                      (['repair', str(p), '-o', str(p)], 'the output is the input')):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert msg in err and err.count('\n') == 1, err
    assert sorted(f.name for f in tmp_path.iterdir()) == ['bad.mcap', 'rec.mcap', 'rec.repaired.mcap', 'run.mcap']


def test_offered_qos_from_ros_discovery_is_what_rosbag2_records():
    """What the recorder passes: the publishers' offered QoS as the ROS graph reports it (here a real
    rclpy publisher, transient-local like /tissue/topology) becomes rosbag2's YAML entry."""
    import os
    import time
    import rclpy
    from rclpy.qos import QoSProfile
    from std_msgs.msg import String
    from tissue_sim.ros.common import qos_latched
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get('ROS_DOMAIN_ID', '0')))
    try:
        node = rclpy.create_node('qos_probe', context=ctx)
        topic = f'/tissue_sim_test/qos_probe_{os.getpid()}'
        node.create_publisher(String, topic, qos_latched())
        infos = []
        for _ in range(100):
            infos = node.get_publishers_info_by_topic(topic)
            if infos:
                break
            time.sleep(0.05)
        assert len(infos) == 1
        q = mcapio.Qos.from_profile(infos[0].qos_profile)
        assert (q.reliability, q.durability, q.liveliness) == ('reliable', 'transient_local', 'automatic')
        assert q.deadline_ns is None and q.lifespan_ns is None       # DDS offers infinite
        # what the simulator node offers is what a headless run records (runio.OFFERED_QOS)
        from tissue_sim.ros.common import qos_stream
        assert mcapio.Qos.from_profile(qos_latched()) == mcapio.QOS_LATCHED == runio.OFFERED_QOS[runio.TOPIC_TOPOLOGY]
        assert mcapio.Qos.from_profile(qos_stream()) == runio.OFFERED_QOS[runio.TOPIC_STATE]
        assert isinstance(qos_latched(), QoSProfile)
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
