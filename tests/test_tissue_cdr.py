"""numpy CDR of TissueState / TissueTopology: round trips, and the bytes checked by independent
deserialisers (rosbags' CDR from the .msg definitions; rclpy when tissue_msgs is built)."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from tissue_sim.core import runio, tissue_cdr
from tissue_sim.core.cdr import CdrError
from tissue_sim.core.model import TissueTopology

import synthetic

MSG_DIR = Path(__file__).resolve().parents[1] / 'src' / 'tissue_msgs' / 'msg'


@pytest.fixture(scope='module')
def tm():
    return synthetic.tube_model(n_around=8, n_slices=4)


def _state(tm, seed=0):
    rng = np.random.default_rng(seed)
    V = tm.n_vertices
    return dict(stamp_ns=1_234_567_890_123, frame_id='world', step=77, sim_time=1.25,
                joint_names=['knee_r'], joint_positions=np.array([0.5]), joint_velocities=np.array([-0.25]),
                muscle_names=list(tm.muscle_names), activations=np.array([0.75, 0.0], np.float32),
                muscle_lengths=np.array([0.4, 0.5], np.float32), muscle_volumes=np.array([1e-4, 2e-4], np.float32),
                segment_poses=np.array([[0, 0, 0, 0, 0, 0, 1], [0.1, 0.2, 0.3, 0, 0.2474, 0, 0.9689]]),
                vertex_positions=rng.normal(size=(V, 3)).astype(np.float32), kinetic_energy=3.5, elastic_energy=7.25)


def test_state_round_trip(tm):
    kw = _state(tm)
    s = tissue_cdr.decode_state(tissue_cdr.encode_state(**kw))
    assert s.stamp_ns == kw['stamp_ns'] and s.step == 77 and s.sim_time == 1.25 and s.frame_id == 'world'
    assert s.joint_names == ['knee_r'] and s.muscle_names == list(tm.muscle_names)
    np.testing.assert_array_equal(s.vertex_positions, kw['vertex_positions'])
    np.testing.assert_array_equal(s.segment_poses, kw['segment_poses'])
    np.testing.assert_array_equal(s.activations, kw['activations'])
    assert s.kinetic_energy == 3.5 and s.elastic_energy == 7.25
    # skipping vertices keeps the fields after them
    s2 = tissue_cdr.decode_state(tissue_cdr.encode_state(**kw), with_vertices=False)
    assert s2.vertex_positions.shape == (0, 3) and s2.elastic_energy == 7.25


def test_topology_round_trip(tm):
    back = tissue_cdr.decode_topology(tissue_cdr.encode_topology(tm, parameters_yaml='set: paper\n'))
    assert isinstance(back, TissueTopology) and isinstance(tm, TissueTopology)    # one model type
    assert back.name == tm.name and back.meta['model_hash'] == tm.content_hash()
    assert back.meta['parameters_yaml'] == 'set: paper\n'
    np.testing.assert_array_equal(back.rest_positions, tm.rest_positions.astype(np.float32))
    np.testing.assert_array_equal(back.cell_vertices, tm.cell_vertices)
    np.testing.assert_array_equal(back.skin_quads, tm.skin_quads)
    np.testing.assert_array_equal(back.bone_triangles, tm.bone_triangles)
    assert back.muscle_groups == tm.muscle_groups and back.surface_group_names == tm.surface_group_names
    for c in range(tm.n_cells):
        np.testing.assert_array_equal(back.cell(c), tm.cell(c))


def test_truncated_and_inconsistent_data_raise(tm):
    b = tissue_cdr.encode_state(**_state(tm))
    with pytest.raises(CdrError, match='truncated'):
        tissue_cdr.decode_state(b[:len(b) // 2])
    cv = tm.cell_vertices.copy()
    cv[0] = 10 ** 6
    bad = dataclasses.replace(tm, cell_vertices=cv)
    with pytest.raises(CdrError, match='out of range'):
        tissue_cdr.decode_topology(tissue_cdr.encode_topology(bad))


def _rosbags_store():
    typesys = pytest.importorskip('rosbags.typesys')
    ts = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    add = {}
    for name in ('TissueState', 'TissueTopology'):
        add.update(typesys.get_types_from_msg((MSG_DIR / f'{name}.msg').read_text(), f'tissue_msgs/msg/{name}'))
    ts.register(add)
    return ts


def test_bytes_match_independent_deserialiser(tm):
    """rosbags builds its CDR codec from the .msg files: our bytes must decode to the same values."""
    ts = _rosbags_store()
    kw = _state(tm)
    m = ts.deserialize_cdr(tissue_cdr.encode_state(**kw), 'tissue_msgs/msg/TissueState')
    assert m.header.stamp.sec == 1234 and m.header.stamp.nanosec == 567_890_123
    assert m.step == 77 and m.joint_names == ['knee_r'] and m.elastic_energy == 7.25
    np.testing.assert_array_equal(m.vertex_positions, kw['vertex_positions'].ravel())
    np.testing.assert_array_equal(m.segment_poses, kw['segment_poses'].ravel())
    # and the other way: rosbags' serialisation decodes with ours
    s = tissue_cdr.decode_state(ts.serialize_cdr(m, 'tissue_msgs/msg/TissueState'))
    np.testing.assert_array_equal(s.vertex_positions, kw['vertex_positions'])
    topo = tissue_cdr.encode_topology(tm, parameters_yaml='x: 1')
    t = ts.deserialize_cdr(topo, 'tissue_msgs/msg/TissueTopology')
    assert t.model_name == tm.name and list(t.bone_names) == list(tm.bone_names)
    np.testing.assert_array_equal(t.cell_tissue, tm.cell_tissue)
    np.testing.assert_array_equal(t.bone_triangles, tm.bone_triangles.ravel())
    assert bytes(ts.serialize_cdr(t, 'tissue_msgs/msg/TissueTopology')) == topo
    # a decoded topology re-encodes to the same bytes
    assert tissue_cdr.encode_topology(tissue_cdr.decode_topology(topo)) == topo


def test_bytes_match_rclpy_when_built(tm):
    try:
        from rclpy.serialization import deserialize_message, serialize_message
        from tissue_msgs.msg import TissueState
    except ImportError:
        pytest.skip('tissue_msgs is not built/sourced (rclpy check runs in the ROS environment)')
    kw = _state(tm)
    data = tissue_cdr.encode_state(**kw)
    m = deserialize_message(data, TissueState)
    np.testing.assert_array_equal(np.asarray(m.vertex_positions, np.float32), kw['vertex_positions'].ravel())
    assert m.header.stamp.sec == 1234 and m.step == 77 and list(m.muscle_names) == list(tm.muscle_names)
    # rclpy's own bytes decode with ours to the same values (byte equality is not expected: Fast CDR
    # leaves its alignment padding uninitialised)
    s = tissue_cdr.decode_state(bytes(serialize_message(m)))
    np.testing.assert_array_equal(s.vertex_positions, kw['vertex_positions'])
    np.testing.assert_array_equal(s.segment_poses, kw['segment_poses'])
    assert s.elastic_energy == 7.25 and s.joint_names == ['knee_r'] and s.step == 77
    from tissue_msgs.msg import TissueTopology
    t = deserialize_message(tissue_cdr.encode_topology(tm, parameters_yaml='x: 1'), TissueTopology)
    assert t.model_name == tm.name and list(t.bone_names) == list(tm.bone_names)
    np.testing.assert_array_equal(np.asarray(t.cell_vertices), tm.cell_vertices)
    back = tissue_cdr.decode_topology(bytes(serialize_message(t)))
    np.testing.assert_array_equal(back.skin_quads, tm.skin_quads)


def test_run_file_has_ros2_schemas(tm, tmp_path):
    """The run files carry the .msg text as ros2msg schemas (what rosbag2/Foxglove need)."""
    from mcap.reader import make_reader
    p = runio.write_run(tmp_path / 'r.mcap', tm, [tissue_cdr.StateFrame(**_state(tm))])
    with open(p, 'rb') as f:
        s = make_reader(f).get_summary()
    schemas = {sc.name: sc for sc in s.schemas.values()}
    assert set(schemas) == {'tissue_msgs/msg/TissueState', 'tissue_msgs/msg/TissueTopology'}
    text = schemas['tissue_msgs/msg/TissueState'].data.decode()
    assert text.startswith((MSG_DIR / 'TissueState.msg').read_text().rstrip()[:40])
    assert 'MSG: std_msgs/Header' in text and schemas['tissue_msgs/msg/TissueState'].encoding == 'ros2msg'
    assert runio.count_states(p) == 1


def test_encode_frame_is_the_solver_state_and_observation():
    """The one frame encoder (simulator node and headless runs): a solver state decodes back to the
    state's step, time and positions and to solver.observe's values."""
    from tissue_sim.core import solver
    from tissue_sim.core.solver import phantom
    tm = phantom.knee(n_gaps=6)
    sim = solver.compile_model(tm, solver.Params.paper())
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[tm.muscle_index(tm.muscle_names[0])] = 1.0
    solver.step(sim, st, ctrl, sim.params.dt, n_steps=20)
    o = solver.observe(sim, st)
    s = tissue_cdr.decode_state(tissue_cdr.encode_frame(tm, st, o, ctrl.activation, frame_id='map'))
    assert s.step == st.step == 20 and s.sim_time == st.time and s.stamp_ns == round(st.time * 1e9)
    assert s.frame_id == 'map' and s.joint_names == list(tm.joint_names) and s.muscle_names == list(tm.muscle_names)
    np.testing.assert_array_equal(s.vertex_positions, st.x.astype(np.float32))
    np.testing.assert_array_equal(s.joint_positions, o['joint_positions'])
    np.testing.assert_array_equal(s.segment_poses, np.asarray(o['segment_poses']).reshape(-1, 7))
    np.testing.assert_array_equal(s.muscle_volumes, np.asarray(o['muscle_volumes'], np.float32))
    np.testing.assert_array_equal(s.activations, ctrl.activation.astype(np.float32))
    assert s.kinetic_energy == o['kinetic_energy'] and s.elastic_energy == o['elastic_energy']
