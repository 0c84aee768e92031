"""Small analytic TissueModels for solver tests and benchmarks (no anatomy, no builder needed).

* ``one_cell(n_ring=4)``: one free prism cell (a hexahedron for n_ring = 4) on a root segment.
* ``knee(...)``: thigh (root) and shank joined by a hinge knee at the origin (axis +y: positive =
  flexion, the shank swings backwards); a "hamstring" prism column behind (x < 0) and a
  "quadriceps" column in front (x > 0), top rings fixed to the thigh, bottom rings to the shank;
  optionally more muscle columns around the bone and a fat layer of hexahedra (inner vertices of
  the end slices fixed to the bones), to reach the size of the default model for benchmarks.
"""
from __future__ import annotations

import numpy as np

from tissue_sim.core.model import JOINT_HINGE, TISSUE_FAT, TISSUE_MUSCLE, VF_FAT, VF_MUSCLE, TissueModel


def _model(name, rest, vseg, flags, cells, tissue, muscle, fibre, cslice, muscles, groups, slice_z,
           n_seg=2, knee_range=(0.0, np.radians(120.0)), seg=None, paths=None):
    off = np.concatenate([[0], np.cumsum([len(c) for c in cells])]).astype(np.int64)
    cv = np.concatenate(cells).astype(np.int32)
    C = len(cells)
    if seg is not None:
        pass
    elif n_seg == 1:
        seg = dict(segment_names=('thigh',), segment_parent=np.array([-1], np.int32), segment_mass=np.array([10.0]),
                   segment_com=np.array([[0, 0, 0.2]]), segment_inertia=np.array([np.diag([0.2, 0.2, 0.04])]),
                   joint_names=(), joint_type=np.zeros(0, np.uint8), joint_parent=np.zeros(0, np.int32),
                   joint_child=np.zeros(0, np.int32), joint_axis=np.zeros((0, 3)), joint_centre=np.zeros((0, 3)),
                   joint_range=np.zeros((0, 2)), joint_rest=np.zeros(0))
    else:
        seg = dict(segment_names=('thigh', 'shank'), segment_parent=np.array([-1, 0], np.int32),
                   segment_mass=np.array([10.4, 3.4]), segment_com=np.array([[0, 0, 0.2], [0, 0, -0.18]]),
                   segment_inertia=np.array([np.diag([0.2, 0.2, 0.04]), np.diag([0.04, 0.04, 0.006])]),
                   joint_names=('knee_r',), joint_type=np.array([JOINT_HINGE], np.uint8),
                   joint_parent=np.array([0], np.int32), joint_child=np.array([1], np.int32),
                   joint_axis=np.array([[0.0, 1.0, 0.0]]), joint_centre=np.zeros((1, 3)),
                   joint_range=np.array([knee_range]), joint_rest=np.zeros(1))
    M = len(muscles)
    return TissueModel(
        name=name, rest_positions=np.asarray(rest, float), vertex_segment=np.asarray(vseg, np.int32),
        vertex_flags=np.asarray(flags, np.uint8), cell_offsets=off, cell_vertices=cv,
        cell_tissue=np.asarray(tissue, np.uint8), cell_muscle=np.asarray(muscle, np.int32),
        cell_fibre=np.asarray(fibre, float).reshape(C, 3), cell_slice=np.asarray(cslice, np.int32),
        cell_k_scale=np.ones(C), skin_quads=np.zeros((0, 4), np.int32), skin_quad_cell=np.zeros(0, np.int32),
        surface_triangles=np.zeros((0, 3), np.int32), surface_group=np.zeros(0, np.int32), surface_group_names=(),
        muscle_names=tuple(muscles), muscle_groups=tuple(groups), muscle_max_force=np.full(M, np.nan),
        muscle_fibre_length=np.full(M, np.nan), bone_names=(), bone_segment=np.zeros(0, np.int32),
        bone_vertex_offsets=np.zeros(1, np.int64), bone_vertices=np.zeros((0, 3)),
        bone_triangle_offsets=np.zeros(1, np.int64), bone_triangles=np.zeros((0, 3), np.int32),
        slice_z=np.asarray(slice_z, float), meta={'phantom': name}, **(paths or {}), **seg).validate()


