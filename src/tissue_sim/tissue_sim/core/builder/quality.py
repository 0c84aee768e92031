"""Quality report of a built model and its Table-1 summary (paper Table 1; docs/builder.md).

Table-1 rows (keys of ``table1``):
  bones            bone meshes in the model
  muscles          muscles with at least one cell
  muscle_cells     muscle prism cells
  muscle_vertices  distinct vertices used by muscle cells (after sharing)
  fat_cells        fat hexahedra
  fat_vertices     fat cell-vertex incidences, 8 per hexahedron: the paper's count (540 cells -> 4320)
  shared_vertices  vertices made by merging vertices of different tissues (paper section 2.4)
Extra: fat_vertices_unique (distinct vertices used by fat cells), vertices (all soft-tissue vertices),
bone_attached_vertices.
"""
from __future__ import annotations

import numpy as np

from tissue_sim.core import model as M

from tissue_sim.core import geometry

PAPER_TABLE1 = {'bones': 6, 'muscles': 28, 'muscle_cells': 292, 'muscle_vertices': 2998,
                'fat_cells': 540, 'fat_vertices': 4320, 'shared_vertices': 873}
TABLE1_LABELS = {'bones': 'bones', 'muscles': 'muscles', 'muscle_cells': 'muscle cells',
                 'muscle_vertices': 'muscle vertices', 'fat_cells': 'fat cells',
                 'fat_vertices': 'fat vertices (cell-vertex incidences, as the paper)',
                 'shared_vertices': 'shared vertices'}


def table1(tm: M.TissueModel) -> dict:
    mus = tm.cell_tissue == M.TISSUE_MUSCLE
    fat = ~mus
    sizes = np.diff(tm.cell_offsets)
    cv_t = np.repeat(tm.cell_tissue, sizes)
    mverts = np.unique(tm.cell_vertices[cv_t == M.TISSUE_MUSCLE])
    fverts = np.unique(tm.cell_vertices[cv_t == M.TISSUE_FAT])
    return {
        'bones': len(tm.bone_names),
        'muscles': int(len(np.unique(tm.cell_muscle[mus]))),
        'muscle_cells': int(mus.sum()),
        'muscle_vertices': int(len(mverts)),
        'fat_cells': int(fat.sum()),
        'fat_vertices': int(sizes[fat].sum()),
        'shared_vertices': int(np.count_nonzero(tm.vertex_flags & M.VF_SHARED)),
        'fat_vertices_unique': int(len(fverts)),
        'vertices': tm.n_vertices,
        'bone_attached_vertices': int(np.count_nonzero(tm.vertex_segment >= 0)),
    }


def cell_volumes(tm: M.TissueModel, positions=None) -> np.ndarray:
    """Volume [m^3] of every cell, positive for a valid cell (fat rings are clockwise by contract)."""
    pos = tm.rest_positions if positions is None else positions
    return geometry.prism_volumes(pos, tm.cell_offsets, tm.cell_vertices, tm.cell_tissue == M.TISSUE_FAT)


def surface_checks(tm: M.TissueModel) -> dict:
    """Per muscle and for the fat layer: closed (watertight) surface and its enclosed volume."""
    import trimesh
    out = {}
    names = tm.surface_group_names
    fat_ids = [i for i, n in enumerate(names) if n == 'skin' or n.startswith('fat/')]
    groups = {n: [i] for i, n in enumerate(names) if n.startswith('muscle/')}
    if fat_ids:
        groups['fat'] = fat_ids
    for g, ids in groups.items():
        tri = tm.surface_triangles[np.isin(tm.surface_group, ids)]
        m = trimesh.Trimesh(tm.rest_positions, tri, process=False)
        wt = bool(m.is_watertight)
        out[g] = {'watertight': wt, 'outward': bool(wt and m.volume > 0),
                  'volume_cm3': round(float(m.volume) * 1e6, 3) if wt else None}
    return out


