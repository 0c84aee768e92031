"""numpy CDR encode/decode of tissue_msgs/TissueState and tissue_msgs/TissueTopology (ROS-free).

The field order follows ``src/tissue_msgs/msg/*.msg`` exactly; the bytes are what rclpy's
``serialize_message`` produces (little-endian CDR with the 4-byte encapsulation header), so the
nodes can publish them raw and the analysis can read recorded MCAP files without ROS.

Two light structures carry the decoded data with numpy arrays already reshaped:

* :class:`Topology` - the model's topology and rest shape (what ``/tissue/topology`` carries).
  ``from_model(TissueModel)`` builds it; ``encode_topology`` / ``decode_topology`` convert it.
* :class:`State` - one frame of ``/tissue/state``. ``encode_state(...)`` takes plain arrays (the
  simulator calls it once per published frame); ``decode_state`` returns a :class:`State`.

Units SI, model frame (REP-103: x forward, y left, z up). Segment poses are 7 numbers per segment:
translation x y z [m] then the unit quaternion qx qy qz qw; a point p_rest on the segment is at
``R(q) @ p_rest + t``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from tissue_sim.core.cdr import CdrError, CdrReader, CdrWriter

STATE_TYPE = 'tissue_msgs/msg/TissueState'
TOPOLOGY_TYPE = 'tissue_msgs/msg/TissueTopology'


@dataclasses.dataclass(eq=False)
class Topology:
    """Decoded TissueTopology. Arrays in the model frame [m]; indices as in TissueModel."""
    model_name: str
    model_hash: str
    parameters_yaml: str
    rest_positions: np.ndarray          # (V, 3) float32
    vertex_segment: np.ndarray          # (V,) int32
    cell_offsets: np.ndarray            # (C+1,) uint32
    cell_vertices: np.ndarray           # (K,) uint32
    cell_tissue: np.ndarray             # (C,) uint8
    cell_muscle: np.ndarray             # (C,) int32
    muscle_names: tuple
    muscle_groups: tuple
    skin_quads: np.ndarray              # (Q, 4) uint32
    skin_quad_cells: np.ndarray         # (Q,) uint32
    surface_triangles: np.ndarray       # (T, 3) uint32
    surface_groups: np.ndarray          # (T,) int32
    surface_group_names: tuple
    segment_names: tuple
    segment_parents: np.ndarray         # (S,) int32
    joint_names: tuple
    bone_names: tuple
    bone_segments: np.ndarray           # (B,) int32
    bone_vertex_offsets: np.ndarray     # (B+1,) uint32
    bone_vertices: np.ndarray           # (NB, 3) float32, rest pose
    bone_triangle_offsets: np.ndarray   # (B+1,) uint32
    bone_triangles: np.ndarray          # (NT, 3) uint32, local to each bone
    stamp_ns: int = 0
    frame_id: str = 'world'

    @property
    def n_vertices(self) -> int:
        return int(self.rest_positions.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cell_tissue.shape[0])

    def cell(self, c: int) -> np.ndarray:
        return self.cell_vertices[self.cell_offsets[c]:self.cell_offsets[c + 1]]

    def bone_mesh(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (n, 3), triangles (m, 3)) of bone b at rest."""
        v = self.bone_vertices[self.bone_vertex_offsets[b]:self.bone_vertex_offsets[b + 1]]
        t = self.bone_triangles[self.bone_triangle_offsets[b]:self.bone_triangle_offsets[b + 1]]
        return v, t

    def validate(self) -> 'Topology':
        """Check index ranges; raise CdrError naming the first inconsistency."""
        V, C = self.n_vertices, self.n_cells

        def need(cond, msg):
            if not cond:
                raise CdrError(f'TissueTopology {self.model_name!r}: {msg}')

        need(self.cell_offsets.shape == (C + 1,) and (C == 0 or (self.cell_offsets[0] == 0
             and self.cell_offsets[-1] == self.cell_vertices.size)), 'cell_offsets inconsistent with cell_vertices')
        need(self.cell_vertices.size == 0 or self.cell_vertices.max() < V, 'cell_vertices index out of range')
        need(self.cell_muscle.shape == (C,), 'cell_muscle must have one entry per cell')
        need(self.vertex_segment.shape == (V,), 'vertex_segment must have one entry per vertex')
        need(self.skin_quads.size == 0 or self.skin_quads.max() < V, 'skin_quads index out of range')
        need(self.skin_quad_cells.size == 0 or self.skin_quad_cells.max() < C, 'skin_quad_cells index out of range')
        need(self.skin_quad_cells.shape[0] == self.skin_quads.shape[0], 'skin_quad_cells must match skin_quads')
        need(self.surface_triangles.size == 0 or self.surface_triangles.max() < V, 'surface_triangles index out of range')
        need(self.surface_groups.shape[0] == self.surface_triangles.shape[0], 'surface_groups must match surface_triangles')
        need(len(self.muscle_groups) == len(self.muscle_names), 'muscle_groups must match muscle_names')
        need(self.segment_parents.shape == (len(self.segment_names),), 'segment_parents must match segment_names')
        B = len(self.bone_names)
        need(self.bone_segments.shape == (B,) and self.bone_vertex_offsets.shape == (B + 1,)
             and self.bone_triangle_offsets.shape == (B + 1,), 'bone arrays inconsistent')
        return self


