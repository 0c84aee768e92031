"""The cell kernel: every cell's force (shape matching, volume, damping, active tension) with SIMD across
cells, and the muscle-tension state it needs (contraction, force-velocity, muscle velocities).

numba, flat arrays, single thread. No fastmath except floating-point contraction (fused multiply-add) in the
hot kernels: deterministic (the compiled code fixes the order), no reassociation (it made results depend on
what ran before in the process), NaN/Inf semantics kept (divergence checks rely on them). The physics is
``reference.cell_forces`` (plain numpy); this module computes the same forces laid out by ``pack_cells``:
rings shared by two cells once, SIMD lanes running along chains of cells of one size (see the notes before
``BLK``). Positions in metres, model frame; forces in N (paper units in the 'paper' preset).
"""
from __future__ import annotations

import collections
import math

import numpy as np
import numba
from numba import njit, prange

def _noalias_option() -> dict:
    """The jit option that marks a function's array arguments noalias (LLVM), as {'_noalias': True}.

    numba has the flag (Flags.noalias: every pointer argument gets LLVM's noalias attribute) but no
    public jit option for it; this registers one on the CPU target (numba pinned in requirements/core.txt).
    It lets LLVM vectorise a loop that loads through an index array (the fused gather of _ring_moments):
    without it LLVM cannot rule out that the stores of the loop write into the gathered arrays. Returns {}
    (the same code, not vectorised: slower, same results) if a numba version lacks the internals."""
    try:
        from numba.core import cpu, options
        if not hasattr(cpu.CPUTargetOptions, '_noalias'):
            cpu.CPUTargetOptions._noalias = options.TargetOptions.Mapping('noalias')
        return {'_noalias': True}
    except (ImportError, AttributeError):      # pragma: no cover - other numba versions
        return {}


NOALIAS = _noalias_option()
FORCE_BOUND = 1e150
NEWTON_DONE = 1e-5          # [rad] a Newton rotation correction below this ends the iteration (next one ~1e-10)


# ------------------------------------------------------------------------------------ contraction
@njit(cache=True)
def update_contraction(lam, act, log_c, log_r, lam_min_full, h_over_ref):
    """Fibre stretch lam (M,) of each muscle's rest shape, in place.

    Target stretch lam* = 1 - a (1 - lam_min_full). Above it, lam shrinks by c^(a h/rate_dt)
    (the paper's c per dT at a = 1); below it (activation lowered or 0), lam recovers by
    1/r^(h/rate_dt) towards lam*, i.e. back to 1 (rest length) at a = 0."""
    for m in range(lam.shape[0]):
        a = min(max(act[m], 0.0), 1.0)
        target = 1.0 - a * (1.0 - lam_min_full)
        if lam[m] > target:
            lam[m] = max(lam[m] * math.exp(log_c * a * h_over_ref), target)
        elif lam[m] < target:
            lam[m] = min(lam[m] * math.exp(-log_r * h_over_ref), target)


# ------------------------------------------------------------------------------------ partly bound end rings
EndRings = collections.namedtuple('EndRings', 'cell top free_off free bound_off bound')
EndRings.__doc__ = """The muscles' end rings that are partly bound to a bone across a joint from the muscle's other end
(end_rings; Params.end_ring_pull 'bound'): per ring its cell, top (1: the cell's top ring, 0: its bottom ring), and its
free and bound vertices (CSR: free[free_off[e]:free_off[e + 1]], bound[bound_off[e]:bound_off[e + 1]])."""


def end_rings(cell_muscle, cell_slice, off, cv, vertex_segment) -> EndRings:
    """The end rings end_ring_shift acts on: of every muscle, the bottom rings of its cells in its lowest slice gap and
    the top rings of those in its highest, where a ring has bound and free vertices, all the bound ones on one segment,
    and no vertex of the muscle's other end is bound to that segment (the ring passes the muscle's force across a joint:
    the vastus medialis' insertion ring on the patella, 6 of 11 vertices bound; a ring whose other end is on the same
    bone moves nothing and is left as it is)."""
    cell_muscle, cell_slice = np.asarray(cell_muscle), np.asarray(cell_slice)
    n = np.diff(off) // 2
    rows = []
    for m in np.unique(cell_muscle[cell_muscle >= 0]):
        cells = np.flatnonzero(cell_muscle == m)
        ends = []
        for top, sl in ((0, cell_slice[cells].min()), (1, cell_slice[cells].max())):
            rings = [(c, cv[off[c] + top * n[c]:off[c] + (top + 1) * n[c]]) for c in cells[cell_slice[cells] == sl]]
            ends.append((top, rings, {int(s) for _, r in rings for s in vertex_segment[r] if s >= 0}))
        for (top, rings, segs), (_, _, other) in ((ends[0], ends[1]), (ends[1], ends[0])):
            for c, r in rings:
                seg = vertex_segment[r]
                bound = seg >= 0
                if 0 < bound.sum() < r.size and len(set(seg[bound].tolist())) == 1 and int(seg[bound][0]) not in other:
                    rows.append((c, top, r[~bound], r[bound]))
    csr = lambda k: (np.concatenate([[0], np.cumsum([len(t[k]) for t in rows])]).astype(np.int64),   # noqa: E731
                     np.concatenate([t[k] for t in rows]).astype(np.int64) if rows else np.zeros(0, np.int64))
    return EndRings(np.array([t[0] for t in rows], np.int64), np.array([t[1] for t in rows], np.int64), *csr(2), *csr(3))


@njit(cache=True)
def end_ring_shift(x, f, off, cv, cell_muscle, k_active, rest_length, cell, top, free_off, free, bound_off, bound,
                   lam, act):
    """On each partly bound end ring (EndRings), the active tension's pull on its free vertices moves to its bound ones:
    f[free] -= p, f[bound] += p n_free / n_bound, p the pull the cell kernel puts on each vertex of that ring (bottom
    ring +t u, top ring -t u; t = a kact n/4 max(l - lam L, 0) 2 / (n l), u the cell's bottom-to-top ring-centroid
    vector, l = |u|: cells.lane_forces' tension). The net force on the ring is unchanged; the free vertices keep their
    cell's elastic and volume forces. Without it a muscle's tension pulls the free part of such a ring along the muscle,
    held only by the cell's soft shape matching, and the muscle slackens (docs/solver.md "Partly bound end rings")."""
    for e in range(cell.shape[0]):
        c = cell[e]
        o = off[c]
        n = off[c + 1] - o
        half = n // 2
        bx = by = bz = tx = ty = tz = 0.0
        for j in range(half):
            i = cv[o + j]
            bx += x[i, 0]; by += x[i, 1]; bz += x[i, 2]
        for j in range(half, n):
            i = cv[o + j]
            tx += x[i, 0]; ty += x[i, 1]; tz += x[i, 2]
        ux, uy, uz = (tx - bx) / half, (ty - by) / half, (tz - bz) / half
        ln = math.sqrt(ux * ux + uy * uy + uz * uz)
        m = cell_muscle[c]
        a, kact = act[m], k_active[c]
        stretch = ln - lam[m] * rest_length[c]
        if not (kact > 0.0 and a > 0.0 and stretch > 0.0 and ln > 0.0):
            continue
        t = (a * kact * 0.25 * n) * stretch * 2.0 / (n * ln) * (-1.0 if top[e] else 1.0)
        px, py, pz = t * ux, t * uy, t * uz
        for k in range(free_off[e], free_off[e + 1]):
            i = free[k]
            f[i, 0] -= px; f[i, 1] -= py; f[i, 2] -= pz
        w = (free_off[e + 1] - free_off[e]) / (bound_off[e + 1] - bound_off[e])
        for k in range(bound_off[e], bound_off[e + 1]):
            i = bound[k]
            f[i, 0] += w * px; f[i, 1] += w * py; f[i, 2] += w * pz


# ------------------------------------------------------------------------------------ force-velocity
FV_HILL_A = 0.25            # Hill's a / F0: curvature of the shortening branch (Hill 1938)
FV_SLOPE = 1.0 + 1.0 / FV_HILL_A    # d f_v / d vn at vn = 0 (5): the lengthening branch has the same slope (C1)


@njit(cache=True)
def force_velocity(vn, fv_max):
    """Hill force-velocity factor of the active force at the normalised fibre velocity vn = v / (v_max L0)
    (lengthening > 0). Shortening: (1 + vn) / (1 - vn / a), a = 0.25 (Hill's hyperbola; 0 at and below
    vn = -1). Lengthening: fv_max - (fv_max - 1) b / (b + vn), b = (fv_max - 1) / 5: 1 at rest with the
    same slope 5 as the shortening branch, rising to the eccentric plateau fv_max."""
    if vn <= -1.0:
        return 0.0
    if vn <= 0.0:
        return (1.0 + vn) / (1.0 - vn / FV_HILL_A)
    b = (fv_max - 1.0) / FV_SLOPE
    return fv_max - (fv_max - 1.0) * b / (b + vn) if b > 0.0 else 1.0


@njit(cache=True)
def muscle_velocity(cell_length, mcells, mcell_muscle, mcell_weight, mlen, mvel, h, alpha, scratch):
    """Per muscle: its length sum_c w_c l_c [m] over its cells (l_c = cell_length, w_c the length weight);
    its lengthening velocity [m/s] by the backward difference over h, low-pass filtered in place:
    mvel += alpha (raw - mvel). mlen holds the previous length; mlen < 0 (a fresh or re-posed state)
    only records it."""
    scratch[:] = 0.0
    for k in range(mcells.shape[0]):
        scratch[mcell_muscle[k]] += mcell_weight[k] * cell_length[mcells[k]]
    for m in range(mlen.shape[0]):
        if mlen[m] >= 0.0:
            mvel[m] += alpha * ((scratch[m] - mlen[m]) / h - mvel[m])
        mlen[m] = scratch[m]


# ------------------------------------------------------------------------------------ cell forces
# The cell kernel runs SIMD across cells, and shares the work of the vertices two cells have in common.
#
# Rings. Every cell is two rings: its bottom ring (its first n // 2 vertices) and its top ring (the
# rest). In a model built from a stack of sections the top ring of a cell is the bottom ring of the
# next cell of its column (the same vertices, the same rest shape): pack_cells links such cells into
# chains. The vertex sums (moments) and the per-vertex forces are computed once per ring, in the ring's
# own frame (origin: its first vertex now; rest shape: its vertices about the ring's rest centroid),
# and each cell combines its two rings' sums (_combine) and hands each ring the coefficients of its
# force map (_ring_coefs); a shared ring gets those of both its cells added, so its vertices are
# gathered, forced and scatter-added once instead of twice. Same equations as per cell; only the
# order of the sums differs (the bundled anatomy: 12,384 cell-vertex entries, ~7,100 ring-vertex entries).
#
# Lanes. A block is one position along BLK lanes (one cell per lane, structure of arrays: every
# per-cell quantity is a row of BLK doubles, so each loop over a block's lanes is contiguous and
# branch-free: the branches of the per-cell algebra are selects, and LLVM vectorises it, AVX2 taking
# 4 cells per instruction, AVX-512 8; BLK depends on the CPU: see lanes_for_cpu). Lane l runs along
# chains of cells of one size n: position j holds a cell between ring j (its bottom) and ring j + 1
# (its top), so the ring sums a cell needs sit in the same
# lane of the two ring blocks around it (no gather between rings and cells). Where a lane passes from
# one chain to the next, a dummy position (no stiffness: its results are dropped) lies between the two
# chains' end rings. Loops over lanes run over the whole block (a constant trip count); every row a
# loop writes lies in one buffer at a compile-time offset (a multiple of BLK), so LLVM knows that the
# rows do not overlap. The gather of a ring block's positions and velocities is fused into its moment
# loop, which LLVM vectorises with scalar loads once the arrays are marked noalias (NOALIAS); the
# scatter-add of the forces is scalar (AVX2 has no scatter; lanes may share a vertex), in a fixed
# order: deterministic.
WIDE_CPUS = ('znver4', 'znver5')     # LLVM's names of the CPUs for which it emits 512-bit vectors by default (not
                                     # Intel's AVX-512 CPUs: LLVM prefers 256 bits there) and
                                     # where 32 lanes were measured faster (AMD Zen 4 and later)


def lanes_for_cpu(name: str | None = None) -> int:
    """Lanes per block for the CPU numba compiles for (``NUMBA_CPU_NAME``, else the host): 32 where LLVM
    emits 512-bit vectors (8 doubles) by default (``WIDE_CPUS``), else 16. Measured with bench/solver.py
    on the 2-core machines here: on AMD Zen 3 (AVX2, 4 doubles per register) 16 lanes are fastest (8
    vectorise poorly, 32 and 64 were 2-10 % slower: the rows outgrow L1); on AMD Zen 4 (AVX-512) 32 lanes
    are 5-10 % faster than 16 (four vectors per row instead of two: more independent chains per loop).
    Read once at import, so it is a compile-time constant of every kernel; numba's on-disk cache is keyed
    by the CPU name too, so a cache never mixes layouts. Only the order of the sums depends on it."""
    return 32 if (compile_cpu() if name is None else name) in WIDE_CPUS else 16


def compile_cpu() -> str:
    """LLVM's name of the CPU numba compiles for: ``NUMBA_CPU_NAME`` if set, else the host's."""
    from numba.core import config
    import llvmlite.binding as llvm
    name = config.CPU_NAME or 'host'
    return llvm.get_host_cpu_name() if name == 'host' else name


BLK = lanes_for_cpu()       # lanes (cells) per block: a multiple of 8 (doubles per AVX-512 register)
FOUR_SLOT_PASSES = BLK == 32     # the fused gather + moment loop takes four vertex slots per pass (each running
                                 # sum loaded and stored once per four slots; Zen 4: 28.8 -> 25.1 us per step)
                                 # with 512-bit vectors (32 registers); two elsewhere (on Zen 3, with 16
                                 # registers, four slots per pass had measured slower)

