"""Implicit Euler of the free soft-tissue vertices (``integrator: implicit``; docs/solver.md "Implicit integrator").

Projective-dynamics / quasi-Newton form. With y = x + h v + h^2 g the inertial prediction (bone-attached vertices
continued with their velocity, ya = xa + h va), one step solves backward Euler's M (x1 - y) / h^2 = f(x1, (x1 - x) / h) approximately by

    A w = f(y, v) - Lhat_fa (xa1 - ya),    x1_free = y + w,    v1 = (x1 - x) / h,

A = M/h^2 + Lhat_ff, Lhat = sum over cells of (k_c + k_active,c)(1 + volume term) + b_c/h times the cell's centring
operator (I - 1 1^T / n) (the Hessian of the shape-matching energy with the cell's rotation held fixed, plus the
deformation damping's over h; the same for x, y and z), the bone-attached vertices predicted as ya = xa + h va and
xa1 - ya their motion beyond that (the skeleton's step, between the force evaluation and the solve).
A is constant per model and h: factored once (scipy's SuperLU, no pivoting: A is SPD; a large system in two
independent blocks and their separator, ``split_order``, whose triangular passes run on two threads in
``parallel_kernels``' copy of the step's kernels). ``implicit_iterations`` > 1
repeats the correction from the last iterate (residual f(x1, v1) - M (x1 - y)/h^2): local/global iterations.
One iteration is stable while every stiffness stays within keff; the one that grows without bound with a cell's shear,
the volume term's, is capped for this integrator in the cell kernel (Params.implicit_volume_cap, SimModel.volume_cap:
at most implicit_volume_cap x keff; docs/solver.md "The volume term's bound").

The system is solved in its star form: one extra unknown per cell (the cell's centroid displacement u_c) with
energy sum_c keff_c sum_i |u_i - u_c|^2, whose Schur complement on the vertices is exactly Lhat. Its factor is
~4x sparser than A's (bundled model: 39k entries against 174k; a 26k-vertex model 434k), the bone-attached
vertices' motion enters the cells' rows (keff_c sum of their displacements), and the triangular solves, the
right-hand side and the update run in numba inside the compiled step (``integrate``, ``correct``).

With a sheath (Params.sheath_group) one more solve follows the last iteration (``sheath_correct``): the sheathed
vertices beyond their radius moved back onto it with the tissue of their neighbourhood (``sheath_region``) following,
A' w = k_s d, A' = A + diag(k_s) over that region (``sheath_weights``), factored once beside A; the plain projection
after the solve (stage 4) alone diverged (docs/solver.md "Implicit integrator", "The sheath").

``system_matrix`` (plain scipy, the vertices' matrix with the cells' blocks written out), ``reference_solve`` and
``reference_sheath_solve`` are the readable definition (reference.reference_step uses them;
tests/test_solver_implicit.py compares).
"""
from __future__ import annotations

import collections

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from numba import njit, prange

from tissue_sim.core.solver import contact as CT, integration as IK
from tissue_sim.core.solver.cells import aligned_zeros
from tissue_sim.core.solver.simd import row_axpy4, row_dot4

Implicit = collections.namedtuple('Implicit', 'on iters y mh2 row_v row_c keff att_ptr att_idx Lp Lj Lx ginv z '
                                  'n_lnz ks sd s_row_v s_Lp s_Lj s_Lx s_ginv s_z bdf2 hs xh vh '
                                  'via_u via_sinv via_g yc yg split sep_e sep_part s_split s_sep_e s_sep_part')
Implicit.__doc__ = """What the compiled step reads for the implicit integrator at one h: on (bool), iters (local/global
iterations per step), y (V, 3) the prediction (scratch), mh2 (V,) m/h^2 of free vertices (0: bone-attached), per row p of the factor
(elimination order) row_v[p] its vertex (-1: a cell row) and row_c[p] its cell (-1), keff (C,) [N/m] each cell's
weight, att_ptr/att_idx the bone-attached vertices of each row's cell (CSR over rows), the factor A = G G^T in the
star form (G = L D^1/2 of SuperLU's L D L^T: _cholesky): G strictly lower in CSR (Lp, Lj, Lx), ginv = D^-1/2 (1 over G's
diagonal), z (n, 4) scratch (simd.row_dot4: a fourth column, unused); n_lnz its entries (informative). Both triangular
passes read G by rows (the backward pass scatters, _backward), so the factor is stored once.
The sheath correction (sheath_correct; empty arrays without a sheath): ks (V,) [N/m] k_s of each vertex
(sheath_weights), sd (V, 6) scratch (each sheathed vertex's way back, its position before the correction), the factor of A' = A + diag(ks) in the same
star form: s_row_v (its rows' vertices, -1: a cell row), s_Lp, s_Lj, s_Lx, s_ginv, s_z (scratch). bdf2 (bool): the scheme is BDF2
(the factor is then at solve_length(h) = 2h/3); hs [s] that solve length (h with backward Euler); xh, vh (V, 3) its
starting point (bdf2_start; scratch). The point via rings held inside the solve (via_correct; empty without
rings or with Params.implicit_via_correction off): via_u (V, R) A^-1 C^T (C: each ring's centroid of its free
vertices' share, per vertex; 0 on bone-attached vertices), via_sinv (R, R) (C A^-1 C^T)^-1, via_g (R, 3) scratch.
yc, yg (V, 3): the prediction's coefficients at hs, y = x + yc v + yg (predict; empty: y = x + hs v).
split (4,) int64 (s_split: the sheath factor's): the rows [split[0], split[1]) and [split[1], split[2]) of the factor
are two independent blocks, [split[2], split[3]) their separator (split_order; [0, n, n, n]: not split); sep_e (ns, 2)
uint64: where each separator row's entries of the second block and of the separator begin; sep_part (ns, 3, 4):
scratch: each block's share of a separator row's sum (_forward)."""


def cell_weights(sim, h: float) -> np.ndarray:
    """(C,) [N/m] keff_c = (k + k_active)(1 + volume_stiffness, or volume_stiffness_fat for a fat cell, where the cell has a volume term) + damp_b / h: the
    stiffness of each cell's centring operator in A (the bound the mass_scaled integrator budgets with, plus the
    deformation damping's implicit share)."""
    p = sim.params
    rel = np.where(sim.cell_muscle >= 0, p.volume_stiffness, p.volume_stiffness_fat)    # (model.py: muscle / fat cells)
    vol = np.where(sim.k_volume > 0, rel, 0.0)
    return (sim.k + sim.k_active) * (1.0 + vol) + sim.damp_b / h