def one_cell(n_ring: int = 4, size: float = 0.02, tissue: int = TISSUE_MUSCLE) -> TissueModel:
    """One free prism (n_ring-gon, circumradius size, height 2*size) centred at the origin."""
    ang = 2 * np.pi * np.arange(n_ring) / n_ring + np.pi / n_ring
    ring = np.stack([size * np.cos(ang), size * np.sin(ang), np.zeros(n_ring)], 1)
    rest = np.concatenate([ring - [0, 0, size], ring + [0, 0, size]])
    is_m = tissue == TISSUE_MUSCLE
    return _model('one_cell', rest, np.full(2 * n_ring, -1), np.full(2 * n_ring, VF_MUSCLE if is_m else VF_FAT),
                  [np.arange(2 * n_ring)], [tissue], [0 if is_m else -1], [[0, 0, 1]], [0],
                  ('m',) if is_m else (), ('',) if is_m else (), [-size, size], n_seg=1)


def knee(n_gaps: int = 6, n_ring: int = 6, radius: float = 0.015, length: float = 0.3, arm: float = 0.04,
         extra_muscles: int = 0, fat_sectors: int = 0, knee_range_deg=(0.0, 120.0),
         quad_arm: float | None = None) -> TissueModel:
    """Two-segment knee phantom (see module doc). Slices evenly from z = +length/2 to -length/2.
    arm/quad_arm: distance of the hamstring/quadriceps axis behind/in front of the knee [m]. The
    quadriceps has no patella: past ~40 deg of flexion its line of action passes behind the axis."""
    z = np.linspace(length / 2, -length / 2, n_gaps + 1)[::-1]          # increasing z: bottom first
    rest, vseg, flags, cells, tissue, muscle, fibre, cslice = [], [], [], [], [], [], [], []
    centres = [(-arm, 0.0), (arm if quad_arm is None else quad_arm, 0.0)]
    for e in range(extra_muscles):
        a = np.pi / 2 + np.pi * (e + 0.5) / max(extra_muscles, 1) * (1 if e % 2 else -1)
        centres.append((2.0 * arm * np.cos(a), 2.0 * arm * np.sin(a)))
    names = ['hamstring', 'quadriceps'] + [f'muscle{e}' for e in range(extra_muscles)]
    groups = ['hamstrings', 'quadriceps'] + ['' for _ in range(extra_muscles)]
    ang = 2 * np.pi * np.arange(n_ring) / n_ring

    def add_ring(pts, seg):
        base = len(rest)
        rest.extend(pts)
        vseg.extend([seg] * len(pts))
        return np.arange(base, base + len(pts))

    for m, (cx, cy) in enumerate(centres):
        rings = []
        for iz, zz in enumerate(z):
            seg = 1 if iz == 0 else (0 if iz == n_gaps else -1)
            pts = np.stack([cx + radius * np.cos(ang), cy + radius * np.sin(ang), np.full(n_ring, zz)], 1)
            rings.append(add_ring(pts, seg))
            flags.extend([VF_MUSCLE] * n_ring)
        for g in range(n_gaps):
            cells.append(np.concatenate([rings[g], rings[g + 1]]))
            tissue.append(TISSUE_MUSCLE); muscle.append(m); fibre.append([0, 0, 1]); cslice.append(g)
    if fat_sectors:
        r1, r2 = 3.2 * arm, 3.7 * arm
        th = 2 * np.pi * np.arange(fat_sectors) / fat_sectors
        rings = []
        for iz, zz in enumerate(z):
            seg = 1 if iz == 0 else (0 if iz == n_gaps else -1)
            inner = add_ring(np.stack([r1 * np.cos(th), r1 * np.sin(th), np.full(fat_sectors, zz)], 1), seg)
            outer = add_ring(np.stack([r2 * np.cos(th), r2 * np.sin(th), np.full(fat_sectors, zz)], 1), -1)
            flags.extend([VF_FAT] * 2 * fat_sectors)
            rings.append((inner, outer))
        for g in range(n_gaps):
            for s in range(fat_sectors):
                a, b = s, (s + 1) % fat_sectors
                lo, hi = rings[g], rings[g + 1]
                cells.append([lo[0][a], lo[0][b], lo[1][b], lo[1][a], hi[0][a], hi[0][b], hi[1][b], hi[1][a]])
                tissue.append(TISSUE_FAT); muscle.append(-1); fibre.append([0, 0, 1]); cslice.append(g)
    # muscle paths (docs/solver.md "Force-length"): the hamstring and the quadriceps each one part, the column's length
    # changing at its constant moment arm, L = length -+ arm q (rigid tendon of zero slack, no pennation, L_opt = length)
    qa = arm if quad_arm is None else quad_arm
    paths = dict(path_muscle=np.array([0, 1], np.int32), path_data=np.array([[1.0, length, 0.0, 0.0]] * 2),
                 path_powers=np.array([[0], [1]], np.int32), path_coef=np.array([[length, -arm], [length, qa]]))
    return _model('knee', np.array(rest), vseg, flags, cells, tissue, muscle, fibre, cslice, names, groups, z,
                  knee_range=tuple(np.radians(knee_range_deg)), paths=paths)


