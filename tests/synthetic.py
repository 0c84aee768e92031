"""Test fixture: small synthetic limbs and analytically deformed runs.

Nothing here runs the solver: vertex positions are moved by closed-form maps (uniform scale,
rigid motion, a bending knee), so the analysis has known answers.

:func:`tube_model` makes a straight limb along z: a thigh and a shank joined by a knee hinge about
+y at the origin (positive angle = flexion: the shank swings to -x), a femur and a tibia (boxes), two
muscles (a hamstring behind the bone, hexagonal prisms; a quadriceps in front, octagonal prisms)
and a ring of fat hexahedra (paper section 2.3 layout) with their skin quads.
"""
from __future__ import annotations

import numpy as np

from tissue_sim.core import model as M
from tissue_sim.core.measures import boundary_faces


def _ring(cx, cy, r, n, z):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a), np.full(n, z)], axis=1)


def _box(x0, x1, y0, y1, z0, z1):
    v = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], float)
    t = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]], np.int32)
    return v, t


def tube_model(n_around: int = 16, n_slices: int = 9, length: float = 0.6, r_in: float = 0.055,
               r_out: float = 0.07, fix_ends: float = 0.22, name: str = 'tube') -> M.TissueModel:
    """A straight synthetic limb centred on the knee at the origin (see module docstring).

    Vertices with |z| >= fix_ends are bone-attached (thigh above, shank below).
    """
    zs = np.linspace(-length / 2, length / 2, n_slices)
    pts, cells, tissue, muscle, fibre, cslice = [], [], [], [], [], []

    def add(p):
        base = sum(len(q) for q in pts)
        pts.append(p)
        return base + np.arange(len(p))

    # muscles: columns of prisms
    for m, (cx, n, r) in enumerate(((-0.03, 6, 0.018), (0.03, 8, 0.02))):
        rings = [add(_ring(cx, 0.0, r, n, z)) for z in zs]
        for k in range(n_slices - 1):
            cells.append(np.concatenate([rings[k], rings[k + 1]]))
            tissue.append(M.TISSUE_MUSCLE)
            muscle.append(m)
            fibre.append((0, 0, 1))
            cslice.append(k)
    # fat ring: inner a, inner b, outer b, outer a per ring (a -> b counter-clockwise)
    inner = [add(_ring(0, 0, r_in, n_around, z)) for z in zs]
    outer = [add(_ring(0, 0, r_out, n_around, z)) for z in zs]
    skin_quads, skin_cell = [], []
    for k in range(n_slices - 1):
        for a in range(n_around):
            b = (a + 1) % n_around
            bot = [inner[k][a], inner[k][b], outer[k][b], outer[k][a]]
            top = [inner[k + 1][a], inner[k + 1][b], outer[k + 1][b], outer[k + 1][a]]
            skin_cell.append(len(cells))
            skin_quads.append([outer[k][a], outer[k][b], outer[k + 1][b], outer[k + 1][a]])
            cells.append(np.array(bot + top))
            tissue.append(M.TISSUE_FAT)
            muscle.append(-1)
            fibre.append((0, 0, 1))
            cslice.append(k)
    X = np.concatenate(pts)
    V = len(X)
    seg = np.full(V, -1, np.int32)
    seg[X[:, 2] >= fix_ends] = 0
    seg[X[:, 2] <= -fix_ends] = 1
    flags = np.zeros(V, np.uint8)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in cells])]).astype(np.int64)
    cv = np.concatenate(cells).astype(np.int32)
    tissue = np.array(tissue, np.uint8)
    muscle = np.array(muscle, np.int32)
    for c in range(len(cells)):
        flags[cells[c]] |= M.VF_MUSCLE if tissue[c] == M.TISSUE_MUSCLE else M.VF_FAT
    # surfaces: skin = outer faces of the fat cells' skin quads; muscles = boundary of each muscle
    sq = np.array(skin_quads, np.int64)
    flags[sq.ravel()] |= M.VF_SKIN
    tris = [np.concatenate([sq[:, [0, 1, 2]], sq[:, [0, 2, 3]]])]
    groups = [np.zeros(2 * len(sq), np.int32)]
    names = ['skin']
    muscle_names = ('biceps_femoris_long_head', 'vastus_intermedius')
    for m, mname in enumerate(muscle_names):
        bf = boundary_faces(offsets, cv, np.flatnonzero(muscle == m))
        tris.append(bf)
        groups.append(np.full(len(bf), len(names), np.int32))
        names.append(f'muscle/{mname}')
    fv, ft = _box(-0.012, 0.012, -0.012, 0.012, 0.01, 0.35)
    tv, tt = _box(-0.012, 0.012, -0.012, 0.012, -0.35, -0.01)
    return M.TissueModel(
        name=name, rest_positions=X, vertex_segment=seg, vertex_flags=flags,
        cell_offsets=offsets, cell_vertices=cv, cell_tissue=tissue, cell_muscle=muscle,
        cell_fibre=np.array(fibre, float), cell_slice=np.array(cslice, np.int32),
        cell_k_scale=np.ones(len(cells)), skin_quads=sq.astype(np.int32),
        skin_quad_cell=np.array(skin_cell, np.int32),
        surface_triangles=np.concatenate(tris).astype(np.int32), surface_group=np.concatenate(groups),
        surface_group_names=tuple(names), muscle_names=muscle_names, muscle_groups=('hamstrings', 'quadriceps'),
        muscle_max_force=np.array([np.nan, np.nan]), muscle_fibre_length=np.array([np.nan, np.nan]),
        bone_names=('femur', 'tibia'), bone_segment=np.array([0, 1], np.int32),
        bone_vertex_offsets=np.array([0, 8, 16], np.int64), bone_vertices=np.concatenate([fv, tv]),
        bone_triangle_offsets=np.array([0, 12, 24], np.int64), bone_triangles=np.concatenate([ft, tt]),
        segment_names=('thigh', 'shank'), segment_parent=np.array([-1, 0], np.int32),
        segment_mass=np.array([10.0, 3.5]), segment_com=np.array([[0, 0, 0.2], [0, 0, -0.2]], float),
        segment_inertia=np.stack([np.eye(3) * 0.1, np.eye(3) * 0.04]),
        joint_names=('knee_r',), joint_type=np.array([M.JOINT_HINGE], np.uint8),
        joint_parent=np.array([0], np.int32), joint_child=np.array([1], np.int32),
        joint_axis=np.array([[0, 1.0, 0]]), joint_centre=np.zeros((1, 3)),
        joint_range=np.array([[0, np.deg2rad(140)]]), joint_rest=np.zeros(1),
        slice_z=zs, meta={'source': 'tests/synthetic.py tube_model'}).validate()


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def quat_y(a: float) -> np.ndarray:
    """Quaternion x y z w of a rotation by a about +y."""
    return np.array([0, np.sin(a / 2), 0, np.cos(a / 2)])