def cell_shear(tm: M.TissueModel, positions=None) -> tuple[np.ndarray, np.ndarray]:
    """(shear, slant) of every cell. Shear: the largest in-plane offset of a top-ring vertex from its
    bottom-ring partner once the ring centroids are aligned and the bottom ring is scaled about its
    centroid by the best uniform factor, over the cell's height (0 for a right, oblique or tapered
    prism; it measures twist and zig-zag between the rings: 2 = a vertex slides twice the height
    sideways relative to its ring). Slant: the centroid offset over the height (the muscle's course
    across the slices; reported, not a defect)."""
    pos = tm.rest_positions if positions is None else positions
    shear, slant = np.zeros(tm.n_cells), np.zeros(tm.n_cells)
    sizes = np.diff(tm.cell_offsets)
    for size in np.unique(sizes):
        cs = np.nonzero(sizes == size)[0]
        n = size // 2
        P = pos[tm.cell_vertices[tm.cell_offsets[cs][:, None] + np.arange(size)[None, :]]]
        d = P[:, n:] - P[:, :n]
        h = np.maximum(np.abs(d[:, :, 2]).mean(axis=1), 1e-12)
        cd = d[:, :, :2].mean(axis=1, keepdims=True)
        B = P[:, :n, :2] - P[:, :n, :2].mean(axis=1, keepdims=True)
        T = P[:, n:, :2] - P[:, n:, :2].mean(axis=1, keepdims=True)
        s = np.sum(B * T, axis=(1, 2)) / np.maximum(np.sum(B * B, axis=(1, 2)), 1e-300)
        shear[cs] = np.linalg.norm(T - s[:, None, None] * B, axis=2).max(axis=1) / h
        slant[cs] = np.linalg.norm(cd[:, 0], axis=1) / h
    return shear, slant


def fat_inner_spacing(tm: M.TissueModel) -> tuple[float, int]:
    """(ratio, slice): the shortest inner edge of a fat ring over that ring's mean inner edge, at the slice where it is
    least (each fat cell's first two vertices are inner a and inner b of its lower ring). Near 0: neighbouring inner
    vertices nearly coincide, and that ring's cells are wedges that fold about their inner edge (docs/builder.md
    "Fat tube"). (1.0, -1) without fat cells."""
    fat = np.flatnonzero(tm.cell_tissue == M.TISSUE_FAT)
    if len(fat) == 0:
        return 1.0, -1
    v = tm.cell_vertices[tm.cell_offsets[fat][:, None] + np.arange(2)]
    e = np.linalg.norm(tm.rest_positions[v[:, 0]] - tm.rest_positions[v[:, 1]], axis=1)
    zs = tm.cell_slice[fat]
    best = (np.inf, -1)
    for zi in np.unique(zs):
        ez = e[zs == zi]
        r = float(ez.min() / max(ez.mean(), 1e-300))
        if r < best[0]:
            best = (r, int(zi))
    return best


def quality_checks(tm, vols, checks: dict) -> tuple[dict, list]:
    """Volume against label volume per tissue, chain breaks, shear, bones without attached
    vertices. Returns (section of the report, warnings)."""
    warn = []
    mus = tm.cell_tissue == M.TISSUE_MUSCLE
    vol_rows = {}
    for mi, name in enumerate(tm.muscle_names):
        lv = checks['label_volume_m3'].get(name)
        if lv:
            vol_rows[name] = round(float(vols[tm.cell_muscle == mi].sum()) / lv, 4)
    lv = checks['label_volume_m3'].get('fat')
    if lv:
        vol_rows['fat'] = round(float(vols[~mus].sum()) / lv, 4)
    for name, r in vol_rows.items():
        if abs(r - 1) > 0.10:
            warn.append(f'{name}: built volume is {100 * (r - 1):+.1f} % of its label volume (limit +-10 %)')
    for b in checks['breaks']:
        warn.append(f'muscle {b["muscle"]} breaks between slices {b["from_slice"]} and {b["to_slice"]} ({b["reason"]})')
    sh, sl = cell_shear(tm)
    lim = checks['shear_limit']
    shear = {}
    for tname, sel in (('muscle', mus), ('fat', ~mus)):
        v, w = sh[sel], sl[sel]
        if len(v):
            shear[tname] = {'median': round(float(np.median(v)), 3), 'p95': round(float(np.percentile(v, 95)), 3),
                            'max': round(float(v.max()), 3), 'over_limit': int(np.count_nonzero(v > lim)), 'cells': int(len(v)),
                            'slant_median': round(float(np.median(w)), 3), 'slant_p95': round(float(np.percentile(w, 95)), 3),
                            'slant_max': round(float(w.max()), 3)}
    over = np.nonzero(sh > lim)[0]
    if len(over):
        worst = over[np.argsort(-sh[over])][:3]
        desc = ', '.join(f'cell {c} ({tm.muscle_names[tm.cell_muscle[c]] if mus[c] else "fat"}, slice {tm.cell_slice[c]}: '
                         f'{sh[c]:.1f})' for c in worst)
        warn.append(f'{len(over)} cell(s) sheared more than {lim:g} x their height (worst: {desc})')
    sp_ratio, sp_slice = fat_inner_spacing(tm)
    for b, n in checks['bone_touch'].items():
        if n == 0:
            warn.append(f'bone {b}: no soft-tissue vertex is attached to it')
    sec = {'volume_ratio': vol_rows, 'label_volume_cm3': {k: round(v * 1e6, 2) for k, v in checks['label_volume_m3'].items()},
           'breaks': checks['breaks'], 'fragments_left_out': checks.get('fragments', []), 'bridged_small_components': checks['bridged'], 'shear_limit': lim, 'shear': shear,
           'fat_inner_spacing': {'min_ratio': round(sp_ratio, 4), 'slice': sp_slice},
           'bone_attached_vertices': checks['bone_touch'], 'attachment_refused_across_joint': checks['refused_across_joint'],
           'free_vertices_moved_out_of_bones': checks.get('moved_out_of_bones', 0),
           'gliding_vertices_bound_where_wrapped': checks.get('wrapped_bound', 0),
           'sections_not_followed': checks['not_represented'],
           'warnings': warn}
    return sec, warn


