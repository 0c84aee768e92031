"""The deformation measures (paper section 4, docs/method.md section 4), vectorised over cells: the one
definition that the analysis (:mod:`tissue_sim.core.analysis.measure`) and the marker colours
(:mod:`tissue_sim.core.markers`) call.

All positions are in the model frame [m]. ``X`` is one frame's soft-tissue vertex array (V, 3);
``model`` is a :class:`~tissue_sim.core.model.TissueModel` or a decoded
:class:`~tissue_sim.core.model.TissueTopology`.

* Skin-area change (paper Fig. 8): the area of each fat cell's skin-side face, relative to a
  reference frame (the paper: frame 0). A quad's area is half the norm of the cross product of its
  diagonals: exact for planar quads, the vector area for warped ones; it scales exactly by s^2 under
  a uniform scale s.
* Fat deformation degree d (paper eq. 2): ``d = (1/N) sum_i |Ro_i - r_i|`` with Ro_i the rest vertex
  positions relative to the cell centroid. The paper says r_i is "as in (1)", i.e. the current
  positions; we read it literally as the current positions relative to the current centroid:
  translation is removed but rotation is NOT, so a cell that turns rigidly by an angle a gets
  d = 2 sin(a/2) * mean|Ro_i| > 0 although it is not deformed (:func:`d_paper`).
* Rotation-free d (:func:`d_rotation_free`): the rest shape is first turned by the least-squares
  rotation R (shape matching / Kabsch: the same optimum as the paper's equilibrium condition (1)),
  ``d_rf = (1/N) sum_i |R Ro_i - r_i|``; any rigid motion gives 0, so d_rf measures only shape change.
* Both are reported in metres and relative to the cell size ``L = sqrt((1/N) sum_i |Ro_i|^2)`` (the
  RMS vertex distance from the rest centroid), so cells of different size can be compared.
* Cell and muscle volumes: :func:`tissue_sim.core.geometry.prism_volumes` (the one prism-volume
  definition, shared with the builder and the solver), made positive for fat cells.
* Per-vertex values for colouring a surface (:func:`skin_area_ratio_per_vertex`,
  :class:`FatDeformation`): the per-cell measures above, averaged onto each cell's vertices.
"""
from __future__ import annotations

import numpy as np

from tissue_sim.core.geometry import prism_volumes
from tissue_sim.core.model import TISSUE_FAT, TISSUE_MUSCLE


# ----------------------------------------------------------------------------- cell tables
def cells_of(offsets: np.ndarray, vertices: np.ndarray, tissue: np.ndarray, kind: int):
    """(cell ids (C,), vertex index table (C, n)) of the cells of one tissue with one vertex count.

    Fat cells are hexahedra (n = 8). Raises ValueError if the selected cells have different sizes.
    """
    offsets = np.asarray(offsets, np.int64)
    ids = np.flatnonzero(np.asarray(tissue) == kind)
    if ids.size == 0:
        return ids, np.zeros((0, 8), np.int64)
    sizes = offsets[ids + 1] - offsets[ids]
    if np.any(sizes != sizes[0]):
        raise ValueError('cells of this tissue have different vertex counts')
    table = np.asarray(vertices, np.int64)[offsets[ids][:, None] + np.arange(sizes[0])[None, :]]
    return ids, table


