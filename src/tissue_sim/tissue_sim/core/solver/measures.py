"""Measures of a state: axial cell lengths, muscle centre lines, cell volumes, kinetic and skeleton energies (observe()
reports them)."""
from __future__ import annotations

import dataclasses
import math
import weakref

import numpy as np
from numba import njit

from tissue_sim.core.geometry import prism_volumes
from tissue_sim.core.model import JOINT_COUPLED, JOINT_HINGE
from tissue_sim.core.solver.skeleton import joint_jacobians



@njit(cache=True)
def cell_axial_lengths(x, off, cv, out):
    """Distance [m] between the bottom-ring and the top-ring centroid of each cell."""
    for c in range(off.shape[0] - 1):
        a0 = off[c]
        n = (off[c + 1] - a0) // 2
        bx = by = bz = tx = ty = tz = 0.0
        for t in range(n):
            i, j = cv[a0 + t], cv[a0 + n + t]
            bx += x[i, 0]; by += x[i, 1]; bz += x[i, 2]
            tx += x[j, 0]; ty += x[j, 1]; tz += x[j, 2]
        out[c] = math.sqrt((tx - bx) ** 2 + (ty - by) ** 2 + (tz - bz) ** 2) / n


@njit(cache=True)
def prism_volumes_compiled(x, off, cv, out):
    """out[c] = the signed volume [m^3] of cell c at positions x: geometry.prism_volumes (the one definition, numpy:
    each cap a fan about its ring's centroid, each side quad four triangles about the quad's centroid, coordinates
    relative to the cell's centroid) compiled, one cell at a time (observe() calls it every frame;
    tests/test_realtime.py checks it against the definition)."""
    for c in range(off.shape[0] - 1):
        a0 = off[c]
        n = (off[c + 1] - a0) // 2
        rx = ry = rz = 0.0
        for t in range(2 * n):
            i = cv[a0 + t]
            rx += x[i, 0]; ry += x[i, 1]; rz += x[i, 2]
        rx /= 2 * n; ry /= 2 * n; rz /= 2 * n
        bx = by = bz = tx = ty = tz = 0.0
        for t in range(n):
            i, j = cv[a0 + t], cv[a0 + n + t]
            bx += x[i, 0] - rx; by += x[i, 1] - ry; bz += x[i, 2] - rz
            tx += x[j, 0] - rx; ty += x[j, 1] - ry; tz += x[j, 2] - rz
        bx /= n; by /= n; bz /= n; tx /= n; ty /= n; tz /= n
        v = 0.0
        for t in range(n):
            u = t + 1 if t + 1 < n else 0
            i0, i1, j0, j1 = cv[a0 + t], cv[a0 + u], cv[a0 + n + t], cv[a0 + n + u]
            b0x, b0y, b0z = x[i0, 0] - rx, x[i0, 1] - ry, x[i0, 2] - rz
            b1x, b1y, b1z = x[i1, 0] - rx, x[i1, 1] - ry, x[i1, 2] - rz
            t0x, t0y, t0z = x[j0, 0] - rx, x[j0, 1] - ry, x[j0, 2] - rz
            t1x, t1y, t1z = x[j1, 0] - rx, x[j1, 1] - ry, x[j1, 2] - rz
            qx, qy, qz = (b0x + b1x + t1x + t0x) / 4.0, (b0y + b1y + t1y + t0y) / 4.0, (b0z + b1z + t1z + t0z) / 4.0
            # caps: -cb . (B x Bn) + ct . (T x Tn); side: qc . (B x Bn + Bn x Tn + Tn x T + T x B)
            cbx, cby, cbz = b0y * b1z - b0z * b1y, b0z * b1x - b0x * b1z, b0x * b1y - b0y * b1x
            ctx, cty, ctz = t0y * t1z - t0z * t1y, t0z * t1x - t0x * t1z, t0x * t1y - t0y * t1x
            v += -(bx * cbx + by * cby + bz * cbz) + (tx * ctx + ty * cty + tz * ctz)
            v += qx * cbx + qy * cby + qz * cbz
            v += qx * (b1y * t1z - b1z * t1y) + qy * (b1z * t1x - b1x * t1z) + qz * (b1x * t1y - b1y * t1x)
            v += qx * (t1y * t0z - t1z * t0y) + qy * (t1z * t0x - t1x * t0z) + qz * (t1x * t0y - t1y * t0x)
            v += qx * (t0y * b0z - t0z * b0y) + qy * (t0z * b0x - t0x * b0z) + qz * (t0x * b0y - t0y * b0x)
        out[c] = v / 6.0