# rows of the per-lane constants (pack_cells: par[block, row * BLK + lane])
P_K = 0                     # spring constant per cell-vertex [N/m]
P_KACT = 1                  # active stiffness [N/m] (axial tension)
P_B = 2                     # deformation damping [N s/m]
P_KVOL = 3                  # volume stiffness [J]
P_QTR = 4                   # tr Q [m^2], Q = sum X0 X0^T
P_QFF = 5                   # f^T Q f [m^2]
P_LEN = 6                   # rest distance of the ring centroids [m]
P_F = 7                     # fibre direction (3)
P_G = 10                    # Qinv f (3) [1/m^2]: D f = A (Qinv f), the current fibre stretch vector
P_DQ = 13                   # det Qinv [1/m^6]: det D = det A det Qinv, cof(D) Qinv = det Qinv cof(A)
P_PB = 14                   # rest centroid of the bottom ring relative to the cell's rest centroid [m] (3)
P_PT = 17                   # the same for the top ring (3)
P_ON = 20                   # 1.0 for a cell, 0.0 for a dummy position
P_Q = 21                    # Q = sum X0 X0^T (6: xx, yy, zz, xy, xz, yz) [m^2]
P_VCAP = 27                 # the volume term's bound on |grad det D|^2 [1/m^2] (0: none; SimModel.volume_cap)
N_PAR = 28

# rows of a ring block's sums (ring buffers: rs[row * BLK + lane]); d_i = x_i - o, o the ring's first vertex
R_S = 0                     # sum d_i (3)
R_A = 3                     # sum d_i Xr_i^T (9), Xr_i the vertex's rest position about the ring's rest centroid
R_Y = 12                    # sum d_i d_i^T: xx, yy, zz, xy, xz, yz (6)
R_V = 18                    # sum v_i (3)
R_L = 21                    # sum d_i x v_i (3)
R_O = 24                    # the ring's origin o [m] (3)
N_R = 27

# rows of the per-lane work buffer (work.w[row * BLK + lane]); the cell's sums relative to its bottom ring's origin
W_S = 0                     # sum d_i, d_i = x_i - x_first (a local origin, for precision) (3)
W_A = 3                     # A = sum d_i X0_i^T (9, row-major)
W_Y = 12                    # sum d_i d_i^T: xx, yy, zz, xy, xz, yz (6)
W_V = 18                    # sum v_i (3); then the cell's mean velocity vbar
W_L = 21                    # sum d_i x v_i (3)
W_U = 24                    # sum d_i over the bottom ring (3)
W_O = 27                    # local origin x_first [m] (3)
W_Q = 30                    # rotation quaternion x, y, z, w (4): warm start in, result out
W_LAM = 34                  # fibre stretch of the rest shape (1 for fat)
W_ACT = 35                  # activation (0 for fat)
W_MUS = 36                  # 1.0 for a muscle cell, 0.0 for fat
W_PRES = 37                 # integral volume pressure (updated)
W_SL = 38                   # cross-section factor s of F
W_B = 39                    # B = A F (9)
W_ON = 48                   # 1.0 while the rotation iteration of the lane runs
W_P = 49                    # volume force map P = g cof(D) Qinv = g det(Qinv) cof(A) (9)
W_EV = 58                   # volume energy [J]
W_TRY = 59                  # tr Y, Y = sum r_i r_i^T about the centroid [m^2]
W_W = 60                    # rigid angular velocity w [rad/s] (3)
W_M = 63                    # force map k T + P (9)
W_C = 72                    # constant force part (3)
W_BW = 75                   # b w (3)
W_TA = 78                   # active tension force on a bottom-ring vertex [N] (3)
W_E = 81                    # cell energy [J]
W_BAD = 82                  # 1.0 where the force is non-finite or absurd
W_LN = 83                   # axial length: distance of the ring centroids [m]
W_NB2 = 84                  # |B|^2 (Frobenius): the scale of B for the regularised Mueller step
W_OM = 85                   # rotation correction omega of the current iteration (3)
W_NT = 88                   # 1.0 where that correction is a Newton step
W_DT = 89                   # the top ring's origin relative to the bottom ring's [m] (3)
# the force map of a ring's vertex i, in the ring's frame: f_i = M Xr_i - k d_i + bw x d_i + C - b v_i
W_RM = 92                   # M (9): the sum of its cells' force maps k T + P
W_RC = 101                  # C (3)
W_RBW = 104                 # bw (3)
W_RK = 107                  # k
W_RB = 108                  # b
W_H = 109                   # the same 17 rows: the top ring's share of the cell at the previous position
N_W = W_H + 17
# A ring block's vertices (gv, one buffer per ring block being worked on): slot s of every lane at rows
# 6 s .. 6 s + 5: x (3 rows, replaced by the force), v (3 rows; zero in a padding slot). Separate buffers:
# LLVM then checks once at run time that they do not overlap the per-lane rows (two offsets it cannot
# see apart in one buffer stop the vectoriser). The moment loops take two slots per pass (half the loads
# and stores of the sums; four with 32 lanes, FOUR_SLOT_PASSES), so a ring of odd size gets a padding
# slot: its own first vertex with Xr = 0, adding exact zeros.


CellLayout = collections.namedtuple('CellLayout', 'groups ids rings ring_idx ring_X0 par lane_muscle lane_of tasks excl '
                                    'gvert gptr gsrc')
CellWork = collections.namedtuple('CellWork', 'w rs0 rs1 gv0 gv1 lq lp le ll tw trs0 trs1 tgv0 tgv1 bh bb bgv bro fr tbad')
CellWork.__doc__ = """The scratch buffers of lane_forces (cell_work): w the per-lane rows (W_*), rs0/rs1 the sums of two
ring blocks (R_*), gv0/gv1 their gathered vertices, and the per-cell state in lane order: lq the rotation
quaternions (rows x, y, z, w of block b at (4 b + r) BLK), lp pressure, le energy, ll axial length (at b BLK).
lane_forces_par's: tw, trs0, trs1, tgv0, tgv1 the same scratch per thread (row = numba's thread id); per task
(CellLayout.tasks) bh the top-ring share of its last cell, bb the bottom-ring share of its first cell, bgv and bro
its first ring's gathered vertices and sums (the ring whose map needs the previous task's bh); fr the forces of
every ring slot ((r0 + s) * 3 + axis) * BLK + lane; tbad each task's lowest bad cell."""
UNITS = 2                   # lane_forces_par's units: two runs of tasks of about equal cost, one per thread; a cut
                            # that depends on the model only, so the results do not depend on the number of threads
COST_SLOT, COST_CELL = 1.0, 6.0     # the relative cost of a ring slot and of a cell's algebra, per lane (measured on
                                    # the 3x limb: 94 ns a fat cell of 4-vertex rings, 362 ns a muscle cell of 33)
BOUNDARY_SLACK = 0.1        # units end at a group's end if their costs are then within 50 +- 10 % of the whole
                            # (the fat and the muscle groups share fewer vertices than two halves of one group)


def _second_moments(off, X0):
    """(C, 6) Q = sum X0_i X0_i^T of each cell (xx, yy, zz, xy, xz, yz)."""
    cell = np.repeat(np.arange(off.size - 1), np.diff(off))
    out = np.zeros((off.size - 1, 6))
    for j, (a, b) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
        out[:, j] = np.bincount(cell, X0[:, a] * X0[:, b], off.size - 1)
    return out


