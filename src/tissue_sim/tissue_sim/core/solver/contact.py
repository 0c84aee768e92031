"""Bone contact: soft tissue is kept outside the bones (docs/contact.md), stage 4 of the step.

At compile time the bone meshes of each segment become one signed-distance grid in its rest frame (the
frame the bone mesh is given in: a rest point X of segment s is at R_s X + t_s): exact point-triangle
distances in a narrow band about the surface, a Euclidean distance transform beyond it, the sign from
the winding number along grid columns (negative inside). They are constants of the model
(``SimModel.contact``, a ``ContactGrids`` named tuple of read-only arrays; no grid when
``Params.bone_contact`` is off). In the step, after the soft tissue has integrated, ``bone_contact``
samples each free vertex in the grids whose box holds it (trilinear value and gradient) and projects a
vertex closer than its floor (the margin) back to it along the gradient, removing its inward velocity
relative to the bone (Coulomb friction optional). Its mutable buffers (the segment poses at the
sub-step's start, the broad phase's records) are a ``ContactWork`` owned by the State being stepped
(``step.Workspace``), so two states stepping one model share nothing.

Stage 4a, before it, ``fold_contact``: the tissue-tissue contact in the fold of each hinge named in
``Params.fold_contact`` (flexion-side tissue kept behind the axis and, with ``fold_plane``, on its side of the plane
bisecting the two segments) and the sheath of ``Params.sheath_group`` and ``Params.sheath_below`` (a retinaculum
holding muscles near their rest lines above and below the hinge); docs/contact.md "Tissue-tissue contact in the fold,
and the sheath". Stage 4b, between them, ``wrap_contact``: the source model's wrap cylinders named in
``Params.wrap_surfaces`` keep the free vertices of the muscles that wrap over them outside (docs/contact.md "Wrap
surfaces").
"""
from __future__ import annotations

import collections
import math

import numpy as np
from numba import njit, prange

ContactGrids = collections.namedtuple('ContactGrids', 'g_seg g_origin g_inv_h g_dims g_off g_phi c_dims c_off c_min '
                                      'floor free_idx par f_seg f_geo f_off f_idx f_side f_floor f_wfloor f_plane s_off s_idx s_X s_side s_r '
                                      'w_seg w_geo w_off w_idx w_floor')
"""Constants (SimModel.contact, read-only): per grid b (B grids, one per segment with bones) its segment
g_seg (B,) int32, origin (B, 3) [m], 1/spacing g_inv_h (B,), dims (B, 3) int64, values g_phi[g_off[b]:g_off[b+1]]
(float32, C order, negative inside); the broad phase's block minima c_min[c_off[b]:...] over blocks of BLOCK^3
cells, block dims c_dims (B, 3); each free vertex's lowest allowed distance floor (V,) [m] (the margin, or its
distance at rest where that is smaller); the free vertices free_idx (F,) int32; par = (margin, friction).
The fold contact (``fold_contact``, docs/contact.md "Tissue-tissue contact in the fold"), per folding hinge k (K):
its (parent, child) segments f_seg (K, 2) int32, f_geo (K, 9) = rest joint centre c0, unit proximal direction n0
(perpendicular to the axis, away from the child), unit flexion direction e (where the child's distal end moves in
flexion), rest frame; its vertices f_idx[f_off[k]:f_off[k+1]] (int32), their side f_side (+1 proximal, -1 distal)
and lowest allowed signed distance to the bisector plane f_floor [m] and to their segment's plane through the axis
normal to e f_wfloor [m]; f_plane (1,) bool: the bisector plane on (Params.fold_plane; off: only the flexion side).
The sheath (``sheath_group`` above, ``sheath_below`` below), per folding hinge k: its vertices s_idx[s_off[k]:s_off[k+1]] (int32) with their rest
positions s_X (N, 3) [m] and side s_side (+1: held in the parent's frame, above the hinge; -1: the child's, below),
kept within s_r (1,) [m] of their rest line along n0 in that segment's frame.
The wrap surfaces (``wrap_contact``, Params.wrap_surfaces, docs/contact.md "Wrap surfaces"), per surface w (W): a
cylinder fixed in segment w_seg (W,) int32, w_geo (W, 11) = centre (3) [m] and unit axis (3) in that segment's rest
frame, unit quadrant direction (3; zeros: every side), radius [m], half length [m]; its vertices w_idx[w_off[w]:
w_off[w+1]] (int32) and their lowest allowed distance from the axis w_floor [m] (the radius, or less where the rest
shape already lies inside)."""
ContactWork = collections.namedtuple('ContactWork', 'R0 t0 qc slack cand stats xf mask dv moved n_moved flag')
"""Mutable buffers (step.Workspace, one per State): the segment poses at the sub-step's start R0 (S, 3, 3), t0 (S, 3);
the broad phase's records qc (B, 3, F) (rest-frame point where a vertex was last tested, by coordinate) and slack (B,
F) (0: test it), float32 (the broad phase streams them every sub-step; SLACK_MARGIN covers their rounding); scratch:
cand (F,) int32, xf (3, F) float32 the free vertices' positions by coordinate, mask (F rounded up to
8,) uint8, dv (F, 4) each candidate's outcome (dv[k, 0] 0: not projected, 1: projected, 2: and its velocity changed
by dv[k, 1:]); stats (2,) int64 = (calls, vertex-grid tests so far); the vertices the stage moved since unmark, each
once (mark): moved (V,) int32, the first n_moved[0] (int64 (1,)) of it, flag (V,) uint8 (1: listed); V = 0 where nothing reads the
list (work's n_listed: only BDF2 does)."""


@njit(inline='always')
def mark(cw, i):
    """Vertex i was moved by the stage (its position or velocity changed): listed in cw.moved once (no list: nothing)."""
    if cw.flag.shape[0] > 0 and cw.flag[i] == 0:
        cw.flag[i] = 1
        cw.moved[cw.n_moved[0]] = i
        cw.n_moved[0] += 1


@njit(cache=True)
def unmark(cw):
    """The list of moved vertices emptied (before stage 4)."""
    for k in range(cw.n_moved[0]):
        cw.flag[cw.moved[k]] = 0
    cw.n_moved[0] = 0


# ------------------------------------------------------------------------------- grid building
@njit(cache=True)
def _tri_dist2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Squared distance from p to triangle abc (Ericson, Real-Time Collision Detection 5.1.5)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = bx, by, bz
        else:
            vc = d1 * d4 - d3 * d2
            if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
                w = d1 / (d1 - d3)
                qx, qy, qz = ax + w * abx, ay + w * aby, az + w * abz
            else:
                cpx, cpy, cpz = px - cx, py - cy, pz - cz
                d5 = abx * cpx + aby * cpy + abz * cpz
                d6 = acx * cpx + acy * cpy + acz * cpz
                if d6 >= 0.0 and d5 <= d6:
                    qx, qy, qz = cx, cy, cz
                else:
                    vb = d5 * d2 - d1 * d6
                    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                        w = d2 / (d2 - d6)
                        qx, qy, qz = ax + w * acx, ay + w * acy, az + w * acz
                    else:
                        va = d3 * d6 - d5 * d4
                        if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                            qx, qy, qz = bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz)
                        else:
                            den = 1.0 / (va + vb + vc)
                            v_ = vb * den
                            w = vc * den
                            qx = ax + abx * v_ + acx * w
                            qy = ay + aby * v_ + acy * w
                            qz = az + abz * v_ + acz * w
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz


@njit(cache=True)
def _band_distances(V, T, origin, h, dims, band, d2):
    """d2[i, j, k] = min squared distance to the triangles of every grid point within `band` of a
    triangle's bounding box (other points keep their value)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for t in range(T.shape[0]):
        a, b, c = T[t, 0], T[t, 1], T[t, 2]
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for d in range(3):
            mn = min(V[a, d], V[b, d], V[c, d]) - band
            mx = max(V[a, d], V[b, d], V[c, d]) + band
            lo[d] = max(0, int(math.floor((mn - origin[d]) / h)))
            hi[d] = min(dims[d] - 1, int(math.ceil((mx - origin[d]) / h)))
        for i in range(lo[0], hi[0] + 1):
            px = origin[0] + i * h
            for j in range(lo[1], hi[1] + 1):
                py = origin[1] + j * h
                for k in range(lo[2], hi[2] + 1):
                    pz = origin[2] + k * h
                    e = _tri_dist2(px, py, pz, V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2],
                                   V[c, 0], V[c, 1], V[c, 2])
                    if e < d2[i, j, k]:
                        d2[i, j, k] = e
    return nx * ny * nz


@njit(cache=True)
def _column_winding(V, T, origin, h, dims, wind):
    """Winding number of every grid point about the mesh, counted along +z columns: each triangle a
    column crosses adds +1 (entering: outward normal facing -z) or -1 (leaving) to the points above
    the crossing. Returns the number of columns that do not end at 0 (an open mesh); they are zeroed."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for t in range(T.shape[0]):
        a, b, c = T[t, 0], T[t, 1], T[t, 2]
        ax, ay, az = V[a, 0], V[a, 1], V[a, 2]
        bx, by, bz = V[b, 0], V[b, 1], V[b, 2]
        cx, cy, cz = V[c, 0], V[c, 1], V[c, 2]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)     # 2 x signed xy area = 2 x normal z
        if area == 0.0:
            continue
        s = -1 if area > 0.0 else 1
        i0 = max(0, int(math.ceil((min(ax, bx, cx) - origin[0]) / h)))
        i1 = min(nx - 1, int(math.floor((max(ax, bx, cx) - origin[0]) / h)))
        j0 = max(0, int(math.ceil((min(ay, by, cy) - origin[1]) / h)))
        j1 = min(ny - 1, int(math.floor((max(ay, by, cy) - origin[1]) / h)))
        for i in range(i0, i1 + 1):
            px = origin[0] + i * h
            for j in range(j0, j1 + 1):
                py = origin[1] + j * h
                # barycentric coordinates in the xy projection (the grid is offset so that no column
                # passes exactly through an edge)
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / area
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = w0 * az + w1 * bz + w2 * cz
                k = int(math.ceil((z - origin[2]) / h))
                if k < 0:
                    k = 0
                if k < nz:
                    wind[i, j, k] += s
    bad = 0
    for i in range(nx):
        for j in range(ny):
            acc = 0
            for k in range(nz):
                acc += wind[i, j, k]
                wind[i, j, k] = acc
            if acc != 0:
                bad += 1
                for k in range(nz):
                    wind[i, j, k] = 0
    return bad


