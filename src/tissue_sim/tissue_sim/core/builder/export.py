"""Exports of a TissueModel: surfaces to GLB/PLY (trimesh), cells to VTU (ParaView, via pyvista/VTK).

GLB: one node per surface group ("muscle/<name>", "skin", "fat/inner", "fat/caps") and per bone
("bone/<name>"), model frame metres (glTF viewers show +y up; the model is z-up, REP-103).
PLY: all surfaces in one mesh with per-face colours. VTU: muscle prisms as VTK_POLYHEDRON (faces
outward), fat cells as VTK_HEXAHEDRON; cell data tissue, muscle, k_scale, volume, fibre; point data
segment, flags.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tissue_sim.core import model as M
from tissue_sim.errors import UserError

_COL = {'skin': (240, 200, 160, 90), 'fat/inner': (250, 220, 130, 255), 'fat/caps': (250, 220, 130, 255),
        'bone': (235, 230, 215, 255)}


def _muscle_colour(i):
    rng = np.random.default_rng(1000 + i)
    return (int(150 + 90 * rng.random()), int(30 + 60 * rng.random()), int(30 + 60 * rng.random()), 255)


def surface_meshes(tm: M.TissueModel) -> dict:
    """{name: trimesh.Trimesh} for every surface group and bone (rest pose, model frame, metres)."""
    import trimesh
    out = {}
    for gi, name in enumerate(tm.surface_group_names):
        tri = tm.surface_triangles[tm.surface_group == gi]
        used, inv = np.unique(tri, return_inverse=True)
        m = trimesh.Trimesh(tm.rest_positions[used], inv.reshape(-1, 3), process=False)
        col = _COL.get(name) or _muscle_colour(gi)
        m.visual.face_colors = np.tile(col, (len(m.faces), 1))
        out[name] = m
    for b, name in enumerate(tm.bone_names):
        v, t = tm.bone_mesh(b)
        m = trimesh.Trimesh(v, t, process=False)
        m.visual.face_colors = np.tile(_COL['bone'], (len(m.faces), 1))
        out[f'bone/{name}'] = m
    return out


def to_glb(tm: M.TissueModel, path) -> Path:
    import trimesh
    path = Path(path)
    scene = trimesh.Scene()
    for name, m in surface_meshes(tm).items():
        scene.add_geometry(m, node_name=name, geom_name=name)
    try:
        path.write_bytes(scene.export(file_type='glb'))
    except OSError as e:
        raise UserError(f'{path}: cannot write ({e.strerror})') from None
    return path


def to_ply(tm: M.TissueModel, path) -> Path:
    import trimesh
    path = Path(path)
    m = trimesh.util.concatenate(list(surface_meshes(tm).values()))
    try:
        path.write_bytes(m.export(file_type='ply'))
    except OSError as e:
        raise UserError(f'{path}: cannot write ({e.strerror})') from None
    return path


def to_unstructured_grid(tm: M.TissueModel):
    """pyvista.UnstructuredGrid of all cells (muscle prisms as polyhedra, fat cells as hexahedra)."""
    import pyvista as pv
    from .quality import cell_volumes
    cells, types = [], []
    for c in range(tm.n_cells):
        v = tm.cell(c)
        n = len(v) // 2
        if tm.cell_tissue[c] == M.TISSUE_FAT and n == 4:
            # contract ring order is clockwise from +z; VTK wants the bottom face counter-clockwise
            cells += [8, *v[[3, 2, 1, 0]], *v[[7, 6, 5, 4]]]
            types.append(pv.CellType.HEXAHEDRON)
            continue
        bot, top = v[:n], v[n:]
        if tm.cell_tissue[c] == M.TISSUE_FAT:
            bot, top = bot[::-1], top[::-1]
        faces = [list(bot[::-1]), list(top)]
        for i in range(n):
            j = (i + 1) % n
            faces.append([bot[i], bot[j], top[j], top[i]])
        stream = [len(faces)]
        for f in faces:
            stream += [len(f), *f]
        cells += [len(stream), *stream]
        types.append(pv.CellType.POLYHEDRON)
    grid = pv.UnstructuredGrid(np.array(cells, dtype=np.int64), np.array(types, dtype=np.uint8),
                               np.asarray(tm.rest_positions, dtype=np.float64))
    grid.cell_data['tissue'] = tm.cell_tissue.astype(np.int32)
    grid.cell_data['muscle'] = tm.cell_muscle.astype(np.int32)
    grid.cell_data['k_scale'] = tm.cell_k_scale
    grid.cell_data['volume'] = cell_volumes(tm)
    grid.cell_data['fibre'] = tm.cell_fibre
    grid.point_data['segment'] = tm.vertex_segment.astype(np.int32)
    grid.point_data['flags'] = tm.vertex_flags.astype(np.int32)
    return grid


def to_vtu(tm: M.TissueModel, path) -> Path:
    path = Path(path)
    grid = to_unstructured_grid(tm)
    try:
        grid.save(str(path), binary=True)
    except OSError as e:
        raise UserError(f'{path}: cannot write ({e})') from None
    return path
