"""Prism-cell geometry, the one definition the builder, the solver and the analysis share: signed prism
volumes, ring triangulation (ear clipping), closed surfaces of prism chains."""
from __future__ import annotations

import numpy as np


def prism_volumes(pos: np.ndarray, offsets: np.ndarray, verts: np.ndarray, flip: np.ndarray | None = None) -> np.ndarray:
    """Signed volume [m^3] of every prism cell (bottom ring then top ring).

    Positive when the rings are counter-clockwise seen from +z and the top ring lies above the
    bottom ring. ``flip`` (C,) bool reverses the ring orientation of those cells first (fat cells,
    whose contract ring order inner a, inner b, outer b, outer a is clockwise). Faces: each cap as a
    fan from its centroid, each side quad as four triangles about its centroid (exact for planar caps).
    """
    C = len(offsets) - 1
    out = np.zeros(C)
    sizes = np.diff(offsets)
    for size in np.unique(sizes):
        cs = np.nonzero(sizes == size)[0]
        n = size // 2
        idx = verts[offsets[cs][:, None] + np.arange(size)[None, :]]
        P = pos[idx]                                   # (c, 2n, 3)
        B, T = P[:, :n], P[:, n:]
        if flip is not None and flip[cs].any():
            f = flip[cs]
            B[f] = B[f][:, ::-1]
            T[f] = T[f][:, ::-1]
        ref = P.mean(axis=1, keepdims=True)
        B, T = B - ref, T - ref
        Bn, Tn = np.roll(B, -1, axis=1), np.roll(T, -1, axis=1)
        cb, ct = B.mean(axis=1, keepdims=True), T.mean(axis=1, keepdims=True)

        def tri(a, b, c):
            return np.einsum('cij,cij->ci', a, np.cross(b, c)).sum(axis=1)
        v = -tri(np.broadcast_to(cb, B.shape), B, Bn)   # bottom, normal -z
        v += tri(np.broadcast_to(ct, T.shape), T, Tn)   # top, normal +z
        qc = (B + Bn + Tn + T) / 4.0
        v += tri(qc, B, Bn) + tri(qc, Bn, Tn) + tri(qc, Tn, T) + tri(qc, T, B)
        out[cs] = v / 6.0
    return out