def bend(X: np.ndarray, angle: float, blend: float = 0.12) -> np.ndarray:
    """Flex the tube at the knee: points below z = 0 turn about +y by angle * w(z), w = 1 below -blend.

    Smoothly blended, so the fat near the knee shears and the skin behind it (x < 0) is compressed
    while the front is stretched, as in paper Figs. 8-9.
    """
    X = np.asarray(X, float)
    w = np.clip(-X[:, 2] / blend, 0.0, 1.0)
    w = w * w * (3 - 2 * w)
    out = X.copy()
    a = angle * w
    c, s = np.cos(a), np.sin(a)
    out[:, 0] = c * X[:, 0] + s * X[:, 2]
    out[:, 2] = -s * X[:, 0] + c * X[:, 2]
    return out


def bending_run(tm: M.TissueModel, path, n_frames: int = 40, rate_hz: float = 34.0,
                max_angle: float = np.deg2rad(90), chunk_size: int = 1 << 20):
    """Write a synthetic MCAP run of the tube flexing its knee from 0 to max_angle (smoothstep in time)."""
    from tissue_sim.core import measures, runio, tissue_cdr
    states = []
    for i in range(n_frames):
        t = i / rate_hz
        u = i / max(n_frames - 1, 1)
        ang = max_angle * u * u * (3 - 2 * u)
        X = bend(tm.rest_positions, ang)
        lengths = []
        for m in range(tm.n_muscles):
            cs = np.flatnonzero(tm.cell_muscle == m)
            cents = np.array([X[tm.cell(c)[:len(tm.cell(c)) // 2]].mean(0) for c in cs]
                             + [X[tm.cell(cs[-1])[len(tm.cell(cs[-1])) // 2:]].mean(0)])
            lengths.append(np.linalg.norm(np.diff(cents, axis=0), axis=1).sum())
        vols = measures.muscle_volumes(X, tm)
        poses = np.array([[0, 0, 0, 0, 0, 0, 1], [0, 0, 0, *quat_y(ang)]], float)
        states.append(tissue_cdr.StateFrame(
            stamp_ns=int(t * 1e9), frame_id='world', step=i * 29, sim_time=t, joint_names=['knee_r'],
            joint_positions=np.array([ang]), joint_velocities=np.zeros(1), muscle_names=list(tm.muscle_names),
            activations=np.array([min(1.0, 2 * u), 0.0], np.float32), muscle_lengths=np.array(lengths, np.float32),
            muscle_volumes=vols.astype(np.float32), segment_poses=poses, vertex_positions=X.astype(np.float32),
            kinetic_energy=0.0, elastic_energy=0.0))
    return runio.write_run(path, tm, states, chunk_size=chunk_size)
