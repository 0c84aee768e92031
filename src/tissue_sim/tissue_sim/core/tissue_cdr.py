"""numpy CDR encode/decode of tissue_msgs/TissueState and tissue_msgs/TissueTopology (ROS-free).

The field order follows ``src/tissue_msgs/msg/*.msg`` exactly; the bytes are what rclpy's
``serialize_message`` produces (little-endian CDR with the 4-byte encapsulation header), so the
nodes can publish them raw and the analysis can read recorded MCAP files without ROS.

* Topology: ``encode_topology(model, ...)`` takes a :class:`~tissue_sim.core.model.TissueModel`
  (or any :class:`~tissue_sim.core.model.TissueTopology`); ``decode_topology`` returns a
  ``TissueTopology`` (the model's topology part, in the model's dtypes) whose ``meta`` holds the
  message's ``model_hash``, ``parameters_yaml``, ``frame_id`` and ``stamp_ns``.
* State: :func:`encode_frame` is THE state-frame encoder of a solver state (the simulator node and
  headless runs both call it); ``encode_state(...)`` takes plain arrays; ``decode_state`` returns a
  :class:`StateFrame`.

Units SI, model frame (REP-103: x forward, y left, z up). Segment poses are 7 numbers per segment:
translation x y z [m] then the unit quaternion qx qy qz qw; a point p_rest on the segment is at
``R(q) @ p_rest + t``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from tissue_sim.core.cdr import CdrError, CdrReader, CdrWriter
from tissue_sim.core.model import ModelError, TissueTopology

STATE_TYPE = 'tissue_msgs/msg/TissueState'
TOPOLOGY_TYPE = 'tissue_msgs/msg/TissueTopology'


@dataclasses.dataclass(eq=False)
class StateFrame:
    """Decoded TissueState (one frame). Units SI, model frame."""
    stamp_ns: int
    frame_id: str
    step: int
    sim_time: float                     # [s]
    joint_names: list
    joint_positions: np.ndarray         # (J,) float64 [rad]
    joint_velocities: np.ndarray        # (J,) float64 [rad/s]
    muscle_names: list
    activations: np.ndarray             # (M,) float32 activation state
    muscle_lengths: np.ndarray          # (M,) float32 [m]
    muscle_volumes: np.ndarray          # (M,) float32 [m^3]
    segment_poses: np.ndarray           # (S, 7) float64: x y z qx qy qz qw
    vertex_positions: np.ndarray        # (V, 3) float32 [m]
    kinetic_energy: float
    elastic_energy: float
    excitations: np.ndarray = None      # (M,) float32 the commands (empty in recordings made before the field)
    muscle_forces: np.ndarray = None    # (M,) float32 [N] (empty in recordings made before the field)


# ------------------------------------------------------------------------------------ topology
def hash_of(model) -> str:
    """The model hash a topology of ``model`` carries: ``model.meta['model_hash']`` (a decoded topology), else
    ``model.content_hash()``."""
    meta = model.meta or {}
    return meta['model_hash'] if 'model_hash' in meta else model.content_hash()


def encode_topology(model, parameters_yaml: str | None = None, model_hash: str | None = None,
                    stamp_ns: int | None = None, frame_id: str | None = None) -> bytes:
    """CDR bytes of the TissueTopology message of ``model`` (a TissueModel or a decoded topology).

    Defaults come from ``model.meta`` (a decoded topology re-encodes to the same bytes), then:
    ``model_hash`` = ``model.content_hash()``, ``parameters_yaml`` = '', stamp 0, frame 'world'.
    """
    meta = model.meta or {}
    if model_hash is None:
        model_hash = hash_of(model)
    if parameters_yaml is None:
        parameters_yaml = meta.get('parameters_yaml', '')
    stamp_ns = int(meta.get('stamp_ns', 0)) if stamp_ns is None else stamp_ns
    frame_id = meta.get('frame_id', 'world') if frame_id is None else frame_id
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.string(model.name)
    w.string(model_hash)
    w.string(parameters_yaml)
    w.array(np.asarray(model.rest_positions).ravel(), np.float32)
    w.array(model.vertex_segment, np.int32)
    w.array(model.cell_offsets, np.uint32)
    w.array(model.cell_vertices, np.uint32)
    w.array(model.cell_tissue, np.uint8)
    w.array(model.cell_muscle, np.int32)
    w.string_seq(list(model.muscle_names))
    w.string_seq(list(model.muscle_groups))
    w.array(np.asarray(model.skin_quads).ravel(), np.uint32)
    w.array(model.skin_quad_cell, np.uint32)
    w.array(np.asarray(model.surface_triangles).ravel(), np.uint32)
    w.array(model.surface_group, np.int32)
    w.string_seq(list(model.surface_group_names))
    w.string_seq(list(model.segment_names))
    w.array(model.segment_parent, np.int32)
    w.string_seq(list(model.joint_names))
    w.string_seq(list(model.bone_names))
    w.array(model.bone_segment, np.int32)
    w.array(model.bone_vertex_offsets, np.uint32)
    w.array(np.asarray(model.bone_vertices).ravel(), np.float32)
    w.array(model.bone_triangle_offsets, np.uint32)
    w.array(np.asarray(model.bone_triangles).ravel(), np.uint32)
    return w.bytes()


def _triples(a: np.ndarray, k: int, what: str) -> np.ndarray:
    if a.size % k:
        raise CdrError(f'{what} has {a.size} numbers, not a multiple of {k}')
    return a.reshape(-1, k)


def decode_topology(data) -> TissueTopology:
    """The model topology of a TissueTopology message; raises CdrError on truncated or inconsistent data.

    Arrays come in the model's dtypes (float64 positions, int64 offsets, int32 indices)."""
    r = CdrReader(data)
    stamp, frame = r.header()
    kw = {}
    kw['name'] = r.string()
    meta = {'source': 'tissue_msgs/msg/TissueTopology', 'model_hash': r.string(),
            'parameters_yaml': r.string(), 'frame_id': frame, 'stamp_ns': stamp}
    i32, i64, f64 = np.int32, np.int64, np.float64
    kw['rest_positions'] = _triples(r.array(np.float32), 3, 'rest_positions').astype(f64)
    kw['vertex_segment'] = r.array(np.int32)
    kw['cell_offsets'] = r.array(np.uint32).astype(i64)
    kw['cell_vertices'] = r.array(np.uint32).astype(i32)
    kw['cell_tissue'] = r.array(np.uint8)
    kw['cell_muscle'] = r.array(np.int32)
    kw['muscle_names'] = tuple(r.string_seq())
    kw['muscle_groups'] = tuple(r.string_seq())
    kw['skin_quads'] = _triples(r.array(np.uint32), 4, 'skin_quads').astype(i32)
    kw['skin_quad_cell'] = r.array(np.uint32).astype(i32)
    kw['surface_triangles'] = _triples(r.array(np.uint32), 3, 'surface_triangles').astype(i32)
    kw['surface_group'] = r.array(np.int32)
    kw['surface_group_names'] = tuple(r.string_seq())
    kw['segment_names'] = tuple(r.string_seq())
    kw['segment_parent'] = r.array(np.int32)
    kw['joint_names'] = tuple(r.string_seq())
    kw['bone_names'] = tuple(r.string_seq())
    kw['bone_segment'] = r.array(np.int32)
    kw['bone_vertex_offsets'] = r.array(np.uint32).astype(i64)
    kw['bone_vertices'] = _triples(r.array(np.float32), 3, 'bone_vertices').astype(f64)
    kw['bone_triangle_offsets'] = r.array(np.uint32).astype(i64)
    kw['bone_triangles'] = _triples(r.array(np.uint32), 3, 'bone_triangles').astype(i32)
    for k in ('cell_offsets', 'bone_vertex_offsets', 'bone_triangle_offsets'):
        if not kw[k].size:
            kw[k] = np.zeros(1, i64)
    try:
        return TissueTopology(meta=meta, **kw).validate_topology()
    except ModelError as e:
        raise CdrError(f'TissueTopology: {e}') from None