def system_matrix(sim, h: float):
    """(A, Lf, free): A = M/h^2 + Lhat over the free vertices (scipy CSC, n_free x n_free; the cells' dense blocks
    keff_c (I - 1 1^T/n) written out), Lhat's free rows (CSR, n_free x V: the bones' motion enters through its
    attached columns) and the free mask (V,)."""
    keff = cell_weights(sim, h)
    sizes = np.diff(sim.off)
    rows, cols, vals = [], [], []
    for c in range(sim.n_cells):
        ids = sim.cv[sim.off[c]:sim.off[c + 1]]
        n = sizes[c]
        rows.append(np.repeat(ids, n))
        cols.append(np.tile(ids, n))
        vals.append((keff[c] * (np.eye(n) - 1.0 / n)).ravel())
    V = sim.n_vertices
    L = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(V, V))
    free = sim.inv_mass > 0
    A = (L[free][:, free] + sp.diags(sim.mass[free] / h ** 2)).tocsc()
    return A, L[free].tocsr(), free


def reference_solve(sim, h: float, f, x_iter, y, xa_moved):
    """The implicit correction of reference.reference_step: w solving A w = f_free - M/h^2 (x_iter - y)_free
    - Lhat_fa (xa_moved) with scipy's sparse direct solve (xa_moved (V, 3): the bone-attached vertices' motion not
    yet in x_iter, zero elsewhere). Returns the new free positions (n_free, 3)."""
    A, Lfa, free = _system_cached(sim, h)
    m = sim.mass[free][:, None] / h ** 2
    r = f[free] - m * (x_iter[free] - y[free]) - Lfa @ xa_moved
    return x_iter[free] + sla.spsolve(A, r).reshape(-1, 3) if r.size else x_iter[free]


SHEATH_STIFFNESS = 1e3      # k_s of a sheathed vertex in the correction's system, relative to its diagonal in A


def sheath_weights(sim, h: float) -> np.ndarray:
    """(V,) [N/m] k_s of each vertex in the sheath correction's system A' = A + diag(k_s): SHEATH_STIFFNESS times its
    diagonal in A's star form (m/h^2 + the summed keff of its cells) for the free sheathed vertices
    (Params.sheath_group; contact.sheath_vertices), 0 elsewhere."""
    keff = cell_weights(sim, h)
    cell = np.repeat(np.arange(sim.n_cells), np.diff(sim.off))
    diag = sim.mass / h ** 2 + np.bincount(sim.cv, keff[cell], sim.n_vertices)
    ks = np.zeros(sim.n_vertices)
    idx = np.asarray(sim.contact.s_idx)
    idx = idx[sim.inv_mass[idx] > 0]
    ks[idx] = SHEATH_STIFFNESS * diag[idx]
    return ks


SHEATH_RINGS = 2            # the correction moves the free vertices within this many cells of a sheathed vertex


def sheath_region(sim) -> np.ndarray:
    """(V,) bool: the free vertices the sheath correction moves: the sheathed ones and those within SHEATH_RINGS cells
    of them (ring 1: the free vertices of the cells with a sheathed vertex; ring 2: of the cells touching ring 1)."""
    free = sim.inv_mass > 0
    reg = np.zeros(sim.n_vertices, bool)
    reg[np.asarray(sim.contact.s_idx)] = True
    reg &= free
    if not reg.any():
        return reg
    cell = np.repeat(np.arange(sim.n_cells), np.diff(sim.off))
    for _ in range(SHEATH_RINGS):
        touch = np.zeros(sim.n_cells, bool)
        touch[cell[reg[sim.cv]]] = True
        reg[sim.cv[touch[cell]]] = True
        reg &= free
    return reg


def reference_sheath_solve(sim, h: float, d):
    """The sheath correction of reference.reference_step: w (n_free, 3) solving A' w = k_s d over the free vertices
    of sheath_region (the principal submatrix of A + diag(k_s): the rest of the tissue held), zero for the other free
    vertices (d (V, 3): each sheathed vertex's way back onto the radius, zero elsewhere), with scipy's sparse direct
    solve."""
    A, _, free = _system_cached(sim, h)
    ks = sheath_weights(sim, h)[free]
    reg = sheath_region(sim)[free]
    w = np.zeros((int(free.sum()), 3))
    Ar = (A + sp.diags(ks)).tocsr()[reg][:, reg].tocsc()
    w[reg] = sla.spsolve(Ar, ks[reg, None] * d[free][reg]).reshape(-1, 3)
    return w


def via_matrix(sim, free) -> np.ndarray:
    """(R, n_free) C: row r takes ring r's centroid (the mean over all its vertices, SimModel.via_*) from its free
    vertices' positions, 1/n_r on each of them (its bone-attached vertices' share is fixed by their segment)."""
    fidx = np.full(sim.n_vertices, -1)
    fidx[free] = np.arange(free.size)
    C = np.zeros((sim.via_seg.size, free.size))
    for r in range(sim.via_seg.size):
        ring = np.asarray(sim.via_idx[sim.via_off[r]:sim.via_off[r + 1]])
        C[r, fidx[ring[fidx[ring] >= 0]]] = 1.0 / ring.size
    return C


def via_system(sim, imp) -> tuple:
    """The point via rings' correction inside the implicit solve (via_correct), with imp's factor: (via_u (V, R) =
    A^-1 C^T on the free vertices, 0 on the others, one solve per ring; via_sinv (R, R) = (C A^-1 C^T)^-1; via_g
    (R, 3) scratch: the centroids' offsets). Empty without rings or with Params.implicit_via_correction off."""
    R, V = sim.via_seg.size, sim.n_vertices
    if R == 0 or not sim.params.implicit_via_correction:
        return np.zeros((V, 0)), np.zeros((0, 0)), np.zeros((0, 3))
    free = np.flatnonzero(sim.inv_mass > 0)
    C = via_matrix(sim, free)
    u = np.zeros((R, V))
    zero = np.zeros((V, 3))
    for r in range(R):
        f = np.zeros((V, 3))
        f[free, 0] = C[r]
        w = np.zeros((V, 3))
        _solve(imp, f, w, zero, True, zero, np.zeros((V, 3)), 0.0, 0.0)     # w = A^-1 f on the free vertices (y = 0)
        u[r] = w[:, 0]
    return np.ascontiguousarray(u.T), np.linalg.inv(u[:, free] @ C.T).reshape(R, R), np.zeros((R, 3))