@dataclasses.dataclass(eq=False)
class State:
    """Decoded TissueState (one frame). Units SI, model frame."""
    stamp_ns: int
    frame_id: str
    step: int
    sim_time: float                     # [s]
    joint_names: list
    joint_positions: np.ndarray         # (J,) float64 [rad]
    joint_velocities: np.ndarray        # (J,) float64 [rad/s]
    muscle_names: list
    activations: np.ndarray             # (M,) float32
    muscle_lengths: np.ndarray          # (M,) float32 [m]
    muscle_volumes: np.ndarray          # (M,) float32 [m^3]
    segment_poses: np.ndarray           # (S, 7) float64: x y z qx qy qz qw
    vertex_positions: np.ndarray        # (V, 3) float32 [m]
    kinetic_energy: float
    elastic_energy: float


# ------------------------------------------------------------------------------------ topology
def from_model(tm, parameters_yaml: str = '', model_hash: str | None = None,
               stamp_ns: int = 0, frame_id: str = 'world') -> Topology:
    """The Topology of a TissueModel (``model_hash`` defaults to ``tm.content_hash()``)."""
    return Topology(
        model_name=tm.name,
        model_hash=tm.content_hash() if model_hash is None else model_hash,
        parameters_yaml=parameters_yaml,
        rest_positions=np.asarray(tm.rest_positions, np.float32).reshape(-1, 3),
        vertex_segment=np.asarray(tm.vertex_segment, np.int32),
        cell_offsets=np.asarray(tm.cell_offsets, np.uint32),
        cell_vertices=np.asarray(tm.cell_vertices, np.uint32),
        cell_tissue=np.asarray(tm.cell_tissue, np.uint8),
        cell_muscle=np.asarray(tm.cell_muscle, np.int32),
        muscle_names=tuple(tm.muscle_names),
        muscle_groups=tuple(tm.muscle_groups),
        skin_quads=np.asarray(tm.skin_quads, np.uint32).reshape(-1, 4),
        skin_quad_cells=np.asarray(tm.skin_quad_cell, np.uint32),
        surface_triangles=np.asarray(tm.surface_triangles, np.uint32).reshape(-1, 3),
        surface_groups=np.asarray(tm.surface_group, np.int32),
        surface_group_names=tuple(tm.surface_group_names),
        segment_names=tuple(tm.segment_names),
        segment_parents=np.asarray(tm.segment_parent, np.int32),
        joint_names=tuple(tm.joint_names),
        bone_names=tuple(tm.bone_names),
        bone_segments=np.asarray(tm.bone_segment, np.int32),
        bone_vertex_offsets=np.asarray(tm.bone_vertex_offsets, np.uint32),
        bone_vertices=np.asarray(tm.bone_vertices, np.float32).reshape(-1, 3),
        bone_triangle_offsets=np.asarray(tm.bone_triangle_offsets, np.uint32),
        bone_triangles=np.asarray(tm.bone_triangles, np.uint32).reshape(-1, 3),
        stamp_ns=stamp_ns, frame_id=frame_id)