@dataclasses.dataclass(frozen=True, eq=False)
class CentreLines:
    """Every muscle's centre line as a linear map of the vertex positions (``centre_lines``): its points are
    ``smooth @ (raw @ x)``, per muscle in order its first end ring's centroid, the mean cell centre of each slice
    gap (Gaussian-smoothed along the muscle, piece by piece between its anchored rings), the centroid of each ring
    inside the muscle that is bound whole to one bone (a via ring) where it lies, its last end ring's centroid."""
    raw: object                     # (P, V) scipy.sparse CSR: each point's unsmoothed position from the vertices
    smooth: object                  # (P, P) scipy.sparse CSR: the Gaussian along each piece's gap points (anchors kept)
    muscle: np.ndarray              # (P,) int32 the muscle of each point
    gap: np.ndarray                 # (P,) int32 the point's slice gap along its muscle (-1: an end or via ring)

    def points(self, x: np.ndarray) -> np.ndarray:
        """(P, 3) [m] the centre lines' points at positions x."""
        return self.smooth @ (self.raw @ x)

    def lengths(self, x: np.ndarray, n_muscles: int) -> np.ndarray:
        """(M,) [m] each muscle's centre-line length at positions x (0 for a muscle with no cells)."""
        d = np.linalg.norm(np.diff(self.points(x), axis=0), axis=1)
        same = self.muscle[1:] == self.muscle[:-1]
        return np.bincount(self.muscle[1:][same], weights=d[same], minlength=n_muscles)[:n_muscles]

    def pieces(self, m: int) -> list:
        """Muscle m's gap points between its anchored rings: a list of index arrays into the points, each in
        gap order (one piece for a muscle with no via ring)."""
        idx = np.flatnonzero(self.muscle == m)
        return [idx[a:b] for a, b in _runs(self.gap[idx])]


def _runs(gap: np.ndarray) -> list:
    """(start, stop) of each run of gap points (gap >= 0) between anchored points (gap -1) of one muscle's points."""
    cut = np.flatnonzero(gap < 0)
    return [(a + 1, b) for a, b in zip(cut[:-1], cut[1:]) if b > a + 1]


def via_rings(tm, cells: np.ndarray, gap: np.ndarray, off: np.ndarray, cv: np.ndarray) -> list:
    """The slice boundaries inside a muscle (b: between its gaps b and b + 1) whose ring is bound whole to one
    segment or is one of the muscle's point via rings (the builder's via rings, tissues.yaml via_points;
    TissueModel.via_point_*): there the muscle's path is held to the bone, as the source model's path is at its via
    point."""
    n = np.diff(off) // 2
    m = tm.cell_muscle[cells[0]] if cells.size else -1
    po, pv = np.asarray(getattr(tm, 'via_point_offsets', [0])), np.asarray(getattr(tm, 'via_point_vertices', []))
    pm = np.asarray(getattr(tm, 'via_point_muscle', []))
    points = [set(pv[po[r]:po[r + 1]].tolist()) for r in np.flatnonzero(pm == m)]
    out = []
    for b in range(int(gap.max()) if gap.size else 0):
        ring = np.concatenate([cv[off[c] + n[c]:off[c] + 2 * n[c]] for c in cells[gap == b]])
        seg = np.asarray(tm.vertex_segment)[ring]
        if (seg.size and seg.min() >= 0 and (seg == seg[0]).all()) or any(set(ring.tolist()) <= p for p in points):
            out.append(b)
    return out


