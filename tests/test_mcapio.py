"""core/mcapio: schema text, writer, reader (incl. a file cut short), read back by `rosbags`."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tissue_sim.core import mcapio
from tissue_sim.core.cdr import CdrReader, CdrWriter

ROOT = Path(__file__).resolve().parents[1]
SHARE = [ROOT / 'src', Path(sys.prefix) / 'share']


def activation_cdr(stamp_ns, names, values):
    w = CdrWriter()
    w.header(stamp_ns, 'world')
    w.string_seq(names)
    w.array(values, np.float32)
    return w.bytes()


def test_schema_text_has_dependencies_in_rosbag2_form():
    s = mcapio.schema_text('tissue_msgs/msg/TissueState', SHARE)
    assert s.startswith('# Compact state')
    assert '\nMSG: std_msgs/Header\n' in s and '\nMSG: builtin_interfaces/Time\n' in s
    assert 'MSG: std_msgs/msg/' not in s
    assert s.count('=' * 80) == 2
    # a deeper tree: each dependency once, relative names resolved within the package
    m = mcapio.schema_text('visualization_msgs/msg/MarkerArray', SHARE)
    for dep in ('visualization_msgs/Marker', 'geometry_msgs/Pose', 'geometry_msgs/Point', 'std_msgs/ColorRGBA',
                'sensor_msgs/CompressedImage', 'visualization_msgs/UVCoordinate', 'visualization_msgs/MeshFile',
                'builtin_interfaces/Duration'):
        assert m.count(f'MSG: {dep}\n') == 1, dep


def test_schema_text_is_parsed_by_independent_readers():
    from rosbags.typesys import get_types_from_msg
    s = mcapio.schema_text('tissue_msgs/msg/MuscleActivation', SHARE)
    # rosbags parses the concatenated definition the same way it parses rosbag2's
    types = get_types_from_msg(s, 'tissue_msgs/msg/MuscleActivation')
    assert 'tissue_msgs/msg/MuscleActivation' in types and 'std_msgs/msg/Header' in types
    from mcap_ros2._dynamic import generate_dynamic
    dec = generate_dynamic('tissue_msgs/msg/MuscleActivation', s)
    msg = dec['tissue_msgs/msg/MuscleActivation'](activation_cdr(5_000_000_123, ['a', 'b'], [0.25, 1.0]))
    assert list(msg.muscle_names) == ['a', 'b'] and msg.header.stamp.nanosec == 123


def test_unknown_type_is_a_clear_error():
    with pytest.raises(mcapio.McapIOError, match='no definition of nope_msgs/msg/X'):
        mcapio.schema_text('nope_msgs/msg/X', SHARE)
    with pytest.raises(mcapio.McapIOError, match='bad message type'):
        mcapio.schema_text('justaname', SHARE)


def write_run(path, n=50, **kw):
    w = mcapio.McapWriter(path, metadata={'model': 'phantom', 'parameters': {'dt': 1e-3}}, share_dirs=SHARE, **kw)
    w.add_channel('/tissue/activation', 'tissue_msgs/msg/MuscleActivation')
    sent = []
    for i in range(n):
        data = activation_cdr(i * 10_000_000, ['bf', 'st'], [i / n, 0.5])
        w.write('/tissue/activation', data, i * 10_000_000)
        sent.append(data)
    return w, sent


def test_round_trip_and_rosbags_reads_it(tmp_path):
    p = tmp_path / 'run.mcap'
    w, sent = write_run(p)
    w.close()
    got = list(mcapio.iter_messages(p))
    assert [m.data for m in got] == sent
    assert got[3].schema_name == 'tissue_msgs/msg/MuscleActivation' and got[3].log_time == 30_000_000
    s = mcapio.scan(p)
    assert not s.truncated and s.counts == {'/tissue/activation': 50}
    assert s.metadata['tissue_sim']['model'] == 'phantom'
    assert '"dt"' in s.metadata['tissue_sim']['parameters']

    from rosbags.highlevel import AnyReader
    with AnyReader([p]) as r:
        msgs = [(c.topic, t, r.deserialize(d, c.msgtype)) for c, t, d in r.messages()]
    assert len(msgs) == 50
    assert np.isclose(msgs[10][2].activations[0], 10 / 50)
    assert msgs[10][2].muscle_names == ['bf', 'st']


def test_split_by_duration(tmp_path):
    w, sent = write_run(tmp_path / 'rec.mcap', n=50, split_seconds=0.1)
    w.close()
    assert len(w.files) == 5 and w.files[0].name == 'rec_0.mcap'
    assert [m.data for m in mcapio.iter_messages(tmp_path)] == sent
    for f in w.files:                       # every part opens on its own
        assert mcapio.scan(f).metadata['tissue_sim']['model'] == 'phantom'


def test_split_by_size(tmp_path):
    w, sent = write_run(tmp_path / 'rec.mcap', n=200, split_bytes=2000, chunk_size=500)
    w.close()
    assert len(w.files) > 2
    assert [m.data for m in mcapio.iter_messages(tmp_path)] == sent


def test_killed_writer_leaves_a_readable_file(tmp_path):
    """A real process writes small chunks and is killed with SIGKILL mid-run."""
    p = tmp_path / 'killed.mcap'
    code = textwrap.dedent(f'''
        import sys, time
        sys.path.insert(0, {str(ROOT / 'src' / 'tissue_sim')!r})
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_mcapio import activation_cdr, SHARE
        from tissue_sim.core import mcapio
        w = mcapio.McapWriter({str(p)!r}, chunk_size=256, flush_seconds=0.05, share_dirs=SHARE)
        w.add_channel('/a', 'tissue_msgs/msg/MuscleActivation')
        i = 0
        while True:
            w.write('/a', activation_cdr(i, ['m'], [0.5]), i)
            i += 1
            if i == 100:
                print('ready', flush=True)
            time.sleep(0.001)
    ''')
    proc = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == 'ready'
    finally:
        proc.kill()
        proc.wait()
    s = mcapio.scan(p)
    assert s.truncated
    assert s.counts['/a'] >= 90
    stamps = [CdrReader(m.data).header()[0] for m in mcapio.iter_messages(p)]
    assert stamps == list(range(len(stamps)))          # complete prefix, no gaps
    # the repaired file is a complete MCAP that rosbags reads, with at least those messages
    from rosbags.highlevel import AnyReader
    rep = mcapio.repair(p, tmp_path / 'repaired.mcap')
    assert not rep.complete and rep.messages >= len(stamps)
    with AnyReader([tmp_path / 'repaired.mcap']) as r:
        got = [CdrReader(d).header()[0] for _, _, d in r.messages()]
    assert got == list(range(rep.messages))


def test_not_an_mcap(tmp_path):
    f = tmp_path / 'x.mcap'
    f.write_bytes(b'hello world')
    with pytest.raises(mcapio.McapIOError, match='not an MCAP file'):
        list(mcapio.iter_messages(f))
    with pytest.raises(mcapio.McapIOError, match='no such file'):
        mcapio.scan(tmp_path / 'missing.mcap')