# ------------------------------------------------------------------------------------ state
def encode_state(*, stamp_ns: int, frame_id: str = 'world', step: int = 0, sim_time: float = 0.0,
                 joint_names=(), joint_positions=(), joint_velocities=(),
                 muscle_names=(), activations=(), muscle_lengths=(), muscle_volumes=(),
                 segment_poses=(), vertex_positions=(), kinetic_energy: float = 0.0,
                 elastic_energy: float = 0.0, excitations=None, muscle_forces=None) -> bytes:
    """CDR bytes of a TissueState message (about 1 ms for 8k vertices).

    segment_poses: (S, 7) x y z qx qy qz qw; vertex_positions: (V, 3) [m]. Arrays are cast to the
    message's types (float32 vertices, float64 joints and poses). excitations: None = the activations;
    muscle_forces [N]: None = empty.
    """
    w = CdrWriter()
    w.header(int(stamp_ns), frame_id)
    w.uint64(int(step))
    w.float64(float(sim_time))
    w.string_seq(list(joint_names))
    w.array(joint_positions, np.float64)
    w.array(joint_velocities, np.float64)
    w.string_seq(list(muscle_names))
    w.array(activations, np.float32)
    w.array(muscle_lengths, np.float32)
    w.array(muscle_volumes, np.float32)
    w.array(np.asarray(segment_poses, np.float64).ravel(), np.float64)
    w.array(np.asarray(vertex_positions, np.float32).ravel(), np.float32)
    w.float64(float(kinetic_energy))
    w.float64(float(elastic_energy))
    w.array(activations if excitations is None else excitations, np.float32)
    w.array(() if muscle_forces is None else muscle_forces, np.float32)
    return w.bytes()