def bone_sdf(V: np.ndarray, T: np.ndarray, h: float, pad: float):
    """Signed-distance grid [m] of a closed triangle mesh (V, T), negative inside: (origin (3,),
    dims (3,) int64, phi (nx, ny, nz) float32, open_columns). Grid points lie at origin + h (i, j, k)
    and cover the mesh's bounding box plus pad on every side. Exact within 3 h of the surface,
    beyond it 2 h + the Euclidean distance transform to that band (within about a cell of the
    distance; the values stay 1-Lipschitz between neighbouring grid points)."""
    from scipy import ndimage
    V = np.ascontiguousarray(V, np.float64)
    T = np.ascontiguousarray(T, np.int64)
    lo, hi = V.min(0) - pad, V.max(0) + pad
    # an irrational sub-cell offset: no grid column runs exactly through a mesh edge or vertex
    origin = lo - h * np.array([0.31830988618, 0.27182818284, 0.14142135623])
    dims = (np.ceil((hi - origin) / h).astype(np.int64) + 1)
    d2 = np.full(tuple(dims), np.inf)
    band = 3.0 * h
    _band_distances(V, T, origin, float(h), dims, band, d2)
    near = d2 <= band * band
    d = np.sqrt(d2)
    if not near.all():
        # beyond the band: 2 h + h x the distance (in cells) to the band; with the band's exact
        # values this keeps the grid 1-Lipschitz (the broad phase relies on it)
        d = np.where(near, d, 2.0 * h + h * ndimage.distance_transform_edt(~near))
    wind = np.zeros(tuple(dims), np.int64)
    open_cols = _column_winding(V, T, origin, float(h), dims, wind)
    phi = np.where(wind > 0, -d, d).astype(np.float32)
    return origin, dims, phi, int(open_cols)


BLOCK = 4      # cells per side of the coarse blocks of the broad phase


@njit(cache=True)
def _block_min(phi, m, out):
    """out[I, J, K] = min of phi over the grid points [m I, m I + m] x ... (the corners every
    trilinear sample in the block's cells reads): a vertex in a block whose minimum is above its
    floor is not in contact (a trilinear value is never below its corners)."""
    nx, ny, nz = phi.shape
    for I in range(out.shape[0]):
        for J in range(out.shape[1]):
            for K in range(out.shape[2]):
                v = np.inf
                for i in range(m * I, min(m * I + m, nx - 1) + 1):
                    for j in range(m * J, min(m * J + m, ny - 1) + 1):
                        for k in range(m * K, min(m * K + m, nz - 1) + 1):
                            if phi[i, j, k] < v:
                                v = phi[i, j, k]
                out[I, J, K] = v


