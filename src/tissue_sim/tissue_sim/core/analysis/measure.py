"""Per-frame measurements of a run (streamed): fat skin area and d, muscle length/volume, joints.

:func:`prepare` precomputes index tables from a Topology; :func:`fat_frame` measures one frame;
:func:`measure_run` streams a run and returns a :class:`Measurements` (arrays, frame axis first).
See :mod:`tissue_sim.core.analysis.deform` for the definitions.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from tissue_sim.core import runio
from tissue_sim.core.analysis import deform


@dataclasses.dataclass(eq=False)
class Measurements:
    """Everything the tables, plots and pictures need; units SI, model frame."""
    model_name: str
    frame_index: np.ndarray        # (F,)
    times: np.ndarray              # (F,) [s]
    steps: np.ndarray              # (F,)
    kinetic_energy: np.ndarray     # (F,)
    elastic_energy: np.ndarray     # (F,)
    joint_names: tuple
    joint_positions: np.ndarray    # (F, J) [rad]
    joint_velocities: np.ndarray   # (F, J) [rad/s]
    muscle_names: tuple
    muscle_groups: tuple
    activations: np.ndarray        # (F, M)
    muscle_lengths: np.ndarray     # (F, M) [m] reported by the simulator
    muscle_volumes: np.ndarray     # (F, M) [m^3] reported by the simulator
    muscle_volumes_mesh: np.ndarray  # (F, M) [m^3] recomputed here from the cell meshes
    fat_cells: np.ndarray          # (Cf,) cell ids of the fat cells
    fat_rest_centroid: np.ndarray  # (Cf, 3) [m]
    fat_size: np.ndarray           # (Cf,) [m] RMS radius of the rest cell
    skin_area_rest: np.ndarray     # (Cf,) [m^2] skin-face area at rest (0: cell has no skin face)
    skin_area: np.ndarray          # (F, Cf) [m^2]
    d_paper: np.ndarray            # (F, Cf) [m]
    d_rotation_free: np.ndarray    # (F, Cf) [m]

    @property
    def n_frames(self) -> int:
        return int(self.times.shape[0])

    @property
    def has_skin(self) -> np.ndarray:
        return self.skin_area_rest > 0

    def area_ratio(self, reference: str = 'frame0') -> np.ndarray:
        """(F, Cf) skin-face area / reference area ('frame0' as in the paper, or 'rest'); NaN without skin."""
        ref = self.skin_area[0] if reference == 'frame0' else self.skin_area_rest
        with np.errstate(invalid='ignore', divide='ignore'):
            r = self.skin_area / ref[None, :]
        r[:, ~(ref > 0)] = np.nan
        return r


def prepare(topo) -> dict:
    """Index tables of a Topology for fast per-frame measurement."""
    fat_ids, fat_tab = deform.cells_of(topo.cell_offsets, topo.cell_vertices, topo.cell_tissue, deform.TISSUE_FAT)
    rest = np.asarray(topo.rest_positions, np.float64)
    rest_cells = rest[fat_tab]
    local = np.full(topo.n_cells, -1, np.int64)
    local[fat_ids] = np.arange(fat_ids.size)
    qc = local[np.asarray(topo.skin_quad_cells, np.int64)]
    ok = qc >= 0
    mcells = np.flatnonzero(np.asarray(topo.cell_tissue) == deform.TISSUE_MUSCLE)
    tris, owner = deform.cell_surface_triangles(topo.cell_offsets, topo.cell_vertices, mcells)
    ctx = dict(fat_ids=fat_ids, fat_tab=fat_tab, rest_cells=rest_cells, quads=np.asarray(topo.skin_quads, np.int64)[ok],
               quad_local=qc[ok], n_fat=fat_ids.size, muscle_tris=tris,
               muscle_owner=np.asarray(topo.cell_muscle, np.int64)[owner], n_muscles=len(topo.muscle_names))
    ctx['skin_area_rest'] = deform.skin_area_per_cell(rest, ctx['quads'], ctx['quad_local'], ctx['n_fat'])
    ctx['fat_size'] = deform.cell_size(rest_cells)
    ctx['fat_centroid'] = rest_cells.mean(axis=1) if fat_ids.size else np.zeros((0, 3))
    return ctx


def fat_frame(ctx: dict, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(skin area (Cf,) [m^2], d paper (Cf,) [m], d rotation-free (Cf,) [m]) of one frame X (V, 3)."""
    X = np.asarray(X, np.float64)
    area = deform.skin_area_per_cell(X, ctx['quads'], ctx['quad_local'], ctx['n_fat'])
    if ctx['n_fat'] == 0:
        return area, np.zeros(0), np.zeros(0)
    cur = X[ctx['fat_tab']]
    return area, deform.d_paper(cur, ctx['rest_cells']), deform.d_rotation_free(cur, ctx['rest_cells'])


