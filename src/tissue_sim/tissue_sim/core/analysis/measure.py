"""Per-frame measurements of a run: fat skin area and d, muscle length/volume, joints.

:func:`prepare` precomputes index tables from a model topology; :func:`fat_frame` measures one frame;
:func:`measure` measures a loaded :class:`~tissue_sim.core.runio.Run` (all its frames or some) and
returns a :class:`Measurements` (arrays, frame axis first); ``analyze`` and ``render`` share it.
The definitions are in :mod:`tissue_sim.core.measures`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from tissue_sim.core import measures, runio
from tissue_sim.core.model import TISSUE_FAT


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
    muscle_forces: np.ndarray = None   # (F, M) [N] reported by the simulator (NaN: not in the recording)
    excitations: np.ndarray = None     # (F, M) the commanded excitations (= activations without activation dynamics)

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
    """Index tables of a model topology for fast per-frame measurement."""
    fat_ids, fat_tab = measures.cells_of(topo.cell_offsets, topo.cell_vertices, topo.cell_tissue, TISSUE_FAT)
    rest = np.asarray(topo.rest_positions, np.float64)
    rest_cells = rest[fat_tab]
    local = np.full(topo.n_cells, -1, np.int64)
    local[fat_ids] = np.arange(fat_ids.size)
    qc = local[np.asarray(topo.skin_quad_cell, np.int64)]
    ok = qc >= 0
    ctx = dict(model=topo, fat_ids=fat_ids, fat_tab=fat_tab, rest_cells=rest_cells,
               quads=np.asarray(topo.skin_quads, np.int64)[ok], quad_local=qc[ok], n_fat=fat_ids.size,
               n_muscles=len(topo.muscle_names))
    ctx['skin_area_rest'] = measures.skin_area_per_cell(rest, ctx['quads'], ctx['quad_local'], ctx['n_fat'])
    ctx['fat_size'] = measures.cell_size(rest_cells)
    ctx['fat_centroid'] = rest_cells.mean(axis=1) if fat_ids.size else np.zeros((0, 3))
    return ctx


def fat_frame(ctx: dict, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(skin area (Cf,) [m^2], d paper (Cf,) [m], d rotation-free (Cf,) [m]) of one frame X (V, 3)."""
    X = np.asarray(X, np.float64)
    area = measures.skin_area_per_cell(X, ctx['quads'], ctx['quad_local'], ctx['n_fat'])
    if ctx['n_fat'] == 0:
        return area, np.zeros(0), np.zeros(0)
    cur = X[ctx['fat_tab']]
    return area, measures.d_paper(cur, ctx['rest_cells']), measures.d_rotation_free(cur, ctx['rest_cells'])


def muscle_volumes_mesh(ctx: dict, X: np.ndarray) -> np.ndarray:
    """Volume of each muscle [m^3] from its cells (:func:`tissue_sim.core.measures.muscle_volumes`)."""
    return measures.muscle_volumes(X, ctx['model'])


def measure(run: runio.Run, frames=None, progress=None) -> Measurements:
    """The measures of a loaded run (every kept frame, or the run positions ``frames`` of
    ``run.frame_index``). ``progress()`` is called per frame measured."""
    topo = run.model
    ctx = prepare(topo)
    sel = np.arange(run.n_frames) if frames is None else np.asarray(frames, np.int64)
    F = sel.size
    area = np.zeros((F, ctx['n_fat']))
    dp, dr = np.zeros_like(area), np.zeros_like(area)
    mvm_t = np.zeros((F, ctx['n_muscles']))
    for k, i in enumerate(sel):
        X = run.frames[i].astype(np.float64)
        area[k], dp[k], dr[k] = fat_frame(ctx, X)
        mvm_t[k] = muscle_volumes_mesh(ctx, X)
        if progress is not None:
            progress()
    mnames = tuple(topo.muscle_names)
    mn = run.muscle_names
    groups = tuple(topo.muscle_groups[mnames.index(n)] if n in mnames else '' for n in mn)
    # mesh volumes are in topology muscle order; reorder to the state's muscle order
    order = [mnames.index(n) if n in mnames else -1 for n in mn]
    mvm = np.stack([mvm_t[:, o] if o >= 0 else np.full(F, np.nan) for o in order], axis=1) if order else np.zeros((F, 0))
    f64 = lambda a: np.asarray(a, np.float64)[sel].reshape(F, -1)   # noqa: E731
    return Measurements(
        model_name=topo.name, frame_index=run.frame_index[sel], times=run.times[sel], steps=run.steps[sel],
        kinetic_energy=f64(run.kinetic_energy)[:, 0], elastic_energy=f64(run.elastic_energy)[:, 0],
        joint_names=run.joint_names, joint_positions=f64(run.joint_positions),
        joint_velocities=f64(run.joint_velocities), muscle_names=mn, muscle_groups=groups,
        activations=f64(run.activations), muscle_lengths=f64(run.muscle_lengths),
        muscle_volumes=f64(run.muscle_volumes), muscle_volumes_mesh=mvm,
        fat_cells=ctx['fat_ids'], fat_rest_centroid=ctx['fat_centroid'], fat_size=ctx['fat_size'],
        skin_area_rest=ctx['skin_area_rest'], skin_area=area, d_paper=dp, d_rotation_free=dr,
        muscle_forces=f64(run.muscle_forces) if run.muscle_forces is not None else np.full((F, len(mn)), np.nan),
        excitations=f64(run.excitations) if run.excitations is not None else f64(run.activations))


def rows_for(run: runio.Run, positions, measures: Measurements | None = None):
    """(Measurements, {run position: row}) covering the run positions ``positions``: ``measures``
    when it already has those frames (``analyze`` passing its own), else the frames measured now."""
    positions = sorted(set(int(p) for p in positions))
    have = {} if measures is None else {int(f): k for k, f in enumerate(measures.frame_index)}
    if not all(int(run.frame_index[p]) in have for p in positions):
        measures = measure(run, frames=positions)
        have = {int(f): k for k, f in enumerate(measures.frame_index)}
    return measures, {p: have[int(run.frame_index[p])] for p in positions}


def measure_run(path, progress=None, stride: int = 1) -> Measurements:
    """Load a run (every ``stride``-th frame) and measure it. ``progress(i)`` is called per frame read."""
    return measure(runio.load_run(path, stride=stride, progress=progress))