@njit(cache=True, fastmath={'contract'})
def via_correct(h, x, xn, vn, imp, via_off, via_idx, via_seg, via_local, seg_R, seg_t, vmax2):
    """The point via rings inside the implicit step (Params.implicit_via_correction; docs/solver.md "Point vias"),
    after the last iteration and the sheath correction: the free vertices move by the least A-norm correction that
    puts every ring's centroid (bone-attached vertices where their segments put them) on its place on its bone,
    xn_free -= A^-1 C^T (C A^-1 C^T)^-1 g (g (R, 3): each centroid's offset from its place, via_u and via_sinv
    precomputed): the ring and the tissue round it move together, as the constant system couples them, instead of the
    ring alone (integration.hold_via_points, which then finds the centroids in place). v1 = (xn - x)/h. Returns how
    many vertices are too fast or not finite."""
    R = imp.via_sinv.shape[0]
    if R == 0:
        return 0
    g = imp.via_g
    for r in range(R):
        a, b = via_off[r], via_off[r + 1]
        cx = cy = cz = 0.0
        for k in range(a, b):
            i = via_idx[k]
            cx += xn[i, 0]; cy += xn[i, 1]; cz += xn[i, 2]
        px, py, pz = IK._via_place(r, via_seg, via_local, seg_R, seg_t)
        n = b - a
        g[r, 0], g[r, 1], g[r, 2] = cx / n - px, cy / n - py, cz / n - pz
    u, si, mh2 = imp.via_u, imp.via_sinv, imp.mh2
    lm = np.empty((R, 3))                       # each ring's multiplier (C A^-1 C^T)^-1 g
    for r in range(R):
        l0 = l1 = l2 = 0.0
        for q in range(R):
            l0 += si[r, q] * g[q, 0]; l1 += si[r, q] * g[q, 1]; l2 += si[r, q] * g[q, 2]
        lm[r, 0], lm[r, 1], lm[r, 2] = l0, l1, l2
    return _via_move(1.0 / h, x, xn, vn, u, lm, mh2, vmax2)


@njit(cache=True, fastmath={'contract'})
def _via_move(ih, x, xn, vn, u, lm, mh2, vmax2):
    """via_correct's moves, xn_i -= sum_r u[i, r] lm[r] on the free vertices (u is 0 on the bone-attached ones), and
    their velocities, in one pass over two halves of the vertices (prange: on two threads in parallel_kernels' copy,
    here one after the other; the same numbers). Returns how many are too fast or not finite."""
    nfast = 0
    for t in prange(2):
        lo, hi = CT.half(t, xn.shape[0])
        nfast += _via_move_span(lo, hi, ih, x, xn, vn, u, lm, mh2, vmax2)
    return nfast


@njit(cache=True, fastmath={'contract'})
def _via_move_span(lo, hi, ih, x, xn, vn, u, lm, mh2, vmax2):
    """_via_move over the vertices lo <= i < hi."""
    R = lm.shape[0]
    nfast = 0
    for i in range(lo, hi):
        if mh2[i] > 0.0:
            d0 = d1 = d2 = 0.0
            for r in range(R):
                w = u[i, r]
                d0 += w * lm[r, 0]; d1 += w * lm[r, 1]; d2 += w * lm[r, 2]
            xn[i, 0] -= d0; xn[i, 1] -= d1; xn[i, 2] -= d2
            nfast += _velocity(i, ih, x, xn, vn, vmax2)
    return nfast


def reference_via_solve(sim, h: float, x, places):
    """The point via rings' correction of reference.reference_step: w (n_free, 3) = -A^-1 C^T (C A^-1 C^T)^-1 g, g
    (R, 3) each ring's centroid at x minus its place (places (R, 3)), with scipy's sparse direct solve on A."""
    A, _, mask = _system_cached(sim, h)
    free = np.flatnonzero(mask)
    C = via_matrix(sim, free)
    g = np.array([x[sim.via_idx[sim.via_off[r]:sim.via_off[r + 1]]].mean(axis=0) for r in range(sim.via_seg.size)]) - places
    AiCt = sla.spsolve(A.tocsc(), C.T).reshape(free.size, -1)
    return -AiCt @ np.linalg.solve(C @ AiCt, g)


_CACHE, _MADE = {}, {}


def _per_model(cache, sim, h, build):
    """build(sim, h), made once per model and h (the last few kept)."""
    key = (id(sim), h)
    hit = cache.get(key)
    if hit is None or hit[0] is not sim:
        if len(cache) > 4:
            cache.clear()
        hit = cache[key] = (sim, build(sim, h))
    return hit[1]


def _system_cached(sim, h):
    return _per_model(_CACHE, sim, h, system_matrix)


def star_system(sim, h: float):
    """A in its star form over the unknowns (free vertices, cells): the vertices' diagonal m/h^2 + sum keff_c over
    their cells, the cells' n_c keff_c, -keff_c between a cell and each of its free vertices. Returns (CSC matrix,
    free vertex ids, keff)."""
    keff = cell_weights(sim, h)
    V, C = sim.n_vertices, sim.n_cells
    sizes = np.diff(sim.off)
    cell = np.repeat(np.arange(C), sizes)
    free = np.flatnonzero(sim.inv_mass > 0)
    nf = free.size
    fidx = np.full(V, -1)
    fidx[free] = np.arange(nf)
    fv = fidx[sim.cv]
    ok = fv >= 0
    kv = keff[cell][ok]
    diag = np.concatenate([sim.mass[free] / h ** 2 + np.bincount(fv[ok], kv, nf), keff * sizes])
    r = np.concatenate([fv[ok], nf + cell[ok]])
    c = np.concatenate([nf + cell[ok], fv[ok]])
    A = sp.csc_matrix((np.concatenate([-kv, -kv]), (r, c)), shape=(nf + C, nf + C)) + sp.diags(diag)
    return A.tocsc(), free, keff


SPLIT_MIN_UNKNOWNS = 5000    # a system with fewer unknowns is factored whole (minimum degree), not split (split_order)


