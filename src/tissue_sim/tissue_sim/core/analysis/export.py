"""Export frames of a run for other tools.

* ``frame_<n>.glb`` / ``frame_<n>.ply`` (trimesh): skin + muscles + posed bones of one frame, vertex
  coloured (skin yellow, hamstrings red, other muscles brown, bones ivory). GLB keeps one named
  node per part (viewers can hide the skin); PLY is one merged coloured mesh.
* ``cells_<n>.vtu`` + ``cells.pvd`` (ParaView time series): the soft-tissue cells as an
  unstructured grid of the cells the solver integrates, one VTK cell per model cell
  (:class:`tissue_sim.core.geometry.CellGrid`, as `build-model --vtu`: prisms as VTK_POLYHEDRON with
  ``prism_volumes``'s faces, 4-vertex fat cells as VTK_HEXAHEDRON, face centroids as extra points) with
  cell data ``cell`` (model cell id), ``tissue`` (1 muscle, 2 fat), ``muscle`` (-1 for fat),
  ``area_ratio``, ``d_paper_m``, ``d_rotfree_m`` (fat; NaN elsewhere) and point data
  ``displacement_m`` (from rest) and ``model_vertex`` (-1 for a centroid). Times in the .pvd are the simulated times [s].
  Bones are written as ``bones_<n>.vtp`` in the same series file (part 1).
"""
from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from tissue_sim.core import measures
from tissue_sim.core.analysis import measure, render
from tissue_sim.core.geometry import CellGrid


def _rgba(c, a=1.0):
    return np.array([int(255 * v) for v in c] + [int(255 * a)], np.uint8)


def frame_scene(topo, X: np.ndarray, poses: np.ndarray):
    """trimesh.Scene of one frame: 'skin', 'muscle/<name>' and bone parts, vertex coloured."""
    import trimesh
    X = np.asarray(X, np.float64)
    scene = trimesh.Scene()
    mnames = list(topo.muscle_names)
    for name, tri in measures.surface_groups(topo).items():
        used, inv = np.unique(tri, return_inverse=True)
        if name.startswith('muscle/'):
            mn = name.split('/', 1)[1]
            k = mnames.index(mn) if mn in mnames else 0
            col = _rgba(render.muscle_colour(mn, topo.muscle_groups[k] if mn in mnames else '', k))
        else:
            col = _rgba(render.FAT_YELLOW, 0.35)
        mesh = trimesh.Trimesh(X[used], inv.reshape(-1, 3), process=False,
                               vertex_colors=np.tile(col, (len(used), 1)))
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    for b, v in enumerate(render.posed_bones(topo, poses)):
        _, t = topo.bone_mesh(b)
        if len(t):
            mesh = trimesh.Trimesh(v, np.asarray(t, np.int64), process=False,
                                   vertex_colors=np.tile(_rgba(render.IVORY), (len(v), 1)))
            scene.add_geometry(mesh, node_name=f'bone/{topo.bone_names[b]}', geom_name=f'bone/{topo.bone_names[b]}')
    return scene


def write_meshes(topo, X, poses, out: Path, stem: str, formats=('glb', 'ply')) -> list[Path]:
    scene = frame_scene(topo, X, poses)
    files = []
    for fmt in formats:
        p = Path(out) / f'{stem}.{fmt}'
        if fmt == 'glb':
            scene.export(p, file_type='glb')
        else:
            scene.to_geometry().export(p, file_type='ply')
        files.append(p)
    return files


def write_vtu_series(run, out: Path, frames=None, measures=None) -> list[Path]:
    """One .vtu (cells) and .vtp (bones) per frame of ``run`` (a runio.Run; ``frames``: positions in
    it, default all) and the ``cells.pvd`` index. ``measures``: the run's Measurements if computed."""
    os.environ.setdefault('VTK_DEFAULT_OPENGL_WINDOW', 'vtkEGLRenderWindow')
    import pyvista as pv
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    topo = run.model
    sel = np.arange(run.n_frames) if frames is None else np.asarray(frames, np.int64)
    m, row = measure.rows_for(run, set(sel.tolist()) | {0}, measures)
    from tissue_sim.core import model as M
    cg = CellGrid(topo.cell_offsets, topo.cell_vertices, np.asarray(topo.cell_tissue) == M.TISSUE_FAT,
                  len(topo.rest_positions))
    owner = np.arange(topo.n_cells)
    rest = cg.points(topo.rest_positions)
    fat_local = np.full(topo.n_cells, -1, np.int64)
    fat_local[m.fat_cells] = np.arange(m.fat_cells.size)
    fl = fat_local
    area0 = m.skin_area[row[0]]
    files, entries = [], []
    for i in sel:
        k = row[int(i)]
        X = cg.points(run.frames[i])
        a, dp, dr = m.skin_area[k], m.d_paper[k], m.d_rotation_free[k]
        grid = pv.UnstructuredGrid(cg.cells, cg.types, X)
        grid.cell_data['cell'] = owner.astype(np.int32)
        grid.cell_data['tissue'] = np.asarray(topo.cell_tissue)[owner].astype(np.int32)
        grid.cell_data['muscle'] = np.asarray(topo.cell_muscle)[owner].astype(np.int32)
        for name, v in (('area_ratio', np.divide(a, area0, out=np.full_like(a, np.nan), where=area0 > 0)),
                        ('d_paper_m', dp), ('d_rotfree_m', dr)):
            col = np.full(len(owner), np.nan)
            col[fl >= 0] = v[fl[fl >= 0]]
            grid.cell_data[name] = col
        grid.point_data['displacement_m'] = X - rest
        grid.point_data['model_vertex'] = cg.model_vertex
        f = int(run.frame_index[i])
        p = out / f'cells_{f:05d}.vtu'
        grid.save(p)
        files.append(p)
        entries.append((run.times[i], 0, p.name))
        bones = render.posed_bones(topo, run.segment_poses[i])
        if bones:
            faces = []
            base = 0
            for b, v in enumerate(bones):
                _, t = topo.bone_mesh(b)
                faces.append(np.asarray(t, np.int64) + base)
                base += len(v)
            tri = np.concatenate(faces)
            bp = pv.PolyData(np.concatenate(bones), np.hstack([np.full((len(tri), 1), 3), tri]).ravel())
            q = out / f'bones_{f:05d}.vtp'
            bp.save(q)
            files.append(q)
            entries.append((run.times[i], 1, q.name))
    pvd = out / 'cells.pvd'
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             '  <Collection>']
    lines += [f'    <DataSet timestep="{t:.9g}" group="" part="{part}" file={quoteattr(name)}/>' for t, part, name in entries]
    lines += ['  </Collection>', '</VTKFile>', '']
    pvd.write_text('\n'.join(lines))
    files.append(pvd)
    return files