def encode_state_obj(s: StateFrame) -> bytes:
    """CDR bytes of a :class:`StateFrame`."""
    return encode_state(**{f.name: getattr(s, f.name) for f in dataclasses.fields(StateFrame)})


def encode_frame(model, state, observation: dict, activations, stamp_ns: int | None = None,
                 frame_id: str = 'world') -> bytes:
    """THE TissueState of a solver state: ``model`` the TissueModel, ``state`` the solver's state
    (``step``, ``time``, ``x``), ``observation`` = ``solver.observe(sim, state)``, ``activations``
    (M,) the commanded activations (the message's excitations; its activations are the observation's activation
    state, its muscle_forces the observation's, both falling back to the commands / empty for an observation
    without them). ``stamp_ns`` defaults to the simulated time."""
    o = observation
    return encode_state(
        stamp_ns=int(round(state.time * 1e9)) if stamp_ns is None else int(stamp_ns), frame_id=frame_id,
        step=state.step, sim_time=state.time, joint_names=model.joint_names,
        joint_positions=o['joint_positions'], joint_velocities=o['joint_velocities'],
        muscle_names=model.muscle_names, activations=o.get('activations', activations), muscle_lengths=o['muscle_lengths'],
        muscle_volumes=o['muscle_volumes'], segment_poses=o['segment_poses'], vertex_positions=state.x,
        kinetic_energy=o['kinetic_energy'], elastic_energy=o['elastic_energy'], excitations=activations,
        muscle_forces=o.get('muscle_forces', ()))


def decode_state(data, with_vertices: bool = True) -> StateFrame:
    """StateFrame from CDR bytes; ``with_vertices=False`` skips copying the vertex array (fast scans)."""
    r = CdrReader(data)
    stamp, frame = r.header()
    step = r.uint64()
    t = r.float64()
    jn = r.string_seq()
    jp = r.array(np.float64)
    jv = r.array(np.float64)
    mn = r.string_seq()
    act = r.array(np.float32)
    ml = r.array(np.float32)
    mv = r.array(np.float32)
    sp = _triples(r.array(np.float64), 7, 'segment_poses')
    if with_vertices:
        vp = _triples(r.array(np.float32), 3, 'vertex_positions')
    else:
        n = r.uint32()
        if n:
            r._align(4)
            r._take(4 * n)
        vp = np.zeros((0, 3), np.float32)
    ke = r.float64()
    ee = r.float64()
    if r.remaining >= 4:
        ex, mf = r.array(np.float32), r.array(np.float32)
    else:                        # a recording made before the fields: the commands were the activations
        ex, mf = act.copy(), np.zeros(0, np.float32)
    return StateFrame(stamp, frame, step, t, jn, jp, jv, mn, act, ml, mv, sp, vp, ke, ee, ex, mf)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) in x y z w order (normalised here)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R