def block_min(phi: np.ndarray, m: int = BLOCK) -> np.ndarray:
    """The broad phase's coarse grid of phi (nx, ny, nz): blocks of m cells, float32."""
    nb = [max(1, -(-(n - 1) // m)) for n in phi.shape]
    out = np.empty(nb, np.float32)
    _block_min(phi, m, out)
    return out


# ------------------------------------------------------------------------------- sampling
@njit(cache=True, inline='always')
def _corner(gx, gy, gz, nx, ny, nz):
    """The lowest corner (i, j, k) of the grid cell holding grid coordinates (gx, gy, gz) (inside [0, n-1])."""
    return min(int(gx), nx - 2), min(int(gy), ny - 2), min(int(gz), nz - 2)


@njit(cache=True, inline='always')
def _block_index(cg, b, i, j, k):
    """Index in c_min of grid b's coarse block holding cell (i, j, k)."""
    return cg.c_off[b] + ((i // BLOCK) * cg.c_dims[b, 1] + j // BLOCK) * cg.c_dims[b, 2] + k // BLOCK


@njit(cache=True, inline='always')
def _sample(phi, base, nx, ny, nz, gx, gy, gz):
    """Trilinear value of grid phi (flat from base, dims nx ny nz) at grid coordinates (gx, gy, gz)
    (inside [0, n-1]) and its gradient in grid units: (value, d/dgx, d/dgy, d/dgz)."""
    i, j, k = _corner(gx, gy, gz, nx, ny, nz)
    fx, fy, fz = gx - i, gy - j, gz - k
    b = base + (i * ny + j) * nz + k
    c000 = phi[b]; c001 = phi[b + 1]
    c010 = phi[b + nz]; c011 = phi[b + nz + 1]
    b1 = b + ny * nz
    c100 = phi[b1]; c101 = phi[b1 + 1]
    c110 = phi[b1 + nz]; c111 = phi[b1 + nz + 1]
    # along z
    c00 = c000 + fz * (c001 - c000); c01 = c010 + fz * (c011 - c010)
    c10 = c100 + fz * (c101 - c100); c11 = c110 + fz * (c111 - c110)
    c0 = c00 + fy * (c01 - c00); c1 = c10 + fy * (c11 - c10)
    gz0 = (1.0 - fy) * (c001 - c000) + fy * (c011 - c010)
    gz1 = (1.0 - fy) * (c101 - c100) + fy * (c111 - c110)
    return (c0 + fx * (c1 - c0), c1 - c0, (1.0 - fx) * (c01 - c00) + fx * (c11 - c10),
            (1.0 - fx) * gz0 + fx * gz1)


@njit(cache=True)
def sample_grid(g_origin, g_inv_h, g_dims, g_off, g_phi, b, P, out, grad_out):
    """Signed distance [m] and unit gradient of bone grid b at rest-frame points P (n, 3); points
    outside the grid get +inf and a zero gradient."""
    nx, ny, nz = g_dims[b, 0], g_dims[b, 1], g_dims[b, 2]
    ih = g_inv_h[b]
    for p in range(P.shape[0]):
        gx = (P[p, 0] - g_origin[b, 0]) * ih
        gy = (P[p, 1] - g_origin[b, 1]) * ih
        gz = (P[p, 2] - g_origin[b, 2]) * ih
        if not (gx >= 0.0 and gy >= 0.0 and gz >= 0.0 and gx <= nx - 1 and gy <= ny - 1 and gz <= nz - 1):
            out[p] = np.inf
            grad_out[p, :] = 0.0
            continue
        out[p], g0, g1, g2 = _sample(g_phi, g_off[b], nx, ny, nz, gx, gy, gz)
        n = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        grad_out[p, 0] = g0 / n if n > 0 else 0.0
        grad_out[p, 1] = g1 / n if n > 0 else 0.0
        grad_out[p, 2] = g2 / n if n > 0 else 0.0


# ------------------------------------------------------------------------------- the step's stage
LIPSCHITZ = 1.7320508075688772 + 1e-6   # bound on |grad| of a trilinear interpolation of a 1-Lipschitz grid
PROJECTIONS = 4         # at most this many projections of a vertex per grid and sub-step (beyond the exact band the
                        # grid's distance is approximate, so one projection from deep inside can fall short)
PROJECTION_TOL = 1e-6   # [m] a projected vertex this close below its floor is done
SLACK_MARGIN = 1e-5     # [m] taken off every broad-phase slack, for its float32 rounding: the record and the position each
                        # move a rest-frame point by at most sqrt(3) 2^-24 r (r the largest coordinate), the transform
                        # R^T (x - t) by at most ~7 sqrt(3) 2^-24 r, the slack by 2^-24 of itself: for r <= 5 m LIPSCHITZ x
                        # their sum < 8e-6 m, so a vertex the broad phase skips is one a full test leaves alone too


@njit(cache=True, inline='always')
def _react(wr, s, share, x, i, m_h, dvx, dvy, dvz):
    """The reaction on segment s of a contact's velocity change dv of vertex i (now at x[i]): the vertex's momentum
    changed by m dv in the sub-step (m = 1/inv_den, the mass the integrator gives it), so the segment (or, share 0.5
    each, the two segments whose bisector plane it was) takes the force -share m dv / h at x[i]: wr[s] += (force [N],
    its moment about the world origin [N m]). m_h = m / h."""
    fx, fy, fz = -share * m_h * dvx, -share * m_h * dvy, -share * m_h * dvz
    wr[s, 0] += fx
    wr[s, 1] += fy
    wr[s, 2] += fz
    wr[s, 3] += x[i, 1] * fz - x[i, 2] * fy
    wr[s, 4] += x[i, 2] * fx - x[i, 0] * fz
    wr[s, 5] += x[i, 0] * fy - x[i, 1] * fx


@njit(cache=True, fastmath={'contract'}, inline='always')
def _narrow(i, b, s, px, py, pz, gx, gy, gz, h, x, v, seg_R, cg, R0, t0, out):
    """Vertex i inside grid b's box (rest-frame point p, grid coordinates g; s the segment): project
    it out when it is closer than its floor, again from where that put it while it is still below it
    (at most PROJECTIONS times), and fix its velocity with the last normal: out (4,) = (2, the velocity change) where
    it changed (its reaction is bone_contact's to apply), out untouched otherwise. Returns a lower bound of
    (sampled distance - floor) before the projection, for the broad phase, and whether it was projected."""
    nx, ny, nz = cg.g_dims[b, 0], cg.g_dims[b, 1], cg.g_dims[b, 2]
    lim = cg.floor[i]
    i_, j_, k_ = _corner(gx, gy, gz, nx, ny, nz)
    cm = cg.c_min[_block_index(cg, b, i_, j_, k_)]
    if cm >= lim:                                    # the block's minimum: no sample needed
        return cm - lim, False
    d, ga, gb, gc = _sample(cg.g_phi, cg.g_off[b], nx, ny, nz, gx, gy, gz)
    if d >= lim:
        return d - lim, False
    gn = math.sqrt(ga * ga + gb * gb + gc * gc)
    if not gn > 0.0:
        return d - lim, False
    d_first = d
    # the bone's velocity at the vertex: (x - x_before) / h, x_before = R0 p + t0
    ih_t = 1.0 / h
    bx = (x[i, 0] - (R0[s, 0, 0] * px + R0[s, 0, 1] * py + R0[s, 0, 2] * pz + t0[s, 0])) * ih_t
    by = (x[i, 1] - (R0[s, 1, 0] * px + R0[s, 1, 1] * py + R0[s, 1, 2] * pz + t0[s, 1])) * ih_t
    bz = (x[i, 2] - (R0[s, 2, 0] * px + R0[s, 2, 1] * py + R0[s, 2, 2] * pz + t0[s, 2])) * ih_t
    ih = cg.g_inv_h[b]
    n0 = n1 = n2 = 0.0
    for _ in range(PROJECTIONS):
        # world normal n = R (grad / |grad|); the vertex moves by (floor - d) n, its rest-frame point by (floor - d) u
        ux, uy, uz = ga / gn, gb / gn, gc / gn
        n0 = seg_R[s, 0, 0] * ux + seg_R[s, 0, 1] * uy + seg_R[s, 0, 2] * uz
        n1 = seg_R[s, 1, 0] * ux + seg_R[s, 1, 1] * uy + seg_R[s, 1, 2] * uz
        n2 = seg_R[s, 2, 0] * ux + seg_R[s, 2, 1] * uy + seg_R[s, 2, 2] * uz
        push = lim - d
        x[i, 0] += push * n0
        x[i, 1] += push * n1
        x[i, 2] += push * n2
        px += push * ux
        py += push * uy
        pz += push * uz
        gx = (px - cg.g_origin[b, 0]) * ih
        gy = (py - cg.g_origin[b, 1]) * ih
        gz = (pz - cg.g_origin[b, 2]) * ih
        if not (gx >= 0.0 and gy >= 0.0 and gz >= 0.0 and gx <= nx - 1 and gy <= ny - 1 and gz <= nz - 1):
            break
        d, ga, gb, gc = _sample(cg.g_phi, cg.g_off[b], nx, ny, nz, gx, gy, gz)
        gn = math.sqrt(ga * ga + gb * gb + gc * gc)
        if d >= lim - PROJECTION_TOL or not gn > 0.0:
            break
    rx, ry, rz = v[i, 0] - bx, v[i, 1] - by, v[i, 2] - bz
    vn = rx * n0 + ry * n1 + rz * n2
    if vn < 0.0:
        tx, ty, tz = rx - vn * n0, ry - vn * n1, rz - vn * n2
        mu = cg.par[1]
        if mu > 0.0:
            vt = math.sqrt(tx * tx + ty * ty + tz * tz)
            keep = max(0.0, 1.0 - mu * (-vn) / vt) if vt > 0.0 else 0.0
            tx *= keep; ty *= keep; tz *= keep
        nvx, nvy, nvz = bx + tx, by + ty, bz + tz
        out[0], out[1], out[2], out[3] = 2.0, nvx - v[i, 0], nvy - v[i, 1], nvz - v[i, 2]
        v[i, 0] = nvx
        v[i, 1] = nvy
        v[i, 2] = nvz
    return d_first - lim, True


@njit(cache=True, inline='always')
def half(t, n):
    """(lo, hi): half t (0 or 1) of range(n), the two parts of the parallel kernels' prange(2) loops (here, in
    implicit.bdf2_start and implicit._via_move), cut at a multiple of 64 so that the halves write separate cache lines
    (of a byte mask as of a float64 array)."""
    m = min(n, ((n // 2 + 63) // 64) * 64)
    return (0, m) if t == 0 else (m, n)


@njit(cache=True, fastmath={'contract'})
def _narrow_span(lo, hi, b, h, x, v, seg_R, seg_t, cg, R0, t0, cand, qc, slack, xf, dv):
    """bone_contact's narrow phase for grid b over its candidates lo <= k < hi (cand[k]: free vertex ii): each one
    inside the grid's box is sampled and projected (_narrow; dv[k] its outcome) and its position by coordinate xf
    renewed (the next grids see it), its record (qc (3, F), slack (F,): grid b's) renewed; returns how many were
    projected. Each candidate writes its own rows only."""
    s = cg.g_seg[b]
    r00, r01, r02 = seg_R[s, 0, 0], seg_R[s, 0, 1], seg_R[s, 0, 2]
    r10, r11, r12 = seg_R[s, 1, 0], seg_R[s, 1, 1], seg_R[s, 1, 2]
    r20, r21, r22 = seg_R[s, 2, 0], seg_R[s, 2, 1], seg_R[s, 2, 2]
    tx, ty, tz = seg_t[s, 0], seg_t[s, 1], seg_t[s, 2]
    ox, oy, oz, ih = cg.g_origin[b, 0], cg.g_origin[b, 1], cg.g_origin[b, 2], cg.g_inv_h[b]
    mx, my, mz = cg.g_dims[b, 0] - 1.0, cg.g_dims[b, 1] - 1.0, cg.g_dims[b, 2] - 1.0
    hits = 0
    for k in range(lo, hi):
        ii = cand[k]
        i = cg.free_idx[ii]
        dx, dy, dz = x[i, 0] - tx, x[i, 1] - ty, x[i, 2] - tz
        px = r00 * dx + r10 * dy + r20 * dz
        py = r01 * dx + r11 * dy + r21 * dz
        pz = r02 * dx + r12 * dy + r22 * dz
        gx, gy, gz = (px - ox) * ih, (py - oy) * ih, (pz - oz) * ih
        dv[k, 0] = 0.0
        if gx >= 0.0 and gy >= 0.0 and gz >= 0.0 and gx <= mx and gy <= my and gz <= mz:
            d, hit = _narrow(i, b, s, px, py, pz, gx, gy, gz, h, x, v, seg_R, cg, R0, t0, dv[k])
            if hit:
                hits += 1
                dv[k, 0] = max(dv[k, 0], 1.0)
            xf[0, ii], xf[1, ii], xf[2, ii] = x[i, 0], x[i, 1], x[i, 2]     # (projected: the next grids see it)
        else:                       # outside the box: a lower bound of the distance to it
            d, hit = max(max(-gx, gx - mx), max(max(-gy, gy - my), max(-gz, gz - mz))) / ih, False
        qc[0, ii], qc[1, ii], qc[2, ii] = px, py, pz
        slack[ii] = 0.0 if hit else (d - SLACK_MARGIN) * (1.0 / LIPSCHITZ)    # projected: tested again next sub-step
    return hits


@njit(cache=True, fastmath={'contract'})
def _narrow_halves(n, b, h, x, v, seg_R, seg_t, cg, R0, t0, cand, qc, slack, xf, dv):
    """_narrow_span over grid b's n candidates in two halves (prange: on two threads in implicit.parallel_kernels'
    copy of bone_contact, here one after the other; the same numbers: each candidate is a vertex of its own)."""
    hits = 0
    for k in prange(2):
        lo, hi = half(k, n)
        hits += _narrow_span(lo, hi, b, h, x, v, seg_R, seg_t, cg, R0, t0, cand, qc, slack, xf, dv)
    return hits


@njit(cache=True, fastmath={'contract'})
def _broad(lo, hi, xf, qc, slack, R, t, mask):
    """bone_contact's broad phase for one grid over the free vertices lo <= ii < hi, in a flat loop the compiler
    vectorises: mask[ii] = 1 where free vertex ii is to be tested (its record's slack is 0, or its rest-frame point
    R^T (x - t) has moved from the record qc (3, F) by at least the slack); returns how many. In float32 (twice the
    SIMD lanes; SLACK_MARGIN bounds the rounding): R (3, 3) and t (3,) the segment's pose."""
    f4 = np.float32
    r00, r01, r02, r10, r11, r12 = f4(R[0, 0]), f4(R[0, 1]), f4(R[0, 2]), f4(R[1, 0]), f4(R[1, 1]), f4(R[1, 2])
    r20, r21, r22, tx, ty, tz = f4(R[2, 0]), f4(R[2, 1]), f4(R[2, 2]), f4(t[0]), f4(t[1]), f4(t[2])
    zero = f4(0.0)
    x0, x1, x2, q0, q1, q2 = xf[0, lo:hi], xf[1, lo:hi], xf[2, lo:hi], qc[0, lo:hi], qc[1, lo:hi], qc[2, lo:hi]
    sl, mk = slack[lo:hi], mask[lo:hi]     # (views and a loop from 0: it vectorises as the whole arrays' loop)
    n = 0
    for k in range(hi - lo):
        dx, dy, dz = x0[k] - tx, x1[k] - ty, x2[k] - tz
        ex = r00 * dx + r10 * dy + r20 * dz - q0[k]
        ey = r01 * dx + r11 * dy + r21 * dz - q1[k]
        ez = r02 * dx + r12 * dy + r22 * dz - q2[k]
        q = sl[k]
        m = np.uint8((q <= zero) | (ex * ex + ey * ey + ez * ez >= q * q))
        mk[k] = m
        n += m
    return n


@njit(cache=True, fastmath={'contract'})
def _broad_halves(xf, qc, slack, R, t, mask):
    """_broad over all the free vertices, in two halves (prange: on two threads in implicit.parallel_kernels' copy
    of bone_contact, here one after the other; the same mask and count)."""
    n = 0
    for k in prange(2):
        lo, hi = half(k, xf.shape[1])
        n += _broad(lo, hi, xf, qc, slack, R, t, mask)
    return n


@njit(cache=True)
def _load_free(x, free_idx, xf):
    """xf (3, F) float32: the free vertices' positions by coordinate (the broad phase's loads), in two halves (as
    _broad_halves)."""
    for k in prange(2):
        lo, hi = half(k, free_idx.shape[0])
        for ii in range(lo, hi):
            i = free_idx[ii]
            xf[0, ii], xf[1, ii], xf[2, ii] = x[i, 0], x[i, 1], x[i, 2]


@njit(cache=True)
def _gather(mask, F, cand):
    """The indices ii < F where mask[ii] != 0, into cand; returns how many (eight mask bytes read at a time)."""
    words = mask.view(np.uint64)
    n = 0
    for w in range(words.shape[0]):
        if words[w] != 0:
            for ii in range(8 * w, min(8 * w + 8, F)):
                if mask[ii] != 0:
                    cand[n] = ii
                    n += 1
    return n


@njit(cache=True, fastmath={'contract'})
def bone_contact(h, x, v, seg_R, seg_t, cg, cw, inv_den, wr):
    """Stage 4 of the step: project every free vertex closer to a bone than its floor (the margin)
    back onto it along the distance gradient, in place on (x, v) (the positions and velocities the
    integration just wrote); its velocity relative to the bone loses its inward normal part (and,
    with friction mu, up to mu x that much of its tangential part). The bone's velocity at the vertex
    comes from the segment pose at the sub-step's start (cw.R0, cw.t0) and now (seg_R, seg_t). The bone takes the
    reaction: wr (S, 6) += each velocity change's -m dv / h at the vertex and its moment (_react; inv_den (V,) the
    integrator's 1/m), which the next sub-step's skeleton step applies. Grid by grid, vertices in ascending order.
    cg: ContactGrids (constants), cw: ContactWork. Returns the contacts made.

    Broad phase, per grid b and vertex: a record, the rest-frame point qc[b, i] where the vertex was
    last tested and a slack (a lower bound there of the grid's sampled distance above the vertex's
    floor, or of the distance to the grid's box; stored as (slack - SLACK_MARGIN) / LIPSCHITZ). A vertex is
    tested again only once its rest-frame point has moved by LIPSCHITZ |p - qc| + SLACK_MARGIN >= slack,
    and its record is renewed (records and positions in float32: SLACK_MARGIN bounds their rounding). The grid is 1-Lipschitz between grid points, its trilinear
    interpolation sqrt(3)-Lipschitz: the result is that of testing every vertex every sub-step,
    whatever the history (reference.contact_stage does that)."""
    g_seg, free_idx = cg.g_seg, cg.free_idx
    R0, t0, qc, slack, cand, stats, xf, mask, dv = cw.R0, cw.t0, cw.qc, cw.slack, cw.cand, cw.stats, cw.xf, cw.mask, cw.dv
    B = g_seg.shape[0]
    F = free_idx.shape[0]
    hits = 0
    stats[0] += 1
    _load_free(x, free_idx, xf)
    for b in range(B):
        s = g_seg[b]
        n = _broad_halves(xf, qc[b], slack[b], seg_R[s], seg_t[s], mask)
        if n == 0:
            continue
        n = _gather(mask, F, cand)
        stats[1] += n
        hits += _narrow_halves(n, b, h, x, v, seg_R, seg_t, cg, R0, t0, cand, qc[b], slack[b], xf, dv)
        for k in range(n):          # in the candidates' order: the moved list and the reactions (the sums of one thread)
            if dv[k, 0] > 0.0:
                i = free_idx[cand[k]]
                if dv[k, 0] > 1.0:
                    _react(wr, s, 1.0, x, i, 1.0 / (inv_den[i] * h), dv[k, 1], dv[k, 2], dv[k, 3])
                mark(cw, i)
    return hits


@njit(cache=True, inline='always')
def _move(cw, x, i, d, nx, ny, nz):
    """A stage's projection: vertex i moves by d along the unit direction n, and is listed as moved (mark)."""
    x[i, 0] += d * nx
    x[i, 1] += d * ny
    x[i, 2] += d * nz
    mark(cw, i)


@njit(cache=True, inline='always')
def _stop(wr, s, x, v, i, m_h, vn, nx, ny, nz):
    """Vertex i's velocity relative to a surface of segment s moving inwards along the unit normal n at vn < 0: that
    part removed (none otherwise), and s takes the reaction (_react, m_h = m / h)."""
    if vn < 0.0:
        _react(wr, s, 1.0, x, i, m_h, -vn * nx, -vn * ny, -vn * nz)
        v[i, 0] -= vn * nx
        v[i, 1] -= vn * ny
        v[i, 2] -= vn * nz


# ------------------------------------------------------------------------------- the fold (tissue-tissue) stage
FOLD_MIN_COS = 0.25     # below this cos(theta/2) (knee flexed beyond ~150 deg) a fold vertex is pushed along the plane's normal


@njit(cache=True, inline='always')
def _fold_plane(R, t, ps, cs, geo, out):
    """The bisector plane of a folding hinge in the pose (R, t): out = (unit normal n (3), a point on the axis c (3),
    the parent's proximal direction R_p n0 (3), the child's R_c n0 (3)); returns the flexion -(R_c n0) . (R_p e)
    (> 0: flexed, the plane is the bisector of the two segments' long axes)."""
    for r in range(3):
        out[6 + r] = R[ps, r, 0] * geo[3] + R[ps, r, 1] * geo[4] + R[ps, r, 2] * geo[5]
        out[9 + r] = R[cs, r, 0] * geo[3] + R[cs, r, 1] * geo[4] + R[cs, r, 2] * geo[5]
        out[3 + r] = R[ps, r, 0] * geo[0] + R[ps, r, 1] * geo[1] + R[ps, r, 2] * geo[2] + t[ps, r]
    nx, ny, nz = out[6] + out[9], out[7] + out[10], out[8] + out[11]
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn > 0.0:
        nx, ny, nz = nx / nn, ny / nn, nz / nn
    out[0], out[1], out[2] = nx, ny, nz
    flex = 0.0
    for r in range(3):
        flex -= out[9 + r] * (R[ps, r, 0] * geo[6] + R[ps, r, 1] * geo[7] + R[ps, r, 2] * geo[8])
    return flex


@njit(cache=True, fastmath={'contract'}, inline='always')
def _sheath_push(x, seg_R, seg_t, cg, ii, ps, n0x, n0y, n0z, out):
    """Sheathed vertex ii (s_idx[ii], held in segment ps's frame) at x: out = (its rest-frame point p = R^T (x - t) (3),
    the outward unit u = R lat / |lat| (3, world), lat its offset from its rest position X across n0); returns how far
    it must move along u to be back within s_r (r - |lat| < 0), 0 when it is within."""
    i = cg.s_idx[ii]
    dx, dy, dz = x[i, 0] - seg_t[ps, 0], x[i, 1] - seg_t[ps, 1], x[i, 2] - seg_t[ps, 2]
    px = seg_R[ps, 0, 0] * dx + seg_R[ps, 1, 0] * dy + seg_R[ps, 2, 0] * dz
    py = seg_R[ps, 0, 1] * dx + seg_R[ps, 1, 1] * dy + seg_R[ps, 2, 1] * dz
    pz = seg_R[ps, 0, 2] * dx + seg_R[ps, 1, 2] * dy + seg_R[ps, 2, 2] * dz
    ex, ey, ez = px - cg.s_X[ii, 0], py - cg.s_X[ii, 1], pz - cg.s_X[ii, 2]
    ax = ex * n0x + ey * n0y + ez * n0z
    lx, ly, lz = ex - ax * n0x, ey - ax * n0y, ez - ax * n0z
    ll = math.sqrt(lx * lx + ly * ly + lz * lz)
    r = cg.s_r[0]
    if ll <= r:
        return 0.0
    out[0], out[1], out[2] = px, py, pz
    out[3] = (seg_R[ps, 0, 0] * lx + seg_R[ps, 0, 1] * ly + seg_R[ps, 0, 2] * lz) / ll
    out[4] = (seg_R[ps, 1, 0] * lx + seg_R[ps, 1, 1] * ly + seg_R[ps, 1, 2] * lz) / ll
    out[5] = (seg_R[ps, 2, 0] * lx + seg_R[ps, 2, 1] * ly + seg_R[ps, 2, 2] * lz) / ll
    return r - ll


@njit(cache=True, fastmath={'contract'})
def _sheath(h, x, v, seg_R, seg_t, cg, cw, k, p_seg, c_seg, geo, inv_den, wr):
    """The sheath of folding hinge k (a retinaculum: docs/contact.md): each of its vertices i, taken to its segment's
    rest frame (p = R^T (x - t); the parent p_seg for side +1, the child c_seg for -1), keeps its offset from its rest position X_i across n0 within s_r: beyond
    it, the offset is scaled back to s_r (the axial part kept: the vertex slides freely along the segment), and its
    outward velocity relative to the segment (whose motion over the sub-step comes from its pose at the start,
    cw.R0 cw.t0, and now) is removed, the segment taking the reaction (_react). Returns the vertices moved."""
    hits = 0
    ih = 1.0 / h
    o = np.empty(6)
    for ii in range(cg.s_off[k], cg.s_off[k + 1]):
        ps = p_seg if cg.s_side[ii] > 0.0 else c_seg
        push = _sheath_push(x, seg_R, seg_t, cg, ii, ps, geo[3], geo[4], geo[5], o)
        if push == 0.0:
            continue
        i = cg.s_idx[ii]
        hits += 1
        mark(cw, i)
        px, py, pz, ux, uy, uz = o[0], o[1], o[2], o[3], o[4], o[5]
        # the segment's velocity at the vertex: (x - (R0 p + t0)) / h, p before the projection
        bx = (x[i, 0] - (cw.R0[ps, 0, 0] * px + cw.R0[ps, 0, 1] * py + cw.R0[ps, 0, 2] * pz + cw.t0[ps, 0])) * ih
        by = (x[i, 1] - (cw.R0[ps, 1, 0] * px + cw.R0[ps, 1, 1] * py + cw.R0[ps, 1, 2] * pz + cw.t0[ps, 1])) * ih
        bz = (x[i, 2] - (cw.R0[ps, 2, 0] * px + cw.R0[ps, 2, 1] * py + cw.R0[ps, 2, 2] * pz + cw.t0[ps, 2])) * ih
        # the vertex moves by (r - |lat|) u
        x[i, 0] += push * ux
        x[i, 1] += push * uy
        x[i, 2] += push * uz
        vn = (v[i, 0] - bx) * ux + (v[i, 1] - by) * uy + (v[i, 2] - bz) * uz
        if vn > 0.0:
            _react(wr, ps, 1.0, x, i, 1.0 / (inv_den[i] * h), -vn * ux, -vn * uy, -vn * uz)
            v[i, 0] -= vn * ux
            v[i, 1] -= vn * uy
            v[i, 2] -= vn * uz
    return hits


@njit(cache=True, fastmath={'contract'})
def sheath_offsets(x, seg_R, seg_t, cg, d):
    """The sheath's way back at x, for the implicit integrator's sheath correction (implicit.sheath_correct): d[i] =
    (r - |lat|) u for each sheathed vertex i beyond the radius (what _sheath would move it by), 0 for the others
    (d's other rows untouched). Returns how many are beyond. reference.sheath_offsets is the same in numpy."""
    hits = 0
    o = np.empty(6)
    for k in range(cg.f_seg.shape[0]):
        for ii in range(cg.s_off[k], cg.s_off[k + 1]):
            ps = cg.f_seg[k, 0] if cg.s_side[ii] > 0.0 else cg.f_seg[k, 1]
            push = _sheath_push(x, seg_R, seg_t, cg, ii, ps, cg.f_geo[k, 3], cg.f_geo[k, 4], cg.f_geo[k, 5], o)
            i = cg.s_idx[ii]
            if push == 0.0:
                d[i, 0] = d[i, 1] = d[i, 2] = 0.0
            else:
                d[i, 0], d[i, 1], d[i, 2] = push * o[3], push * o[4], push * o[5]
                hits += 1
    return hits


@njit(cache=True, fastmath={'contract'})
def sheath_reaction(x, cg, ks, sd, wr):
    """The reaction of the implicit integrator's sheath correction (implicit.sheath_correct) after its solve: a
    sheathed vertex i that was beyond the radius (sd[i, :3] its way back d, sd[i, 3:] its position before the
    correction) was held by the force g = k_s (d - w) (w = x[i] - sd[i, 3:], k_s = ks[i]: A w = g on its row of
    A' w = k_s d); its segment (the parent above the hinge, the child below) takes -g at x[i] (_react, into wr)."""
    for k in range(cg.f_seg.shape[0]):
        for ii in range(cg.s_off[k], cg.s_off[k + 1]):
            i = cg.s_idx[ii]
            if sd[i, 0] == 0.0 and sd[i, 1] == 0.0 and sd[i, 2] == 0.0:
                continue
            seg = cg.f_seg[k, 0] if cg.s_side[ii] > 0.0 else cg.f_seg[k, 1]
            _react(wr, seg, 1.0, x, i, ks[i], sd[i, 0] - (x[i, 0] - sd[i, 3]), sd[i, 1] - (x[i, 1] - sd[i, 4]),
                   sd[i, 2] - (x[i, 2] - sd[i, 5]))


@njit(cache=True, fastmath={'contract'})
def fold_contact(h, x, v, seg_R, seg_t, cg, cw, inv_den, wr):
    """Stage 4a of the step, the tissue-tissue contact in the fold of each folding hinge (docs/contact.md), in place
    on (x, v): while the hinge is flexed, a fold vertex i of side s (+1 proximal, -1 distal) must keep
    s n . (x_i - c) >= floor_i, n the unit normal of the plane through the hinge axis that bisects the two segments'
    long axes (n ~ R_p n0 + R_c n0). A vertex below its floor moves onto it along its own segment's long axis
    (s R_side n0 s, so that thigh tissue is pushed up the thigh and calf tissue down the calf, not round the bone;
    along s n where cos(theta/2) < FOLD_MIN_COS), and its velocity relative to the plane loses its inward normal
    part (the plane's rate at x from its pose at the sub-step's start, cw.R0 cw.t0, and now). The plane's owners take
    the reaction (_react into wr, inv_den the integrator's 1/m): the bisector plane moves as the mean of the two
    segments' motions at x (its angular velocity is their mean, its axis common to both), so each takes half; the
    flexion-side plane, its own segment. Returns the projections made. reference.fold_stage is the same stage in numpy."""
    K = cg.f_seg.shape[0]
    if K == 0:
        return 0
    hits = 0
    pl = np.empty(12)
    p0 = np.empty(12)
    ih = 1.0 / h
    for k in range(K):
        ps, cs = cg.f_seg[k, 0], cg.f_seg[k, 1]
        geo = cg.f_geo[k]
        hits += _sheath(h, x, v, seg_R, seg_t, cg, cw, k, ps, cs, geo, inv_den, wr)
        if _fold_plane(seg_R, seg_t, ps, cs, geo, pl) <= 0.0:
            continue                            # straight or hyperextended: no fold
        _fold_plane(cw.R0, cw.t0, ps, cs, geo, p0)
        nx, ny, nz, cx, cy, cz = pl[0], pl[1], pl[2], pl[3], pl[4], pl[5]
        # the plane's own rate at a fixed point x: (n.(x - c) - n0.(x - c0)) / h = a.x + b
        ax, ay, az = (nx - p0[0]) * ih, (ny - p0[1]) * ih, (nz - p0[2]) * ih
        bq = ((p0[0] * p0[3] + p0[1] * p0[4] + p0[2] * p0[5]) - (nx * cx + ny * cy + nz * cz)) * ih
        for ii in range(cg.f_off[k], cg.f_off[k + 1] if cg.f_plane[0] else cg.f_off[k]):     # (plane off: none)
            i = cg.f_idx[ii]
            s = cg.f_side[ii]
            phi = s * (nx * (x[i, 0] - cx) + ny * (x[i, 1] - cy) + nz * (x[i, 2] - cz))
            lim = cg.f_floor[ii]
            if phi >= lim:
                continue
            o = 6 if s > 0.0 else 9             # the vertex's own segment's proximal direction
            dx, dy, dz = s * pl[o], s * pl[o + 1], s * pl[o + 2]
            dn = s * (nx * dx + ny * dy + nz * dz)
            if dn < FOLD_MIN_COS:
                dx, dy, dz, dn = s * nx, s * ny, s * nz, 1.0
            push = (lim - phi) / dn
            x[i, 0] += push * dx
            x[i, 1] += push * dy
            x[i, 2] += push * dz
            hits += 1
            mark(cw, i)
            # the vertex's rate of s phi: s (n . v + plane rate at x); inward: remove it along n
            vn = s * (nx * v[i, 0] + ny * v[i, 1] + nz * v[i, 2] + ax * x[i, 0] + ay * x[i, 1] + az * x[i, 2] + bq)
            if vn < 0.0:
                m_h = 1.0 / (inv_den[i] * h)
                _react(wr, ps, 0.5, x, i, m_h, -vn * s * nx, -vn * s * ny, -vn * s * nz)
                _react(wr, cs, 0.5, x, i, m_h, -vn * s * nx, -vn * s * ny, -vn * s * nz)
                v[i, 0] -= vn * s * nx
                v[i, 1] -= vn * s * ny
                v[i, 2] -= vn * s * nz
        # the flexion side: a fold vertex keeps to the flexion side of its own segment's plane through the axis
        # normal to e (it does not slide round the condyles to the front)
        for side in range(2):
            seg = ps if side == 0 else cs
            sgn = 1.0 if side == 0 else -1.0
            ex = seg_R[seg, 0, 0] * geo[6] + seg_R[seg, 0, 1] * geo[7] + seg_R[seg, 0, 2] * geo[8]
            ey = seg_R[seg, 1, 0] * geo[6] + seg_R[seg, 1, 1] * geo[7] + seg_R[seg, 1, 2] * geo[8]
            ez = seg_R[seg, 2, 0] * geo[6] + seg_R[seg, 2, 1] * geo[7] + seg_R[seg, 2, 2] * geo[8]
            fx = cw.R0[seg, 0, 0] * geo[6] + cw.R0[seg, 0, 1] * geo[7] + cw.R0[seg, 0, 2] * geo[8]
            fy = cw.R0[seg, 1, 0] * geo[6] + cw.R0[seg, 1, 1] * geo[7] + cw.R0[seg, 1, 2] * geo[8]
            fz = cw.R0[seg, 2, 0] * geo[6] + cw.R0[seg, 2, 1] * geo[7] + cw.R0[seg, 2, 2] * geo[8]
            eb = ((fx * p0[3] + fy * p0[4] + fz * p0[5]) - (ex * cx + ey * cy + ez * cz)) * ih
            for ii in range(cg.f_off[k], cg.f_off[k + 1]):
                if cg.f_side[ii] != sgn:
                    continue
                i = cg.f_idx[ii]
                w = ex * (x[i, 0] - cx) + ey * (x[i, 1] - cy) + ez * (x[i, 2] - cz)
                lim = cg.f_wfloor[ii]
                if w >= lim:
                    continue
                _move(cw, x, i, lim - w, ex, ey, ez)
                hits += 1
                vn = (ex * v[i, 0] + ey * v[i, 1] + ez * v[i, 2] + ((ex - fx) * x[i, 0] + (ey - fy) * x[i, 1]
                                                                    + (ez - fz) * x[i, 2]) * ih + eb)
                _stop(wr, seg, x, v, i, 1.0 / (inv_den[i] * h), vn, ex, ey, ez)
    return hits


@njit(cache=True, fastmath={'contract'})
def wrap_contact(h, x, v, seg_R, seg_t, cg, cw, inv_den, wr):
    """Stage 4b of the step, the wrap surfaces (docs/contact.md "Wrap surfaces"), in place on (x, v): a vertex i of
    wrap cylinder w (centre c, unit axis a, radius r, half length l, in segment s's rest frame) whose rest-frame point
    p = R_s^T (x_i - t_s) lies within the length (|a.(p - c)| <= l), on the quadrant's side (d.q >= 0, q the
    quadrant direction, zeros: every side) and nearer the axis than its floor (|d| < floor_i, d = p - c - (a.(p - c))
    a) moves radially onto the floor, R_s d / |d|; its velocity relative to the cylinder (the segment's velocity there,
    from its pose at the sub-step's start cw.R0 cw.t0 and now) loses its inward radial part (frictionless, as
    OpenSim's wrapping), and the segment takes the reaction (_react; inv_den the integrator's 1/m). Returns the
    projections made. reference.wrap_stage is the same stage in numpy."""
    W = cg.w_seg.shape[0]
    hits = 0
    ih = 1.0 / h
    for w in range(W):
        s = cg.w_seg[w]
        g = cg.w_geo[w]
        cx, cy, cz, ax, ay, az, qx, qy, qz, half = g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[10]
        r00, r01, r02 = seg_R[s, 0, 0], seg_R[s, 0, 1], seg_R[s, 0, 2]
        r10, r11, r12 = seg_R[s, 1, 0], seg_R[s, 1, 1], seg_R[s, 1, 2]
        r20, r21, r22 = seg_R[s, 2, 0], seg_R[s, 2, 1], seg_R[s, 2, 2]
        tx, ty, tz = seg_t[s, 0], seg_t[s, 1], seg_t[s, 2]
        for ii in range(cg.w_off[w], cg.w_off[w + 1]):
            i = cg.w_idx[ii]
            ex, ey, ez = x[i, 0] - tx, x[i, 1] - ty, x[i, 2] - tz
            px = r00 * ex + r10 * ey + r20 * ez
            py = r01 * ex + r11 * ey + r21 * ez
            pz = r02 * ex + r12 * ey + r22 * ez
            ux, uy, uz = px - cx, py - cy, pz - cz
            along = ux * ax + uy * ay + uz * az
            if along > half or along < -half:
                continue
            dx, dy, dz = ux - along * ax, uy - along * ay, uz - along * az
            if dx * qx + dy * qy + dz * qz < 0.0:
                continue
            rho = math.sqrt(dx * dx + dy * dy + dz * dz)
            lim = cg.w_floor[ii]
            if rho >= lim or not rho > 0.0:
                continue
            # the cylinder's velocity at the vertex: (x - (R0 p + t0)) / h
            bx = (x[i, 0] - (cw.R0[s, 0, 0] * px + cw.R0[s, 0, 1] * py + cw.R0[s, 0, 2] * pz + cw.t0[s, 0])) * ih
            by = (x[i, 1] - (cw.R0[s, 1, 0] * px + cw.R0[s, 1, 1] * py + cw.R0[s, 1, 2] * pz + cw.t0[s, 1])) * ih
            bz = (x[i, 2] - (cw.R0[s, 2, 0] * px + cw.R0[s, 2, 1] * py + cw.R0[s, 2, 2] * pz + cw.t0[s, 2])) * ih
            dx, dy, dz = dx / rho, dy / rho, dz / rho
            n0 = r00 * dx + r01 * dy + r02 * dz
            n1 = r10 * dx + r11 * dy + r12 * dz
            n2 = r20 * dx + r21 * dy + r22 * dz
            _move(cw, x, i, lim - rho, n0, n1, n2)
            hits += 1
            vn = (v[i, 0] - bx) * n0 + (v[i, 1] - by) * n1 + (v[i, 2] - bz) * n2
            _stop(wr, s, x, v, i, 1.0 / (inv_den[i] * h), vn, n0, n1, n2)
    return hits


def fold_vertices(tm, joints: str, reach: float, margin: float, rest: np.ndarray, vertex_segment: np.ndarray):
    """The fold contact's constants (f_seg, f_geo, f_off, f_idx, f_side, f_floor; ContactGrids) for the hinges of
    TissueModel tm named in joints (comma-separated; a hinge matches an entry equal to its name or its name's
    start, e.g. 'knee' matches 'knee_r'; entries no hinge of the model matches are ignored, as the presets serve
    every model). Per hinge: n0 = the unit direction from the centroid of the child's bone-bound vertices to the
    joint centre, made perpendicular to the axis; e = where the child's distal end moves towards the end of the
    joint's range farther from its rest coordinate (flexion). Its vertices: the free ones on the flexion side
    (e . (X - c0) > 0) within reach of the joint along n0 (|n0 . (X - c0)| <= reach), side +1 above the centre
    (n0 . (X - c0) >= 0) else -1, floor min(margin, |n0 . (X - c0)|) (a vertex closer to the plane at rest than the
    margin keeps its rest distance: the rest state is at rest)."""
    from tissue_sim.core.model import JOINT_HINGE
    vs = np.asarray(vertex_segment)
    names = [n.strip() for n in str(joints).split(',') if n.strip()]
    segs, geos, off, idx, side, floor, wfloor = [], [], [0], [], [], [], []
    for j, jn in enumerate(tm.joint_names):
        if tm.joint_type[j] != JOINT_HINGE or not any(jn == n or jn.startswith(n) for n in names):
            continue
        ps, cs = int(tm.joint_parent[j]), int(tm.joint_child[j])
        a = np.asarray(tm.joint_axis[j], float)
        a = a / np.linalg.norm(a)
        c0 = np.asarray(tm.joint_centre[j], float)
        bound = rest[vs == cs]
        cc = bound.mean(0) if len(bound) else np.asarray(tm.segment_com[cs], float)
        u = c0 - cc
        n0 = u - (u @ a) * a
        if not np.linalg.norm(n0) > 0:
            continue
        n0 /= np.linalg.norm(n0)
        lo, hi = np.asarray(tm.joint_range[j], float) - float(tm.joint_rest[j])
        ang = hi if abs(hi) >= abs(lo) else lo
        # the child's distal direction -n0 rotated by ang about a (Rodrigues): its displacement gives e
        dist = -n0
        rot = dist * math.cos(ang) + np.cross(a, dist) * math.sin(ang) + a * (a @ dist) * (1 - math.cos(ang))
        e = rot - dist
        e = e - (e @ n0) * n0 - (e @ a) * a
        if not np.linalg.norm(e) > 0:
            continue
        e /= np.linalg.norm(e)
        X = rest - c0
        hgt, w = X @ n0, X @ e
        sel = np.flatnonzero((vs < 0) & (np.abs(hgt) <= reach) & (w > 0)).astype(np.int32)
        segs.append((ps, cs))
        geos.append(np.concatenate([c0, n0, e]))
        idx.append(sel)
        side.append(np.where(hgt[sel] >= -1e-9, 1.0, -1.0))      # (on the axis to rounding: proximal)
        floor.append(np.minimum(float(margin), np.abs(hgt[sel])))
        wfloor.append(np.minimum(float(margin), w[sel]))
        off.append(off[-1] + len(sel))
    cat = lambda parts, dt: np.concatenate(parts).astype(dt) if parts else np.zeros(0, dt)  # noqa: E731
    return dict(f_seg=np.array(segs, np.int32).reshape(-1, 2), f_geo=np.array(geos, np.float64).reshape(-1, 9),
                f_off=np.array(off, np.int64), f_idx=cat(idx, np.int32), f_side=cat(side, np.float64),
                f_floor=cat(floor, np.float64), f_wfloor=cat(wfloor, np.float64))


SHEATH_FROM = 0.005     # [m] the sheath holds a group's vertices from this height above the hinge centre (along n0) up


def muscle_free_vertices(tm, muscles, vertex_segment) -> np.ndarray:
    """The free vertices (vertex_segment < 0) of the cells of the given muscles (indices), ascending int32, a point via
    ring's vertices excepted (the via holds the ring's centroid and lets it turn; docs/solver.md "Point vias"): what
    the sheath holds and a wrap surface keeps out."""
    cells = np.flatnonzero(np.isin(tm.cell_muscle, muscles))
    cand = np.unique(np.concatenate([tm.cell_vertices[tm.cell_offsets[c]:tm.cell_offsets[c + 1]] for c in cells])
                     if len(cells) else np.zeros(0, np.int64))
    keep = (np.asarray(vertex_segment)[cand] < 0) & ~np.isin(cand, np.asarray(tm.via_point_vertices))
    return cand[keep].astype(np.int32)


def cylinder_coordinates(p: np.ndarray, c: np.ndarray, a: np.ndarray) -> tuple:
    """Points p (N, 3) relative to a cylinder through c with unit axis a: (along (N,), the coordinate along the axis;
    d (N, 3), the radial vector; rho (N,), its length). wrap_contact computes the same per vertex."""
    u = p - c
    along = u @ a
    d = u - along[:, None] * a
    return along, d, np.linalg.norm(d, axis=1)


def sheath_vertices(tm, fold: dict, group: str, radius: float, reach: float, rest: np.ndarray, vertex_segment,
                    below: str = '', shared: bool = True) -> dict:
    """The sheath's constants (s_off, s_idx, s_X, s_r; ContactGrids) for the folding hinges in fold (fold_vertices):
    per hinge, the free vertices of the cells of the muscles of `group` (muscle groups or names, comma-separated; ''
    none) whose rest height above the hinge centre along n0 is in [SHEATH_FROM, reach] (the part of the thigh above the
    knee: the chain may bend over the condyles below it), held in the parent's frame (side +1); and those of the
    muscles of `below` from SHEATH_FROM to reach below it, held in the child's frame (side -1). A point via ring's
    vertices are not sheathed: the via holds the ring's centroid and lets it turn (docs/solver.md "Point vias"); held
    each near its rest line, the ring would turn with the bone, and the cell above semitendinosus' turned inside out at
    the knee's 120-deg stop. shared False: a vertex these muscles share with another muscle's cells is not sheathed
    (the sheath holds their own tissue; a shared vertex would hold the neighbour's too, e.g. a calf muscle's pull
    passed to the tibia through sartorius' sheath below the knee)."""
    cm = np.asarray(tm.cell_muscle)[np.repeat(np.arange(len(tm.cell_offsets) - 1), np.diff(tm.cell_offsets))]

    def free_vertices(spec):
        names = [g.strip() for g in str(spec).split(',') if g.strip()]
        mus = [m for m in range(len(tm.muscle_names)) if tm.muscle_groups[m] in names or tm.muscle_names[m] in names]
        cand = muscle_free_vertices(tm, mus, vertex_segment)
        if not shared:          # not on another muscle's cell (fat cells are no muscle: cell_muscle -1)
            other = np.asarray(tm.cell_vertices)[(cm >= 0) & ~np.isin(cm, mus)]
            cand = cand[~np.isin(cand, other)]
        return cand
    up, down = free_vertices(group), free_vertices(below)
    cand = np.union1d(up, down)
    held = {1.0: np.isin(cand, up), -1.0: np.isin(cand, down)}
    off, idx, side = [0], [], []
    for k in range(len(fold['f_seg'])):
        c0, n0 = fold['f_geo'][k, :3], fold['f_geo'][k, 3:6]
        hgt = (rest[cand] - c0) @ n0
        sel = (np.abs(hgt) >= SHEATH_FROM) & (np.abs(hgt) <= reach) & np.where(hgt > 0, held[1.0], held[-1.0])
        idx.append(cand[sel].astype(np.int32))
        side.append(np.where(hgt[sel] > 0, 1.0, -1.0))
        off.append(off[-1] + int(sel.sum()))
    i = np.concatenate(idx).astype(np.int32) if idx else np.zeros(0, np.int32)
    out = dict(s_off=np.array(off, np.int64), s_idx=i, s_X=np.ascontiguousarray(rest[i], np.float64),
               s_side=np.concatenate(side) if side else np.zeros(0), s_r=np.array([float(radius)]))
    for a in out.values():
        a.flags.writeable = False
    return out


# ------------------------------------------------------------------------------- compile time
_SDF_CACHE: dict = {}


def build(tm, p, rest: np.ndarray, vertex_segment: np.ndarray) -> ContactGrids:
    """SimModel.contact for TissueModel tm under Params p: when p.bone_contact one grid (spacing p.contact_grid)
    per segment that carries bones, the union of its bone meshes (distance to the nearest triangle of any,
    inside where the summed winding number is positive), so a vertex is tested once per segment; none
    otherwise (the stage then does nothing)."""
    meshes, segs = [], []
    if p.bone_contact:
        for s in sorted(set(int(b) for b in tm.bone_segment)):
            parts = [tm.bone_mesh(b) for b in np.flatnonzero(np.asarray(tm.bone_segment) == s)]
            parts = [(V, T) for V, T in parts if len(T)]
            if not parts:
                continue
            off = np.cumsum([0] + [len(V) for V, _ in parts])
            meshes.append((np.concatenate([V for V, _ in parts]),
                           np.concatenate([np.asarray(T, np.int64) + o for (_, T), o in zip(parts, off)])))
            segs.append(s)
    cg = build_grids(meshes, np.array(segs, np.int32), float(p.contact_margin), float(p.contact_friction),
                     float(p.contact_grid), rest, vertex_segment)
    if p.fold_contact:          # the tissue-tissue contact in the fold of the named hinges (fold_contact)
        fold = fold_vertices(tm, p.fold_contact, float(p.fold_reach), float(p.contact_margin), rest, vertex_segment)
        fold['f_plane'] = np.array([bool(p.fold_plane)])
        fold.update(sheath_vertices(tm, fold, p.sheath_group, float(p.sheath_radius), float(p.fold_reach), rest,
                                    vertex_segment, p.sheath_below, bool(p.sheath_shared)))
        for a in fold.values():
            a.flags.writeable = False
        cg = cg._replace(**fold)
    if p.wrap_surfaces:         # the model's wrap cylinders named (wrap_surfaces)
        cg = cg._replace(**wrap_vertices(tm, p.wrap_surfaces, rest, vertex_segment))
    return cg


def wrap_vertices(tm, names: str, rest: np.ndarray, vertex_segment) -> dict:
    """The wrap surfaces' constants (w_seg, w_geo, w_off, w_idx, w_floor; ContactGrids) for the model's wrap surfaces
    named in `names` (comma-separated TissueModel.wrap_names; 'all': every one; a name the model does not have is
    skipped, as a preset names the bundled limb's): per surface the free vertices of the cells of its muscles
    (TissueModel.wrap_muscles; a point via ring's vertices excepted, as in the sheath: the via holds the ring), each
    with its floor: the radius, or its rest distance from the axis where the rest shape already lies inside (within
    the length, on the quadrant's side)."""
    want = [n.strip() for n in str(names).split(',') if n.strip()]
    segs, geos, off, idx, floors = [], [], [0], [], []
    for w, name in enumerate(tm.wrap_names):
        if name not in want and 'all' not in want:
            continue
        g = np.asarray(tm.wrap_geometry[w], np.float64)
        c, a, q, r, half = g[:3], g[3:6], g[6:9], float(g[9]), 0.5 * float(g[10])
        mus = np.asarray(tm.wrap_muscles)[tm.wrap_muscle_offsets[w]:tm.wrap_muscle_offsets[w + 1]]
        cand = muscle_free_vertices(tm, mus, vertex_segment)
        along, d, rho = cylinder_coordinates(rest[cand], c, a)
        inside = (np.abs(along) <= half) & (d @ q >= 0.0) & (rho < r)
        segs.append(int(tm.wrap_segment[w]))
        geos.append(np.concatenate([c, a, q, [r, half]]))
        idx.append(cand)
        floors.append(np.where(inside, rho, r))
        off.append(off[-1] + len(cand))
    out = dict(w_seg=np.array(segs, np.int32), w_geo=np.array(geos, np.float64).reshape(-1, 11),
               w_off=np.array(off, np.int64),
               w_idx=np.concatenate(idx).astype(np.int32) if idx else np.zeros(0, np.int32),
               w_floor=np.concatenate(floors) if floors else np.zeros(0))
    for a_ in out.values():
        a_.flags.writeable = False
    return out


NO_FOLD = dict(f_seg=np.zeros((0, 2), np.int32), f_geo=np.zeros((0, 9)), f_off=np.zeros(1, np.int64),
               f_idx=np.zeros(0, np.int32), f_side=np.zeros(0), f_floor=np.zeros(0), f_wfloor=np.zeros(0),
               f_plane=np.zeros(1, np.bool_), s_off=np.zeros(1, np.int64), s_idx=np.zeros(0, np.int32),
               s_X=np.zeros((0, 3)), s_side=np.zeros(0), s_r=np.zeros(1), w_seg=np.zeros(0, np.int32),
               w_geo=np.zeros((0, 11)), w_off=np.zeros(1, np.int64), w_idx=np.zeros(0, np.int32), w_floor=np.zeros(0))


def build_grids(meshes, bone_segment, margin: float, friction: float, spacing: float, rest: np.ndarray,
                vertex_segment: np.ndarray) -> ContactGrids:
    """ContactGrids for bone meshes [(V, T), ...] (rest frame) on segments bone_segment, free vertices those
    with vertex_segment < 0 at rest positions rest. Every array read-only (with or without grids: one
    compiled step). A bone whose mesh is open has grid columns whose winding does not return to 0: they
    count as outside."""
    free_idx = np.flatnonzero(np.asarray(vertex_segment) < 0).astype(np.int32)
    par = np.array([float(margin), float(friction)])
    origins, dims, phis, inv_h, segs, cdims, cmins = [], [], [], [], [], [], []
    for b, (V, T) in enumerate(meshes):
        if len(T) == 0:
            continue
        o, d, phi, cmin, _open = _cached_sdf(V, T, float(spacing))
        origins.append(o), dims.append(d), phis.append(phi.reshape(-1)), inv_h.append(1.0 / spacing)
        cdims.append(cmin.shape), cmins.append(cmin.reshape(-1))
        segs.append(int(bone_segment[b]))
    g_off = np.zeros(len(phis) + 1, np.int64)
    g_off[1:] = np.cumsum([a.size for a in phis]) if phis else []
    c_off = np.zeros(len(cmins) + 1, np.int64)
    c_off[1:] = np.cumsum([a.size for a in cmins]) if cmins else []
    f32 = lambda parts: np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)  # noqa: E731
    g = dict(g_seg=np.array(segs, np.int32), g_origin=np.array(origins, np.float64).reshape(-1, 3),
             g_inv_h=np.array(inv_h, np.float64), g_dims=np.array(dims, np.int64).reshape(-1, 3), g_off=g_off,
             g_phi=f32(phis), c_dims=np.array(cdims, np.int64).reshape(-1, 3), c_off=c_off, c_min=f32(cmins))
    for a in g.values():        # read-only before sample_grid sees them, as the stage's are: one compiled signature
        a.flags.writeable = False
    # each free vertex's floor: the margin, or less where the rest shape already is closer
    floor = np.full(len(rest), float(margin))
    if len(segs):
        d = np.empty(len(free_idx))
        gr = np.empty((len(free_idx), 3))
        for b in range(len(segs)):
            sample_grid(g['g_origin'], g['g_inv_h'], g['g_dims'], g['g_off'], g['g_phi'], b,
                        np.ascontiguousarray(rest[free_idx], np.float64), d, gr)
            floor[free_idx] = np.minimum(floor[free_idx], d)
    cg = ContactGrids(floor=floor, free_idx=free_idx, par=par, **g, **NO_FOLD)
    for a in cg:
        a.flags.writeable = False
    return cg


def work(cg: ContactGrids, n_segments: int, n_listed: int = 0) -> ContactWork:
    """Fresh mutable buffers of the contact stage for one State (records empty: every vertex tested first); n_listed:
    the model's vertices where the moved vertices are to be listed (mark), else 0."""
    S, B, F, V = max(int(n_segments), 1), cg.g_seg.shape[0], cg.free_idx.shape[0], int(n_listed)
    return ContactWork(np.tile(np.eye(3), (S, 1, 1)), np.zeros((S, 3)), np.zeros((B, 3, F), np.float32),
                       np.zeros((B, F), np.float32), np.zeros(F, np.int32), np.zeros(2, np.int64), np.zeros((3, F), np.float32),
                       np.zeros(-(-F // 8) * 8, np.uint8), np.zeros((F, 4)),
                       np.zeros(V, np.int32), np.zeros(1, np.int64), np.zeros(V, np.uint8))


def _cached_sdf(V, T, h):
    """bone_sdf, memoised on the mesh bytes and h (a model compiled twice builds its grids once)."""
    import hashlib
    key = (hashlib.sha1(np.ascontiguousarray(V, np.float64).tobytes() + np.ascontiguousarray(T, np.int64).tobytes())
           .hexdigest(), h)
    r = _SDF_CACHE.get(key)
    if r is None:
        if len(_SDF_CACHE) > 64:
            _SDF_CACHE.clear()
        o, d, phi, n_open = bone_sdf(V, T, h, pad=max(4.0 * h, 5e-3))
        cmin = block_min(phi)
        phi.flags.writeable = False
        r = _SDF_CACHE[key] = (o, d, phi, cmin, n_open)
    return r


def signed_distances(sim, positions: np.ndarray, seg_R: np.ndarray, seg_t: np.ndarray) -> np.ndarray:
    """(P, G) signed distance [m] of world points to every contact grid (bone) of a compiled model,
    in the pose (seg_R, seg_t); +inf outside a grid. For analysis and tests."""
    cg = sim.contact
    P = np.asarray(positions, np.float64)
    out = np.full((len(P), len(cg.g_seg)), np.inf)
    d = np.empty(len(P))
    gr = np.empty((len(P), 3))
    for b, s in enumerate(cg.g_seg):
        X = np.ascontiguousarray((P - seg_t[s]) @ seg_R[s])       # R^T (x - t), row-wise
        sample_grid(cg.g_origin, cg.g_inv_h, cg.g_dims, cg.g_off, cg.g_phi, b, X, d, gr)
        out[:, b] = d
    return out


# ------------------------------------------------------------------------------- measurement
def mesh_penetration(sim, state) -> dict:
    """Free vertices inside each bone, measured on the bone meshes themselves (not the grids): the
    generalised winding number of the posed mesh (> 0.5 inside) and the exact distance to its
    triangles. {bone name: (count inside, count deeper than 1 mm, max depth [m])}."""
    import trimesh
    from tissue_sim.core.builder.bones import winding_number
    tm = sim.tissue
    P = state.x[sim.free_idx]
    out = {}
    for b, name in enumerate(tm.bone_names):
        V, T = tm.bone_mesh(b)
        s = int(tm.bone_segment[b])
        Vw = V @ state.seg_R[s].T + state.seg_t[s]
        lo, hi = Vw.min(0), Vw.max(0)
        box = np.all((P >= lo) & (P <= hi), axis=1)
        inside = np.zeros(len(P), bool)
        if np.any(box):
            inside[box] = winding_number(Vw, T, P[box]) > 0.5
        depth = np.zeros(int(inside.sum()))
        if depth.size:
            tri = Vw[T]
            Q = np.repeat(P[inside], len(T), axis=0)
            cp = trimesh.triangles.closest_point(np.tile(tri, (depth.size, 1, 1)), Q)
            depth = np.linalg.norm(cp - Q, axis=1).reshape(depth.size, len(T)).min(1)
        out[name] = (int(inside.sum()), int(np.sum(depth > 1e-3)), float(depth.max()) if depth.size else 0.0)
    return out


def inverted_cells(sim, x) -> tuple:
    """(indices of cells with V/V0 <= 0 at positions x, their V/V0, V/V0 of every cell): signed
    volumes from core.geometry.prism_volumes (fat rings reversed, as the builder's quality check)."""
    from tissue_sim.core.geometry import prism_volumes
    from tissue_sim.core.model import TISSUE_FAT
    tm = sim.tissue
    flip = tm.cell_tissue == TISSUE_FAT
    r = prism_volumes(x, tm.cell_offsets, tm.cell_vertices, flip) / prism_volumes(tm.rest_positions, tm.cell_offsets,
                                                                                   tm.cell_vertices, flip)
    bad = np.flatnonzero(r <= 0)
    return bad, r[bad], r