def split_order(A, nv: int, coord) -> tuple | None:
    """A nested-dissection split of a star-form system (its first nv unknowns vertices at coordinates coord along
    the model's long axis, the rest cells; vertices are coupled only through cells): the vertices below and above a
    plane across the axis, each cell with the vertices it couples (both sides: the separator). Returns (order, split):
    order the unknowns block 0 (in minimum-degree order of its own), block 1 (the same), separator; split =
    [0, n0, n0 + n1, n]. The two blocks' rows of the factor are then independent (none reads the other's), so the
    triangular passes run them on two threads (_forward, _backward); the plane is placed where the two blocks' own
    factors have the same number of entries (bisection on the quantile). None below SPLIT_MIN_UNKNOWNS unknowns."""
    n = A.shape[0]
    if n < SPLIT_MIN_UNKNOWNS or nv < 2:
        return None
    A = A.tocsr()
    B = (A[nv:, :nv] != 0).astype(np.int64)

    def parts(frac):
        upper = coord > np.quantile(coord, frac)
        lo, hi = B @ (~upper).astype(np.int64) > 0, B @ upper.astype(np.int64) > 0
        side = np.concatenate([upper.astype(np.int64), np.where(lo & hi, 2, np.where(hi & ~lo, 1, 0))])
        return [np.flatnonzero(side == k) for k in range(3)]

    def mmd(idx):
        if idx.size == 0:
            return idx, 0
        lu = sla.splu(A[idx][:, idx].tocsc(), permc_spec='MMD_AT_PLUS_A', diag_pivot_thresh=0.0,
                      options=dict(SymmetricMode=True))
        return idx[np.argsort(lu.perm_c)], lu.L.nnz

    a, b = 0.3, 0.7
    for _ in range(6):                  # (to 0.6 % of the unknowns)
        frac = 0.5 * (a + b)
        p0, p1, _sep = parts(frac)
        if mmd(p0)[1] > mmd(p1)[1]:
            b = frac
        else:
            a = frac
    p0, p1, sep = parts(0.5 * (a + b))
    order = np.concatenate([mmd(p0)[0], mmd(p1)[0], sep])
    return order, np.array([0, p0.size, p0.size + p1.size, n], np.int64)