def muscle_volumes_mesh(ctx: dict, X: np.ndarray) -> np.ndarray:
    """Volume of each muscle [m^3] from its cells' closed prism surfaces."""
    return np.abs(deform.signed_volumes(X, ctx['muscle_tris'], ctx['muscle_owner'], ctx['n_muscles']))


def measure_run(path, progress=None, stride: int = 1) -> Measurements:
    """Stream a run and measure every ``stride``-th frame. ``progress(i)`` is called per frame read."""
    topo = runio.read_topology(path)
    ctx = prepare(topo)
    V = topo.n_vertices
    rows = {k: [] for k in ('idx', 't', 'step', 'ke', 'ee', 'jp', 'jv', 'act', 'ml', 'mv', 'mvm', 'a', 'dp', 'dr')}
    jn = mn = None
    for i, s in enumerate(runio.iter_states(path, with_vertices=True)):
        if progress is not None:
            progress(i)
        if i % stride:
            continue
        if s.vertex_positions.shape[0] != V:
            raise runio.RunError(f'{path}: state #{i} has {s.vertex_positions.shape[0]} vertices, the topology {V}')
        if jn is None:
            jn, mn = tuple(s.joint_names), tuple(s.muscle_names)
        a, dp, dr = fat_frame(ctx, s.vertex_positions)
        for k, v in (('idx', i), ('t', s.sim_time), ('step', s.step), ('ke', s.kinetic_energy), ('ee', s.elastic_energy),
                     ('jp', s.joint_positions), ('jv', s.joint_velocities), ('act', s.activations),
                     ('ml', s.muscle_lengths), ('mv', s.muscle_volumes),
                     ('mvm', muscle_volumes_mesh(ctx, s.vertex_positions)), ('a', a), ('dp', dp), ('dr', dr)):
            rows[k].append(v)
    if not rows['idx']:
        raise runio.RunError(f'{path}: no TissueState frames (was /tissue/state recorded?)')
    F = len(rows['idx'])

    def arr(k, dtype=np.float64, width=None):
        try:
            a = np.array(rows[k], dtype)
        except ValueError:
            raise runio.RunError(f'{path}: frames disagree in the size of {k}') from None
        return a.reshape(F, -1) if width is None else a

    mnames = tuple(topo.muscle_names)
    groups = tuple(topo.muscle_groups[mnames.index(n)] if n in mnames else '' for n in mn)
    # mesh volumes are in topology muscle order; reorder to the state's muscle order
    mvm = arr('mvm')
    order = [mnames.index(n) if n in mnames else -1 for n in mn]
    mvm = np.stack([mvm[:, o] if o >= 0 else np.full(F, np.nan) for o in order], axis=1) if order else np.zeros((F, 0))
    return Measurements(
        model_name=topo.model_name, frame_index=np.array(rows['idx'], np.int64), times=arr('t', width=0),
        steps=np.array(rows['step'], np.uint64), kinetic_energy=arr('ke', width=0), elastic_energy=arr('ee', width=0),
        joint_names=jn, joint_positions=arr('jp'), joint_velocities=arr('jv'), muscle_names=mn, muscle_groups=groups,
        activations=arr('act'), muscle_lengths=arr('ml'), muscle_volumes=arr('mv'), muscle_volumes_mesh=mvm,
        fat_cells=ctx['fat_ids'], fat_rest_centroid=ctx['fat_centroid'], fat_size=ctx['fat_size'],
        skin_area_rest=ctx['skin_area_rest'], skin_area=arr('a'), d_paper=arr('dp'), d_rotation_free=arr('dr'))