def ear_clip(xy: np.ndarray) -> np.ndarray:
    """Triangulate a simple polygon (n, 2), counter-clockwise; returns (n-2, 3) local indices with
    counter-clockwise triangles. Falls back to a fan when the polygon is not simple."""
    n = len(xy)
    idx = list(range(n))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3 and guard < 4 * n * n:
        guard += 1
        m = len(idx)
        found = False
        for k in range(m):
            i0, i1, i2 = idx[(k - 1) % m], idx[k], idx[(k + 1) % m]
            a, b, c = xy[i0], xy[i1], xy[i2]
            if cross(a, b, c) <= 0:
                continue
            ok = True
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = xy[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    ok = False
                    break
            if ok:
                tris.append((i0, i1, i2))
                idx.pop(k)
                found = True
                break
        if not found:
            break
    if len(idx) == 3:
        tris.append(tuple(idx))
        return np.array(tris, dtype=np.int64)
    return np.array([(0, i, i + 1) for i in range(1, n - 1)], dtype=np.int64)   # not simple: fan


def chain_surface(rings: list[np.ndarray], pos: np.ndarray) -> np.ndarray:
    """Closed outward triangle surface of a chain of rings (vertex-index arrays, bottom to top, CCW)."""
    tris = []
    for a, b in zip(rings[:-1], rings[1:]):
        an, bn = np.roll(a, -1), np.roll(b, -1)
        tris.append(np.stack([a, an, bn], 1))
        tris.append(np.stack([a, bn, b], 1))
    bot, top = rings[0], rings[-1]
    tb = ear_clip(pos[bot, :2])
    tris.append(bot[tb[:, ::-1]])                      # bottom cap faces down
    tt = ear_clip(pos[top, :2])
    tris.append(top[tt])
    return np.concatenate(tris).astype(np.int32)


VTK_HEXAHEDRON = 12
VTK_POLYHEDRON = 42


def cell_faces(bot, top, cap_bot: int, cap_top: int, quad_centres) -> list:
    """The outward triangles of one prism cell exactly as :func:`prism_volumes` decomposes it: each
    cap a fan from its centroid (point ``cap_bot``/``cap_top``), each side quad four triangles about its
    centroid (point ``quad_centres[i]`` for the quad bot[i], bot[i+1], top[i+1], top[i]). Rings
    counter-clockwise seen from +z (fat rings reversed before)."""
    n = len(bot)
    faces = []
    for i in range(n):
        j = (i + 1) % n
        q = quad_centres[i]
        faces += [(cap_bot, bot[j], bot[i]), (cap_top, top[i], top[j]),
                  (q, bot[i], bot[j]), (q, bot[j], top[j]), (q, top[j], top[i]), (q, top[i], bot[i])]
    return faces


class CellGrid:
    """The model's cells as VTK cells, the same cells the solver integrates (one VTK cell per model
    cell): a prism cell is a VTK_POLYHEDRON whose faces are :func:`prism_volumes`'s triangles, so VTK's
    polyhedron volume equals the model's cell volume also where side quads are not planar; a fat cell
    with 4-vertex rings a VTK_HEXAHEDRON (its trilinear volume is the same decomposition's). The cap and
    side-quad centroids are extra points after the model's vertices: ``points(X)`` appends them for any
    vertex positions X (a frame of a run), ``model_vertex`` maps points back (-1 for a centroid).

    ``offsets``, ``vertices``: the model's cell arrays; ``fat``: (C,) bool, cells whose rings are
    clockwise by the model contract (fat)."""

    def __init__(self, offsets, vertices, fat, n_vertices: int):
        offsets = np.asarray(offsets, np.int64)
        vertices = np.asarray(vertices, np.int64)
        V = int(n_vertices)
        groups, index = [], {}

        def centre(ids) -> int:
            key = tuple(sorted(int(i) for i in ids))
            k = index.get(key)
            if k is None:
                k = index[key] = V + len(groups)
                groups.append(np.array(key, np.int64))
            return k

        cells, types = [], []
        for c in range(len(offsets) - 1):
            v = vertices[offsets[c]:offsets[c + 1]]
            n = len(v) // 2
            if fat[c] and n == 4:
                # contract ring order is clockwise from +z; VTK wants the bottom face counter-clockwise
                cells += [8, *v[[3, 2, 1, 0]], *v[[7, 6, 5, 4]]]
                types.append(VTK_HEXAHEDRON)
                continue
            bot, top = v[:n], v[n:]
            if fat[c]:
                bot, top = bot[::-1], top[::-1]
            quads = [centre((bot[i], bot[(i + 1) % n], top[(i + 1) % n], top[i])) for i in range(n)]
            faces = cell_faces(bot, top, centre(bot), centre(top), quads)
            stream = [len(faces)]
            for f in faces:
                stream += [3, *f]
            cells += [len(stream), *stream]
            types.append(VTK_POLYHEDRON)
        self.cells = np.array(cells, np.int64)
        self.types = np.array(types, np.uint8)
        self.n_vertices = V
        sizes = np.array([len(g) for g in groups], np.int64)
        self._members = np.concatenate(groups) if groups else np.zeros(0, np.int64)
        self._starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]) if groups else np.zeros(0, np.int64)
        self._sizes = sizes
        self.model_vertex = np.concatenate([np.arange(V), np.full(len(groups), -1)]).astype(np.int32)

    def points(self, X) -> np.ndarray:
        """(V + centroids, 3): the model's vertex positions X followed by the centroids."""
        X = np.asarray(X, np.float64)
        if not len(self._sizes):
            return X.copy()
        sums = np.add.reduceat(X[self._members], self._starts, axis=0)
        return np.vstack([X, sums / self._sizes[:, None]])