def pack_cells(off, cv, X0, cell_muscle, k, k_active, damp_b, k_volume, q_tr, q_ff, rest_length, fibre, Qinv,
               task_positions=None, volume_cap=None):
    """The layout lane_forces reads (numpy, at compile time). Returns a CellLayout (groups, ids, rings,
    ring_idx, ring_X0, par, lane_muscle, lane_of, tasks, excl, gvert, gptr, gsrc):

    - groups (G, 5) int64: per cell size n (ascending): n, positions L, first cell block, first ring block
      (a group has L cell blocks and L + 1 ring blocks), the kernel version it runs: 0 general, 1 no muscle,
      volume or tension (plain fat), 2 no muscle or tension but a volume term (fat with its volume term);
    - ids (Bc, BLK) int32: the cell of each lane of each cell block (-1: a dummy position);
    - rings (Br, 4) int64 per ring block: real slots, slots (even), first slot row r0, real lanes (a prefix);
    - ring_idx (R, BLK) uint32: 3 x the vertex of slot s of each lane at row r0 + s (its offset in the flat
      position array: unsigned, so no negative-index wrap-around; a padding slot or lane repeats a vertex);
    - ring_X0 (R * 3 * BLK,): the slot's rest position about its ring's rest centroid, axis d at
      ((r0 + s) * 3 + d) * BLK (0 for padding);
    - par (Bc, N_PAR * BLK): per-lane constants (P_* rows, 0 for a dummy; volume_cap (C,): P_VCAP, None = zeros);
    - lane_muscle (Bc, BLK) int32: muscle of each lane (-1: fat or dummy);
    - lane_of (C,) int64: the lane of each cell, b * BLK + lane (the order of the kernel's per-cell state);
    - tasks (T, 4) int64: lane_forces_par's tasks, group, positions j0 .. j1 - 1 and unit: every group whole but the
      one where the UNITS units' estimated costs (COST_SLOT, COST_CELL) meet, cut there (task_positions k: every
      group cut into runs of k positions, the units cut between tasks); a unit's tasks are consecutive and it runs
      them in order on one thread;
    - excl (R, BLK) uint8: 1 where the slot's vertex gets all its ring forces from one unit of lane_forces_par
      (one unit's tasks, or the cut rings' pass), which then adds them into f itself;
    - gvert (S,), gptr (S + 1,), gsrc (E,) int64: the other (shared) vertices and per shared vertex (CSR) the
      offsets in CellWork.fr of its ring slots' forces, in the order lane_forces adds them.

    Chains: cell c continues into cell d when c's top ring and d's bottom ring are the same vertices with
    the same rest shape about their centroids (to 1e-12 of the cells' size), both cells have the same even
    size, and no other cell claims either ring that way. Chains are laid end to end and cut into at most
    BLK lanes of equal length (a cut costs one ring computed twice, a change of chain one dummy position).
    Read-only; the float arrays 64-byte aligned (vector loads)."""
    off = np.asarray(off, np.int64)
    cv = np.asarray(cv)
    X0 = np.asarray(X0, float)
    sizes = np.diff(off)
    C = sizes.size
    half = sizes // 2
    Qi = np.asarray(Qinv, float).reshape(-1, 3, 3)
    pb = np.array([X0[off[c]:off[c] + half[c]].mean(0) for c in range(C)]).reshape(C, 3)
    pt = np.array([X0[off[c] + half[c]:off[c + 1]].mean(0) for c in range(C)]).reshape(C, 3)
    rows = np.concatenate([np.asarray(k, float)[None], np.asarray(k_active, float)[None],
                           np.asarray(damp_b, float)[None], np.asarray(k_volume, float)[None],
                           np.asarray(q_tr, float)[None], np.asarray(q_ff, float)[None],
                           np.asarray(rest_length, float)[None], np.asarray(fibre, float).T,
                           np.einsum('cij,cj->ci', Qi, np.asarray(fibre, float)).T, np.linalg.det(Qi)[None],
                           pb.T, pt.T, np.ones((1, C)), _second_moments(off, X0).T,
                           (np.zeros(C) if volume_cap is None else np.asarray(volume_cap, float))[None]])
    # the chains
    tol = 1e-12 * max(float(np.abs(X0).max()) if X0.size else 0.0, 1e-300)
    bottoms, tops = {}, {}
    for c in range(C):
        if sizes[c] % 2 == 0 and sizes[c] > 0:
            a, m, e = off[c], off[c] + half[c], off[c + 1]
            bottoms.setdefault((sizes[c], frozenset(cv[a:m].tolist())), []).append(c)
            tops.setdefault((sizes[c], frozenset(cv[m:e].tolist())), []).append(c)
    nxt = np.full(C, -1)
    has_prev = np.zeros(C, bool)
    for key, below in tops.items():
        above = bottoms.get(key, [])
        if len(below) != 1 or len(above) != 1 or below[0] == above[0]:
            continue
        c, d = below[0], above[0]
        top_shape = dict(zip(cv[off[c] + half[c]:off[c + 1]].tolist(), X0[off[c] + half[c]:off[c + 1]] - pt[c]))
        bottom = X0[off[d]:off[d] + half[d]] - pb[d]
        if all(np.abs(top_shape[i] - r).max() <= tol for i, r in zip(cv[off[d]:off[d] + half[d]].tolist(), bottom)):
            nxt[c], has_prev[d] = d, True
    chains, seen = [], np.zeros(C, bool)
    for starts in (np.flatnonzero(~has_prev), np.arange(C)):      # then what is left: cycles, cut at their lowest cell
        for c in starts:
            if not seen[c]:
                chain = []
                while c >= 0 and not seen[c]:
                    seen[c] = True
                    chain.append(int(c))
                    c = nxt[c]
                chains.append(chain)
    # per size: lanes of equal length
    groups, cell_blocks, ring_blocks = [], [], []
    for n in np.unique(sizes):
        mine = [ch for ch in chains if sizes[ch[0]] == n]
        L = -(-sum(map(len, mine)) // BLK)
        while (lanes := _fill_lanes(mine, nxt, L)) is None:
            L += 1
        lanes.sort(key=len, reverse=True)                      # real rings then form a prefix of the lanes
        seq = np.full((BLK, L), -1)
        for lane, cells in enumerate(lanes):
            seq[lane, :len(cells)] = cells
        cs = np.concatenate(mine)
        plain = bool(np.all(np.asarray(cell_muscle)[cs] < 0) and np.all(rows[1, cs] == 0))
        if plain and np.any(rows[3, cs] != 0):
            plain = 2          # no muscle or tension but a volume term (fat with volume_stiffness_fat > 0)
        groups.append((int(n), L, len(cell_blocks), len(ring_blocks), int(plain)))
        cell_blocks += [seq[:, j] for j in range(L)]
        for j in range(L + 1):
            ring = []
            for lane in range(BLK):
                below = seq[lane, j - 1] if j > 0 else -1
                above = seq[lane, j] if j < L else -1
                if below >= 0:
                    a, e, centre = off[below] + half[below], off[below + 1], pt[below]
                elif above >= 0:
                    a, e, centre = off[above], off[above] + half[above], pb[above]
                else:
                    ring.append(None)
                    continue
                ring.append((cv[a:e], X0[a:e] - centre))
            ring_blocks.append(ring)
    # the arrays
    Bc, Br = len(cell_blocks), len(ring_blocks)
    ids = np.full((Bc, BLK), -1, np.int32)
    lane_muscle = np.full((Bc, BLK), -1, np.int32)
    par = aligned_zeros((Bc, N_PAR, BLK))
    for b, cells in enumerate(cell_blocks):
        real = cells >= 0
        ids[b, real] = cells[real]
        lane_muscle[b, real] = np.asarray(cell_muscle)[cells[real]]
        par[b][:, real] = rows[:, cells[real]]
    rings = np.zeros((Br, 4), np.int64)
    r0 = 0
    for q, ring in enumerate(ring_blocks):
        real = [r for r in ring if r is not None]
        cnt = len(real)
        assert all(r is not None for r in ring[:cnt]), 'real rings are a prefix of the lanes'
        m_real = max((len(r[0]) for r in real), default=1)
        assert all(len(r[0]) == m_real for r in real), 'the rings of a block have one size'
        rings[q] = m_real, m_real + m_real % 2, r0, cnt
        r0 += m_real + m_real % 2
    ring_idx = np.zeros((r0, BLK), np.uint32)
    ring_X0 = aligned_zeros((r0, 3, BLK))
    pad_vertex = 3 * int(cv[0]) if cv.size else 0
    for q, ring in enumerate(ring_blocks):
        m_real, m, a = rings[q, 0], rings[q, 1], rings[q, 2]
        for lane, r in enumerate(ring):
            if r is None:
                ring_idx[a:a + m, lane] = pad_vertex
                continue
            verts, shape = r
            ring_idx[a:a + m, lane] = 3 * verts[0]
            ring_idx[a:a + m_real, lane] = 3 * verts
            ring_X0[a:a + m_real, :, lane] = shape
    lane_of = np.zeros(C, np.int64)
    real = ids >= 0
    lane_of[ids[real]] = np.flatnonzero(real.reshape(-1))
    # lane_forces_par: its tasks and units, and per vertex its ring slots' forces in the order lane_forces adds them
    # (ring blocks, then slots, then lanes: ascending flat offsets)
    tasks = _tasks(groups, task_positions)
    unit = np.zeros(Br, np.int64)                       # the unit that forces each ring block, or UNITS (cut rings)
    for gi, j0, j1, u in tasks:
        q0, L = groups[gi][3], groups[gi][1]
        unit[q0 + j0:q0 + j1 + (1 if j1 == L else 0)] = u
        if j0 > 0:
            unit[q0 + j0] = UNITS
    src, dst, uni = [], [], []
    for q in range(Br):
        m_real, r0, cnt = rings[q, 0], rings[q, 2], rings[q, 3]
        for s in range(m_real):
            src.append((r0 + s) * 3 * BLK + np.arange(cnt))
            dst.append(ring_idx[r0 + s, :cnt] // 3)
            uni.append(np.full(cnt, unit[q]))
    src = np.concatenate(src).astype(np.int64) if src else np.zeros(0, np.int64)
    dst = np.concatenate(dst).astype(np.int64) if dst else np.zeros(0, np.int64)
    uni = np.concatenate(uni).astype(np.int64) if uni else np.zeros(0, np.int64)
    n_v = int(cv.max()) + 1 if cv.size else 0
    lo, hi = np.full(n_v, np.iinfo(np.int64).max), np.full(n_v, -1)
    np.minimum.at(lo, dst, uni)
    np.maximum.at(hi, dst, uni)
    own = lo == hi                                      # the vertex's ring forces all come from one unit
    excl = np.zeros(ring_idx.shape, np.uint8)
    excl[src // (3 * BLK), src % (3 * BLK)] = own[dst]
    shared = ~own[dst]
    src, dst = src[shared], dst[shared]
    order = np.argsort(dst, kind='stable')              # per vertex, src stays ascending
    gvert, counts = np.unique(dst, return_counts=True)
    gptr = np.zeros(gvert.size + 1, np.int64)
    np.cumsum(counts, out=gptr[1:])
    out = CellLayout(np.array(groups, np.int64).reshape(-1, 5), ids, rings, ring_idx, ring_X0.reshape(-1),
                     par.reshape(Bc, N_PAR * BLK), lane_muscle, lane_of, tasks, excl, gvert.astype(np.int64), gptr,
                     src[order])
    for arr in out:
        arr.flags.writeable = False
    return out


def _tasks(groups, task_positions=None) -> np.ndarray:
    """pack_cells' tasks (T, 4): group, j0, j1, unit (see there)."""
    cost = [BLK * ((g[0] // 2) * COST_SLOT + COST_CELL) for g in groups]       # per position
    total = sum(c * g[1] for c, g in zip(cost, groups))
    if task_positions is None:
        ends = np.cumsum([c * g[1] for c, g in zip(cost, groups)])
        k = int(np.argmin(abs(ends - total / 2))) if len(groups) else 0
        if len(groups) > 1 and abs(ends[k] - total / 2) <= BOUNDARY_SLACK * total:
            runs = [(gi, 0, g[1]) for gi, g in enumerate(groups)]        # the units split between groups k, k + 1
            return np.array([(gi, j0, j1, int(gi > k)) for gi, j0, j1 in runs], np.int64).reshape(-1, 4)
        runs, acc = [], 0.0
        for gi, g in enumerate(groups):
            L = g[1]
            jc = int(round((total / UNITS - acc) / cost[gi])) if acc < total / UNITS < acc + cost[gi] * L else 0
            runs += [(gi, 0, jc), (gi, jc, L)] if 0 < jc < L else [(gi, 0, L)]
            acc += cost[gi] * L
    else:
        runs = [(gi, j0, min(j0 + task_positions, g[1])) for gi, g in enumerate(groups)
                for j0 in range(0, g[1], task_positions)]
    out, acc = [], 0.0
    for gi, j0, j1 in runs:
        c = cost[gi] * (j1 - j0)
        out.append((gi, j0, j1, min(int((acc + 0.5 * c) * UNITS / total), UNITS - 1) if total > 0 else 0))
        acc += c
    return np.array(out, np.int64).reshape(-1, 4)


def _fill_lanes(chains, nxt, L):
    """Chains laid end to end into lanes of at most L positions (-1: a dummy between two chains), or
    None if more than BLK lanes would be needed."""
    lanes = [[]]
    for chain in chains:
        for c in chain:
            lane = lanes[-1]
            cont = bool(lane) and lane[-1] >= 0 and nxt[lane[-1]] == c
            need = 1 if not lane or cont else 2
            if len(lane) + need > L:
                if len(lanes) == BLK:
                    return None
                lanes.append([])
                lane, need = lanes[-1], 1
            if need == 2:
                lane.append(-1)
            lane.append(c)
    return lanes


def aligned_zeros(shape):
    """Zeros of shape (an int or a tuple), float64, C order, starting on a 64-byte boundary (vector loads;
    misaligned rows measured +50 % in the moment loop, +15 % in the implicit solve)."""
    size = int(np.prod(shape))
    buf = np.zeros(size + 8)
    a = (-buf.ctypes.data % 64) // 8
    return buf[a:a + size].reshape(shape)


def cell_work(cells: CellLayout) -> CellWork:
    """The scratch buffers of lane_forces for the layout cells (allocate once, reuse every call; 64-byte
    aligned; their contents on entry do not matter, except that a dummy lane holds the identity rotation and
    zeros for good; to_lanes and from_lanes convert the per-cell state)."""
    n_lanes = cells.ids.shape[0] * BLK
    m_max = max(2, int(cells.rings[:, 1].max(initial=0)))
    lq = aligned_zeros(4 * n_lanes)
    lq.reshape(-1, 4, BLK)[:, 3] = 1.0
    nt, T = max(int(numba.config.NUMBA_NUM_THREADS), 1), max(cells.tasks.shape[0], 1)
    slots = int(cells.ring_idx.shape[0])

    def rows(k, size):
        return aligned_zeros((k, size))
    return CellWork(aligned_zeros(N_W * BLK), aligned_zeros(N_R * BLK), aligned_zeros(N_R * BLK),
                    aligned_zeros(6 * m_max * BLK), aligned_zeros(6 * m_max * BLK), lq, aligned_zeros(n_lanes),
                    aligned_zeros(n_lanes), aligned_zeros(n_lanes),
                    rows(nt, N_W * BLK), rows(nt, N_R * BLK), rows(nt, N_R * BLK), rows(nt, 6 * m_max * BLK),
                    rows(nt, 6 * m_max * BLK), rows(T, 17 * BLK), rows(T, 17 * BLK), rows(T, 6 * m_max * BLK),
                    rows(T, N_R * BLK), aligned_zeros(3 * slots * BLK), np.full(T, -1, np.int64))


@njit(cache=True)
def to_lanes(quat, pressure, cell_energy, cell_length, cells, work):
    """The per-cell state (quat (C, 4), pressure, cell_energy, cell_length (C,)) into the lane-ordered
    copies of work (dummy lanes are left as cell_work made them)."""
    lane_of = cells.lane_of
    lq, lp, le, ll = work.lq, work.lp, work.le, work.ll
    for j in range(lane_of.shape[0]):
        a = np.uint64(lane_of[j])
        i = a + np.uint64(3 * BLK) * (a // np.uint64(BLK))          # ((4 b) BLK + c) for a = b BLK + c
        lq[i] = quat[j, 0]; lq[i + BLK] = quat[j, 1]; lq[i + 2 * BLK] = quat[j, 2]; lq[i + 3 * BLK] = quat[j, 3]
        lp[a] = pressure[j]
        le[a] = cell_energy[j]
        ll[a] = cell_length[j]


@njit(cache=True)
def from_lanes(work, cells, quat, pressure, cell_energy, cell_length):
    """The lane-ordered per-cell state of work back into the per-cell arrays."""
    lane_of = cells.lane_of
    lq, lp, le, ll = work.lq, work.lp, work.le, work.ll
    for j in range(lane_of.shape[0]):
        a = np.uint64(lane_of[j])
        i = a + np.uint64(3 * BLK) * (a // np.uint64(BLK))
        quat[j, 0] = lq[i]; quat[j, 1] = lq[i + BLK]; quat[j, 2] = lq[i + 2 * BLK]; quat[j, 3] = lq[i + 3 * BLK]
        pressure[j] = lp[a]
        cell_energy[j] = le[a]
        cell_length[j] = ll[a]


def cell_forces(x, v, f, quat, cells, lam, act, volume_actual, iters, cell_energy, pressure, vol_gain, work,
                cell_length):
    """lane_forces on per-cell state: quat, pressure (read and updated), cell_energy, cell_length
    (written) per cell as in State. Returns the lowest bad cell or -1 (see lane_forces)."""
    to_lanes(quat, pressure, cell_energy, cell_length, cells, work)
    bad = lane_forces(x, v, f, cells, lam, act, volume_actual, iters, vol_gain, work)
    from_lanes(work, cells, quat, pressure, cell_energy, cell_length)
    return bad


@njit(cache=True, fastmath={'contract'}, error_model='numpy', inline='always')
def _cell_block(w, rb, rt, pb, n, lq, lp, le, ll, at, lam, act, lane_muscle_b, ids_b, plain, fatvol, volume_actual,
                vol_gain, iters, bad):
    """One block of BLK cells between rings rb and rt (lane_forces and lane_forces_par): its muscles, moments, algebra,
    rotations, force maps and ring coefficients into w; returns the lowest bad cell so far (bad, or one of ids_b)."""
    _load_muscles(lam, act, lane_muscle_b, w)
    _combine(w, rb, rt, pb, n, lq, lp, at)
    if plain:       # no muscle, volume or tension in the group: a version compiled without them
        _cell_algebra(w, pb, n, volume_actual, vol_gain, True)
        _rotations(w, iters)
        _force_maps(w, pb, n, True)
    elif fatvol:    # no muscle or tension, a volume term: compiled without the muscle parts
        _cell_algebra(w, pb, n, volume_actual, vol_gain, True, True)
        _rotations(w, iters)
        _force_maps(w, pb, n, True)
    else:
        _cell_algebra(w, pb, n, volume_actual, vol_gain, None)
        _rotations(w, iters)
        _force_maps(w, pb, n, None)
    _ring_coefs(w, pb, lq, lp, le, ll, at)
    for c in range(BLK):
        cell = ids_b[c]
        if w[W_BAD * BLK + c] != 0.0 and cell >= 0 and (bad < 0 or cell < bad):
            bad = cell
    return bad


@njit(cache=True, fastmath={'contract'}, error_model='numpy')
def lane_forces(x, v, f, cells, lam, act, volume_actual, iters, vol_gain, work):
    """Elastic (+ volume, + deformation-damping) forces of all cells, accumulated into f (V, 3)
    (zeroed here). Returns the lowest cell whose force is non-finite or overflowing, else -1.
    cells: the layout of pack_cells; work: cell_work(cells), holding each cell's rotation quaternion and
    pressure (read and updated), energy and axial length (written) in lane order (to_lanes, from_lanes);
    lam, act (per muscle) as in State; act is the activation of the active tension (the solver passes
    it times the force-velocity factor). The axial length is the distance between the cell's bottom- and
    top-ring centroids [m] (an odd-sized cell: |sum top - sum bottom| / (n // 2)).

    Per cell (moments of its vertices, then its 3x3 algebra, then one affine map per vertex):
    centroid c = mean x_i; A = sum (x_i - c) X0_i^T; rest shape X'_i = F X0_i with
    F = lam f f^T + s (I - f f^T) for muscle cells (fibre f, s the cross-section factor: 1/sqrt(lam),
    or 1/sqrt(mu) with mu = |D f| the current fibre stretch when volume_actual), F = I for fat;
    R = rotation of A F (Newton-Mueller iteration warm-started from quat, at most iters iterations);
    goal G_i = c + R F X0_i; force k (G_i - x_i). R being the polar factor, this satisfies eq. (1):
    zero net force and moment. Volume (kvol > 0): with D = A Qinv the cell's best-fit affine
    deformation, energy 0.5 kvol (det D - 1)^2 adds -kvol (det D - 1) cof(D) Qinv X0_i (internal:
    rotation and translation invariant; computed as det D = det A det Qinv, cof(D) Qinv = det Qinv
    cof(A), Qinv being symmetric, so D is never formed), plus an integral term: pressure += vol_gain * (-kvol
    (det D - 1)) each call acts the same way, so a cell held from reaching its volume (e.g. by
    bone-attached vertices) builds up pressure until det D = 1 (vol_gain = h / volume_relax_time;
    0 = off). Damping (b > 0): -b (v_i - v_rigid_i) with v_rigid the cell's mean linear + angular
    velocity (momentum conserving, rigid motion undamped). cell_energy gets 0.5 k sum |G_i - x_i|^2
    + the volume energy + the tension energy, the first from the cell's moments:
    tr(F^2 Q) - 2 tr(T^T A) + tr(Y) with q_tr = tr Q, q_ff = f^T Q f (Q = sum X0 X0^T), Y = sum r r^T.

    Active tension (kact > 0, muscle cells): a contractile force along the cell's axis only, between
    the centroids of its bottom ring (first n/2 vertices) and top ring (last n/2): with l the current
    centroid distance, u its direction and rest_len the rest distance, T = a kact n/4 max(l - lam
    rest_len, 0) pulls the rings together (-2T/n u on each top vertex, +2T/n u on each bottom vertex:
    zero net force and moment). At l = rest_len, lam = lam_min that is n_ring kact (1 - lam_min) L / 2,
    the force the calibration (model.active_stiffness) sets. Being axial, it does not stiffen the
    cell against bending or shear (a muscle pulls, it does not hold its shape).

    Per cell-vertex entry one affine map gives the force: f_i = (k T + P) X0_i + (b [w]x - k I) r_i
    - b v_i + b vbar (elastic + volume + damping together), plus the tension. The cell's moments come
    from its two rings' sums and the maps of the (up to) two cells of a ring are added into one map of
    the ring's vertices (see the layout notes above): per position of a lane, the next ring's sums, the
    cell's algebra, then the forces of the cell's bottom ring, which is then complete."""
    groups, ids, rings, ring_idx, ring_X0, par, lane_muscle = (cells.groups, cells.ids, cells.rings, cells.ring_idx,
                                                              cells.ring_X0, cells.par, cells.lane_muscle)
    w, rs0, rs1, gv0, gv1, lq, lp, le, ll = work.w, work.rs0, work.rs1, work.gv0, work.gv1, work.lq, work.lp, work.le, work.ll
    f[:] = 0.0
    xf, vf, ff = x.reshape(-1), v.reshape(-1), f.reshape(-1)
    bad = -1
    for gi in range(groups.shape[0]):
        n, L, b0, q0, plain = groups[gi, 0], groups[gi, 1], groups[gi, 2], groups[gi, 3], groups[gi, 4] == 1
        fatvol = groups[gi, 4] == 2
        m_real, m, r0 = rings[q0, 0], rings[q0, 1], rings[q0, 2]
        w[W_H * BLK:N_W * BLK] = 0.0        # no cell below the first ring
        _ring_moments(rs0, gv0, ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], m, m_real, xf, vf, ring_idx[r0:r0 + m])
        for j in range(L + 1):
            rb, rt, gb, gt = (rs0, rs1, gv0, gv1) if j % 2 == 0 else (rs1, rs0, gv1, gv0)
            if j < L:           # the cell at position j, between ring j (rb, gb) and ring j + 1 (rt, gt)
                q = q0 + j + 1
                m_real, m, r0 = rings[q, 0], rings[q, 1], rings[q, 2]
                _ring_moments(rt, gt, ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], m, m_real, xf, vf,
                              ring_idx[r0:r0 + m])
                b = b0 + j
                pb = par[b]
                at = np.uint64(b * BLK)         # the block's lanes in the lane-ordered state (unsigned: no wrap-around)
                bad = _cell_block(w, rb, rt, pb, n, lq, lp, le, ll, at, lam, act, lane_muscle[b], ids[b], plain, fatvol,
                                  volume_actual, vol_gain, iters, bad)
            else:               # the group's last ring: the share of the cell below it only
                _last_ring_coefs(w)
            q = q0 + j          # ring j is complete: its vertices' forces
            m_real, m, r0, cnt = rings[q, 0], rings[q, 1], rings[q, 2], rings[q, 3]
            _ring_forces(w, gb, ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], rb, m)
            _scatter(ff, gb, ring_idx[r0:r0 + m], m_real, cnt)
    return bad


@njit(cache=True)
def _scatter(ff, gv, idx, n, cnt):
    """Adds the ring block's vertex forces (gv) into f (flat), slot by slot, lane by lane (a fixed order)."""
    for s in range(n):
        g = 6 * s * BLK
        for c in range(cnt):
            i = idx[s, c]
            ff[i] += gv[g + c]; ff[i + 1] += gv[g + BLK + c]; ff[i + 2] += gv[g + 2 * BLK + c]


@njit(cache=True, parallel=True)
def lane_forces_par(x, v, f, cells, lam, act, volume_actual, iters, vol_gain, work):
    """lane_forces over numba's threads (numba.set_num_threads), bit-identical to it for any number of threads.

    Three passes, two of them parallel. (1) The units (cells.tasks: UNITS runs of tasks of about equal cost, a cut
    that does not depend on the number of threads) in parallel, each running its tasks in order, each task as
    lane_forces runs its positions, with the thread's own scratch: its rings' sums, its cells' algebra and state (each cell block belongs to one task),
    and the forces of the rings it completes, added into f or stored per ring slot (work.fr, see below). The ring
    at a cut gets its map from two tasks: the task above stores its share and the ring's gathered vertices
    (bb, bgv, bro), the task below the share of its last cell (bh). (2) Those rings (serially: one ring block per
    cut, a few per cent of the work; a parallel region costs more where the cores are shared): map = bh of
    the task below + bb. The maps are the same sums as lane_forces' (0 + share, then share below + that), so
    every slot's force is the same number. A vertex whose ring forces all come from one unit (or all from the
    cut rings) gets them added into f by it, in lane_forces' order (cells.excl); the others' are stored per slot.
    (3) Per shared vertex in parallel, its slots' forces added in lane_forces' order (cells.gvert/gptr/gsrc):
    f is bit-identical to lane_forces', with no two threads writing one vertex. Returns the lowest bad cell or -1, as lane_forces."""
    # (arrays only into the prange body, no named tuple: numba lost writes through a tuple's array there, and a
    # step segfaulted now and then)
    tasks, tbad = cells.tasks, work.tbad
    groups, ids, rings, ring_idx, ring_X0, par, lane_muscle = (cells.groups, cells.ids, cells.rings, cells.ring_idx,
                                                              cells.ring_X0, cells.par, cells.lane_muscle)
    tw, trs0, trs1, tgv0, tgv1 = work.tw, work.trs0, work.trs1, work.tgv0, work.tgv1
    lq, lp, le, ll, fr, bh, bb, bgv, bro = work.lq, work.lp, work.le, work.ll, work.fr, work.bh, work.bb, work.bgv, work.bro
    excl = cells.excl
    f[:] = 0.0
    xf, vf, ff = x.reshape(-1), v.reshape(-1), f.reshape(-1)
    for u in prange(UNITS):
        tid = numba.get_thread_id()
        for t in range(tasks.shape[0]):         # (the unit's tasks, in order)
            if tasks[t, 3] == u:
                tbad[t] = _task_forces(xf, vf, ff, groups, ids, rings, ring_idx, ring_X0, par, lane_muscle, tasks,
                                       excl, lam, act, volume_actual, iters, vol_gain, tw[tid], trs0[tid], trs1[tid],
                                       tgv0[tid], tgv1[tid], lq, lp, le, ll, fr, bh, bb, bgv, bro, t)
    for t in range(tasks.shape[0]):             # (a few rings: serially, one parallel region less)
        if tasks[t, 1] > 0:
            _cut_ring_forces(ff, cells, work, t, 0)
    gvert, gptr, gsrc = cells.gvert, cells.gptr, cells.gsrc
    for u in prange(gvert.shape[0]):
        s0 = s1 = s2 = 0.0
        for e in range(gptr[u], gptr[u + 1]):
            k = gsrc[e]
            s0 += fr[k]; s1 += fr[k + BLK]; s2 += fr[k + 2 * BLK]
        i = gvert[u]
        f[i, 0] = s0; f[i, 1] = s1; f[i, 2] = s2
    bad = -1
    for t in range(tasks.shape[0]):
        b = tbad[t]
        if b >= 0 and (bad < 0 or b < bad):
            bad = b
    return bad


@njit(cache=True, fastmath={'contract'}, error_model='numpy')
def _task_forces(xf, vf, ff, groups, ids, rings, ring_idx, ring_X0, par, lane_muscle, tasks, excl, lam, act, volume_actual,
                 iters, vol_gain, w, rs0, rs1, gv0, gv1, lq, lp, le, ll, fr, bh, bb, bgv, bro, t):
    """Task t of lane_forces_par (positions j0 .. j1 - 1 of its group) on one thread's scratch (w, rs0, rs1, gv0,
    gv1). Returns its lowest bad cell or -1."""
    gi, j0, j1 = tasks[t, 0], tasks[t, 1], tasks[t, 2]
    n, L, b0, q0, plain = groups[gi, 0], groups[gi, 1], groups[gi, 2], groups[gi, 3], groups[gi, 4] == 1
    fatvol = groups[gi, 4] == 2
    q = q0 + j0
    m_real, m, r0 = rings[q, 0], rings[q, 1], rings[q, 2]
    w[W_H * BLK:N_W * BLK] = 0.0        # no cell below the first ring (its share comes in the cut pass)
    _ring_moments(rs0, gv0, ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], m, m_real, xf, vf, ring_idx[r0:r0 + m])
    bad = -1
    for j in range(j0, j1 + 1):
        rb, rt, gb, gt = (rs0, rs1, gv0, gv1) if (j - j0) % 2 == 0 else (rs1, rs0, gv1, gv0)
        if j < j1:
            q = q0 + j + 1
            m_real, m, r0 = rings[q, 0], rings[q, 1], rings[q, 2]
            _ring_moments(rt, gt, ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], m, m_real, xf, vf, ring_idx[r0:r0 + m])
            b = b0 + j
            pb = par[b]
            at = np.uint64(b * BLK)
            bad = _cell_block(w, rb, rt, pb, n, lq, lp, le, ll, at, lam, act, lane_muscle[b], ids[b], plain, fatvol,
                              volume_actual, vol_gain, iters, bad)
        elif j1 == L:
            _last_ring_coefs(w)
        else:               # ring j1 is the next task's first: its share of it
            bh[t, :] = w[W_H * BLK:(W_H + 17) * BLK]
            break
        q = q0 + j
        m_real, m, r0 = rings[q, 0], rings[q, 1], rings[q, 2]
        if j == j0 and j0 > 0:          # the cut ring: completed in the cut pass
            bb[t, :] = w[W_RM * BLK:(W_RM + 17) * BLK]
            bgv[t, :6 * m * BLK] = gb[:6 * m * BLK]
            bro[t, :] = rb
            continue
        _ring_forces(w, gb, ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], rb, m)
        _scatter_store(ff, fr, gb, ring_idx[r0:r0 + m], excl[r0:r0 + m], r0, m_real, rings[q, 3])
    return bad


@njit(cache=True)
def _cut_ring_forces(ff, cells, work, t, tid):
    """The first ring of task t (j0 > 0): its map the share of the task below's last cell (bh[t - 1]) + the share
    of t's first cell (bb[t]), its forces into the slots' buffer."""
    w, bh, bb = work.tw[tid], work.bh[t - 1], work.bb[t]
    for r in range(17 * BLK):
        w[W_RM * BLK + r] = bh[r] + bb[r]
    gi, j0 = cells.tasks[t, 0], cells.tasks[t, 1]
    q = cells.groups[gi, 3] + j0
    m_real, m, r0 = cells.rings[q, 0], cells.rings[q, 1], cells.rings[q, 2]
    gv = work.bgv[t]
    _ring_forces(w, gv, cells.ring_X0[r0 * 3 * BLK:(r0 + m) * 3 * BLK], work.bro[t], m)
    _scatter_store(ff, work.fr, gv, cells.ring_idx[r0:r0 + m], cells.excl[r0:r0 + m], r0, m_real, cells.rings[q, 3])


@njit(cache=True)
def _scatter_store(ff, fr, gv, idx, ex, r0, n, cnt):
    """A ring block's slot forces (gv after _ring_forces): added into f (flat) where the vertex is its unit's alone
    (ex; in lane_forces' order: slot by slot, lane by lane), else stored into fr at rows r0 .. r0 + n for the gather."""
    for s in range(n):
        g, o = 6 * s * BLK, (r0 + s) * 3 * BLK
        for c in range(cnt):
            if ex[s, c]:
                i = idx[s, c]
                ff[i] += gv[g + c]; ff[i + 1] += gv[g + BLK + c]; ff[i + 2] += gv[g + 2 * BLK + c]
            else:
                fr[o + c] = gv[g + c]; fr[o + BLK + c] = gv[g + BLK + c]; fr[o + 2 * BLK + c] = gv[g + 2 * BLK + c]


@njit(cache=True)
def _load_muscles(lam, act, mus, w):
    """Per lane: the muscle's lam and activation (1 and 0 for fat or a dummy) and the muscle flag."""
    for c in range(BLK):
        m = mus[c]
        la, a, mu = 1.0, 0.0, 0.0
        if m >= 0:
            la, a, mu = lam[m], act[m], 1.0
        w[W_LAM * BLK + c] = la; w[W_ACT * BLK + c] = a; w[W_MUS * BLK + c] = mu


@njit(cache=True, inline='always')
def _slot(gv, X0, x, v, i, g, h, c, ox, oy, oz, real):
    """One vertex slot of lane c in _ring_moments' four-slot pass: its position and velocity (times real:
    0 for a padding slot) into gv rows g .. g + 5 BLK, and (d = x - o, v, Xr) for the sums."""
    px, py, pz = x[i], x[i + 1], x[i + 2]
    ux, uy, uz = v[i] * real, v[i + 1] * real, v[i + 2] * real
    gv[g + c] = px; gv[g + BLK + c] = py; gv[g + 2 * BLK + c] = pz
    gv[g + 3 * BLK + c] = ux; gv[g + 4 * BLK + c] = uy; gv[g + 5 * BLK + c] = uz
    return px - ox, py - oy, pz - oz, ux, uy, uz, X0[h + c], X0[h + BLK + c], X0[h + 2 * BLK + c]


@njit(cache=True, fastmath={'contract'}, error_model='numpy', **NOALIAS)
def _ring_moments(rs, gv, X0, m, m_real, x, v, idx):
    """Gathers the ring block's vertex positions and velocities (x, v flat (3V,), idx the slot rows) into
    gv and sums over each lane's ring in the same pass (vectorised over lanes, two or four slots per pass), in the
    ring's frame (origin: its first vertex): sum d, sum d Xr^T, sum d d^T, sum v and sum d x v. Slots from
    m_real on are padding (the first vertex again, Xr = 0: zero velocity, exact zeros in every sum).
    noalias: rs and gv must not overlap x, v, X0 or idx (x and v may be the same array: both are only read)."""
    for c in range(BLK):
        i = idx[0, c]
        rs[R_O * BLK + c] = x[i]
        rs[(R_O + 1) * BLK + c] = x[i + 1]
        rs[(R_O + 2) * BLK + c] = x[i + 2]
        for r in range(R_S, R_L + 3):
            rs[r * BLK + c] = 0.0
    for s4 in range(m // 4 if FOUR_SLOT_PASSES else 0):     # four slots per pass (see FOUR_SLOT_PASSES)
        s = 4 * s4
        g, h = 6 * s * BLK, 3 * s * BLK     # every row from one base per pass + a constant: LLVM sees they do not overlap
        r3 = 1.0 if s + 3 < m_real else 0.0          # 0: the padding slot of an odd-sized ring
        for c in range(BLK):
            ox, oy, oz = rs[R_O * BLK + c], rs[(R_O + 1) * BLK + c], rs[(R_O + 2) * BLK + c]
            dx0, dy0, dz0, ux0, uy0, uz0, rX0, rY0, rZ0 = _slot(gv, X0, x, v, idx[s, c], g, h, c, ox, oy, oz, 1.0)
            dx1, dy1, dz1, ux1, uy1, uz1, rX1, rY1, rZ1 = _slot(gv, X0, x, v, idx[s + 1, c], g + 6 * BLK, h + 3 * BLK,
                                                              c, ox, oy, oz, 1.0)
            dx2, dy2, dz2, ux2, uy2, uz2, rX2, rY2, rZ2 = _slot(gv, X0, x, v, idx[s + 2, c], g + 12 * BLK, h + 6 * BLK,
                                                              c, ox, oy, oz, 1.0)
            dx3, dy3, dz3, ux3, uy3, uz3, rX3, rY3, rZ3 = _slot(gv, X0, x, v, idx[s + 3, c], g + 18 * BLK, h + 9 * BLK,
                                                              c, ox, oy, oz, r3)
            rs[R_S * BLK + c] += (dx0 + dx1) + (dx2 + dx3)
            rs[(R_S + 1) * BLK + c] += (dy0 + dy1) + (dy2 + dy3)
            rs[(R_S + 2) * BLK + c] += (dz0 + dz1) + (dz2 + dz3)
            rs[R_A * BLK + c] += (dx0 * rX0 + dx1 * rX1) + (dx2 * rX2 + dx3 * rX3)
            rs[(R_A + 1) * BLK + c] += (dx0 * rY0 + dx1 * rY1) + (dx2 * rY2 + dx3 * rY3)
            rs[(R_A + 2) * BLK + c] += (dx0 * rZ0 + dx1 * rZ1) + (dx2 * rZ2 + dx3 * rZ3)
            rs[(R_A + 3) * BLK + c] += (dy0 * rX0 + dy1 * rX1) + (dy2 * rX2 + dy3 * rX3)
            rs[(R_A + 4) * BLK + c] += (dy0 * rY0 + dy1 * rY1) + (dy2 * rY2 + dy3 * rY3)
            rs[(R_A + 5) * BLK + c] += (dy0 * rZ0 + dy1 * rZ1) + (dy2 * rZ2 + dy3 * rZ3)
            rs[(R_A + 6) * BLK + c] += (dz0 * rX0 + dz1 * rX1) + (dz2 * rX2 + dz3 * rX3)
            rs[(R_A + 7) * BLK + c] += (dz0 * rY0 + dz1 * rY1) + (dz2 * rY2 + dz3 * rY3)
            rs[(R_A + 8) * BLK + c] += (dz0 * rZ0 + dz1 * rZ1) + (dz2 * rZ2 + dz3 * rZ3)
            rs[R_Y * BLK + c] += (dx0 * dx0 + dx1 * dx1) + (dx2 * dx2 + dx3 * dx3)
            rs[(R_Y + 1) * BLK + c] += (dy0 * dy0 + dy1 * dy1) + (dy2 * dy2 + dy3 * dy3)
            rs[(R_Y + 2) * BLK + c] += (dz0 * dz0 + dz1 * dz1) + (dz2 * dz2 + dz3 * dz3)
            rs[(R_Y + 3) * BLK + c] += (dx0 * dy0 + dx1 * dy1) + (dx2 * dy2 + dx3 * dy3)
            rs[(R_Y + 4) * BLK + c] += (dx0 * dz0 + dx1 * dz1) + (dx2 * dz2 + dx3 * dz3)
            rs[(R_Y + 5) * BLK + c] += (dy0 * dz0 + dy1 * dz1) + (dy2 * dz2 + dy3 * dz3)
            rs[R_V * BLK + c] += (ux0 + ux1) + (ux2 + ux3)
            rs[(R_V + 1) * BLK + c] += (uy0 + uy1) + (uy2 + uy3)
            rs[(R_V + 2) * BLK + c] += (uz0 + uz1) + (uz2 + uz3)
            rs[R_L * BLK + c] += ((dy0 * uz0 - dz0 * uy0) + (dy1 * uz1 - dz1 * uy1)) + ((dy2 * uz2 - dz2 * uy2) + (dy3 * uz3 - dz3 * uy3))
            rs[(R_L + 1) * BLK + c] += ((dz0 * ux0 - dx0 * uz0) + (dz1 * ux1 - dx1 * uz1)) + ((dz2 * ux2 - dx2 * uz2) + (dz3 * ux3 - dx3 * uz3))
            rs[(R_L + 2) * BLK + c] += ((dx0 * uy0 - dy0 * ux0) + (dx1 * uy1 - dy1 * ux1)) + ((dx2 * uy2 - dy2 * ux2) + (dx3 * uy3 - dy3 * ux3))
    for s2 in range(2 * (m // 4) if FOUR_SLOT_PASSES else 0, m // 2):       # two slots per pass
        g = 12 * s2 * BLK           # slots s = 2 s2 (d, X0) and s + 1 (e, E)
        h = 6 * s2 * BLK
        real1 = 1.0 if 2 * s2 + 1 < m_real else 0.0          # 0: the padding slot of an odd-sized ring
        for c in range(BLK):
            i0, i1 = idx[2 * s2, c], idx[2 * s2 + 1, c]
            px, py, pz = x[i0], x[i0 + 1], x[i0 + 2]
            qx, qy, qz = x[i1], x[i1 + 1], x[i1 + 2]
            gv[g + c] = px; gv[g + BLK + c] = py; gv[g + 2 * BLK + c] = pz
            gv[g + 6 * BLK + c] = qx; gv[g + 7 * BLK + c] = qy; gv[g + 8 * BLK + c] = qz
            ox, oy, oz = rs[R_O * BLK + c], rs[(R_O + 1) * BLK + c], rs[(R_O + 2) * BLK + c]
            dx, dy, dz = px - ox, py - oy, pz - oz
            ex, ey, ez = qx - ox, qy - oy, qz - oz
            X, Y, Z = X0[h + c], X0[h + BLK + c], X0[h + 2 * BLK + c]
            EX, EY, EZ = X0[h + 3 * BLK + c], X0[h + 4 * BLK + c], X0[h + 5 * BLK + c]
            rs[R_S * BLK + c] += dx + ex; rs[(R_S + 1) * BLK + c] += dy + ey; rs[(R_S + 2) * BLK + c] += dz + ez
            rs[R_A * BLK + c] += dx * X + ex * EX
            rs[(R_A + 1) * BLK + c] += dx * Y + ex * EY
            rs[(R_A + 2) * BLK + c] += dx * Z + ex * EZ
            rs[(R_A + 3) * BLK + c] += dy * X + ey * EX
            rs[(R_A + 4) * BLK + c] += dy * Y + ey * EY
            rs[(R_A + 5) * BLK + c] += dy * Z + ey * EZ
            rs[(R_A + 6) * BLK + c] += dz * X + ez * EX
            rs[(R_A + 7) * BLK + c] += dz * Y + ez * EY
            rs[(R_A + 8) * BLK + c] += dz * Z + ez * EZ
            rs[R_Y * BLK + c] += dx * dx + ex * ex
            rs[(R_Y + 1) * BLK + c] += dy * dy + ey * ey
            rs[(R_Y + 2) * BLK + c] += dz * dz + ez * ez
            rs[(R_Y + 3) * BLK + c] += dx * dy + ex * ey
            rs[(R_Y + 4) * BLK + c] += dx * dz + ex * ez
            rs[(R_Y + 5) * BLK + c] += dy * dz + ey * ez
            # velocities (an odd-sized ring's padding slot: zero)
            ux, uy, uz = v[i0], v[i0 + 1], v[i0 + 2]
            tx, ty, tz = v[i1] * real1, v[i1 + 1] * real1, v[i1 + 2] * real1
            gv[g + 3 * BLK + c] = ux; gv[g + 4 * BLK + c] = uy; gv[g + 5 * BLK + c] = uz
            gv[g + 9 * BLK + c] = tx; gv[g + 10 * BLK + c] = ty; gv[g + 11 * BLK + c] = tz
            rs[R_V * BLK + c] += ux + tx; rs[(R_V + 1) * BLK + c] += uy + ty; rs[(R_V + 2) * BLK + c] += uz + tz
            rs[R_L * BLK + c] += (dy * uz - dz * uy) + (ey * tz - ez * ty)
            rs[(R_L + 1) * BLK + c] += (dz * ux - dx * uz) + (ez * tx - ex * tz)
            rs[(R_L + 2) * BLK + c] += (dx * uy - dy * ux) + (ex * ty - ey * tx)


@njit(cache=True, fastmath={'contract'}, error_model='numpy', **NOALIAS)
def _combine(w, rb, rt, pb, n, lq, lp, at):
    """Per lane (vectorised): the cell's moments about its bottom ring's origin o from its bottom ring's
    sums rb and its top ring's sums rt. With the top ring's origin at o + e (e = W_DT), its vertex i at
    d_i = d'_i + e, and each ring's rest shape Xr about its own rest centroid, X0_i = Xr_i + p (p = P_PB,
    P_PT: the ring's rest centroid about the cell's; sum Xr = 0): sum d = Sb + St + nt e;
    A = Ab + Sb pb^T + At + (St + nt e) pt^T; Y = Yb + Yt + e St^T + St e^T + nt e e^T;
    sum v = Vb + Vt; sum d x v = Lb + Lt + e x Vt; the bottom ring's sum d = Sb. A dummy lane gets A = 0
    (its rotation then does not run; a product, not a select: LLVM turns selects into masked loads).
    Also loads the block's rotation warm start and pressure from the lane-ordered state (lq, lp at lane at)."""
    nt = float(n - n // 2)
    a4 = np.uint64(4) * at
    for c in range(BLK):
        u = np.uint64(c)
        w[W_Q * BLK + c] = lq[a4 + u]
        w[(W_Q + 1) * BLK + c] = lq[a4 + np.uint64(BLK) + u]
        w[(W_Q + 2) * BLK + c] = lq[a4 + np.uint64(2 * BLK) + u]
        w[(W_Q + 3) * BLK + c] = lq[a4 + np.uint64(3 * BLK) + u]
        w[W_PRES * BLK + c] = lp[at + u]
    for c in range(BLK):
        on = pb[P_ON * BLK + c]
        ox, oy, oz = rb[R_O * BLK + c], rb[(R_O + 1) * BLK + c], rb[(R_O + 2) * BLK + c]
        ex, ey, ez = rt[R_O * BLK + c] - ox, rt[(R_O + 1) * BLK + c] - oy, rt[(R_O + 2) * BLK + c] - oz
        bx, by, bz = rb[R_S * BLK + c], rb[(R_S + 1) * BLK + c], rb[(R_S + 2) * BLK + c]
        sx, sy, sz = rt[R_S * BLK + c], rt[(R_S + 1) * BLK + c], rt[(R_S + 2) * BLK + c]
        tx, ty, tz = sx + nt * ex, sy + nt * ey, sz + nt * ez
        w[W_O * BLK + c] = ox; w[(W_O + 1) * BLK + c] = oy; w[(W_O + 2) * BLK + c] = oz
        w[W_DT * BLK + c] = ex; w[(W_DT + 1) * BLK + c] = ey; w[(W_DT + 2) * BLK + c] = ez
        w[W_U * BLK + c] = bx; w[(W_U + 1) * BLK + c] = by; w[(W_U + 2) * BLK + c] = bz
        w[W_S * BLK + c] = bx + tx; w[(W_S + 1) * BLK + c] = by + ty; w[(W_S + 2) * BLK + c] = bz + tz
        px, py, pz = pb[P_PB * BLK + c], pb[(P_PB + 1) * BLK + c], pb[(P_PB + 2) * BLK + c]
        qx, qy, qz = pb[P_PT * BLK + c], pb[(P_PT + 1) * BLK + c], pb[(P_PT + 2) * BLK + c]
        a00 = (rb[R_A * BLK + c] + bx * px) + (rt[R_A * BLK + c] + tx * qx)
        a01 = (rb[(R_A + 1) * BLK + c] + bx * py) + (rt[(R_A + 1) * BLK + c] + tx * qy)
        a02 = (rb[(R_A + 2) * BLK + c] + bx * pz) + (rt[(R_A + 2) * BLK + c] + tx * qz)
        a10 = (rb[(R_A + 3) * BLK + c] + by * px) + (rt[(R_A + 3) * BLK + c] + ty * qx)
        a11 = (rb[(R_A + 4) * BLK + c] + by * py) + (rt[(R_A + 4) * BLK + c] + ty * qy)
        a12 = (rb[(R_A + 5) * BLK + c] + by * pz) + (rt[(R_A + 5) * BLK + c] + ty * qz)
        a20 = (rb[(R_A + 6) * BLK + c] + bz * px) + (rt[(R_A + 6) * BLK + c] + tz * qx)
        a21 = (rb[(R_A + 7) * BLK + c] + bz * py) + (rt[(R_A + 7) * BLK + c] + tz * qy)
        a22 = (rb[(R_A + 8) * BLK + c] + bz * pz) + (rt[(R_A + 8) * BLK + c] + tz * qz)
        w[W_A * BLK + c] = a00 * on
        w[(W_A + 1) * BLK + c] = a01 * on
        w[(W_A + 2) * BLK + c] = a02 * on
        w[(W_A + 3) * BLK + c] = a10 * on
        w[(W_A + 4) * BLK + c] = a11 * on
        w[(W_A + 5) * BLK + c] = a12 * on
        w[(W_A + 6) * BLK + c] = a20 * on
        w[(W_A + 7) * BLK + c] = a21 * on
        w[(W_A + 8) * BLK + c] = a22 * on
        # e St^T + St e^T + nt e e^T = e (St + nt e)^T + St e^T
        w[W_Y * BLK + c] = rb[R_Y * BLK + c] + rt[R_Y * BLK + c] + (ex * tx + sx * ex)
        w[(W_Y + 1) * BLK + c] = rb[(R_Y + 1) * BLK + c] + rt[(R_Y + 1) * BLK + c] + (ey * ty + sy * ey)
        w[(W_Y + 2) * BLK + c] = rb[(R_Y + 2) * BLK + c] + rt[(R_Y + 2) * BLK + c] + (ez * tz + sz * ez)
        w[(W_Y + 3) * BLK + c] = rb[(R_Y + 3) * BLK + c] + rt[(R_Y + 3) * BLK + c] + (ex * ty + sx * ey)
        w[(W_Y + 4) * BLK + c] = rb[(R_Y + 4) * BLK + c] + rt[(R_Y + 4) * BLK + c] + (ex * tz + sx * ez)
        w[(W_Y + 5) * BLK + c] = rb[(R_Y + 5) * BLK + c] + rt[(R_Y + 5) * BLK + c] + (ey * tz + sy * ez)
        vx, vy, vz = rt[R_V * BLK + c], rt[(R_V + 1) * BLK + c], rt[(R_V + 2) * BLK + c]
        w[W_V * BLK + c] = rb[R_V * BLK + c] + vx
        w[(W_V + 1) * BLK + c] = rb[(R_V + 1) * BLK + c] + vy
        w[(W_V + 2) * BLK + c] = rb[(R_V + 2) * BLK + c] + vz
        w[W_L * BLK + c] = rb[R_L * BLK + c] + rt[R_L * BLK + c] + (ey * vz - ez * vy)
        w[(W_L + 1) * BLK + c] = rb[(R_L + 1) * BLK + c] + rt[(R_L + 1) * BLK + c] + (ez * vx - ex * vz)
        w[(W_L + 2) * BLK + c] = rb[(R_L + 2) * BLK + c] + rt[(R_L + 2) * BLK + c] + (ex * vy - ey * vx)


@njit(cache=True, inline='always')
def _times_rest_map(m00, m01, m02, m10, m11, m12, m20, m21, m22, la, sl, fx, fy, fz, mus):
    """M F for a muscle cell (F = la f f^T + sl (I - f f^T), the contracted rest shape's map; fibre f),
    M itself for fat (F = I). Inlined into the lane loops (a select, not a branch: they stay vectorised)."""
    f00 = (la - sl) * fx * fx + sl; f01 = (la - sl) * fx * fy; f02 = (la - sl) * fx * fz
    f11 = (la - sl) * fy * fy + sl; f12 = (la - sl) * fy * fz; f22 = (la - sl) * fz * fz + sl
    return (m00 * f00 + m01 * f01 + m02 * f02 if mus else m00, m00 * f01 + m01 * f11 + m02 * f12 if mus else m01,
            m00 * f02 + m01 * f12 + m02 * f22 if mus else m02, m10 * f00 + m11 * f01 + m12 * f02 if mus else m10,
            m10 * f01 + m11 * f11 + m12 * f12 if mus else m11, m10 * f02 + m11 * f12 + m12 * f22 if mus else m12,
            m20 * f00 + m21 * f01 + m22 * f02 if mus else m20, m20 * f01 + m21 * f11 + m22 * f12 if mus else m21,
            m20 * f02 + m21 * f12 + m22 * f22 if mus else m22)


@njit(cache=True, fastmath={'contract'}, error_model='numpy')
def _cell_algebra(w, pb, n, volume_actual, vol_gain, plain, fatvol=None):
    """Per lane (vectorised): the rest shape F, B = A F for the rotation, the volume term
    (force map P, energy, pressure), tr Y and the rigid velocity (vbar, w) of the damping. plain: None,
    or True for a group without muscle cells, volume or tension (pack_cells' flag): numba then compiles a
    version in which F = I and the volume term are constants, and LLVM drops the dead parts. fatvol: None, or
    True with plain True for a group without muscle or tension but with a volume term (fat cells with
    volume_stiffness_fat > 0): F = I, the volume term kept."""
    inv_n = 1.0 / n
    # the cross-section factor first, in a short loop of its own (a chain of two square roots and a
    # division: short loops let the processor overlap the chains of several lanes)
    for c in range(BLK):
        if plain is not None:      # (a group of plain cells: F = I, sl unused)
            w[W_SL * BLK + c] = 1.0
        elif volume_actual:        # current fibre stretch mu = |D f|, D f = A (Qinv f)
            gx, gy, gz = pb[P_G * BLK + c], pb[(P_G + 1) * BLK + c], pb[(P_G + 2) * BLK + c]
            ux = w[W_A * BLK + c] * gx + w[(W_A + 1) * BLK + c] * gy + w[(W_A + 2) * BLK + c] * gz
            uy = w[(W_A + 3) * BLK + c] * gx + w[(W_A + 4) * BLK + c] * gy + w[(W_A + 5) * BLK + c] * gz
            uz = w[(W_A + 6) * BLK + c] * gx + w[(W_A + 7) * BLK + c] * gy + w[(W_A + 8) * BLK + c] * gz
            w[W_SL * BLK + c] = 1.0 / math.sqrt(min(max(math.sqrt(ux * ux + uy * uy + uz * uz), 0.25), 4.0))
        else:
            w[W_SL * BLK + c] = 1.0 / math.sqrt(w[W_LAM * BLK + c])
    for c in range(BLK):
        a00, a01, a02 = w[W_A * BLK + c], w[(W_A + 1) * BLK + c], w[(W_A + 2) * BLK + c]
        a10, a11, a12 = w[(W_A + 3) * BLK + c], w[(W_A + 4) * BLK + c], w[(W_A + 5) * BLK + c]
        a20, a21, a22 = w[(W_A + 6) * BLK + c], w[(W_A + 7) * BLK + c], w[(W_A + 8) * BLK + c]
        # rest shape F = lam f f^T + s (I - f f^T) (muscle), B = A F (fat: B = A)
        mus = w[W_MUS * BLK + c] != 0.0 if plain is None else False
        la = w[W_LAM * BLK + c]
        fx, fy, fz = pb[P_F * BLK + c], pb[(P_F + 1) * BLK + c], pb[(P_F + 2) * BLK + c]
        sl = w[W_SL * BLK + c]
        b00, b01, b02, b10, b11, b12, b20, b21, b22 = _times_rest_map(a00, a01, a02, a10, a11, a12, a20, a21, a22,
                                                                      la, sl, fx, fy, fz, mus)   # B = A F
        # the rotation iteration is scale-free (B is not normalised: a square root and a division less on
        # the lane's longest chain); a zero or non-finite B keeps the warm start
        nrm2 = ((b00 * b00 + b01 * b01 + b02 * b02) + (b10 * b10 + b11 * b11 + b12 * b12)
                + (b20 * b20 + b21 * b21 + b22 * b22))
        w[W_ON * BLK + c] = 1.0 if nrm2 > 0.0 and math.isfinite(nrm2) else 0.0
        w[W_NB2 * BLK + c] = nrm2
        w[W_B * BLK + c] = b00; w[(W_B + 1) * BLK + c] = b01; w[(W_B + 2) * BLK + c] = b02
        w[(W_B + 3) * BLK + c] = b10; w[(W_B + 4) * BLK + c] = b11; w[(W_B + 5) * BLK + c] = b12
        w[(W_B + 6) * BLK + c] = b20; w[(W_B + 7) * BLK + c] = b21; w[(W_B + 8) * BLK + c] = b22
        # volume (kvol > 0): with D = A Qinv the best-fit affine deformation, P = g cof(D) Qinv and
        # g = -kvol (det D - 1) + the integral pressure; cof(D) Qinv = det(Qinv) cof(A) and
        # det D = det A det Qinv (Qinv symmetric), so D itself is never formed
        kv = pb[P_KVOL * BLK + c]
        vol = kv > 0.0 if plain is None or fatvol is not None else False
        c00 = a11 * a22 - a12 * a21; c01 = a12 * a20 - a10 * a22; c02 = a10 * a21 - a11 * a20
        c10 = a02 * a21 - a01 * a22; c11 = a00 * a22 - a02 * a20; c12 = a01 * a20 - a00 * a21
        c20 = a01 * a12 - a02 * a11; c21 = a02 * a10 - a00 * a12; c22 = a00 * a11 - a01 * a10
        dq = pb[P_DQ * BLK + c]
        det = (a00 * c00 + a01 * c01 + a02 * c02) * dq
        g = -kv * (det - 1.0)
        pres = w[W_PRES * BLK + c] + vol_gain * g if vol else w[W_PRES * BLK + c]
        w[W_PRES * BLK + c] = pres
        g = (g + pres) * dq
        # the volume term's bound (P_VCAP > 0): |grad det D|^2 = dq^2 tr(cof(A) Q cof(A)^T), the volume
        # term's stiffness relative to its rest value, beyond the bound the force scaled by bound / |grad det D|^2
        vcap = pb[P_VCAP * BLK + c]
        q00, q11, q22 = pb[P_Q * BLK + c], pb[(P_Q + 1) * BLK + c], pb[(P_Q + 2) * BLK + c]
        q01, q02, q12 = pb[(P_Q + 3) * BLK + c], pb[(P_Q + 4) * BLK + c], pb[(P_Q + 5) * BLK + c]
        gn = ((c00 * (q00 * c00 + q01 * c01 + q02 * c02) + c01 * (q01 * c00 + q11 * c01 + q12 * c02)
               + c02 * (q02 * c00 + q12 * c01 + q22 * c02))
              + (c10 * (q00 * c10 + q01 * c11 + q02 * c12) + c11 * (q01 * c10 + q11 * c11 + q12 * c12)
                 + c12 * (q02 * c10 + q12 * c11 + q22 * c12))
              + (c20 * (q00 * c20 + q01 * c21 + q02 * c22) + c21 * (q01 * c20 + q11 * c21 + q12 * c22)
                 + c22 * (q02 * c20 + q12 * c21 + q22 * c22))) * (dq * dq)
        g = g * (vcap / gn) if vcap > 0.0 and gn > vcap else g
        w[W_EV * BLK + c] = 0.5 * kv * ((det - 1.0) * (det - 1.0)) if vol else 0.0
        w[W_P * BLK + c] = g * c00 if vol else 0.0
        w[(W_P + 1) * BLK + c] = g * c01 if vol else 0.0
        w[(W_P + 2) * BLK + c] = g * c02 if vol else 0.0
        w[(W_P + 3) * BLK + c] = g * c10 if vol else 0.0
        w[(W_P + 4) * BLK + c] = g * c11 if vol else 0.0
        w[(W_P + 5) * BLK + c] = g * c12 if vol else 0.0
        w[(W_P + 6) * BLK + c] = g * c20 if vol else 0.0
        w[(W_P + 7) * BLK + c] = g * c21 if vol else 0.0
        w[(W_P + 8) * BLK + c] = g * c22 if vol else 0.0
        # second moments of the current vertices about the centroid: Y = sum r r^T
        mx, my, mz = w[W_S * BLK + c] * inv_n, w[(W_S + 1) * BLK + c] * inv_n, w[(W_S + 2) * BLK + c] * inv_n
        qxx = w[W_Y * BLK + c] - n * mx * mx; qyy = w[(W_Y + 1) * BLK + c] - n * my * my
        qzz = w[(W_Y + 2) * BLK + c] - n * mz * mz; qxy = w[(W_Y + 3) * BLK + c] - n * mx * my
        qxz = w[(W_Y + 4) * BLK + c] - n * mx * mz; qyz = w[(W_Y + 5) * BLK + c] - n * my * mz
        tr = qxx + qyy + qzz
        w[W_TRY * BLK + c] = tr
        # damping (b > 0): rigid velocity of the cell, mean vbar + angular w = I^-1 L about the centroid
        damp = pb[P_B * BLK + c] > 0.0
        vx, vy, vz = w[W_V * BLK + c] * inv_n, w[(W_V + 1) * BLK + c] * inv_n, w[(W_V + 2) * BLK + c] * inv_n
        Lx = w[W_L * BLK + c] - n * (my * vz - mz * vy)
        Ly = w[(W_L + 1) * BLK + c] - n * (mz * vx - mx * vz)
        Lz = w[(W_L + 2) * BLK + c] - n * (mx * vy - my * vx)
        eps = 1e-9 * tr + 1e-300
        I00 = tr - qxx + eps; I11 = tr - qyy + eps; I22 = tr - qzz + eps
        I01 = -qxy; I02 = -qxz; I12 = -qyz
        e00 = I11 * I22 - I12 * I12; e01 = I02 * I12 - I01 * I22; e02 = I01 * I12 - I02 * I11
        e11 = I00 * I22 - I02 * I02; e12 = I01 * I02 - I00 * I12; e22 = I00 * I11 - I01 * I01
        det = I00 * e00 + I01 * e01 + I02 * e02
        rot = damp and det > 0.0 and math.isfinite(det)
        idet = 1.0 / det
        w[W_W * BLK + c] = (e00 * Lx + e01 * Ly + e02 * Lz) * idet if rot else 0.0
        w[(W_W + 1) * BLK + c] = (e01 * Lx + e11 * Ly + e12 * Lz) * idet if rot else 0.0
        w[(W_W + 2) * BLK + c] = (e02 * Lx + e12 * Ly + e22 * Lz) * idet if rot else 0.0
        w[W_V * BLK + c] = vx if damp else 0.0
        w[(W_V + 1) * BLK + c] = vy if damp else 0.0
        w[(W_V + 2) * BLK + c] = vz if damp else 0.0


@njit(cache=True, fastmath={'contract'}, error_model='numpy')
def _rotations(w, iters):
    """Rotational part R of each lane's B (Mueller et al. 2016, "A Robust Method to Extract the
    Rotational Part of Deformations"), vectorised over lanes: the quaternion rows (x, y, z, w) are
    warm-started and updated; always a rotation, robust for flat and inverted B.

    Each iteration maximises tr(R^T B) over a rotation increment omega: gradient g = sum_j r_j x b_j
    (r_j, b_j the columns of R, B). Mueller's step is g / |tr(B R^T)|; here the Newton step
    H^-1 g with H = tr(N) I - sym(N), N = B R^T, is used whenever H is positive definite (it is near
    the solution unless B is degenerate), which converges quadratically also for thin, anisotropic
    cells where Mueller's step crawls; otherwise Mueller's step (regularised: g / (|tr| + 1e-9 |B|)).
    Both are scale-free, so B is used as it is (not normalised). Steps are capped at 1 rad. A lane
    stops after iters iterations, when its correction is below 1e-12 rad (not applied), or after a
    Newton correction below NEWTON_DONE (its successor would be of order NEWTON_DONE^2: warm-started,
    one iteration per step is then the usual case); the loop ends when every lane has stopped."""
    for _ in range(iters):
        running = 0
        for c in range(BLK):
            x, y, z, qw = w[W_Q * BLK + c], w[(W_Q + 1) * BLK + c], w[(W_Q + 2) * BLK + c], w[(W_Q + 3) * BLK + c]
            r00 = 1 - 2 * (y * y + z * z); r01 = 2 * (x * y - z * qw); r02 = 2 * (x * z + y * qw)
            r10 = 2 * (x * y + z * qw); r11 = 1 - 2 * (x * x + z * z); r12 = 2 * (y * z - x * qw)
            r20 = 2 * (x * z - y * qw); r21 = 2 * (y * z + x * qw); r22 = 1 - 2 * (x * x + y * y)
            b00, b01, b02 = w[W_B * BLK + c], w[(W_B + 1) * BLK + c], w[(W_B + 2) * BLK + c]
            b10, b11, b12 = w[(W_B + 3) * BLK + c], w[(W_B + 4) * BLK + c], w[(W_B + 5) * BLK + c]
            b20, b21, b22 = w[(W_B + 6) * BLK + c], w[(W_B + 7) * BLK + c], w[(W_B + 8) * BLK + c]
            # g = sum_j R[:, j] x B[:, j];  N = B R^T = sum_j b_j r_j^T (symmetric part)
            gx = (r10 * b20 - r20 * b10) + (r11 * b21 - r21 * b11) + (r12 * b22 - r22 * b12)
            gy = (r20 * b00 - r00 * b20) + (r21 * b01 - r01 * b21) + (r22 * b02 - r02 * b22)
            gz = (r00 * b10 - r10 * b00) + (r01 * b11 - r11 * b01) + (r02 * b12 - r12 * b02)
            n00 = b00 * r00 + b01 * r01 + b02 * r02
            n11 = b10 * r10 + b11 * r11 + b12 * r12
            n22 = b20 * r20 + b21 * r21 + b22 * r22
            n01 = 0.5 * (b00 * r10 + b10 * r00) + 0.5 * (b01 * r11 + b11 * r01) + 0.5 * (b02 * r12 + b12 * r02)
            n02 = 0.5 * (b00 * r20 + b20 * r00) + 0.5 * (b01 * r21 + b21 * r01) + 0.5 * (b02 * r22 + b22 * r02)
            n12 = 0.5 * (b10 * r20 + b20 * r10) + 0.5 * (b11 * r21 + b21 * r11) + 0.5 * (b12 * r22 + b22 * r12)
            tr = n00 + n11 + n22
            h00, h11, h22 = tr - n00, tr - n11, tr - n22
            h01, h02, h12 = -n01, -n02, -n12
            c00 = h11 * h22 - h12 * h12; c01 = h02 * h12 - h01 * h22; c02 = h01 * h12 - h02 * h11
            c11 = h00 * h22 - h02 * h02; c12 = h01 * h02 - h00 * h12; c22 = h00 * h11 - h01 * h01
            det = h00 * c00 + h01 * c01 + h02 * c02
            newton = h00 > 0.0 and c22 > 0.0 and det > 1e-9 * tr * tr * tr   # Sylvester: H positive definite
            eps = 1e-9 * math.sqrt(w[W_NB2 * BLK + c])               # (B is not normalised)
            sc = 1.0 / (det if newton else abs(tr) + eps)           # Newton: H^-1 = cof(H) / det; Mueller: 1/|tr|
            ox = (c00 * gx + c01 * gy + c02 * gz if newton else gx) * sc
            oy = (c01 * gx + c11 * gy + c12 * gz if newton else gy) * sc
            oz = (c02 * gx + c12 * gy + c22 * gz if newton else gz) * sc
            w[W_OM * BLK + c] = ox; w[(W_OM + 1) * BLK + c] = oy; w[(W_OM + 2) * BLK + c] = oz
            w[W_NT * BLK + c] = 1.0 if newton else 0.0
        # the update in a loop of its own (two short chains overlap across lanes better than one long one)
        for c in range(BLK):
            x, y, z, qw = w[W_Q * BLK + c], w[(W_Q + 1) * BLK + c], w[(W_Q + 2) * BLK + c], w[(W_Q + 3) * BLK + c]
            ox, oy, oz = w[W_OM * BLK + c], w[(W_OM + 1) * BLK + c], w[(W_OM + 2) * BLK + c]
            newton = w[W_NT * BLK + c] != 0.0
            # dq = (omega/2, 1) normalised: a rotation by 2 atan(w/2) = w - w^3/12 + ... about omega (no
            # sin/cos; the cubic error is removed by the next iteration); q = dq * q, omega capped at 1 rad.
            # |dq * q| = |dq| |q| gives the normalisation without waiting for the product (a shorter chain).
            om2 = ox * ox + oy * oy + oz * oz
            move = w[W_ON * BLK + c] != 0.0 and not om2 < 1e-24
            big = om2 > 1.0
            cap = 0.5 / math.sqrt(om2) if big else 0.5
            om2 = 1.0 if big else om2
            s = 1.0 / math.sqrt((x * x + y * y + z * z + qw * qw) * (1.0 + 0.25 * om2))
            px = ox * qw + oy * z - oz * y
            py = -ox * z + oy * qw + oz * x
            pz = ox * y - oy * x + oz * qw
            pw = -ox * x - oy * y - oz * z
            nx, ny, nz, nw = x + cap * px, y + cap * py, z + cap * pz, qw + cap * pw
            w[W_Q * BLK + c] = nx * s if move else x
            w[(W_Q + 1) * BLK + c] = ny * s if move else y
            w[(W_Q + 2) * BLK + c] = nz * s if move else z
            w[(W_Q + 3) * BLK + c] = nw * s if move else qw
            on = move and not (newton and om2 < NEWTON_DONE * NEWTON_DONE)   # quadratic convergence: the next ~om^2
            w[W_ON * BLK + c] = 1.0 if on else 0.0
            running += 1 if on else 0
        if running == 0:
            break


@njit(cache=True, fastmath={'contract'}, error_model='numpy')
def _force_maps(w, pb, n, plain):
    """Per lane (vectorised): T = R F, the elastic energy, the active tension, and the coefficients
    of the affine force map of the lane's vertices; flags a non-finite or absurd result. plain: as in
    _cell_algebra (no muscle: T = R, no tension)."""
    inv_n = 1.0 / n
    half = n // 2
    odd = float(n - 2 * half)
    for c in range(BLK):
        x, y, z, qw = w[W_Q * BLK + c], w[(W_Q + 1) * BLK + c], w[(W_Q + 2) * BLK + c], w[(W_Q + 3) * BLK + c]
        r00 = 1 - 2 * (y * y + z * z); r01 = 2 * (x * y - z * qw); r02 = 2 * (x * z + y * qw)
        r10 = 2 * (x * y + z * qw); r11 = 1 - 2 * (x * x + z * z); r12 = 2 * (y * z - x * qw)
        r20 = 2 * (x * z - y * qw); r21 = 2 * (y * z + x * qw); r22 = 1 - 2 * (x * x + y * y)
        mus = w[W_MUS * BLK + c] != 0.0 if plain is None else False
        la, sl = w[W_LAM * BLK + c], w[W_SL * BLK + c]
        fx, fy, fz = pb[P_F * BLK + c], pb[(P_F + 1) * BLK + c], pb[(P_F + 2) * BLK + c]
        # T = R F (muscle), R (fat): the goal positions are c + T X0_i
        t00, t01, t02, t10, t11, t12, t20, t21, t22 = _times_rest_map(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                                                      la, sl, fx, fy, fz, mus)
        # elastic energy from the moments (R orthogonal, F symmetric, sum X0 = 0):
        # sum |T X0_i - r_i|^2 = tr(F^2 Q) - 2 tr(T^T A) + tr(Y), Q = sum X0 X0^T (q_tr = tr Q, q_ff = f^T Q f)
        fqf, qtr = pb[P_QFF * BLK + c], pb[P_QTR * BLK + c]
        tf2q = la * la * fqf + sl * sl * (qtr - fqf) if mus else qtr
        tta = ((t00 * w[W_A * BLK + c] + t01 * w[(W_A + 1) * BLK + c] + t02 * w[(W_A + 2) * BLK + c])
               + (t10 * w[(W_A + 3) * BLK + c] + t11 * w[(W_A + 4) * BLK + c] + t12 * w[(W_A + 5) * BLK + c])
               + (t20 * w[(W_A + 6) * BLK + c] + t21 * w[(W_A + 7) * BLK + c] + t22 * w[(W_A + 8) * BLK + c]))
        e = max(tf2q - 2.0 * tta + w[W_TRY * BLK + c], 0.0)
        # active axial tension between the ring centroids: u = (sum top x - sum bottom x) / half, the top ring
        # the last n - half vertices (the origin o cancels but for an odd-sized cell's extra top vertex)
        sx, sy, sz = w[W_S * BLK + c], w[(W_S + 1) * BLK + c], w[(W_S + 2) * BLK + c]
        ux = (sx - 2.0 * w[W_U * BLK + c] + odd * w[W_O * BLK + c]) / half
        uy = (sy - 2.0 * w[(W_U + 1) * BLK + c] + odd * w[(W_O + 1) * BLK + c]) / half
        uz = (sz - 2.0 * w[(W_U + 2) * BLK + c] + odd * w[(W_O + 2) * BLK + c]) / half
        a, kact = w[W_ACT * BLK + c], pb[P_KACT * BLK + c]
        ln = math.sqrt(ux * ux + uy * uy + uz * uz)
        w[W_LN * BLK + c] = ln
        stretch = ln - la * pb[P_LEN * BLK + c]
        pull = mus and kact > 0.0 and a > 0.0 and stretch > 0.0 and ln > 0.0
        ka = a * kact * 0.25 * n
        tt = ka * stretch * 2.0 / (n * ln)          # per-vertex force / l, along u
        w[W_TA * BLK + c] = tt * ux if pull else 0.0
        w[(W_TA + 1) * BLK + c] = tt * uy if pull else 0.0
        w[(W_TA + 2) * BLK + c] = tt * uz if pull else 0.0
        ea = 0.5 * ka * stretch * stretch if pull else 0.0
        # force on vertex i, elastic + volume + damping in one affine map of (X0_i, r_i, v_i):
        # k (T X0 - r) + P X0 - b (v - vbar - w x r) = (k T + P) X0 + (b [w]x - k I) r - b v + b vbar
        k, b = pb[P_K * BLK + c], pb[P_B * BLK + c]
        m00 = k * t00 + w[W_P * BLK + c]
        w[W_M * BLK + c] = m00
        w[(W_M + 1) * BLK + c] = k * t01 + w[(W_P + 1) * BLK + c]
        w[(W_M + 2) * BLK + c] = k * t02 + w[(W_P + 2) * BLK + c]
        w[(W_M + 3) * BLK + c] = k * t10 + w[(W_P + 3) * BLK + c]
        w[(W_M + 4) * BLK + c] = k * t11 + w[(W_P + 4) * BLK + c]
        w[(W_M + 5) * BLK + c] = k * t12 + w[(W_P + 5) * BLK + c]
        w[(W_M + 6) * BLK + c] = k * t20 + w[(W_P + 6) * BLK + c]
        w[(W_M + 7) * BLK + c] = k * t21 + w[(W_P + 7) * BLK + c]
        w[(W_M + 8) * BLK + c] = k * t22 + w[(W_P + 8) * BLK + c]
        bwx, bwy, bwz = b * w[W_W * BLK + c], b * w[(W_W + 1) * BLK + c], b * w[(W_W + 2) * BLK + c]
        w[W_BW * BLK + c] = bwx; w[(W_BW + 1) * BLK + c] = bwy; w[(W_BW + 2) * BLK + c] = bwz
        # f0 = m X0 - k r - b v + b (vbar + w x (x_i - c)) with r = x_i - c: the constant part uses the
        # local origin o: w x (x_i - c) = w x d_i - w x mm (d_i = x_i - o, mm = c - o)
        mx, my, mz = sx * inv_n, sy * inv_n, sz * inv_n
        cx0 = b * w[W_V * BLK + c] - (bwy * mz - bwz * my) + k * mx
        w[W_C * BLK + c] = cx0
        w[(W_C + 1) * BLK + c] = b * w[(W_V + 1) * BLK + c] - (bwz * mx - bwx * mz) + k * my
        w[(W_C + 2) * BLK + c] = b * w[(W_V + 2) * BLK + c] - (bwx * my - bwy * mx) + k * mz
        ev = w[W_EV * BLK + c]
        w[W_E * BLK + c] = 0.5 * k * e + ev + ea
        ok = e * k * k < FORCE_BOUND and ev < FORCE_BOUND and abs(m00) + abs(cx0) < FORCE_BOUND   # False for NaN
        w[W_BAD * BLK + c] = 0.0 if ok else 1.0


@njit(cache=True, fastmath={'contract'}, error_model='numpy', **NOALIAS)
def _ring_coefs(w, pb, lq, lp, le, ll, at):
    """Per lane (vectorised): the force map of the cell's bottom ring, complete now (the share of the cell
    below it, W_H, plus this cell's), and this cell's share of its top ring's map (into W_H). In a ring's
    frame (d_i = x_i - o_ring, Xr_i about the ring's rest centroid) the cell's map f_i = M X0_i - k d_i +
    bw x d_i + C - b v_i (+ the tension: + on the bottom ring, - on the top ring) reads M Xr_i - k d_i +
    bw x d_i + C' - b v_i, with C' = C + M pb + ta on the bottom ring and C' = C + M pt - k e + bw x e - ta
    on the top ring (o_top = o + e). A dummy lane adds nothing (its shares times P_ON = 0). Also stores the
    block's rotation, pressure, energy and axial length into the lane-ordered state (lq, lp, le, ll at lane at)."""
    a4 = np.uint64(4) * at
    for c in range(BLK):
        u = np.uint64(c)
        lq[a4 + u] = w[W_Q * BLK + c]
        lq[a4 + np.uint64(BLK) + u] = w[(W_Q + 1) * BLK + c]
        lq[a4 + np.uint64(2 * BLK) + u] = w[(W_Q + 2) * BLK + c]
        lq[a4 + np.uint64(3 * BLK) + u] = w[(W_Q + 3) * BLK + c]
        lp[at + u] = w[W_PRES * BLK + c]
        le[at + u] = w[W_E * BLK + c]
        ll[at + u] = w[W_LN * BLK + c]
    for c in range(BLK):
        on = pb[P_ON * BLK + c]
        k, b = pb[P_K * BLK + c], pb[P_B * BLK + c]
        m00, m01, m02 = w[W_M * BLK + c], w[(W_M + 1) * BLK + c], w[(W_M + 2) * BLK + c]
        m10, m11, m12 = w[(W_M + 3) * BLK + c], w[(W_M + 4) * BLK + c], w[(W_M + 5) * BLK + c]
        m20, m21, m22 = w[(W_M + 6) * BLK + c], w[(W_M + 7) * BLK + c], w[(W_M + 8) * BLK + c]
        bwx, bwy, bwz = w[W_BW * BLK + c], w[(W_BW + 1) * BLK + c], w[(W_BW + 2) * BLK + c]
        cx, cy, cz = w[W_C * BLK + c], w[(W_C + 1) * BLK + c], w[(W_C + 2) * BLK + c]
        tax, tay, taz = w[W_TA * BLK + c], w[(W_TA + 1) * BLK + c], w[(W_TA + 2) * BLK + c]
        px, py, pz = pb[P_PB * BLK + c], pb[(P_PB + 1) * BLK + c], pb[(P_PB + 2) * BLK + c]
        qx, qy, qz = pb[P_PT * BLK + c], pb[(P_PT + 1) * BLK + c], pb[(P_PT + 2) * BLK + c]
        ex, ey, ez = w[W_DT * BLK + c], w[(W_DT + 1) * BLK + c], w[(W_DT + 2) * BLK + c]
        # the bottom ring: the share of the cell below + this cell's
        w[W_RM * BLK + c] = w[W_H * BLK + c] + m00 * on
        w[(W_RM + 1) * BLK + c] = w[(W_H + 1) * BLK + c] + m01 * on
        w[(W_RM + 2) * BLK + c] = w[(W_H + 2) * BLK + c] + m02 * on
        w[(W_RM + 3) * BLK + c] = w[(W_H + 3) * BLK + c] + m10 * on
        w[(W_RM + 4) * BLK + c] = w[(W_H + 4) * BLK + c] + m11 * on
        w[(W_RM + 5) * BLK + c] = w[(W_H + 5) * BLK + c] + m12 * on
        w[(W_RM + 6) * BLK + c] = w[(W_H + 6) * BLK + c] + m20 * on
        w[(W_RM + 7) * BLK + c] = w[(W_H + 7) * BLK + c] + m21 * on
        w[(W_RM + 8) * BLK + c] = w[(W_H + 8) * BLK + c] + m22 * on
        w[W_RC * BLK + c] = w[(W_H + 9) * BLK + c] + ((cx + (m00 * px + m01 * py + m02 * pz)) + tax) * on
        w[(W_RC + 1) * BLK + c] = w[(W_H + 10) * BLK + c] + ((cy + (m10 * px + m11 * py + m12 * pz)) + tay) * on
        w[(W_RC + 2) * BLK + c] = w[(W_H + 11) * BLK + c] + ((cz + (m20 * px + m21 * py + m22 * pz)) + taz) * on
        w[W_RBW * BLK + c] = w[(W_H + 12) * BLK + c] + bwx * on
        w[(W_RBW + 1) * BLK + c] = w[(W_H + 13) * BLK + c] + bwy * on
        w[(W_RBW + 2) * BLK + c] = w[(W_H + 14) * BLK + c] + bwz * on
        w[W_RK * BLK + c] = w[(W_H + 15) * BLK + c] + k * on
        w[W_RB * BLK + c] = w[(W_H + 16) * BLK + c] + b * on
        # this cell's share of its top ring
        w[W_H * BLK + c] = m00 * on
        w[(W_H + 1) * BLK + c] = m01 * on
        w[(W_H + 2) * BLK + c] = m02 * on
        w[(W_H + 3) * BLK + c] = m10 * on
        w[(W_H + 4) * BLK + c] = m11 * on
        w[(W_H + 5) * BLK + c] = m12 * on
        w[(W_H + 6) * BLK + c] = m20 * on
        w[(W_H + 7) * BLK + c] = m21 * on
        w[(W_H + 8) * BLK + c] = m22 * on
        w[(W_H + 9) * BLK + c] = (((cx + (m00 * qx + m01 * qy + m02 * qz)) - k * ex + (bwy * ez - bwz * ey)) - tax) * on
        w[(W_H + 10) * BLK + c] = (((cy + (m10 * qx + m11 * qy + m12 * qz)) - k * ey + (bwz * ex - bwx * ez)) - tay) * on
        w[(W_H + 11) * BLK + c] = (((cz + (m20 * qx + m21 * qy + m22 * qz)) - k * ez + (bwx * ey - bwy * ex)) - taz) * on
        w[(W_H + 12) * BLK + c] = bwx * on
        w[(W_H + 13) * BLK + c] = bwy * on
        w[(W_H + 14) * BLK + c] = bwz * on
        w[(W_H + 15) * BLK + c] = k * on
        w[(W_H + 16) * BLK + c] = b * on


@njit(cache=True)
def _last_ring_coefs(w):
    """A group's last ring block: its map is the share of the cells below it only."""
    for r in range(17):
        for c in range(BLK):
            w[(W_RM + r) * BLK + c] = w[(W_H + r) * BLK + c]


@njit(cache=True, fastmath={'contract'}, error_model='numpy')
def _ring_forces(w, gv, X0, ro, m):
    """The force of every vertex slot of the ring block (vectorised over lanes, two slots per pass), in
    place of its gathered position: f_i = M Xr_i - k d_i + bw x d_i + C - b v_i with the ring's map
    (W_R* rows) and d_i = x_i - o (o: the ring's origin, in its sums ro)."""
    for s2 in range(m // 2):
        g = 12 * s2 * BLK
        h = 6 * s2 * BLK
        for c in range(BLK):
            k, b = w[W_RK * BLK + c], w[W_RB * BLK + c]
            ox, oy, oz = ro[R_O * BLK + c], ro[(R_O + 1) * BLK + c], ro[(R_O + 2) * BLK + c]
            m00, m01, m02 = w[W_RM * BLK + c], w[(W_RM + 1) * BLK + c], w[(W_RM + 2) * BLK + c]
            m10, m11, m12 = w[(W_RM + 3) * BLK + c], w[(W_RM + 4) * BLK + c], w[(W_RM + 5) * BLK + c]
            m20, m21, m22 = w[(W_RM + 6) * BLK + c], w[(W_RM + 7) * BLK + c], w[(W_RM + 8) * BLK + c]
            bwx, bwy, bwz = w[W_RBW * BLK + c], w[(W_RBW + 1) * BLK + c], w[(W_RBW + 2) * BLK + c]
            cx0, cy0, cz0 = w[W_RC * BLK + c], w[(W_RC + 1) * BLK + c], w[(W_RC + 2) * BLK + c]
            # slot 2 s2 (d, X0 = X, Y, Z)
            X, Y, Z = X0[h + c], X0[h + BLK + c], X0[h + 2 * BLK + c]
            dx, dy, dz = gv[g + c] - ox, gv[g + BLK + c] - oy, gv[g + 2 * BLK + c] - oz
            fx = m00 * X + m01 * Y + m02 * Z - k * dx + (bwy * dz - bwz * dy) + cx0
            fy = m10 * X + m11 * Y + m12 * Z - k * dy + (bwz * dx - bwx * dz) + cy0
            fz = m20 * X + m21 * Y + m22 * Z - k * dz + (bwx * dy - bwy * dx) + cz0
            gv[g + c] = fx - b * gv[g + 3 * BLK + c]
            gv[g + BLK + c] = fy - b * gv[g + 4 * BLK + c]
            gv[g + 2 * BLK + c] = fz - b * gv[g + 5 * BLK + c]
            # slot 2 s2 + 1 (e, X0 = U, V, W)
            U, V, W = X0[h + 3 * BLK + c], X0[h + 4 * BLK + c], X0[h + 5 * BLK + c]
            ex, ey, ez = gv[g + 6 * BLK + c] - ox, gv[g + 7 * BLK + c] - oy, gv[g + 8 * BLK + c] - oz
            fx = m00 * U + m01 * V + m02 * W - k * ex + (bwy * ez - bwz * ey) + cx0
            fy = m10 * U + m11 * V + m12 * W - k * ey + (bwz * ex - bwx * ez) + cy0
            fz = m20 * U + m21 * V + m22 * W - k * ez + (bwx * ey - bwy * ex) + cz0
            gv[g + 6 * BLK + c] = fx - b * gv[g + 9 * BLK + c]
            gv[g + 7 * BLK + c] = fy - b * gv[g + 10 * BLK + c]
            gv[g + 8 * BLK + c] = fz - b * gv[g + 11 * BLK + c]
