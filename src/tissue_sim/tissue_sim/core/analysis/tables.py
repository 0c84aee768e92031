"""Tidy tables (CSV, and Parquet when pyarrow is installed) and the JSON summary of a run's analysis.

Tables (one row per frame x item, long format; units in the column names):

* ``fat_cells.csv``: frame, time_s, cell, x_m, y_m, z_m (rest centroid), skin_area_m2,
  area_ratio (vs frame 0, paper Fig. 8), area_ratio_rest, d_paper_m, d_paper_rel,
  d_rotfree_m, d_rotfree_rel (relative = divided by the cell's RMS radius).
* ``muscles.csv``: frame, time_s, muscle, group, activation, length_m, length_ratio, volume_m3,
  volume_ratio, volume_mesh_m3 (recomputed from the cell meshes).
* ``joints.csv``: frame, time_s, joint, position_rad, position_deg, velocity_rad_s.
* ``frames.csv``: one row per frame: energies, joint angles [deg], fat statistics.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from tissue_sim.core.analysis.measure import Measurements


def _write(path: Path, columns: dict, fmt: dict) -> list[Path]:
    """Write a column dict as CSV (and Parquet if pyarrow is importable). Returns the files."""
    names = list(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    cols = []
    for k in names:
        v = columns[k]
        f = fmt.get(k)
        if isinstance(v, np.ndarray) and v.dtype.kind == 'f':
            cols.append(np.char.mod(f or '%.7g', v).astype(object))
            cols[-1][~np.isfinite(v)] = ''
        else:
            cols.append(np.asarray(v).astype(str).astype(object))
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(names)
        if n:
            w.writerows(zip(*cols))
    out = [path]
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return out
    pq.write_table(pa.table({k: np.asarray(columns[k]) for k in names}), path.with_suffix('.parquet'))
    out.append(path.with_suffix('.parquet'))
    return out


def write_tables(m: Measurements, out: Path) -> list[Path]:
    """Write the four tables into folder ``out``; returns the files written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    F, Cf = m.skin_area.shape
    M, J = len(m.muscle_names), len(m.joint_names)
    files = []
    rep = lambda a, k: np.repeat(a, k)          # noqa: E731  frame-major
    til = lambda a, k: np.tile(a, k)             # noqa: E731
    size = np.where(m.fat_size > 0, m.fat_size, np.nan)
    files += _write(out / 'fat_cells.csv', {
        'frame': rep(m.frame_index, Cf), 'time_s': rep(m.times, Cf), 'cell': til(m.fat_cells, F),
        'x_m': til(m.fat_rest_centroid[:, 0], F), 'y_m': til(m.fat_rest_centroid[:, 1], F),
        'z_m': til(m.fat_rest_centroid[:, 2], F), 'skin_area_m2': m.skin_area.ravel(),
        'area_ratio': m.area_ratio('frame0').ravel(), 'area_ratio_rest': m.area_ratio('rest').ravel(),
        'd_paper_m': m.d_paper.ravel(), 'd_paper_rel': (m.d_paper / size).ravel(),
        'd_rotfree_m': m.d_rotation_free.ravel(), 'd_rotfree_rel': (m.d_rotation_free / size).ravel()},
        {'time_s': '%.6f', 'x_m': '%.5f', 'y_m': '%.5f', 'z_m': '%.5f'})
    with np.errstate(invalid='ignore', divide='ignore'):
        lr = m.muscle_lengths / m.muscle_lengths[:1]
        vr = m.muscle_volumes / m.muscle_volumes[:1]
    files += _write(out / 'muscles.csv', {
        'frame': rep(m.frame_index, M), 'time_s': rep(m.times, M), 'muscle': til(np.array(m.muscle_names, object), F),
        'group': til(np.array(m.muscle_groups, object), F), 'activation': m.activations.ravel(),
        'length_m': m.muscle_lengths.ravel(), 'length_ratio': lr.ravel(), 'volume_m3': m.muscle_volumes.ravel(),
        'volume_ratio': vr.ravel(), 'volume_mesh_m3': m.muscle_volumes_mesh.ravel(),
        'excitation': _or_nan(m.excitations, F, M).ravel(), 'force_n': _or_nan(m.muscle_forces, F, M).ravel()},
        {'time_s': '%.6f'})
    files += _write(out / 'joints.csv', {
        'frame': rep(m.frame_index, J), 'time_s': rep(m.times, J), 'joint': til(np.array(m.joint_names, object), F),
        'position_rad': m.joint_positions.ravel(), 'position_deg': np.rad2deg(m.joint_positions).ravel(),
        'velocity_rad_s': m.joint_velocities.ravel()}, {'time_s': '%.6f'})
    ar = m.area_ratio('frame0')
    cols = {'frame': m.frame_index, 'time_s': m.times, 'step': m.steps,
            'kinetic_energy': m.kinetic_energy, 'elastic_energy': m.elastic_energy}
    for j, n in enumerate(m.joint_names):
        cols[f'{n}_deg'] = np.rad2deg(m.joint_positions[:, j])
    with np.errstate(all='ignore'):
        for k, a in (('area_ratio', ar), ('d_paper_m', m.d_paper), ('d_rotfree_m', m.d_rotation_free)):
            ok = np.isfinite(a).any(axis=1) if a.size else np.zeros(F, bool)
            for stat, fn in (('min', np.nanmin), ('mean', np.nanmean), ('max', np.nanmax)):
                v = np.full(F, np.nan)
                if a.size:
                    v[ok] = fn(a[ok], axis=1)
                cols[f'{k}_{stat}'] = v
    files += _write(out / 'frames.csv', cols, {'time_s': '%.6f'})
    return files