def encode_topology(topo: Topology, stamp_ns: int | None = None, frame_id: str | None = None) -> bytes:
    """CDR bytes of a TissueTopology message."""
    w = CdrWriter()
    w.header(topo.stamp_ns if stamp_ns is None else stamp_ns, topo.frame_id if frame_id is None else frame_id)
    w.string(topo.model_name)
    w.string(topo.model_hash)
    w.string(topo.parameters_yaml)
    w.array(topo.rest_positions, np.float32)
    w.array(topo.vertex_segment, np.int32)
    w.array(topo.cell_offsets, np.uint32)
    w.array(topo.cell_vertices, np.uint32)
    w.array(topo.cell_tissue, np.uint8)
    w.array(topo.cell_muscle, np.int32)
    w.string_seq(list(topo.muscle_names))
    w.string_seq(list(topo.muscle_groups))
    w.array(topo.skin_quads, np.uint32)
    w.array(topo.skin_quad_cells, np.uint32)
    w.array(topo.surface_triangles, np.uint32)
    w.array(topo.surface_groups, np.int32)
    w.string_seq(list(topo.surface_group_names))
    w.string_seq(list(topo.segment_names))
    w.array(topo.segment_parents, np.int32)
    w.string_seq(list(topo.joint_names))
    w.string_seq(list(topo.bone_names))
    w.array(topo.bone_segments, np.int32)
    w.array(topo.bone_vertex_offsets, np.uint32)
    w.array(topo.bone_vertices, np.float32)
    w.array(topo.bone_triangle_offsets, np.uint32)
    w.array(topo.bone_triangles, np.uint32)
    return w.bytes()


def _triples(a: np.ndarray, k: int, what: str) -> np.ndarray:
    if a.size % k:
        raise CdrError(f'{what} has {a.size} numbers, not a multiple of {k}')
    return a.reshape(-1, k)


def decode_topology(data) -> Topology:
    """Topology from CDR bytes; raises CdrError on truncated or inconsistent data."""
    r = CdrReader(data)
    stamp, frame = r.header()
    kw = dict(stamp_ns=stamp, frame_id=frame)
    kw['model_name'] = r.string()
    kw['model_hash'] = r.string()
    kw['parameters_yaml'] = r.string()
    kw['rest_positions'] = _triples(r.array(np.float32), 3, 'rest_positions')
    kw['vertex_segment'] = r.array(np.int32)
    kw['cell_offsets'] = r.array(np.uint32)
    kw['cell_vertices'] = r.array(np.uint32)
    kw['cell_tissue'] = r.array(np.uint8)
    kw['cell_muscle'] = r.array(np.int32)
    kw['muscle_names'] = tuple(r.string_seq())
    kw['muscle_groups'] = tuple(r.string_seq())
    kw['skin_quads'] = _triples(r.array(np.uint32), 4, 'skin_quads')
    kw['skin_quad_cells'] = r.array(np.uint32)
    kw['surface_triangles'] = _triples(r.array(np.uint32), 3, 'surface_triangles')
    kw['surface_groups'] = r.array(np.int32)
    kw['surface_group_names'] = tuple(r.string_seq())
    kw['segment_names'] = tuple(r.string_seq())
    kw['segment_parents'] = r.array(np.int32)
    kw['joint_names'] = tuple(r.string_seq())
    kw['bone_names'] = tuple(r.string_seq())
    kw['bone_segments'] = r.array(np.int32)
    kw['bone_vertex_offsets'] = r.array(np.uint32)
    kw['bone_vertices'] = _triples(r.array(np.float32), 3, 'bone_vertices')
    kw['bone_triangle_offsets'] = r.array(np.uint32)
    kw['bone_triangles'] = _triples(r.array(np.uint32), 3, 'bone_triangles')
    if not kw['cell_offsets'].size:
        kw['cell_offsets'] = np.zeros(1, np.uint32)
    for k in ('bone_vertex_offsets', 'bone_triangle_offsets'):
        if not kw[k].size:
            kw[k] = np.zeros(1, np.uint32)
    return Topology(**kw).validate()


# ------------------------------------------------------------------------------------ state
def encode_state(*, stamp_ns: int, frame_id: str = 'world', step: int = 0, sim_time: float = 0.0,
                 joint_names=(), joint_positions=(), joint_velocities=(),
                 muscle_names=(), activations=(), muscle_lengths=(), muscle_volumes=(),
                 segment_poses=(), vertex_positions=(), kinetic_energy: float = 0.0,
                 elastic_energy: float = 0.0) -> bytes:
    """CDR bytes of a TissueState message (about 1 ms for 8k vertices).

    segment_poses: (S, 7) x y z qx qy qz qw; vertex_positions: (V, 3) [m]. Arrays are cast to the
    message's types (float32 vertices, float64 joints and poses).
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
    return w.bytes()


def encode_state_obj(s: State) -> bytes:
    """CDR bytes of a :class:`State`."""
    return encode_state(**{f.name: getattr(s, f.name) for f in dataclasses.fields(State)})


def decode_state(data, with_vertices: bool = True) -> State:
    """State from CDR bytes; ``with_vertices=False`` skips copying the vertex array (fast scans)."""
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
    return State(stamp, frame, step, t, jn, jp, jv, mn, act, ml, mv, sp, vp, ke, ee)


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