def centre_lines(tm, off: np.ndarray, cv: np.ndarray, x: np.ndarray, sigma: float) -> CentreLines:
    """Each muscle's centre line (docs/solver.md "Muscle length"): from its first end ring's centroid (the mean of the
    bottom-ring centroids of the cells in its first slice gap) through the mean of each slice gap's cell centres to its
    last end ring's centroid, passing through the centroid of each via ring (``via_rings``: a ring inside the muscle
    bound whole to one bone, where the path is held as the source model's at its via point). The gap points are
    smoothed along the muscle, each piece between anchored rings on its own, with a Gaussian of ``sigma`` [m] (in gap
    steps: sigma / the mean distance between the muscle's consecutive gap points at positions x; scipy's
    gaussian_filter1d, 'nearest' ends, as a matrix); a piece of fewer than 3 gaps is not smoothed. Linear in the
    positions: built once (compile_model)."""
    from scipy import sparse
    from scipy.ndimage import gaussian_filter1d
    n = np.diff(off) // 2
    rows, cols, vals, muscle, gaps = [], [], [], [], []
    P = 0

    def ring_point(row, cells_, ring):       # the mean over cells_ of their bottom (0) / top (1) ring centroids
        for c in cells_:
            rows.append(np.full(n[c], row))
            cols.append(cv[off[c] + ring * n[c]:off[c] + (ring + 1) * n[c]])
            vals.append(np.full(n[c], 1.0 / (n[c] * cells_.size)))

    for m in range(tm.n_muscles):
        cells = np.flatnonzero(tm.cell_muscle == m)
        if cells.size == 0:
            continue
        _, gap = np.unique(tm.cell_slice[cells], return_inverse=True)
        G, count = int(gap.max()) + 1, np.bincount(gap)
        vias = via_rings(tm, cells, gap, off, cv)
        row_of = P + 1 + np.arange(G) + np.searchsorted(vias, np.arange(G))      # gap g's row (after the vias below it)
        for c, g in zip(cells, gap):           # gap point: the mean over the gap's cells of each cell's 2 n vertices
            rows.append(np.full(2 * n[c], row_of[g]))
            cols.append(cv[off[c]:off[c + 1]])
            vals.append(np.full(2 * n[c], 1.0 / (2 * n[c] * count[g])))
        ring_point(P, cells[gap == 0], 0)                           # end points: the bottom / top rings
        ring_point(P + G + len(vias) + 1, cells[gap == G - 1], 1)
        for b in vias:                                              # via points: gap b's top ring
            ring_point(row_of[b] + 1, cells[gap == b], 1)
        pieces = np.split(np.arange(G), np.asarray(vias, int) + 1)
        muscle.append(np.full(G + len(vias) + 2, m))
        gaps.append(np.concatenate([[-1]] + [np.r_[piece, -1] for piece in pieces]))
        P += G + len(vias) + 2
    V = x.shape[0]
    cat = (lambda a, dt: np.concatenate(a).astype(dt)) if rows else (lambda a, dt: np.zeros(0, dt))
    raw = sparse.csr_matrix((cat(vals, np.float64), (cat(rows, np.int64), cat(cols, np.int64))), shape=(P, V))
    pts = raw @ np.asarray(x, np.float64)
    mats, start = [], 0
    for g in gaps:                            # per muscle: its points' gaps (-1 at the anchored points)
        W = np.eye(g.size)
        line = pts[start + np.flatnonzero(g >= 0)]
        step = sigma / max(float(np.mean(np.linalg.norm(np.diff(line, axis=0), axis=1))), 1e-9) if len(line) > 1 else 0
        for a, b in _runs(g):
            if b - a >= 3:
                W[a:b, a:b] = gaussian_filter1d(np.eye(b - a), step, axis=0, mode='nearest')
        mats.append(sparse.csr_matrix(W))
        start += g.size
    smooth = sparse.block_diag(mats, format='csr') if mats else sparse.csr_matrix((0, 0))
    return CentreLines(raw, smooth, cat(muscle, np.int32), cat(gaps, np.int32))


def cell_volumes(sim, x: np.ndarray, cells: str = 'all') -> np.ndarray:
    """(C,) volume [m^3] of every cell at positions x: core.geometry.prism_volumes (the one definition: cap
    fans about each ring's centroid, side quads as four triangles about the quad centroid), signed so that
    it is positive at rest (sim.cell_sign: the rest orientation of each cell's rings). cells='muscle': the
    muscle cells' only, (number of muscle cells,) in cell order (each cell's volume is computed alone: the same
    values as the whole array's; observe() needs no others, and the fat cells are a third of the work)."""
    if cells == 'all':
        off, cv, sign = sim.off, sim.cv, sim.cell_sign
    else:
        sel, off, cv = _muscle_layout(sim)
        sign = sim.cell_sign[sel]
    out = np.empty(len(off) - 1)
    prism_volumes_compiled(np.ascontiguousarray(x, np.float64), off, cv, out)
    return out * sign


_LAYOUTS = weakref.WeakKeyDictionary()      # SimModel -> (muscle cells, their offsets, their vertices)


def _muscle_layout(sim):
    t = _LAYOUTS.get(sim)
    if t is None:
        sel = np.flatnonzero(sim.cell_muscle >= 0)
        sizes = np.diff(sim.off)[sel]
        off = np.concatenate([[0], np.cumsum(sizes)]).astype(sim.off.dtype)
        cv = (np.concatenate([sim.cv[sim.off[c]:sim.off[c + 1]] for c in sel]) if sel.size
              else np.zeros(0, sim.cv.dtype)).astype(sim.cv.dtype)
        t = _LAYOUTS[sim] = (sel, off, cv)
    return t


def kinetic_energy(sim, state) -> float:
    """Kinetic energy [J] of the free vertices (true masses)."""
    free = sim.inv_mass > 0
    return 0.5 * float(np.dot(sim.mass[free], np.einsum('ij,ij->i', state.v[free], state.v[free])))