def _or_nan(a, F, M):
    """(F, M) a, or NaN where the measurements have none (a recording made before the field)."""
    return np.full((F, M), np.nan) if a is None else np.asarray(a, np.float64).reshape(F, M)


def _f(x):
    x = float(x)
    return None if not math.isfinite(x) else round(x, 9)


def summary(m: Measurements, run_path=None) -> dict:
    """JSON-able summary: run, joints, muscles, fat (skin area, d both variants) and the definitions."""
    F = m.n_frames
    ar = m.area_ratio('frame0')
    size = np.where(m.fat_size > 0, m.fat_size, np.nan)
    dt = np.diff(m.times)
    out = {
        'run': str(run_path) if run_path is not None else None, 'model': m.model_name, 'frames': F,
        'duration_s': _f(m.times[-1] - m.times[0]) if F else 0.0,
        'frame_rate_hz': _f(1.0 / np.median(dt)) if F > 1 and np.median(dt) > 0 else None,
        'joints': {}, 'muscles': {}, 'fat': {},
    }
    for j, n in enumerate(m.joint_names):
        q = np.rad2deg(m.joint_positions[:, j])
        out['joints'][n] = {'min_deg': _f(q.min()), 'max_deg': _f(q.max()), 'final_deg': _f(q[-1]),
                            'range_deg': _f(np.ptp(q)), 'time_of_max_s': _f(m.times[int(np.argmax(q))]),
                            'time_of_min_s': _f(m.times[int(np.argmin(q))])}
    from tissue_sim.core.analysis.plots import main_joint, pick_motion_frames
    jm = main_joint(m.joint_positions) if F else None
    out['main_joint'] = m.joint_names[jm] if jm is not None else None
    out['picture_frames'] = [int(m.frame_index[f]) for f in pick_motion_frames(m.times, m.joint_positions, 4)] if F else []
    for k, n in enumerate(m.muscle_names):
        L, Vv, Vm = m.muscle_lengths[:, k], m.muscle_volumes[:, k], m.muscle_volumes_mesh[:, k]
        with np.errstate(all='ignore'):
            out['muscles'][n] = {
                'group': m.muscle_groups[k], 'length0_m': _f(L[0]), 'length_min_ratio': _f(L.min() / L[0]),
                'length_max_ratio': _f(L.max() / L[0]), 'volume0_m3': _f(Vv[0]),
                'volume_max_change': _f(np.max(np.abs(Vv / Vv[0] - 1))),
                'volume_mesh_max_change': _f(np.max(np.abs(Vm / Vm[0] - 1))),
                'max_activation': _f(m.activations[:, k].max()),
                'max_force_n': _f(np.max(_or_nan(m.muscle_forces, F, len(m.muscle_names))[:, k])) if F else None}
    if m.fat_cells.size:
        skin = m.has_skin
        a = ar[:, skin]
        dp, dr = m.d_paper, m.d_rotation_free
        fmax = int(np.argmax(np.nanmean(dr, axis=1)))
        worst = np.argsort(-dr[fmax])[:5]
        with np.errstate(all='ignore'):
            out['fat'] = {
                'cells': int(m.fat_cells.size), 'cells_with_skin_face': int(skin.sum()),
                'area_ratio_min': _f(np.nanmin(a)) if a.size else None,
                'area_ratio_max': _f(np.nanmax(a)) if a.size else None,
                'area_ratio_final_p5_p50_p95': [_f(v) for v in np.nanpercentile(a[-1], [5, 50, 95])] if a.size else None,
                'total_skin_area_ratio_final': _f(m.skin_area[-1, skin].sum() / m.skin_area[0, skin].sum()) if a.size else None,
                'd_paper_max_m': _f(dp.max()), 'd_paper_mean_final_m': _f(dp[-1].mean()),
                'd_rotfree_max_m': _f(dr.max()), 'd_rotfree_mean_final_m': _f(dr[-1].mean()),
                'd_paper_rel_max': _f(np.nanmax(dp / size)), 'd_rotfree_rel_max': _f(np.nanmax(dr / size)),
                'frame_of_max_mean_d_rotfree': int(m.frame_index[fmax]), 'time_of_max_mean_d_rotfree_s': _f(m.times[fmax]),
                'most_deformed_cells': [{'cell': int(m.fat_cells[c]), 'rest_centroid_m': [_f(v) for v in m.fat_rest_centroid[c]],
                                         'd_rotfree_m': _f(dr[fmax, c]), 'd_paper_m': _f(dp[fmax, c])} for c in worst],
            }
    out['definitions'] = {
        'area_ratio': 'skin-side face area of a fat cell / the same at frame 0 (paper Fig. 8); >1 grown, <1 shrunk',
        'd_paper': 'paper eq. (2): mean |Ro_i - r_i|, rest and current vertices each relative to their own '
                   'centroid; translation removed, rotation NOT removed (a rigidly turned cell has d > 0) [m]',
        'd_rotfree': 'mean |R Ro_i - r_i| with R the least-squares rotation (shape matching); 0 for any rigid motion [m]',
        'rel': 'divided by the cell size: RMS distance of its rest vertices from their centroid',
    }
    return out


def write_summary(m: Measurements, out: Path, run_path=None) -> Path:
    p = Path(out) / 'summary.json'
    p.write_text(json.dumps(summary(m, run_path), indent=2) + '\n')
    return p