def chain(n_links: int = 2, length: float = 0.4, mass: float = 3.0, fixed_last: bool = False) -> TissueModel:
    """A chain of rigid links hanging from a fixed root along -z, joined by hinges about +y at
    z = 0, -length, -2 length, ... (a multi-joint skeleton test: pendulum, double pendulum). Each
    link is a uniform rod (COM at its middle, I = m L^2 / 12 across). One free cell far away keeps
    the model valid; it does not touch the skeleton. fixed_last: the last joint is a fixed joint."""
    from tissue_sim.core.model import JOINT_FIXED
    cellm = one_cell(tissue=TISSUE_FAT)
    rest = cellm.rest_positions + [5.0, 0.0, 0.0]
    S = n_links + 1
    com = np.array([[0.0, 0.0, 0.1]] + [[0.0, 0.0, -(i + 0.5) * length] for i in range(n_links)])
    inertia = np.array([np.diag([0.01, 0.01, 0.01])] + [np.diag([mass * length ** 2 / 12, mass * length ** 2 / 12, 1e-4])
                                                         for _ in range(n_links)])
    types = [JOINT_HINGE] * n_links
    if fixed_last:
        types[-1] = JOINT_FIXED
    seg = dict(segment_names=tuple(f'link{i}' for i in range(S)), segment_parent=np.arange(-1, S - 1, dtype=np.int32),
               segment_mass=np.array([1.0] + [mass] * n_links), segment_com=com, segment_inertia=inertia,
               joint_names=tuple(f'j{i}' for i in range(n_links)), joint_type=np.array(types, np.uint8),
               joint_parent=np.arange(0, n_links, dtype=np.int32), joint_child=np.arange(1, S, dtype=np.int32),
               joint_axis=np.tile([0.0, 1.0, 0.0], (n_links, 1)),
               joint_centre=np.array([[0.0, 0.0, -i * length] for i in range(n_links)]),
               joint_range=np.tile([-10.0, 10.0], (n_links, 1)), joint_rest=np.zeros(n_links))
    return _model('chain', rest, np.full(8, -1), np.full(8, VF_FAT), [np.arange(8)], [TISSUE_FAT], [-1], [[0, 0, 1]],
                  [0], (), (), [-0.02, 0.02], seg=seg)