def joint_torques(sim, state, f: np.ndarray, idx=None, vias: bool = True) -> np.ndarray:
    """(J,) [N m] generalized force on each hinge of forces f (V, 3) on bone-attached vertices (idx: which;
    default all), by virtual work as the skeleton kernel applies them: a hinge j gets (W_j x (x - P_j) + D_j) . f
    (a plain hinge: a_j . (x - p_j) x f) from the vertices of the segments it moves; the driver of a coupled joint gets
    (W x (x - P) + R_p d') . f from the vertices of its child (skeleton.joint_jacobians; docs/solver.md "Skeleton").
    A point via ring on one of those vertices' segments adds the net force f on its free vertices at its centroid's
    place on the bone, as the step's skeleton stage takes it (integration.via_forces; vias=False: not). 0 for a fixed
    or coupled joint."""
    idx = sim.att_idx if idx is None else np.asarray(idx)
    seg = sim.vertex_segment[idx]
    x, F = state.x[idx], f[idx]
    if vias:
        vseg, where, pull = via_pulls(sim, f, state.seg_R, state.seg_t)
        mine = np.isin(vseg, seg)
        seg, x, F = np.concatenate([seg, vseg[mine]]), np.concatenate([x, where[mine]]), np.concatenate([F, pull[mine]])
    return _generalized(sim, state, seg, F, np.cross(x, F))


def wrench_torques(sim, state, wr: np.ndarray) -> np.ndarray:
    """(J,) [N m] generalized force on each hinge of wrenches wr (S, 6) on the segments (force, its moment about the
    world origin: State.contact_wrench, the reaction the contact stages and the sheath correction leave for the next
    sub-step's skeleton step), by the same virtual work as joint_torques."""
    return _generalized(sim, state, np.arange(wr.shape[0]), wr[:, :3], wr[:, 3:])


def _generalized(sim, state, seg, F, M) -> np.ndarray:
    """(J,) the generalized forces of forces F (N, 3) on segments seg (N,) with their moments M (N, 3) about the world
    origin: hinge j gets W_j . (sum M - P_j x sum F) + D_j . sum F over the segments it moves (= (W_j x (x - P_j) +
    D_j) . F for a force F at x); a coupled joint's driver from its child."""
    tau = np.zeros(sim.n_joints)
    W, P, D = joint_jacobians(state.q, sim.skeleton, state.seg_R, state.seg_t)
    for j in range(sim.n_joints):
        if sim.j_type[j] == JOINT_COUPLED:
            sel, k = seg == sim.j_child[j], sim.j_driver[j]
        elif sim.j_type[j] == JOINT_HINGE:
            sel, k = sim.anc[j][seg], j
        else:
            continue
        f, m = F[sel].sum(0), M[sel].sum(0)
        tau[k] += float(W[j] @ (m - np.cross(P[j], f)) + D[j] @ f)
    return tau


def via_pulls(sim, f: np.ndarray, seg_R: np.ndarray, seg_t: np.ndarray) -> tuple:
    """The point via rings' pull on their bones (docs/solver.md "Point vias"; integration.via_forces compiled): per ring
    its segment, its centroid's place p = R_s local + t_s in the poses (seg_R, seg_t) and the net force f on its free
    vertices. Returns (segments (R,), places (R, 3), forces (R, 3))."""
    R = sim.via_seg.size
    free = sim.inv_mass > 0
    where = np.einsum('rij,rj->ri', seg_R[sim.via_seg], sim.via_local).reshape(R, 3) + seg_t[sim.via_seg].reshape(R, 3)
    pull = np.array([f[v[free[v]]].sum(axis=0) for v in np.split(sim.via_idx, sim.via_off[1:-1])] if R else
                    np.zeros((0, 3))).reshape(R, 3)
    return np.asarray(sim.via_seg), where, pull


def skeleton_energy(sim, state) -> float:
    """Kinetic + gravitational potential energy [J] of the segments (masses incl. attached vertices
    when params.attached_mass_to_segment), potential relative to the rest pose."""
    e = 0.0
    S, J = sim.n_segments, sim.n_joints
    W, P, D = joint_jacobians(state.q, sim.skeleton, state.seg_R, state.seg_t)
    for s in range(S):
        com = state.seg_R[s] @ sim.seg_com[s] + state.seg_t[s]
        w = np.zeros(3)
        v = np.zeros(3)
        for j in range(J):
            if sim.j_type[j] == JOINT_HINGE and sim.anc[j, s]:
                w += W[j] * state.qd[j]
                v += (np.cross(W[j], com - P[j]) + D[j]) * state.qd[j]
        j = sim.seg_joint[s]
        if j >= 0 and sim.j_type[j] == JOINT_COUPLED:       # + the coupling's motion
            w += W[j] * state.qd[sim.j_driver[j]]
            v += (np.cross(W[j], com - P[j]) + D[j]) * state.qd[sim.j_driver[j]]
        Iw = state.seg_R[s] @ sim.seg_inertia[s] @ state.seg_R[s].T
        e += 0.5 * sim.seg_mass[s] * v @ v + 0.5 * w @ Iw @ w - sim.seg_mass[s] * sim.gravity @ (com - sim.seg_com[s])
    return float(e)
