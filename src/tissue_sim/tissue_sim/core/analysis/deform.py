"""Deformation measures of the paper's section 4 (docs/method.md section 4), vectorised over cells.

All positions are in the model frame [m]. ``X`` is one frame's soft-tissue vertex array (V, 3).

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
"""
from __future__ import annotations

import numpy as np

TISSUE_MUSCLE = 1
TISSUE_FAT = 2


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


# ----------------------------------------------------------------------------- prism surfaces, volumes
def prism_faces(n: int) -> tuple[list, list]:
    """Local (triangles, quads) of the closed surface of a prism with rings of n vertices.

    Bottom ring 0..n-1 counter-clockwise seen from +z, top ring n..2n-1; faces oriented outward.
    Caps are fan-triangulated from their first vertex.
    """
    tris = [(0, i + 1, i) for i in range(1, n - 1)]                  # bottom: normal -z
    tris += [(n, n + i, n + i + 1) for i in range(1, n - 1)]         # top: normal +z
    quads = [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]
    return tris, quads


def cell_surface_triangles(offsets: np.ndarray, vertices: np.ndarray, cells: np.ndarray):
    """Closed outward triangulated surface of each cell: (triangles (T, 3) global ids, owner cell (T,))."""
    offsets = np.asarray(offsets, np.int64)
    vertices = np.asarray(vertices, np.int64)
    cells = np.asarray(cells, np.int64)
    out_t, out_c = [], []
    sizes = offsets[cells + 1] - offsets[cells]
    for size in np.unique(sizes):
        sel = cells[sizes == size]
        n = int(size) // 2
        tris, quads = prism_faces(n)
        local = np.array(tris + [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads], np.int64)
        table = vertices[offsets[sel][:, None] + np.arange(size)[None, :]]
        out_t.append(table[:, local].reshape(-1, 3))
        out_c.append(np.repeat(sel, local.shape[0]))
    if not out_t:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_t), np.concatenate(out_c)


def signed_volumes(X: np.ndarray, triangles: np.ndarray, owner: np.ndarray, n_groups: int) -> np.ndarray:
    """Volume enclosed by each group's closed triangulated surface [m^3] (divergence theorem)."""
    X = np.asarray(X, np.float64)
    a, b, c = X[triangles[:, 0]], X[triangles[:, 1]], X[triangles[:, 2]]
    v = np.einsum('ij,ij->i', a, np.cross(b, c)) / 6.0
    return np.bincount(owner, weights=v, minlength=n_groups)


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