# ----------------------------------------------------------------------------- skin area
def quad_areas(X: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Area of each quad (Q,) [m^2]: 0.5 |(p2 - p0) x (p3 - p1)|."""
    X = np.asarray(X, np.float64)
    q = np.asarray(quads, np.int64)
    c = np.cross(X[q[:, 2]] - X[q[:, 0]], X[q[:, 3]] - X[q[:, 1]])
    return 0.5 * np.linalg.norm(c, axis=1)


def skin_area_per_cell(X: np.ndarray, quads: np.ndarray, quad_cells: np.ndarray, n_cells: int) -> np.ndarray:
    """Skin-face area of every cell (n_cells,) [m^2]: the sum of its skin quads (0 for cells without)."""
    return np.bincount(np.asarray(quad_cells, np.int64), weights=quad_areas(X, quads), minlength=n_cells)


# ----------------------------------------------------------------------------- deformation degree
def _centred(P: np.ndarray) -> np.ndarray:
    return P - P.mean(axis=1, keepdims=True)


def cell_size(rest_cells: np.ndarray) -> np.ndarray:
    """RMS distance of the rest vertices from their centroid (C,) [m]; rest_cells is (C, N, 3)."""
    Ro = _centred(np.asarray(rest_cells, np.float64))
    return np.sqrt(np.mean(np.sum(Ro * Ro, axis=2), axis=1))


def d_paper(cur_cells: np.ndarray, rest_cells: np.ndarray) -> np.ndarray:
    """The paper's d (eq. 2), translation removed, rotation not removed: (C,) [m].

    cur_cells, rest_cells: (C, N, 3) current and rest vertex positions of each cell.
    """
    Ro = _centred(np.asarray(rest_cells, np.float64))
    r = _centred(np.asarray(cur_cells, np.float64))
    return np.mean(np.linalg.norm(Ro - r, axis=2), axis=1)


def best_rotations(cur_cells: np.ndarray, rest_cells: np.ndarray) -> np.ndarray:
    """Least-squares rotation (C, 3, 3) taking each centred rest shape onto the centred current shape.

    Kabsch / polar decomposition of A = sum_i r_i Ro_i^T with the reflection fixed (det R = +1).
    """
    Ro = _centred(np.asarray(rest_cells, np.float64))
    r = _centred(np.asarray(cur_cells, np.float64))
    A = np.einsum('cni,cnj->cij', r, Ro)
    U, _, Vt = np.linalg.svd(A)
    D = np.ones((A.shape[0], 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    D[D[:, 2] == 0, 2] = 1.0
    return (U * D[:, None, :]) @ Vt


def d_rotation_free(cur_cells: np.ndarray, rest_cells: np.ndarray) -> np.ndarray:
    """d measured against the matched (best rigidly moved) rest shape: (C,) [m]; 0 for rigid motion."""
    Ro = _centred(np.asarray(rest_cells, np.float64))
    r = _centred(np.asarray(cur_cells, np.float64))
    R = best_rotations(cur_cells, rest_cells)
    matched = np.einsum('cij,cnj->cni', R, Ro)
    return np.mean(np.linalg.norm(matched - r, axis=2), axis=1)


# ----------------------------------------------------------------------------- volumes, surfaces
def cell_volumes(X: np.ndarray, model) -> np.ndarray:
    """Volume of every cell (C,) [m^3], positive: :func:`~tissue_sim.core.geometry.prism_volumes`
    with the fat cells' clockwise rings flipped (model contract)."""
    return prism_volumes(np.asarray(X, np.float64), np.asarray(model.cell_offsets, np.int64),
                         np.asarray(model.cell_vertices, np.int64), np.asarray(model.cell_tissue) == TISSUE_FAT)


def muscle_volumes(X: np.ndarray, model) -> np.ndarray:
    """Volume of each muscle (M,) [m^3]: the sum of its cells' :func:`cell_volumes`."""
    mus = np.asarray(model.cell_tissue) == TISSUE_MUSCLE
    return np.bincount(np.asarray(model.cell_muscle, np.int64)[mus], weights=cell_volumes(X, model)[mus],
                       minlength=len(model.muscle_names))


def enclosed_volumes(X: np.ndarray, triangles: np.ndarray, owner: np.ndarray, n_groups: int) -> np.ndarray:
    """Signed volume enclosed by each group's closed triangulated surface [m^3] (divergence theorem;
    positive for outward triangles)."""
    X = np.asarray(X, np.float64)
    triangles = np.asarray(triangles, np.int64)
    a, b, c = X[triangles[:, 0]], X[triangles[:, 1]], X[triangles[:, 2]]
    v = np.einsum('ij,ij->i', a, np.cross(b, c)) / 6.0
    return np.bincount(np.asarray(owner, np.int64), weights=v, minlength=n_groups)


def boundary_faces(offsets: np.ndarray, vertices: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Outer surface (T, 3) of a set of prism cells: the faces not shared by two cells of the set.

    Shared faces are found by their sorted vertex sets (caps between stacked prisms and side quads
    between neighbours), so the result is the boundary of the union, outward oriented.
    """
    offsets = np.asarray(offsets, np.int64)
    vertices = np.asarray(vertices, np.int64)
    faces = []                                         # (key, triangles)
    for c in np.asarray(cells, np.int64):
        vs = vertices[offsets[c]:offsets[c + 1]]
        n = len(vs) // 2
        bottom = tuple(vs[[0] + list(range(n - 1, 0, -1))])
        top = tuple(vs[n:])
        faces.append(bottom)
        faces.append(top)
        for i in range(n):
            j = (i + 1) % n
            faces.append((vs[i], vs[j], vs[n + j], vs[n + i]))
    count = {}
    for f in faces:
        k = tuple(sorted(f))
        count[k] = count.get(k, 0) + 1
    tris = []
    for f in faces:
        if count[tuple(sorted(f))] == 1:
            tris.extend((f[0], f[i], f[i + 1]) for i in range(1, len(f) - 1))
    return np.array(tris, np.int64).reshape(-1, 3)


def surface_groups(model) -> dict:
    """{'skin': (T,3), 'muscle/<name>': (T,3), ...} from the model (boundary of the cells if absent)."""
    out = {}
    tri = np.asarray(model.surface_triangles, np.int64)
    if tri.size:
        g = np.asarray(model.surface_group, np.int64)
        for i, name in enumerate(model.surface_group_names):
            sel = tri[g == i]
            if sel.size:
                out[name] = sel
        return out
    tissue = np.asarray(model.cell_tissue)
    fat = np.flatnonzero(tissue == TISSUE_FAT)
    if fat.size:
        out['skin'] = boundary_faces(model.cell_offsets, model.cell_vertices, fat)
    cm = np.asarray(model.cell_muscle)
    for m, name in enumerate(model.muscle_names):
        cells = np.flatnonzero((tissue == TISSUE_MUSCLE) & (cm == m))
        if cells.size:
            out[f'muscle/{name}'] = boundary_faces(model.cell_offsets, model.cell_vertices, cells)
    return out


# ----------------------------------------------------------------------------- per-vertex values (colours)
def skin_area_ratio_per_vertex(model, X: np.ndarray, rest_area: np.ndarray | None = None):
    """Paper Fig. 8 quantity per vertex: the area of each skin quad relative to rest (:func:`quad_areas`),
    averaged onto its vertices (1 for vertices on no skin quad). Returns (ratio (V,), rest quad
    areas): pass the latter back next frame."""
    q = np.asarray(model.skin_quads, np.int64).reshape(-1, 4)
    if rest_area is None:
        rest_area = quad_areas(model.rest_positions, q)
    ratio = quad_areas(X, q) / np.maximum(rest_area, 1e-18)
    V = model.n_vertices
    acc = np.bincount(q.ravel(), weights=np.repeat(ratio, 4), minlength=V)
    cnt = np.bincount(q.ravel(), minlength=V).astype(np.float64)
    out = np.ones(V)
    has = cnt > 0
    out[has] = acc[has] / cnt[has]
    return out, rest_area


class FatDeformation:
    """Paper Fig. 9 quantity per vertex, precomputed for one model: ``fd(X)`` -> (V,) [m]: the
    rotation-free d (:func:`d_rotation_free`) of each fat cell, averaged onto the cell's vertices
    (0 for vertices of no fat cell)."""

    def __init__(self, model):
        fat = np.flatnonzero(np.asarray(model.cell_tissue) == TISSUE_FAT)
        offs, cv = np.asarray(model.cell_offsets, np.int64), np.asarray(model.cell_vertices, np.int64)
        rest = np.asarray(model.rest_positions, np.float64)
        self.V = model.n_vertices
        self.groups = []                               # (vertex table (c, n), rest cells (c, n, 3))
        cnt = np.zeros(self.V)
        sizes = offs[fat + 1] - offs[fat]
        for n in np.unique(sizes):
            cells = fat[sizes == n]
            idx = cv[offs[cells][:, None] + np.arange(n)[None, :]]
            self.groups.append((idx, rest[idx]))
            cnt += np.bincount(idx.ravel(), minlength=self.V)
        self.inv_cnt = np.where(cnt > 0, 1.0 / np.maximum(cnt, 1), 0.0)

    def __call__(self, X):
        X = np.asarray(X, np.float64)
        acc = np.zeros(self.V)
        for idx, rest_cells in self.groups:
            d = d_rotation_free(X[idx], rest_cells)
            acc += np.bincount(idx.ravel(), weights=np.repeat(d, idx.shape[1]), minlength=self.V)
        return acc * self.inv_cnt
