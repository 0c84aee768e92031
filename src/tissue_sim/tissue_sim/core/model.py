"""The immutable tissue model: topology, rest shapes, skeleton. Flat numpy arrays, no behaviour.

This is the contract between the model builder (which makes it), the solver (which compiles it with
physical parameters into a simulation), the nodes (which publish it) and the analysis (which reads
recorded runs against it).

Frames and units
----------------
Everything is SI (metres, kilograms, radians) in the *model frame*, REP-103 body convention:
x anterior (forward), y left, z superior (up). The builder converts a NIfTI volume's RAS+
millimetre world coordinates to it by ``model = (A, -R, S) / 1000``; the origin is wherever the
label volume's affine puts it (the bundled anatomy puts it at the right hip joint centre).

Soft tissue
-----------
* ``rest_positions`` (V, 3): soft-tissue (muscle and fat) vertices at rest.
* Cells are *prisms*: a cell with ``2n`` vertices lists its bottom ring (lower slice, ``n`` vertices)
  then its top ring (upper slice, ``n`` vertices) in the same angular order. Muscle cells are the
  paper's polygonal prisms (n = polygon vertex count), rings counter-clockwise seen from +z; fat
  cells are the paper's hexahedra (n = 4, ring order: inner a, inner b, outer b, outer a, where
  a -> b is counter-clockwise about the limb axis seen from +z and "outer" is the skin side; this
  ring is therefore *clockwise* seen from +z). Code that needs a cell's orientation (signed volume)
  must take it from the cell's tissue (or its signed rest volume), not assume one winding.
* ``vertex_segment`` (V,): -1 for a free vertex, else the index of the skeleton segment the vertex is
  fixed to (bone-attached vertex: it moves rigidly with that segment; its rest position is its
  position in the segment's rest pose).
* ``skin_quads`` (Q, 4): the skin-side face of each fat cell (outer a/b bottom, outer b/a top),
  ``skin_quad_cell`` (Q,) its fat cell. Used by the area-change analysis (paper Fig. 8).

Skeleton (a tree; nothing may assume a single joint)
---------------------------------------------------
* Segments: ``segment_parent[s]`` (-1 for the root), mass [kg], centre of mass [m, model frame at
  rest], inertia tensor about the COM [kg m^2, model frame axes at rest].
* Joints: one per non-root segment, joining ``joint_parent`` to ``joint_child``; ``joint_type``
  JOINT_FIXED, JOINT_HINGE or JOINT_COUPLED; hinge axis (unit, model frame at rest; positive rotation
  about it is the positive joint coordinate, e.g. knee flexion), centre [m], range [rad], rest coordinate.
* A coupled joint (e.g. the patellofemoral joint) has no degree of freedom of its own: its child's
  pose relative to its parent is a function of its driver hinge's coordinate (``joint_driver[j]``), a
  table ``coupling_table[coupling_offsets[j]:coupling_offsets[j + 1]]`` of rows (driver coordinate
  [rad], angle [rad], dx, dy, dz [m]) interpolated by a cubic spline: a rest point p of the child goes
  to Rot(axis, angle) (p - centre) + centre + d in its parent's frame (axis and centre: the joint's).
  Its coordinate (q) is the angle; its range is the table's angle range.
* A hinge may have a path (the knee: the source model's walker knee): a table
  ``joint_path_table[joint_path_offsets[j]:joint_path_offsets[j + 1]]`` of rows (q [rad], angle 2 [rad],
  angle 3 [rad], dx, dy, dz [m]) interpolated by a cubic spline, and two secondary axes ``joint_path_axes[j]``
  (unit, parent's rest frame): a rest point p of the child goes to Rot(axis, q - rest) Rot(axes[0], angle 2)
  Rot(axes[1], angle 3) (p - centre) + centre + d, each axis taken in the frame the rotations before it have
  turned (an OpenSim CustomJoint with one coordinate). The solver follows it with ``Params.joint_paths``.
* The pose of a segment is a rigid transform applied to *rest* coordinates: a point p_rest on the
  segment is at ``R_s @ p_rest + t_s``; at rest every segment has R = I, t = 0.

Bones are rigid surface meshes, each on one segment.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np

FORMAT = 'tissue_sim.model'
FORMAT_VERSION = 1

TISSUE_MUSCLE = 1
TISSUE_FAT = 2

JOINT_FIXED = 0
JOINT_HINGE = 1
JOINT_COUPLED = 2       # pose a function of another joint's coordinate (joint_driver, coupling_table)

# vertex_flags bits
VF_MUSCLE = 1       # used by at least one muscle cell
VF_FAT = 2          # used by at least one fat cell
VF_SHARED = 4       # merged from vertices of different tissues (paper section 2.4)
VF_SKIN = 8         # on the skin surface


class ModelError(ValueError):
    """A model file or array set that is not a valid TissueModel (message names the problem)."""


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class TissueTopology:
    """The topology and rest shape of a model: what the ``TissueTopology`` message carries.

    :class:`TissueModel` extends it with the mechanical data (masses, joints, fibres, ...); a
    decoded topology message (:func:`tissue_sim.core.tissue_cdr.decode_topology`) is a
    ``TissueTopology`` whose ``meta`` holds the message's ``model_hash``, ``parameters_yaml``,
    ``frame_id`` and ``stamp_ns``. Code that only draws or measures a model (the analysis, the
    markers) takes either.
    """
    name: str
    # --- soft tissue -------------------------------------------------------------------------
    rest_positions: np.ndarray          # (V, 3) float64 [m]
    vertex_segment: np.ndarray          # (V,) int32, -1 free
    cell_offsets: np.ndarray            # (C+1,) int64
    cell_vertices: np.ndarray           # (K,) int32
    cell_tissue: np.ndarray             # (C,) uint8, TISSUE_*
    cell_muscle: np.ndarray             # (C,) int32, -1 for fat
    skin_quads: np.ndarray              # (Q, 4) int32
    skin_quad_cell: np.ndarray          # (Q,) int32
    surface_triangles: np.ndarray       # (T, 3) int32 into rest_positions, outward
    surface_group: np.ndarray           # (T,) int32 into surface_group_names
    surface_group_names: tuple          # ("skin", "muscle/<name>", ...)
    # --- muscles -----------------------------------------------------------------------------
    muscle_names: tuple                 # (M,) str
    muscle_groups: tuple                # (M,) str, e.g. "hamstrings", "quadriceps", ""
    # --- bones -------------------------------------------------------------------------------
    bone_names: tuple                   # (B,) str
    bone_segment: np.ndarray            # (B,) int32
    bone_vertex_offsets: np.ndarray     # (B+1,) int64
    bone_vertices: np.ndarray           # (NB, 3) float64 [m], rest pose, model frame
    bone_triangle_offsets: np.ndarray   # (B+1,) int64
    bone_triangles: np.ndarray          # (NT, 3) int32, local to each bone's vertex block
    # --- skeleton ----------------------------------------------------------------------------
    segment_names: tuple                # (S,) str
    segment_parent: np.ndarray          # (S,) int32, -1 root
    joint_names: tuple                  # (J,) str
    meta: dict = dataclasses.field(default_factory=dict)   # JSON-able: source, builder settings, ...

    # ---------------------------------------------------------------------------- conveniences
    @property
    def n_vertices(self) -> int:
        return int(self.rest_positions.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cell_tissue.shape[0])

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_names)

    @property
    def n_segments(self) -> int:
        return len(self.segment_names)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def cell(self, c: int) -> np.ndarray:
        """Vertex indices of cell c (bottom ring then top ring)."""
        return self.cell_vertices[self.cell_offsets[c]:self.cell_offsets[c + 1]]

    def muscle_index(self, name: str) -> int:
        """Index of a muscle name; KeyError naming the model's muscles (tissue_sim.core.activation)."""
        from tissue_sim.core.activation import Muscles
        return Muscles.of(self).index(name)

    def bone_mesh(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, triangles) of bone b at rest."""
        v = self.bone_vertices[self.bone_vertex_offsets[b]:self.bone_vertex_offsets[b + 1]]
        t = self.bone_triangles[self.bone_triangle_offsets[b]:self.bone_triangle_offsets[b + 1]]
        return v, t

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v.flags.writeable = False

    def validate_topology(self) -> 'TissueTopology':
        """Check the index ranges of the topology arrays; raise ModelError naming the first problem
        (what a decoded topology message can be checked for; :meth:`TissueModel.validate` checks more)."""
        V, C = self.n_vertices, self.n_cells

        def need(cond, msg):
            if not cond:
                raise ModelError(f'topology {self.name!r}: {msg}')

        need(self.rest_positions.ndim == 2 and self.rest_positions.shape[1] == 3, 'rest_positions must be (V, 3)')
        need(self.cell_offsets.shape == (C + 1,) and self.cell_offsets[0] == 0
             and self.cell_offsets[-1] == self.cell_vertices.size, 'cell_offsets inconsistent with cell_vertices')
        need(np.all(np.diff(self.cell_offsets) >= 0), 'cell_offsets must not decrease')
        need(self.cell_vertices.size == 0 or (self.cell_vertices.min() >= 0 and self.cell_vertices.max() < V),
             'cell_vertices index out of range')
        need(self.cell_muscle.shape == (C,), 'cell_muscle must have one entry per cell')
        need(self.vertex_segment.shape == (V,), 'vertex_segment must have one entry per vertex')
        need(self.skin_quads.size == 0 or self.skin_quads.max() < V, 'skin_quads index out of range')
        need(self.skin_quad_cell.size == 0 or self.skin_quad_cell.max() < C, 'skin_quad_cell index out of range')
        need(self.skin_quad_cell.shape[0] == self.skin_quads.shape[0], 'skin_quad_cell must match skin_quads')
        need(self.surface_triangles.size == 0 or self.surface_triangles.max() < V, 'surface_triangles index out of range')
        need(self.surface_group.shape[0] == self.surface_triangles.shape[0], 'surface_group must match surface_triangles')
        need(len(self.muscle_groups) == len(self.muscle_names), 'muscle_groups must match muscle_names')
        need(self.segment_parent.shape == (len(self.segment_names),), 'segment_parent must match segment_names')
        B = len(self.bone_names)
        need(self.bone_segment.shape == (B,) and self.bone_vertex_offsets.shape == (B + 1,)
             and self.bone_triangle_offsets.shape == (B + 1,), 'bone arrays inconsistent')
        return self


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class TissueModel(TissueTopology):
    """The whole model: its :class:`TissueTopology` plus what the solver needs."""
    vertex_flags: np.ndarray            # (V,) uint8, VF_* bits
    cell_fibre: np.ndarray              # (C, 3) float64 unit fibre (long) axis at rest; fat: limb axis
    cell_slice: np.ndarray              # (C,) int32 index into slice_z of the bottom ring
    cell_k_scale: np.ndarray            # (C,) float64 stiffness multiplier from the tissue table (1.0)
    muscle_max_force: np.ndarray        # (M,) float64 [N] max isometric force, NaN if unknown
    muscle_fibre_length: np.ndarray     # (M,) float64 [m] optimal fibre length, NaN if unknown
    segment_mass: np.ndarray            # (S,) float64 [kg]
    segment_com: np.ndarray             # (S, 3) float64 [m]
    segment_inertia: np.ndarray         # (S, 3, 3) float64 [kg m^2] about the COM
    joint_type: np.ndarray              # (J,) uint8
    joint_parent: np.ndarray            # (J,) int32 segment
    joint_child: np.ndarray             # (J,) int32 segment
    joint_axis: np.ndarray              # (J, 3) float64 unit
    joint_centre: np.ndarray            # (J, 3) float64 [m]
    joint_range: np.ndarray             # (J, 2) float64 [rad]
    joint_rest: np.ndarray              # (J,) float64 [rad] coordinate of the rest pose
    slice_z: np.ndarray                 # (Z,) float64 [m] height of each slice used
    # coupled joints (JOINT_COUPLED); None = none (defaults filled in): see the module docstring
    joint_driver: np.ndarray = None     # (J,) int32 driving hinge of a coupled joint, -1 otherwise
    coupling_offsets: np.ndarray = None     # (J+1,) int64 rows of each joint in coupling_table
    coupling_table: np.ndarray = None   # (N, 5) float64 rows (driver [rad], angle [rad], dx, dy, dz [m])
    # hinges with a path (see the module docstring); None = none
    joint_path_offsets: np.ndarray = None   # (J+1,) int64 rows of each hinge in joint_path_table
    joint_path_table: np.ndarray = None     # (N, 6) float64 rows (q [rad], angle 2, angle 3 [rad], dx, dy, dz [m])
    joint_path_axes: np.ndarray = None      # (J, 2, 3) float64 the secondary rotation axes (unit; zeros without a path)

    muscle_rest_fibre_length: np.ndarray = None   # (M,) float64 normalised fibre length in the rest pose (tissue table's
                                                  # rest_fibre_length); None / absent from a file: 1.0 each
    # muscle paths (the tissue table's muscle_paths file; docs/solver.md "Force-length"); None / absent: none (P = 0).
    # Per OpenSim muscle part p: the musculotendon length L_MT = sum_t path_coef[p, t] prod_j q_j^path_powers[t, j]
    # [m] of the joint coordinates q [rad]
    path_muscle: np.ndarray = None      # (P,) int32 the muscle of each part
    path_data: np.ndarray = None        # (P, 4) float64 Fmax share (of its muscle's), L_opt [m], tendon slack [m],
                                        # fibre height L_opt sin(pennation at L_opt) [m]
    path_powers: np.ndarray = None      # (T, J) int32 exponents of each monomial
    path_coef: np.ndarray = None        # (P, T) float64 [m] coefficients
    # point via rings (the builder's via points whose ring cannot be bound whole; docs/builder.md "Via points"): ring r's
    # vertices via_point_vertices[via_point_offsets[r]:via_point_offsets[r + 1]] keep their centroid at its rest place
    # in segment via_point_segment[r]'s frame while the ring turns freely; via_point_muscle[r] its muscle.
    # None / absent from a file: none (R = 0)
    via_point_offsets: np.ndarray = None    # (R+1,) int64
    via_point_vertices: np.ndarray = None   # (N,) int32
    via_point_segment: np.ndarray = None    # (R,) int32
    via_point_muscle: np.ndarray = None     # (R,) int32
    # wrap surfaces (the source model's wrap cylinders; docs/contact.md "Wrap surfaces"): surface w is a cylinder fixed in
    # segment wrap_segment[w]'s frame (its rest frame is the model frame at rest); wrap_geometry[w] = centre (3) [m], unit
    # axis (3), unit quadrant direction (3; zeros: every side), radius [m], length [m]; it keeps out the free vertices of
    # the cells of muscles wrap_muscles[wrap_muscle_offsets[w]:wrap_muscle_offsets[w + 1]]; wrap_names[w] its name.
    # None / absent from a file: none (W = 0)
    wrap_names: tuple = None              # (W,) str
    wrap_segment: np.ndarray = None       # (W,) int32
    wrap_geometry: np.ndarray = None      # (W, 11) float64
    wrap_muscle_offsets: np.ndarray = None   # (W+1,) int64
    wrap_muscles: np.ndarray = None       # (N,) int32

    def __post_init__(self):
        J = len(self.joint_names)
        for name, default in (('joint_driver', lambda: np.full(J, -1, np.int32)),
                              ('coupling_offsets', lambda: np.zeros(J + 1, np.int64)),
                              ('coupling_table', lambda: np.zeros((0, 5))),
                              ('joint_path_offsets', lambda: np.zeros(J + 1, np.int64)),
                              ('joint_path_table', lambda: np.zeros((0, 6))),
                              ('joint_path_axes', lambda: np.zeros((J, 2, 3))),
                              ('muscle_rest_fibre_length', lambda: np.ones(len(self.muscle_names))),
                              ('path_muscle', lambda: np.zeros(0, np.int32)), ('path_data', lambda: np.zeros((0, 4))),
                              ('path_powers', lambda: np.zeros((0, J), np.int32)),
                              ('via_point_offsets', lambda: np.zeros(1, np.int64)),
                              ('via_point_vertices', lambda: np.zeros(0, np.int32)),
                              ('via_point_segment', lambda: np.zeros(0, np.int32)),
                              ('via_point_muscle', lambda: np.zeros(0, np.int32)),
                              ('wrap_names', lambda: ()), ('wrap_segment', lambda: np.zeros(0, np.int32)),
                              ('wrap_geometry', lambda: np.zeros((0, 11))),
                              ('wrap_muscle_offsets', lambda: np.zeros(1, np.int64)),
                              ('wrap_muscles', lambda: np.zeros(0, np.int32)),
                              ('path_coef', lambda: np.zeros((len(self.path_muscle) if self.path_muscle is not None
                                                              else 0, 0)))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, default())
        super().__post_init__()

    # ---------------------------------------------------------------------------- validation
    def validate(self) -> 'TissueModel':
        """Check shapes, index ranges and finiteness; raise ModelError naming the first problem."""
        V, C = self.n_vertices, self.n_cells
        M, S, J, B = self.n_muscles, self.n_segments, self.n_joints, len(self.bone_names)

        def need(cond, msg):
            if not cond:
                raise ModelError(f'model {self.name!r}: {msg}')

        need(self.rest_positions.shape == (V, 3), 'rest_positions must be (V, 3)')
        need(np.all(np.isfinite(self.rest_positions)), 'rest_positions has non-finite values')
        need(self.vertex_segment.shape == (V,) and self.vertex_flags.shape == (V,), 'vertex arrays must be (V,)')
        need(np.all((self.vertex_segment >= -1) & (self.vertex_segment < S)), 'vertex_segment out of range')
        need(self.cell_offsets.shape == (C + 1,) and self.cell_offsets[0] == 0
             and self.cell_offsets[-1] == self.cell_vertices.shape[0], 'cell_offsets inconsistent with cell_vertices')
        sizes = np.diff(self.cell_offsets)
        need(np.all(sizes >= 6) and np.all(sizes % 2 == 0), 'every cell must be a prism with an even vertex count >= 6')
        need(self.cell_vertices.size == 0 or (self.cell_vertices.min() >= 0 and self.cell_vertices.max() < V),
             'cell_vertices index out of range')
        need(self.cell_tissue.shape == (C,) and self.cell_muscle.shape == (C,) and self.cell_slice.shape == (C,),
             'cell arrays must be (C,)')
        need(np.all(np.isin(self.cell_tissue, (TISSUE_MUSCLE, TISSUE_FAT))), 'cell_tissue must be 1 (muscle) or 2 (fat)')
        mus = self.cell_tissue == TISSUE_MUSCLE
        need(np.all((self.cell_muscle[mus] >= 0) & (self.cell_muscle[mus] < M)), 'muscle cell with bad cell_muscle')
        need(np.all(self.cell_muscle[~mus] == -1), 'fat cell with cell_muscle != -1')
        need(self.cell_fibre.shape == (C, 3) and np.allclose(np.linalg.norm(self.cell_fibre, axis=1), 1.0, atol=1e-6),
             'cell_fibre must be (C, 3) unit vectors')
        need(self.cell_k_scale.shape == (C,) and np.all(self.cell_k_scale > 0), 'cell_k_scale must be (C,) positive')
        if C:
            # no inverted cell: muscle rings counter-clockwise seen from +z (positive volume), fat cells
            # all wound alike (clockwise by contract; the solver takes a cell's orientation from its
            # signed rest volume, so a model whose fat cells are all counter-clockwise still
            # simulates, but a cell wound against the others is inverted)
            from tissue_sim.core.geometry import prism_volumes
            fat = self.cell_tissue == TISSUE_FAT
            vol = prism_volumes(self.rest_positions, self.cell_offsets, self.cell_vertices, flip=fat)
            fat_sign = 1.0 if np.sum(vol[fat] > 0) >= np.sum(vol[fat] < 0) else -1.0
            bad = np.nonzero(np.isnan(vol) | (~fat & (vol < 0)) | (fat & (vol * fat_sign < 0)))[0]
            if len(bad):
                c = int(bad[0])
                need(False, f'{len(bad)} inverted cell(s) (the first: cell {c}, {"fat" if fat[c] else "muscle"}, '
                     f'rest volume {vol[c] * 1e9:.3g} mm^3, rings wound against '
                     f'{"the other fat cells" if fat[c] else "the contract (counter-clockwise from +z)"})')
        R = self.via_point_segment.shape[0]
        vo, vv = self.via_point_offsets, self.via_point_vertices
        need(vo.shape == (R + 1,) and vo[0] == 0 and vo[-1] == vv.shape[0] and np.all(np.diff(vo) >= 3)
             and self.via_point_muscle.shape == (R,), 'via_point_offsets inconsistent with via_point_vertices, '
             'via_point_segment and via_point_muscle (rings of >= 3 vertices)')
        need(vv.size == 0 or (vv.min() >= 0 and vv.max() < V), 'via_point_vertices index out of range')
        need(np.all((self.via_point_segment >= 0) & (self.via_point_segment < S))
             and np.all((self.via_point_muscle >= 0) & (self.via_point_muscle < M)),
             'via_point_segment or via_point_muscle out of range')
        W = len(self.wrap_names)
        wg, wo, wm = self.wrap_geometry, self.wrap_muscle_offsets, self.wrap_muscles
        need(self.wrap_segment.shape == (W,) and wg.shape == (W, 11) and wo.shape == (W + 1,) and wm.ndim == 1
             and wo[0] == 0 and wo[-1] == wm.shape[0] and np.all(np.diff(wo) >= 0),
             'wrap arrays inconsistent (wrap_segment (W,), wrap_geometry (W, 11), wrap_muscle_offsets (W+1,) into '
             'wrap_muscles, one row per wrap_names)')
        need(np.all((self.wrap_segment >= 0) & (self.wrap_segment < S)) and np.all((wm >= 0) & (wm < M)),
             'wrap_segment or wrap_muscles out of range')
        need(len(set(self.wrap_names)) == W, 'wrap names must be unique')
        need(np.all(np.isfinite(wg)), 'wrap_geometry has non-finite values')
        if W:
            quad = np.linalg.norm(wg[:, 6:9], axis=1)
            need(np.allclose(np.linalg.norm(wg[:, 3:6], axis=1), 1.0, atol=1e-6)
                 and np.all(np.isclose(quad, 1.0, atol=1e-6) | (quad == 0.0)),
                 'wrap_geometry axes must be unit vectors, quadrant directions unit or zero')
            need(np.all(wg[:, 9:11] > 0), 'wrap_geometry radius and length must be > 0')
        need(self.skin_quads.ndim == 2 and self.skin_quads.shape[1] == 4 and self.skin_quad_cell.shape == (self.skin_quads.shape[0],),
             'skin_quads must be (Q, 4) with skin_quad_cell (Q,)')
        need(self.surface_triangles.ndim == 2 and self.surface_triangles.shape[1] == 3, 'surface_triangles must be (T, 3)')
        need(self.surface_group.shape == (self.surface_triangles.shape[0],), 'surface_group must be (T,)')
        need(len(self.muscle_groups) == M and self.muscle_max_force.shape == (M,) and self.muscle_fibre_length.shape == (M,),
             'muscle arrays must be (M,)')
        need(len(set(self.muscle_names)) == M, 'muscle names must be unique')
        need(np.shape(self.muscle_rest_fibre_length) == (M,) and np.all(np.isfinite(self.muscle_rest_fibre_length))
             and np.all(np.asarray(self.muscle_rest_fibre_length) > 0), 'muscle_rest_fibre_length must be (M,) and > 0')
        P, T = len(self.path_muscle), len(self.path_powers)
        need(self.path_data.shape == (P, 4) and self.path_powers.shape == (T, J) and self.path_coef.shape == (P, T)
             and np.all((self.path_muscle >= 0) & (self.path_muscle < M)) and np.all(self.path_powers >= 0)
             and np.all(np.isfinite(self.path_data)) and np.all(np.isfinite(self.path_coef))
             and np.all(self.path_data[:, :2] > 0), 'muscle path arrays inconsistent (path_muscle (P,), path_data (P, 4) '
             'with Fmax share and L_opt > 0, path_powers (T, J), path_coef (P, T))')
        need(self.bone_segment.shape == (B,) and self.bone_vertex_offsets.shape == (B + 1,)
             and self.bone_triangle_offsets.shape == (B + 1,), 'bone arrays inconsistent')
        need(self.segment_parent.shape == (S,) and self.segment_mass.shape == (S,) and self.segment_com.shape == (S, 3)
             and self.segment_inertia.shape == (S, 3, 3), 'segment arrays must be (S, ...)')
        need(np.sum(self.segment_parent == -1) == 1, 'the skeleton must have exactly one root segment')
        need(np.all(self.segment_mass > 0), 'segment masses must be positive')
        for a in (self.joint_type, self.joint_parent, self.joint_child, self.joint_rest):
            need(a.shape[0] == J, 'joint arrays must have one row per joint')
        need(self.joint_axis.shape == (J, 3) and self.joint_centre.shape == (J, 3) and self.joint_range.shape == (J, 2),
             'joint axis/centre/range shapes')
        need(np.all(self.joint_range[:, 0] <= self.joint_range[:, 1]), 'joint range lower > upper')
        need(np.all((self.joint_parent >= 0) & (self.joint_parent < S)) and np.all((self.joint_child >= 0) & (self.joint_child < S))
             and np.all((self.segment_parent >= -1) & (self.segment_parent < S)), 'joint or segment parent index out of range')
        need(np.all((self.bone_segment >= 0) & (self.bone_segment < S)), 'bone_segment out of range')
        need(all(np.all(np.isfinite(a)) for a in (self.segment_com, self.segment_inertia, self.joint_axis, self.joint_centre,
                                                   self.bone_vertices, self.cell_fibre, self.slice_z)),
             'skeleton, bone or cell arrays have non-finite values')
        for nm, tri, n in (('skin_quads', self.skin_quads, V), ('surface_triangles', self.surface_triangles, V),
                           ('skin_quad_cell', self.skin_quad_cell, C), ('surface_group', self.surface_group, len(self.surface_group_names))):
            need(tri.size == 0 or (tri.min() >= 0 and tri.max() < n), f'{nm} index out of range')
        need(self.bone_vertices.ndim == 2 and self.bone_vertices.shape[1] == 3 and self.bone_triangles.ndim == 2
             and self.bone_triangles.shape[1] == 3, 'bone_vertices and bone_triangles must be (N, 3)')
        need(self.bone_vertex_offsets[0] == 0 and self.bone_vertex_offsets[-1] == len(self.bone_vertices)
             and np.all(np.diff(self.bone_vertex_offsets) >= 0) and self.bone_triangle_offsets[0] == 0
             and self.bone_triangle_offsets[-1] == len(self.bone_triangles) and np.all(np.diff(self.bone_triangle_offsets) >= 0),
             'bone offsets inconsistent with bone_vertices/bone_triangles')
        for b in range(B):
            v, t = self.bone_mesh(b)
            need(t.size == 0 or (t.min() >= 0 and t.max() < len(v)), f'bone {self.bone_names[b]!r}: triangle index out of range')
        for j in range(J):
            need(self.segment_parent[self.joint_child[j]] == self.joint_parent[j],
                 f'joint {self.joint_names[j]!r}: parent/child do not match segment_parent')
        need(np.all(np.isin(self.joint_type, (JOINT_FIXED, JOINT_HINGE, JOINT_COUPLED))), 'joint_type must be 0, 1 or 2')
        need(self.joint_driver.shape == (J,) and self.coupling_offsets.shape == (J + 1,)
             and self.coupling_table.ndim == 2 and self.coupling_table.shape[1] == 5
             and self.coupling_offsets[0] == 0 and self.coupling_offsets[-1] == len(self.coupling_table)
             and np.all(np.diff(self.coupling_offsets) >= 0), 'coupling arrays inconsistent')
        need(np.all(np.isfinite(self.coupling_table)), 'coupling_table has non-finite values')
        need(self.joint_path_offsets.shape == (J + 1,) and self.joint_path_table.ndim == 2
             and self.joint_path_table.shape[1] == 6 and self.joint_path_axes.shape == (J, 2, 3)
             and self.joint_path_offsets[0] == 0 and self.joint_path_offsets[-1] == len(self.joint_path_table)
             and np.all(np.diff(self.joint_path_offsets) >= 0), 'joint path arrays inconsistent')
        need(np.all(np.isfinite(self.joint_path_table)) and np.all(np.isfinite(self.joint_path_axes)),
             'joint path arrays have non-finite values')
        for j in range(J):
            rows = self.joint_path_table[self.joint_path_offsets[j]:self.joint_path_offsets[j + 1]]
            if len(rows):
                need(self.joint_type[j] == JOINT_HINGE, f'joint {self.joint_names[j]!r}: only a hinge may have a path')
                need(len(rows) >= 4 and np.all(np.diff(rows[:, 0]) > 0),
                     f'hinge {self.joint_names[j]!r}: its path needs >= 4 rows in increasing coordinate')
                need(np.allclose(np.linalg.norm(self.joint_path_axes[j], axis=1), 1.0, atol=1e-6),
                     f'hinge {self.joint_names[j]!r}: its path axes must be unit vectors')
        for j in range(J):
            rows = self.coupling_table[self.coupling_offsets[j]:self.coupling_offsets[j + 1]]
            if self.joint_type[j] == JOINT_COUPLED:
                d = int(self.joint_driver[j])
                need(0 <= d < J and self.joint_type[d] == JOINT_HINGE,
                     f'coupled joint {self.joint_names[j]!r}: its driver must be a hinge')
                need(len(rows) >= 4 and np.all(np.diff(rows[:, 0]) > 0),
                     f'coupled joint {self.joint_names[j]!r}: needs >= 4 table rows in increasing driver coordinate')
                need(not np.any(self.segment_parent == self.joint_child[j]),
                     f'coupled joint {self.joint_names[j]!r}: its child segment must be a leaf of the skeleton')
            else:
                need(self.joint_driver[j] == -1 and len(rows) == 0,
                     f'joint {self.joint_names[j]!r}: only a coupled joint has a driver and a table')
        return self

    # ---------------------------------------------------------------------------- file I/O
    def to_arrays(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                out[f.name] = v
            elif isinstance(v, tuple):
                out[f.name] = np.array(v, dtype=str) if len(v) else np.zeros(0, dtype='<U1')
        return out

    def save(self, path) -> Path:
        """Write one versioned file (.npz: arrays + a JSON header). Returns the path."""
        path = Path(path)
        header = {'format': FORMAT, 'version': FORMAT_VERSION, 'name': self.name, 'meta': self.meta}
        buf = io.BytesIO()
        np.savez_compressed(buf, __header__=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8),
                            **self.to_arrays())
        path.write_bytes(buf.getvalue())
        return path

    @classmethod
    def load(cls, path) -> 'TissueModel':
        """Read a model file written by :meth:`save`; raise ModelError naming the problem (never
        another exception) for a file that is missing, not a model, of another format version,
        or whose arrays do not make a valid model (see :meth:`validate`)."""
        path = Path(path)
        if not path.is_file():
            raise ModelError(f'{path}: no such model file')
        try:
            z = np.load(path, allow_pickle=False)
            if not hasattr(z, 'files'):
                raise ValueError('a single array, not an .npz archive')
            with z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as e:
            raise ModelError(f'{path}: not a tissue_sim model file ({e})') from None
        if '__header__' not in arrays:
            raise ModelError(f'{path}: not a tissue_sim model file (no header)')
        hb = arrays.pop('__header__')
        try:
            if hb.dtype != np.uint8 or hb.ndim != 1:
                raise ValueError(f'header array is {hb.dtype} {hb.shape}, expected uint8 bytes')
            header = json.loads(hb.tobytes().decode('utf-8'))
        except (ValueError, UnicodeDecodeError) as e:
            raise ModelError(f'{path}: damaged model header (not UTF-8 JSON: {e})') from None
        if not isinstance(header, dict):
            raise ModelError(f'{path}: damaged model header (a JSON {type(header).__name__}, expected an object)')
        if header.get('format') != FORMAT:
            raise ModelError(f'{path}: format {header.get("format")!r}, expected {FORMAT!r}')
        ver = header.get('version')
        if type(ver) is not int or ver != FORMAT_VERSION:
            raise ModelError(f'{path}: model format version {ver!r} ({type(ver).__name__}), this tissue_sim reads '
                             f'version {FORMAT_VERSION} (an integer); rebuild the model')
        name, meta = header.get('name'), header.get('meta', {})
        if not isinstance(name, str) or not name:
            raise ModelError(f'{path}: damaged model header (no model "name")')
        if not isinstance(meta, dict):
            raise ModelError(f'{path}: damaged model header ("meta" is a {type(meta).__name__}, expected an object)')
        index_fields = {'vertex_segment', 'vertex_flags', 'cell_offsets', 'cell_vertices', 'cell_tissue', 'cell_muscle',
                        'cell_slice', 'skin_quads', 'skin_quad_cell', 'surface_triangles', 'surface_group',
                        'bone_segment', 'bone_vertex_offsets', 'bone_triangle_offsets', 'bone_triangles',
                        'segment_parent', 'joint_type', 'joint_parent', 'joint_child', 'joint_driver',
                        'coupling_offsets', 'path_muscle', 'path_powers', 'joint_path_offsets',
                        'via_point_offsets', 'via_point_vertices', 'via_point_segment', 'via_point_muscle',
                        'wrap_segment', 'wrap_muscle_offsets', 'wrap_muscles'}
        optional = {'joint_driver', 'coupling_offsets', 'coupling_table',      # a model without coupled joints
                    'joint_path_offsets', 'joint_path_table', 'joint_path_axes',  # no hinge with a path
                    'muscle_rest_fibre_length',                             # a file written before the field: 1.0
                    'path_muscle', 'path_data', 'path_powers', 'path_coef',  # no muscle paths
                    'via_point_offsets', 'via_point_vertices', 'via_point_segment', 'via_point_muscle',   # none
                    'wrap_names', 'wrap_segment', 'wrap_geometry', 'wrap_muscle_offsets', 'wrap_muscles'}  # no wrap surfaces
        kw = {}
        for f in dataclasses.fields(cls):
            if f.name in ('name', 'meta'):
                continue
            if f.name not in arrays:
                if f.name in optional:
                    continue
                raise ModelError(f'{path}: missing array {f.name!r}')
            a = arrays[f.name]
            if f.type == 'tuple':
                if a.ndim != 1 or a.dtype.kind not in 'U':
                    raise ModelError(f'{path}: array {f.name!r} must be a list of names, got {a.dtype} {a.shape}')
                kw[f.name] = tuple(str(s) for s in a)
            else:
                integer = f.name in index_fields
                if a.dtype.kind not in ('iu' if integer else 'iuf'):
                    raise ModelError(f'{path}: array {f.name!r} has dtype {a.dtype}, expected '
                                     f'{"an integer" if integer else "a numeric"} type')
                kw[f.name] = a
        try:
            return cls(name=name, meta=meta, **kw).validate()
        except ModelError as e:
            raise ModelError(f'{path}: {e}') from None
        except (ValueError, IndexError, TypeError) as e:      # an array shape the checks did not anticipate
            raise ModelError(f'{path}: damaged model ({type(e).__name__}: {e})') from None

    def content_hash(self) -> str:
        h = hashlib.sha256()
        for k, v in sorted(self.to_arrays().items()):
            h.update(k.encode())
            h.update(np.ascontiguousarray(v).tobytes())
        return h.hexdigest()