def _factor(A, split=None):
    """A = L D L^T (SuperLU, no pivoting: A is SPD; checked), in minimum-degree order on A^T + A, or in split's order
    (split_order's (order, split): two independent blocks and their separator). Returns (perm: the unknown of each
    row of the factor, L strictly lower (CSR, sorted), D's diagonal, split: the block bounds, [0, n, n, n] whole)."""
    n = A.shape[0]
    if split is None:
        order, bounds = np.arange(n), np.array([0, n, n, n], np.int64)
        lu = sla.splu(A, permc_spec='MMD_AT_PLUS_A', diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    else:
        order, bounds = split
        lu = sla.splu(A.tocsr()[order][:, order].tocsc(), permc_spec='NATURAL', diag_pivot_thresh=0.0,
                      options=dict(SymmetricMode=True))
    if not np.array_equal(lu.perm_r, lu.perm_c):
        raise RuntimeError('implicit integrator: SuperLU pivoted the SPD system (perm_r != perm_c)')
    Lf = sp.csr_matrix(lu.L)
    d = lu.U.diagonal()
    if not np.all(d > 0):
        raise RuntimeError('implicit integrator: the system matrix is not positive definite')
    U_expected = sp.diags(d) @ Lf.T
    if abs(lu.U - U_expected).max() > 1e-9 * abs(d).max():
        raise RuntimeError('implicit integrator: the factor is not symmetric (U != D L^T)')
    Ls = sp.tril(Lf, k=-1).tocsr()
    Ls.sort_indices()
    rows = np.repeat(np.arange(n), np.diff(Ls.indptr))
    if np.any((rows >= bounds[1]) & (rows < bounds[2]) & (Ls.indices < bounds[1])):
        raise RuntimeError('implicit integrator: the split blocks of the factor are not independent')
    # row p of the factor is unknown order[perm_c[p]] of A (Pr A Pc = L U, perm_r == perm_c)
    return order[np.argsort(lu.perm_c)], Ls, d, bounds


def _separator_entries(Lp, Lj, split):
    """(ns, 2) uint64: where each separator row's entries in the second block's columns and in the separator's
    begin (_forward sums a separator row's three spans apart)."""
    b1, b2, n = int(split[1]), int(split[2]), int(split[3])
    e = np.zeros((n - b2, 2), np.uint64)
    for s in range(n - b2):
        lo, hi = int(Lp[b2 + s]), int(Lp[b2 + s + 1])
        e[s, 0] = lo + np.searchsorted(Lj[lo:hi], b1)
        e[s, 1] = lo + np.searchsorted(Lj[lo:hi], b2)
    return e


def long_axis(sim) -> np.ndarray:
    """The unit direction of the free vertices' largest extent at rest (the principal axis; split_order's)."""
    x = np.asarray(sim.rest)[sim.inv_mass > 0]
    if x.shape[0] < 2:
        return np.array([0.0, 0.0, 1.0])
    w, u = np.linalg.eigh(np.cov((x - x.mean(0)).T))
    a = u[:, -1]
    return a if a[np.argmax(abs(a))] > 0 else -a


def solve_length(p, h: float) -> float:
    """[s] The step length the implicit solve is made with for sub-step length h: h (backward Euler), 2h/3 (BDF2:
    x1 = xh + (2h/3) v1, v1 = vh + (2h/3) a1, bdf2_start)."""
    return h * 2.0 / 3.0 if p.implicit_scheme == 'bdf2' else h


@njit(cache=True, fastmath={'contract'})
def bdf2_start(h, x, v, x_prev, v_prev, history_h, xh, vh, y, yc, yg, hs):
    """BDF2's starting point of a sub-step of length h from the last two, xh = (4 x - x_prev) / 3, vh = (4 v - v_prev) / 3
    (the step is then backward Euler's from (xh, vh) over hs = 2h/3), and its prediction y = xh + yc vh + yg (predict)
    in the same pass (yc empty: y = xh + hs vh, prediction). Without a history at h (history_h[0] != h: the first
    sub-step, or h changed) the past is taken at constant velocity, x_prev = x - h v, v_prev = v: then xh = x + h v /
    3, vh = v, and the prediction xh + (2h/3) vh = x + h v is backward Euler's. Flat loops over the arrays (they
    vectorise; a third multiplies: the division was bound by the divider; with yc empty two arrays fewer are read)."""
    xf, vf, xpf, vpf, xhf, vhf = x.reshape(-1), v.reshape(-1), x_prev.reshape(-1), v_prev.reshape(-1), xh.reshape(-1), vh.reshape(-1)
    yf, ycf, ygf = y.reshape(-1), yc.reshape(-1), yg.reshape(-1)
    uniform = ycf.shape[0] == 0
    fresh = history_h[0] != h
    for t in prange(2):             # (two halves: on two threads in parallel_kernels' copy; the same numbers)
        lo, hi = CT.half(t, xf.shape[0])
        _bdf2_span(h, hs, fresh, uniform, xf[lo:hi], vf[lo:hi], xpf[lo:hi], vpf[lo:hi], xhf[lo:hi], vhf[lo:hi],
                   yf[lo:hi], ycf if uniform else ycf[lo:hi], ygf if uniform else ygf[lo:hi])


@njit(cache=True, fastmath={'contract'})
def _bdf2_span(h, hs, fresh, uniform, xf, vf, xpf, vpf, xhf, vhf, yf, ycf, ygf):
    """bdf2_start over one span of the flat arrays. (Views and a loop from 0: a loop over range(lo, hi) of the whole
    arrays measured 10-15 % slower, not vectorised as well.)"""
    third = 1.0 / 3.0
    if fresh:
        for k in range(xf.shape[0]):
            xa = xf[k] + h * vf[k] * third
            xhf[k] = xa
            vhf[k] = vf[k]
            yf[k] = xa + hs * vf[k] if uniform else xa + ycf[k] * vf[k] + ygf[k]
    else:
        for k in range(xf.shape[0]):
            xa = (4.0 * xf[k] - xpf[k]) * third
            va = (4.0 * vf[k] - vpf[k]) * third
            xhf[k] = xa
            vhf[k] = va
            yf[k] = xa + hs * va if uniform else xa + ycf[k] * va + ygf[k]


@njit(cache=True)
def bdf2_history(h, xn, vn, x_old, v_old, history_h, moved, n_moved):
    """After a BDF2 sub-step from (x_old, v_old) to (xn, vn): the next one's history is (x_old, v_old) itself (the
    step rotates its buffers, step.advance: nothing is copied), except for the vertices a stage after the solve
    moved or whose velocity it changed (the fold and bone contact, stage 4: their indices are moved[:n_moved[0]],
    contact.mark): their past is taken at constant velocity, x_prev = xn - h vn, v_prev = vn, written into x_old,
    v_old (a projection is not motion: carried in the history, BDF2's extrapolation would turn the jump into
    velocity, and a vertex pushed out of a bone every sub-step ran away: the 6x limb at 16 sub-steps diverged at
    step 296)."""
    for k in range(n_moved[0]):
        i = moved[k]
        for a in range(3):
            x_old[i, a] = xn[i, a] - h * vn[i, a]
            v_old[i, a] = vn[i, a]
    history_h[0] = h


SCRATCH = ('y', 'z', 'sd', 's_z', 'xh', 'vh', 'via_g', 'sep_part', 's_sep_part')    # Implicit's scratch arrays


def make(sim, h: float) -> Implicit:
    """The Implicit tuple for sub-step length h (an inert one, on = False, for the other integrators); its system at
    solve_length(h). Its constants (the factors, the point vias' columns) are made once per model and h and shared
    by every State of the model; each call gets scratch arrays of its own, 64-byte aligned (z's
    rows straddling two cache lines measured +15 % in the bundled limb's solve)."""
    imp = _per_model(_MADE, sim, h, _make)
    fresh = {name: aligned_zeros(getattr(imp, name).shape) for name in SCRATCH}
    return imp._replace(**fresh)


def _make(sim, h: float) -> Implicit:
    """make's Implicit, made afresh."""
    V = sim.n_vertices
    e_i, e_f, e_p = np.zeros(0, np.int32), np.zeros(0), np.zeros(1, np.int64)
    e_u, e_q = np.zeros(0, np.uint32), np.zeros(1, np.uint64)       # (a factor's index arrays: _csr)
    if sim.params.integrator != 'implicit':
        return Implicit(False, 1, np.zeros((0, 3)), np.zeros(V), e_i, e_i, e_f, e_p,
                        e_i, e_q, e_u, e_f, e_f, np.zeros((0, 3)), 0, e_f, np.zeros((0, 3)), e_i, e_q, e_u, e_f, e_f,
                        np.zeros((0, 3)), False, float(h), np.zeros((0, 3)), np.zeros((0, 3)),
                        np.zeros((V, 0)), np.zeros((0, 0)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                        *(np.zeros(4, np.int64), np.zeros((0, 2), np.uint64), np.zeros((0, 3, 4))) * 2)
    bdf2 = sim.params.implicit_scheme == 'bdf2'
    h = solve_length(sim.params, h)
    A, free, keff = star_system(sim, h)
    nf, n = free.size, A.shape[0]
    axis = long_axis(sim)
    unk, Ls, d, split = _factor(A, split_order(A, nf, np.asarray(sim.rest)[free] @ axis))
    row_v = np.where(unk < nf, free[np.minimum(unk, nf - 1)] if nf else -1, -1).astype(np.int32)
    row_c = np.where(unk >= nf, unk - nf, -1).astype(np.int32)
    # the bone-attached vertices of each cell row (their motion enters that row: keff_c sum of displacements)
    att = sim.inv_mass <= 0
    ptr = np.zeros(n + 1, np.int64)
    idx = []
    for p in range(n):
        c = row_c[p]
        if c >= 0:
            ids = sim.cv[sim.off[c]:sim.off[c + 1]]
            idx.append(ids[att[ids]])
            ptr[p + 1] = ptr[p] + idx[-1].size
        else:
            ptr[p + 1] = ptr[p]
    idx = np.concatenate(idx).astype(np.int32) if idx else np.zeros(0, np.int32)
    mh2 = np.where(sim.inv_mass > 0, sim.mass / h ** 2, 0.0)
    ks = sheath_weights(sim, h)
    if ks.any():              # the sheath correction's system A' = A + diag(k_s) over sheath_region (sheath_correct)
        fidx = np.full(V, -1)
        fidx[free] = np.arange(nf)
        sel = np.flatnonzero(ks > 0)
        add = np.zeros(n)
        add[fidx[sel]] = ks[sel]
        reg = np.flatnonzero(sheath_region(sim)[free])                  # its vertices' unknowns, then the cells
        cell = np.repeat(np.arange(sim.n_cells), np.diff(sim.off))      # touching them
        touch = np.zeros(sim.n_cells, bool)
        touch[cell[np.isin(sim.cv, free[reg])]] = True
        keep = np.concatenate([reg, nf + np.flatnonzero(touch)])
        As = (A + sp.diags(add)).tocsr()[keep][:, keep].tocsc()
        s_unk, sLs, sd_, s_split = _factor(As, split_order(As, reg.size, np.asarray(sim.rest)[free[reg]] @ axis))
        s_rows = np.where(s_unk < reg.size, free[reg][np.minimum(s_unk, reg.size - 1)], -1).astype(np.int32)
        sheath = (ks, np.zeros((V, 6)), s_rows, *_cholesky(sLs, sd_), np.zeros((keep.size, 4)))
        s_sep = _separator_entries(sLs.indptr, sLs.indices, s_split)
        s_parts = (s_split, s_sep, np.zeros((s_sep.shape[0], 3, 4)))
    else:
        sheath = (e_f, np.zeros((0, 6)), e_i, e_q, e_u, e_f, e_f, np.zeros((0, 3)))
        s_parts = (np.array([0, 0, 0, 0], np.int64), np.zeros((0, 2), np.uint64), np.zeros((0, 3, 4)))
    sep = _separator_entries(Ls.indptr, Ls.indices, split)
    imp = Implicit(True, int(sim.params.implicit_iterations), np.zeros((V, 3)), mh2, row_v, row_c,
                    np.ascontiguousarray(keff), ptr, idx, *_cholesky(Ls, d),
                    np.zeros((n, 4)), int(Ls.nnz + n), *sheath, bdf2, float(h),
                    np.zeros((V, 3)), np.zeros((V, 3)), np.zeros((V, 0)), np.zeros((0, 0)), np.zeros((0, 3)),
                    *prediction(sim, h), split, sep, np.zeros((sep.shape[0], 3, 4)), *s_parts)
    return imp._replace(**dict(zip(('via_u', 'via_sinv', 'via_g'), via_system(sim, imp))))


def _csr(M) -> tuple:
    """(indptr uint64, indices uint32, data) of a sorted CSR matrix, as the solves read them. Unsigned: numba then
    indexes with them directly (a signed index costs a negative-index test per entry, ~10 % of the solves)."""
    return M.indptr.astype(np.uint64), M.indices.astype(np.uint32), M.data.copy()


def _cholesky(Ls, d) -> tuple:
    """(Lp, Lj, Gx, ginv): A = L D L^T (_factor: L unit lower, Ls its strictly lower part) as A = G G^T, G = L D^1/2:
    _csr of G's strictly lower part (column j of Ls times sqrt(D_j)) and ginv = D^-1/2 (1 over G's diagonal), the
    form in which both triangular passes divide by the diagonal once per row (_forward, _backward)."""
    g = np.sqrt(d)
    G = sp.csr_matrix(Ls @ sp.diags(g))
    G.sort_indices()
    return (*_csr(G), 1.0 / g)


def prediction(sim, h: float) -> tuple:
    """(yc, yg) (V, 3), the prediction's coefficients at step length h (predict): free vertices yc = h (1 - h c_v),
    yg = h^2 (1 - h c_v) g; bone-attached ones yc = h, yg = 0. Both empty where they are uniform (no velocity damping
    and no gravity, as in both presets): then y = x + h v for every vertex."""
    if sim.params.velocity_damping == 0.0 and not np.any(np.asarray(sim.gravity, float)):
        return np.zeros((0, 3)), np.zeros((0, 3))
    free = (sim.inv_mass > 0)[:, None]
    damp = 1.0 - h * sim.params.velocity_damping
    yc = np.where(free, h * damp, h) * np.ones(3)
    yg = np.where(free, h * h * damp * np.asarray(sim.gravity, float)[None, :], 0.0)
    return np.ascontiguousarray(yc), np.ascontiguousarray(yg)


@njit(cache=True, fastmath={'contract'})
def predict(x, v, y, yc, yg, hs):
    """y = x + yc v + yg (implicit.prediction's coefficients at hs; yc empty: y = x + hs v): y = x + h (1 - h c_v)(v +
    h g) for the free vertices, y = x + h v for the bone-attached ones (their segment's motion continued): the
    positions the step's forces are evaluated at (the same free positions integration.integrate writes with a zero
    force). The bones must be predicted too: with them where they are, tissue moving with a bone would lie h v ahead of
    it and pull it on (a negative damping k h: the knee diverged in 24 steps). One flat loop (it vectorises)."""
    xf, vf, yf, ycf, ygf = x.reshape(-1), v.reshape(-1), y.reshape(-1), yc.reshape(-1), yg.reshape(-1)
    uniform = ycf.shape[0] == 0
    for k in range(xf.shape[0]):
        yf[k] = xf[k] + hs * vf[k] if uniform else xf[k] + ycf[k] * vf[k] + ygf[k]


@njit(cache=True, fastmath={'contract'})
def _solve(imp, f, xk, y, first, xs, vn, ih, vmax2):
    """The implicit solve A w = rhs on the free vertices, and their velocities: G z = rhs (formed row by row as the
    forward pass reaches it, _forward), then G^T w = z (_backward: each w_p final when the backward pass reaches
    row p, and the vertex updated there). first: the step's first iteration, from the prediction: rhs = f on the
    vertices' rows (xk = y there: its free rows are not read) and, on the cells' rows, the bones' motion beyond the
    prediction, keff_c sum (xk_a - y_a); xk_free = y + w. Otherwise rhs = f - M (xk - y)/h^2, xk_free += w. Either
    way vn_free = (xk - xs) ih (_velocity). Returns how many free vertices are faster than sqrt(vmax2) or not finite."""
    _forward(False, imp.row_v, imp.row_c, f, xk, y, first, imp.mh2, imp.keff, imp.att_ptr, imp.att_idx, imp.ks,
             imp.sd, imp.Lp, imp.Lj, imp.Lx, imp.ginv, imp.z, imp.split, imp.sep_e, imp.sep_part)
    return _backward(imp.Lp, imp.Lj, imp.Lx, imp.ginv, imp.row_v, imp.z, xk, y, first, xs, vn, ih, vmax2, imp.split)


@njit(cache=True, fastmath={'contract'})
def _forward(sheath, row_v, row_c, f, xk, y, first, mh2, keff, att_ptr, att_idx, ks, d, Lp, Lj, Lx, ginv, z, split,
             sep_e, sep_part):
    """The forward pass G z = rhs of _solve (sheath False) and _solve_sheath (True: rhs = k_s d on a sheathed vertex's
    row, 0 elsewhere), z (n, 4) (simd.row_dot4: its fourth column unused), in split's blocks (split_order): each
    block's rows, z_p = (rhs_p - sum_j<p G_pj z_j) ginv_p, and its share of each separator row's sum, apart (prange: on two
    threads in parallel_kernels' copy, here one after the other); then the separator's rows (cells: their rhs the
    bones' motion beyond the prediction, first iteration only), z_p = (rhs_p - ((share 0 + share 1) + the separator's
    own entries)) ginv_p. The same sums in the same order for any number of threads. Not split ([0, n, n, n]): one range
    of rows (_forward_rows; the block structure measured +5 us, 20 %, on the bundled limb)."""
    b2, n = split[2], split[3]
    if split[1] == split[3]:
        _forward_rows(sheath, row_v, row_c, f, xk, y, first, mh2, keff, att_ptr, att_idx, ks, d, Lp, Lj, Lx, ginv, z, 0,
                      n)
        return
    for t in prange(2):
        _forward_rows(sheath, row_v, row_c, f, xk, y, first, mh2, keff, att_ptr, att_idx, ks, d, Lp, Lj, Lx, ginv, z,
                      split[t], split[t + 1])
        for k in range(n - b2):
            lo = Lp[b2 + k] if t == 0 else sep_e[k, 0]
            a0, a1, a2, _ = row_dot4(Lx, Lj, z, lo, sep_e[k, t])
            sep_part[k, t, 0] = a0; sep_part[k, t, 1] = a1; sep_part[k, t, 2] = a2
    for k in range(n - b2):
        p = b2 + k
        s0 = s1 = s2 = 0.0
        if first and not sheath:
            s0, s1, s2 = _cell_rhs(p, row_c, xk, y, keff, att_ptr, att_idx)
        a0, a1, a2, _ = row_dot4(Lx, Lj, z, sep_e[k, 1], Lp[p + 1])
        g = ginv[p]
        z[p, 0] = (s0 - ((sep_part[k, 0, 0] + sep_part[k, 1, 0]) + a0)) * g
        z[p, 1] = (s1 - ((sep_part[k, 0, 1] + sep_part[k, 1, 1]) + a1)) * g
        z[p, 2] = (s2 - ((sep_part[k, 0, 2] + sep_part[k, 1, 2]) + a2)) * g


@njit(cache=True, fastmath={'contract'})
def _forward_rows(sheath, row_v, row_c, f, xk, y, first, mh2, keff, att_ptr, att_idx, ks, d, Lp, Lj, Lx, ginv, z, lo,
                  hi):
    """Rows lo to hi - 1 of _forward outside the separator: z_p = (rhs_p - sum_j<p G_pj z_j) ginv_p. (A range per
    call, as _backward_rows.)"""
    for p in range(lo, hi):
        i = row_v[p]
        s0 = s1 = s2 = 0.0
        if sheath:
            if i >= 0:
                k = ks[i]
                if k > 0.0:
                    s0, s1, s2 = k * d[i, 0], k * d[i, 1], k * d[i, 2]
        elif i >= 0:
            s0, s1, s2 = f[i, 0], f[i, 1], f[i, 2]
            if not first:
                mm = mh2[i]
                s0 -= mm * (xk[i, 0] - y[i, 0])
                s1 -= mm * (xk[i, 1] - y[i, 1])
                s2 -= mm * (xk[i, 2] - y[i, 2])
        elif first:
            s0, s1, s2 = _cell_rhs(p, row_c, xk, y, keff, att_ptr, att_idx)
        a0, a1, a2, _ = row_dot4(Lx, Lj, z, Lp[p], Lp[p + 1])
        g = ginv[p]
        z[p, 0] = (s0 - a0) * g; z[p, 1] = (s1 - a1) * g; z[p, 2] = (s2 - a2) * g


@njit(cache=True)
def _cell_rhs(p, row_c, xk, y, keff, att_ptr, att_idx):
    """A cell row's right-hand side on the first iteration: keff_c sum over its bone-attached vertices of (xk - y)."""
    s0 = s1 = s2 = 0.0
    for q in range(att_ptr[p], att_ptr[p + 1]):
        a = att_idx[q]
        s0 += xk[a, 0] - y[a, 0]; s1 += xk[a, 1] - y[a, 1]; s2 += xk[a, 2] - y[a, 2]
    k = keff[row_c[p]]
    return s0 * k, s1 * k, s2 * k


@njit(cache=True, fastmath={'contract'})
def _backward_rows(Lp, Lj, Lx, ginv, row_v, z, xk, y, first, xs, vn, ih, vmax2, lo, hi):
    """Rows hi - 1 down to lo of _backward; how many of their vertices are too fast or not finite. (A range per call:
    a call per row costs several times the row.)"""
    nfast = 0
    for p in range(hi - 1, lo - 1, -1):
        g = ginv[p]
        s0, s1, s2 = z[p, 0] * g, z[p, 1] * g, z[p, 2] * g
        z[p, 0] = s0; z[p, 1] = s1; z[p, 2] = s2
        row_axpy4(Lx, Lj, z, Lp[p], Lp[p + 1], s0, s1, s2)
        i = row_v[p]
        if i >= 0:
            if first:
                xk[i, 0] = y[i, 0] + s0; xk[i, 1] = y[i, 1] + s1; xk[i, 2] = y[i, 2] + s2
            else:
                xk[i, 0] += s0; xk[i, 1] += s1; xk[i, 2] += s2
            nfast += _velocity(i, ih, xs, xk, vn, vmax2)
    return nfast


@njit(cache=True, fastmath={'contract'})
def _backward(Lp, Lj, Lx, ginv, row_v, z, xk, y, first, xs, vn, ih, vmax2, split):
    """The backward pass of _solve and _solve_sheath: G^T w = z in scatter form, reading G by rows as the forward pass
    does (rows p from the last: w_p = z_p ginv_p, then z_j -= G_pj w_p for the row's entries j < p, w in place of z),
    each w_p final when its row is reached; its vertex i = row_v[p] (-1: a cell row) updated there, xk_i = y_i + w_p
    (first) or xk_i += w_p, and vn_i = (xk_i - xs_i) ih. The separator's rows first, then split's two blocks (prange:
    in parallel in parallel_kernels' copy; a block's rows write only its own). Not split: one range (the three calls
    measured +3.5 us, 10 %, on the bundled limb). Returns how many are faster than sqrt(vmax2) or not finite."""
    if split[1] == split[3]:
        return _backward_rows(Lp, Lj, Lx, ginv, row_v, z, xk, y, first, xs, vn, ih, vmax2, 0, split[3])
    nfast = _backward_rows(Lp, Lj, Lx, ginv, row_v, z, xk, y, first, xs, vn, ih, vmax2, split[2], split[3])
    for t in prange(2):
        nfast += _backward_rows(Lp, Lj, Lx, ginv, row_v, z, xk, y, first, xs, vn, ih, vmax2, split[t], split[t + 1])
    return nfast


@njit(inline='always')
def _velocity(i, ih, x, xn, vn, vmax2):
    """vn[i] = (xn[i] - x[i]) / h (ih = 1/h); 1 if it is faster than sqrt(vmax2) or not finite (NaN counts), else 0."""
    a = (xn[i, 0] - x[i, 0]) * ih
    b = (xn[i, 1] - x[i, 1]) * ih
    c = (xn[i, 2] - x[i, 2]) * ih
    vn[i, 0] = a; vn[i, 1] = b; vn[i, 2] = c
    return 0 if a * a + b * b + c * c <= vmax2 else 1


@njit(cache=True)
def integrate(h, x, f, xn, vn, imp, att_idx, att_seg, rest, seg_R, seg_t, vmax2):
    """Stage 3 with the implicit integrator, first iteration: f = the forces at imp.y (predict); the bone-attached
    vertices take their segment's new pose (integration.pose_attached), the free ones x1 = y + A^-1 (f - Lhat_fa
    (xa1 - ya)), v1 = (x1 - x)/h (_solve). Reads x, writes xn, vn; returns how many vertices are too fast or not
    finite."""
    nfast = IK.pose_attached(h, x, xn, vn, att_idx, att_seg, rest, seg_R, seg_t, vmax2)
    return nfast + _solve(imp, f, xn, imp.y, True, x, vn, 1.0 / h, vmax2)


@njit(cache=True)
def correct(h, x, f, xn, vn, imp, vmax2):
    """A further local/global iteration: f = the forces at (xn, vn); xn_free += A^-1 (f - M (xn - y)/h^2)."""
    return _solve(imp, f, xn, imp.y, False, x, vn, 1.0 / h, vmax2)


@njit(cache=True, fastmath={'contract'})
def _solve_sheath(imp, xk, xs, vn, ih, vmax2):
    """xk += w over sheath_region's vertices, A' w = k_s d (imp.sd, the sheathed vertices' way back; A' = A +
    diag(k_s) over the region, the rest held), and their velocities vn = (xk - xs) ih: the forward and the backward
    pass of _solve on its factor. Returns how many are faster than sqrt(vmax2) or not finite."""
    _forward(True, imp.s_row_v, imp.row_c, xk, xk, xk, False, imp.mh2, imp.keff, imp.att_ptr, imp.att_idx, imp.ks,
             imp.sd, imp.s_Lp, imp.s_Lj, imp.s_Lx, imp.s_ginv, imp.s_z, imp.s_split, imp.s_sep_e, imp.s_sep_part)
    return _backward(imp.s_Lp, imp.s_Lj, imp.s_Lx, imp.s_ginv, imp.s_row_v, imp.s_z, xk, xk, False, xs, vn, ih, vmax2,
                     imp.s_split)


@njit(cache=True)
def sheath_correct(h, x, xn, vn, imp, seg_R, seg_t, cg, vmax2, wr):
    """The sheath with the implicit integrator (Params.sheath_group; docs/solver.md "Implicit integrator"), after the
    last iteration: the sheathed vertices beyond their radius at xn (contact.sheath_offsets, in the segments' new
    poses) are moved back onto it and the tissue follows them, xn_free += A'^-1 (k_s d), A' = A + diag(k_s) (k_s =
    SHEATH_STIFFNESS x a vertex's diagonal: the sheathed vertices held where the correction puts them, the rest of
    each cell following as the constant system says); v1 = (xn - x)/h. Stage 4's projection (contact._sheath) then
    finds them on the radius within ~1/SHEATH_STIFFNESS of their way back. The segments take the reaction of the
    force that held each sheathed vertex (contact.sheath_reaction, into wr (S, 6)). Returns how many vertices are too
    fast or not finite (0 with nothing beyond the radius: nothing done)."""
    if imp.sd.shape[0] == 0 or CT.sheath_offsets(xn, seg_R, seg_t, cg, imp.sd) == 0:
        return 0
    for i in cg.s_idx:
        imp.sd[i, 3], imp.sd[i, 4], imp.sd[i, 5] = xn[i, 0], xn[i, 1], xn[i, 2]
    nfast = _solve_sheath(imp, xn, x, vn, 1.0 / h, vmax2)     # (the velocities: of the region's vertices, the
    CT.sheath_reaction(xn, cg, imp.ks, imp.sd, wr)             # others did not move)
    return nfast


def recompiled(fn, g: dict, name: str, **options):
    """A numba function compiled afresh from fn's Python code with the globals g (its callees as g names them), not
    cached: how step.parallel_advance and parallel_kernels make parallel copies of cached serial code."""
    import types
    return njit(types.FunctionType(fn.py_func.__code__, g, name), **options)


_PARALLEL = []


def parallel_kernels() -> tuple:
    """(bdf2_start, integrate, correct, sheath_correct, via_correct, contact.bone_contact) on numba's threads
    (step.parallel_advance; Params.threads != 1): the same code, compiled once per process from these functions with
    bdf2_start, _forward, _backward, _via_move and contact's _load_free, _broad_halves and _narrow_halves compiled
    parallel (their prange loops: two halves of the arrays or of the contact's candidates, the passes' two blocks of
    split), not cached on disk (as step.parallel_advance). The results are the serial ones, bit for bit: every row's
    sum is the same in the same order, each contact candidate writes its own rows, and the reactions' sums are made
    after, in the candidates' order."""
    if not _PARALLEL:
        g = dict(globals())
        for name in ('_forward', '_backward', 'bdf2_start', '_via_move'):
            g[name] = recompiled(globals()[name], g, name + '_parallel', parallel=True, fastmath={'contract'})
        for name in ('_solve', '_solve_sheath'):
            g[name] = recompiled(globals()[name], g, name + '_parallel', fastmath={'contract'})
        gc = dict(CT.__dict__)
        for name in ('_load_free', '_broad_halves', '_narrow_halves'):
            gc[name] = recompiled(getattr(CT, name), gc, name + '_parallel', parallel=True, fastmath={'contract'})
        _PARALLEL.append((g['bdf2_start'],) + tuple(recompiled(globals()[name], g, name + '_parallel')
                                                    for name in ('integrate', 'correct', 'sheath_correct'))
                         + (recompiled(via_correct, g, 'via_correct_parallel', fastmath={'contract'}),
                            recompiled(CT.bone_contact, gc, 'bone_contact_parallel', fastmath={'contract'})))
    return _PARALLEL[0]
