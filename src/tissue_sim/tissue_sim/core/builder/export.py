"""Exports of a TissueModel: surfaces to GLB/PLY (trimesh), cells to VTU (ParaView, via pyvista/VTK).

GLB: one node per surface group ("muscle/<name>", "skin", "fat/inner", "fat/caps") and per bone
("bone/<name>"), model frame metres (glTF viewers show +y up; the model is z-up, REP-103).
PLY: all surfaces in one mesh with per-face colours. VTU: the solver's cells (see
``to_unstructured_grid``): prisms as VTK_POLYHEDRON with the faces of ``geometry.prism_volumes``'s
decomposition, 4-vertex fat cells as VTK_HEXAHEDRON.
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


def _write_bytes(path, data: bytes, name=None) -> Path:
    path = Path(path)
    try:
        path.write_bytes(data)
    except OSError as e:
        raise UserError(f'{name or path}: cannot write ({e.strerror or e})') from None
    return path


def to_glb(tm: M.TissueModel, path, name=None) -> Path:
    """Surfaces as glTF binary. ``name``: the path named in error messages (when ``path`` is a staging file)."""
    import trimesh
    scene = trimesh.Scene()
    for gname, m in surface_meshes(tm).items():
        scene.add_geometry(m, node_name=gname, geom_name=gname)
    return _write_bytes(path, scene.export(file_type='glb'), name)


def to_ply(tm: M.TissueModel, path, name=None) -> Path:
    import trimesh
    m = trimesh.util.concatenate(list(surface_meshes(tm).values()))
    return _write_bytes(path, m.export(file_type='ply'), name)


def to_unstructured_grid(tm: M.TissueModel):
    """pyvista.UnstructuredGrid of all cells, the same cells the solver integrates
    (:class:`tissue_sim.core.geometry.CellGrid`: prisms as VTK_POLYHEDRON with ``prism_volumes``'s faces,
    4-vertex fat cells as VTK_HEXAHEDRON, the face centroids as extra points). Cell data: tissue,
    muscle, k_scale, volume (the model's, m^3), fibre; point data: segment, flags, model_vertex (the
    model vertex index, -1 for a centroid)."""
    import pyvista as pv
    from tissue_sim.core.geometry import CellGrid, prism_volumes
    pos = np.asarray(tm.rest_positions, dtype=np.float64)
    fat = tm.cell_tissue == M.TISSUE_FAT
    cg = CellGrid(tm.cell_offsets, tm.cell_vertices, fat, len(pos))
    grid = pv.UnstructuredGrid(cg.cells, cg.types, cg.points(pos))
    grid.cell_data['tissue'] = tm.cell_tissue.astype(np.int32)
    grid.cell_data['muscle'] = tm.cell_muscle.astype(np.int32)
    grid.cell_data['k_scale'] = tm.cell_k_scale
    grid.cell_data['volume'] = prism_volumes(pos, tm.cell_offsets, tm.cell_vertices, fat)
    grid.cell_data['fibre'] = tm.cell_fibre
    extra = len(cg.model_vertex) - len(pos)
    pad = np.full(extra, -1, np.int32)
    grid.point_data['segment'] = np.concatenate([tm.vertex_segment.astype(np.int32), pad])
    grid.point_data['flags'] = np.concatenate([tm.vertex_flags.astype(np.int32), np.zeros(extra, np.int32)])
    grid.point_data['model_vertex'] = cg.model_vertex
    return grid


def to_vtu(tm: M.TissueModel, path, name=None) -> Path:
    """Cells as a VTK XML unstructured grid (binary). VTK's own error output is silenced: a failure
    is one UserError naming the file."""
    from vtkmodules.vtkCommonCore import vtkObject
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter
    path = Path(path)
    grid = to_unstructured_grid(tm)
    w = vtkXMLUnstructuredGridWriter()
    w.SetFileName(str(path))
    w.SetInputData(grid)
    w.SetDataModeToBinary()
    shown = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()
    try:
        ok = w.Write() == 1 and w.GetErrorCode() == 0
    finally:
        vtkObject.SetGlobalWarningDisplay(shown)
    if not ok:
        folder = path.parent if str(path.parent) else Path('.')
        why = ('no such folder' if not folder.exists() else f'{folder} is not a folder' if not folder.is_dir()
               else 'the VTK writer failed (disk full or no permission?)')
        raise UserError(f'{name or path}: cannot write ({why})')
    return path