def quality_report(tm, *, checks, cell_vol, area_rows, fats, dropped, dropped_cells, warnings, n_unshared,
                   n_before_sharing, bone_info, build_s) -> dict:
    vols = cell_volumes(tm)
    qsec, qwarn = quality_checks(tm, vols, checks)
    surf = surface_checks(tm)
    ratios = {}
    for r in area_rows:
        if r['label_mm2'] > 0:
            ratios.setdefault(r['muscle'], []).append(r['polygon_mm2'] / r['label_mm2'])
    per_muscle = {m: {'median_area_ratio': round(float(np.median(v)), 3), 'min_area_ratio': round(float(np.min(v)), 3),
                      'slices': len(v)} for m, v in ratios.items()}
    allr = np.concatenate([np.array(v) for v in ratios.values()]) if ratios else np.zeros(0)
    fat_rows = []
    for zi, f in enumerate(fats):
        ring = np.concatenate([f['inner'], f['outer'][::-1]])
        # area of the fat ring = area(outer polygon) - area(inner polygon)
        from .rays import polygon_area
        a = (polygon_area(f['outer'][:, :2]) - polygon_area(f['inner'][:, :2])) * 1e6
        fat_rows.append({'slice': zi, 'label_mm2': round(float(f['fat_area_mm2']), 1), 'tube_mm2': round(a, 1)})
    t1 = table1(tm)
    inverted = int(np.count_nonzero(vols <= 0))
    return {
        'table1': t1,
        'paper_table1': PAPER_TABLE1,
        'build_s': round(build_s, 3),
        'cells': {'count': tm.n_cells, 'inverted': inverted, 'min_volume_mm3': round(float(vols.min()) * 1e9, 4) if len(vols) else None,
                  'dropped_degenerate': dropped_cells, 'muscle_volume_cm3': round(float(vols[tm.cell_tissue == M.TISSUE_MUSCLE].sum()) * 1e6, 2),
                  'fat_volume_cm3': round(float(vols[tm.cell_tissue == M.TISSUE_FAT].sum()) * 1e6, 2)},
        'areas': {'rows': area_rows, 'per_muscle': per_muscle,
                  'median_ratio': round(float(np.median(allr)), 3) if len(allr) else None, 'fat': fat_rows},
        'surfaces': surf,
        'closed_surfaces': all(v['watertight'] for v in surf.values()),
        'bones': bone_info,
        'attachment': {name: int(np.count_nonzero(tm.vertex_segment == i)) for i, name in enumerate(tm.segment_names)},
        'dropped_components': dropped,
        'sharing': {'vertices_before': n_before_sharing, 'vertices_after': tm.n_vertices,
                    'unshared_to_avoid_inversion': n_unshared},
        'quality': qsec,
        'warnings': warnings + [w for w in qwarn if w not in warnings],
    }
