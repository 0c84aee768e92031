"""The volume energy on each cell's enclosed volume (Params.volume_measure 'enclosed'; docs/solver.md "Volume"):
E_c = 1/2 kvol_c (V_c / V0_c - 1)^2, V_c the signed volume of the cell's closed surface as core.geometry.prism_volumes
defines it (each ring cap a fan about its centroid, each side quad four triangles about its centroid), its force the
exact gradient -kvol (V/V0 - 1) / V0 dV/dx_i, scaled by cap / |grad (V/V0)|^2 where a bound cap is given and exceeded
(SimModel.volume_cap: the volume term's stiffness along its gradient held within the integrator's budget, as the
affine term's in the cell kernel; docs/solver.md "The volume term's bound"). A prism deformed unevenly (half its
vertices bound, the other half moved) keeps the determinant of its best-fit affine map but not its volume; this
energy holds the volume itself.
Compiled with SIMD across cells as the cell kernel (cells.py): pack_enclosed lays the cells out in blocks of BLK cells
of one size (lanes), enclosed_lanes computes a block's volumes and gradients lane by lane (the readable form of the
same sums is reference.enclosed_forces).
Thin cells (tendons, whose rings are ~5-mm discs: rest ring radius below THIN_RADIUS) keep the affine measure: held on
their enclosed volume, the semitendinosus' tendon cells behind the knee, their rings splayed by the fold and sheath
projections, and the soleus' above the calcaneus drove runs to diverge (docs/solver.md "What the volume energy holds")."""
from __future__ import annotations

import collections

import numpy as np
from numba import njit

from tissue_sim.core.solver.cells import BLK as L, NOALIAS


THIN_RADIUS = 6e-3      # [m] cells whose rest bottom ring's mean radius is below this keep the affine measure (tendons)


def ring_radii(rest, off, cv) -> np.ndarray:
    """(C,) [m] the mean distance of each cell's bottom-ring vertices (the first half of its vertices) from their centroid."""
    out = np.zeros(len(off) - 1)
    for c in range(len(off) - 1):
        ring = rest[cv[off[c]:off[c] + (off[c + 1] - off[c]) // 2]]
        out[c] = np.linalg.norm(ring - ring.mean(0), axis=1).mean()
    return out


Enclosed = collections.namedtuple('Enclosed', 'size start cell s6 v0 k cap idx')
Enclosed.__doc__ = """The enclosed-volume cells in blocks of L (= cells.BLK) cells of one vertex count (pack_enclosed): per
block size (its cells' vertex count) and start (its first entry in idx); per lane (block * L + lane) cell (-1: a dummy
lane, a copy of the block's first cell with k = 0), s6 = sign / 6, v0 the rest volume [m^3], k the stiffness [J], cap
the bound on |grad (V/V0)|^2 [1/m^2] (0: none);
idx[start + slot * L + lane] = 3 x the vertex of that slot (flat x)."""


def pack_enclosed(off, cv, sign, rest_volume, k, cap=None) -> Enclosed:
    """The layout enclosed_lanes reads for the cells with k > 0 (cells of off/cv, their signs, rest volumes,
    stiffnesses and bounds on |grad (V/V0)|^2, None: none), grouped by vertex count in blocks of L lanes."""
    sizes = np.diff(off)
    on = np.flatnonzero(np.asarray(k) > 0)
    size, start, cell, idx = [], [], [], []
    at = 0
    for s in np.unique(sizes[on]):
        cs = on[sizes[on] == s]
        for b in range(0, cs.size, L):
            lane = np.concatenate([cs[b:b + L], np.full(L - min(L, cs.size - b), -1)])
            src = np.where(lane >= 0, lane, lane[0])
            blk = np.asarray(cv)[np.asarray(off)[src][None, :] + np.arange(s)[:, None]]      # (slot, lane)
            size.append(s); start.append(at); cell.append(lane); idx.append(3 * blk.reshape(-1)); at += blk.size
    cell = np.concatenate(cell).astype(np.int64) if cell else np.zeros(0, np.int64)
    ok = cell >= 0
    src = np.where(ok, cell, 0)
    pick = (lambda a, pad: np.where(ok, np.asarray(a, np.float64)[src], pad)) if cell.size else (lambda a, pad: np.zeros(0))
    return Enclosed(np.array(size, np.int64), np.array(start, np.int64), cell, pick(sign, 1.0) / 6.0,
                    pick(rest_volume, 1.0), pick(k, 0.0), pick(np.zeros(len(off) - 1) if cap is None else cap, 0.0),
                    np.concatenate(idx).astype(np.int64) if idx else np.zeros(0, np.int64))


def enclosed_work(enc: Enclosed):
    """enclosed_lanes' scratch (P, GB, GT, T) for the layout enc: a block's gathered positions and its bottom and top
    rings' volume gradients (slot * 3 + axis) * L + lane, and its per-lane rows (T_*)."""
    m = int(enc.size.max(initial=2))
    return np.zeros(m * 3 * L), np.zeros(m // 2 * 3 * L), np.zeros(m // 2 * 3 * L), np.zeros(N_T * L)


def enclosed_forces(x, f, off, cv, sign, v0, kvol, energy, cap=None):
    """f += -kvol (V/V0 - 1) / V0 dV/dx for every cell with kvol > 0 (bounded by cap, None: none), energy[c] = 1/2 kvol
    (V/V0 - 1)^2 (0 for the others): enclosed_lanes on pack_enclosed's layout, made for this call (the solver packs once
    per model)."""
    enc = pack_enclosed(off, cv, sign, v0, kvol, cap)
    energy[:] = 0.0
    if enc.size.size:
        enclosed_lanes(x, f, *enc, *enclosed_work(enc), energy)


# rows of enclosed_lanes' per-lane buffer T (T[row * L + lane])
T_V = 0         # the cell's volume V [m^3]
T_S6 = 1        # sign / 6
T_Z = 2         # a cap's centroid (3)
T_S = 5         # a cap's sum of v_j x v_j+1 (3)
T_W = 8         # the cap's weight (-s6 bottom, +s6 top)
T_F = 9         # -k (V/V0 - 1) / V0 (x the bound's scale): the factor of the gradient in the force
T_CB = 10       # the previous side quad's share of its b vertex (3), carried to the next bottom-ring vertex
T_CC = 13       # and of its c vertex (3), to the next top-ring vertex
T_G2 = 16       # |dV/dx|^2 summed over the cell's vertices
N_T = 17

@njit(cache=True, error_model='numpy', **NOALIAS)
def enclosed_lanes(x, f, size, start, cell, s6v, v0, kv, capv, idx, P, GB, GT, T, energy):
    """f (V, 3) += -k (V/V0 - 1) / V0 dV/dx for the cells of the layout (size ... idx: Enclosed), times
    min(1, cap / |dV/dx / V0|^2) where cap > 0, energy[c] = 1/2 k (V/V0 - 1)^2 (cells of the layout only). V = sign x
    the prism volume of core.geometry.prism_volumes: bottom ring the first half of a cell's vertices, top the second;
    each ring cap a fan about its centroid z (sum_j z . (v_j x v_j+1) = z . S; d/dv_j = S/n + z x (v_j-1 - v_j+1)), each
    side quad (a, b, c, d) = (j, j+1, n+j+1, n+j) four triangles about its centroid q (q . X with X = (c - a) x (d - b);
    d/da = X/4 - u x q, d/dc = X/4 + u x q with u = d - b, d/db = X/4 - q x w, d/dd = X/4 + q x w with w = c - a), all
    / 6, positions about each cell's first vertex.
    Lane by lane (vectorised over the block's L cells), every buffer row at one base + a constant per loop (noalias:
    the scratch P, GB, GT, T must not overlap the other arrays). No fused multiply-add (fastmath 'contract'): with it
    the serial and the thread-parallel step, each compiled with this kernel inlined, rounded differently
    (tests/test_solver_threads.py)."""
    xf, ff = x.reshape(-1), f.reshape(-1)
    for b in range(size.shape[0]):
        m = size[b]; n = m // 2; o = start[b]
        inv_n = 1.0 / n
        for j in range(m):
            g = 3 * j * L
            for l in range(L):
                i = idx[o + j * L + l]; i0 = idx[o + l]
                P[g + l] = xf[i] - xf[i0]
                P[g + L + l] = xf[i + 1] - xf[i0 + 1]
                P[g + 2 * L + l] = xf[i + 2] - xf[i0 + 2]
        for l in range(L):
            T[T_V * L + l] = 0.0
            T[T_S6 * L + l] = s6v[b * L + l]
        for cap in range(2):
            b0 = cap * n
            G = GT if cap else GB
            ws = 1.0 if cap else -1.0
            for l in range(L):
                for r in range(T_Z, T_S + 3):
                    T[r * L + l] = 0.0
            for j in range(n):
                a = 3 * (b0 + j) * L
                bb = 3 * (b0 + j + 1 if j + 1 < n else b0) * L
                for l in range(L):
                    ax, ay, az = P[a + l], P[a + L + l], P[a + 2 * L + l]
                    bx, by, bz = P[bb + l], P[bb + L + l], P[bb + 2 * L + l]
                    T[T_Z * L + l] += ax; T[(T_Z + 1) * L + l] += ay; T[(T_Z + 2) * L + l] += az
                    T[T_S * L + l] += ay * bz - az * by
                    T[(T_S + 1) * L + l] += az * bx - ax * bz
                    T[(T_S + 2) * L + l] += ax * by - ay * bx
            for l in range(L):
                w = ws * T[T_S6 * L + l]
                zx, zy, zz = T[T_Z * L + l] * inv_n, T[(T_Z + 1) * L + l] * inv_n, T[(T_Z + 2) * L + l] * inv_n
                T[T_Z * L + l] = zx; T[(T_Z + 1) * L + l] = zy; T[(T_Z + 2) * L + l] = zz
                T[T_V * L + l] += w * (zx * T[T_S * L + l] + zy * T[(T_S + 1) * L + l] + zz * T[(T_S + 2) * L + l])
                T[T_W * L + l] = w
            for j in range(n):
                p = 3 * (b0 + j - 1 if j > 0 else b0 + n - 1) * L
                q = 3 * (b0 + j + 1 if j + 1 < n else b0) * L
                a = 3 * j * L
                for l in range(L):
                    w = T[T_W * L + l]
                    zx, zy, zz = T[T_Z * L + l], T[(T_Z + 1) * L + l], T[(T_Z + 2) * L + l]
                    dx, dy, dz = P[p + l] - P[q + l], P[p + L + l] - P[q + L + l], P[p + 2 * L + l] - P[q + 2 * L + l]
                    G[a + l] = w * (T[T_S * L + l] * inv_n + zy * dz - zz * dy)
                    G[a + L + l] = w * (T[(T_S + 1) * L + l] * inv_n + zz * dx - zx * dz)
                    G[a + 2 * L + l] = w * (T[(T_S + 2) * L + l] * inv_n + zx * dy - zy * dx)
        for l in range(L):
            for r in range(T_CB, T_CC + 3):
                T[r * L + l] = 0.0
        # side quads (a, b, c, d) = (j, j+1, n+j+1, n+j): a and d complete with the carried shares of quad j-1's b and c
        for j in range(n):
            jn = j + 1 if j + 1 < n else 0
            a, bq, cc, d = 3 * j * L, 3 * jn * L, 3 * (n + jn) * L, 3 * (n + j) * L
            g = 3 * j * L
            for l in range(L):
                s6 = T[T_S6 * L + l]
                ax, ay, az = P[a + l], P[a + L + l], P[a + 2 * L + l]
                bx, by, bz = P[bq + l], P[bq + L + l], P[bq + 2 * L + l]
                cx, cy, cz = P[cc + l], P[cc + L + l], P[cc + 2 * L + l]
                ex, ey, ez = P[d + l], P[d + L + l], P[d + 2 * L + l]
                wx, wy, wz = cx - ax, cy - ay, cz - az
                ux, uy, uz = ex - bx, ey - by, ez - bz
                qx = 0.25 * (ax + bx + cx + ex); qy = 0.25 * (ay + by + cy + ey); qz = 0.25 * (az + bz + cz + ez)
                Xx = wy * uz - wz * uy; Xy = wz * ux - wx * uz; Xz = wx * uy - wy * ux
                T[T_V * L + l] += s6 * (qx * Xx + qy * Xy + qz * Xz)
                uqx = s6 * (uy * qz - uz * qy); uqy = s6 * (uz * qx - ux * qz); uqz = s6 * (ux * qy - uy * qx)
                qwx = s6 * (qy * wz - qz * wy); qwy = s6 * (qz * wx - qx * wz); qwz = s6 * (qx * wy - qy * wx)
                hx = 0.25 * s6 * Xx; hy = 0.25 * s6 * Xy; hz = 0.25 * s6 * Xz
                GB[g + l] += hx - uqx + T[T_CB * L + l]
                GB[g + L + l] += hy - uqy + T[(T_CB + 1) * L + l]
                GB[g + 2 * L + l] += hz - uqz + T[(T_CB + 2) * L + l]
                GT[g + l] += hx + qwx + T[T_CC * L + l]
                GT[g + L + l] += hy + qwy + T[(T_CC + 1) * L + l]
                GT[g + 2 * L + l] += hz + qwz + T[(T_CC + 2) * L + l]
                T[T_CB * L + l] = hx - qwx; T[(T_CB + 1) * L + l] = hy - qwy; T[(T_CB + 2) * L + l] = hz - qwz
                T[T_CC * L + l] = hx + uqx; T[(T_CC + 1) * L + l] = hy + uqy; T[(T_CC + 2) * L + l] = hz + uqz
        for l in range(L):       # quad n-1's b and c shares: vertices 0 and n
            GB[l] += T[T_CB * L + l]; GB[L + l] += T[(T_CB + 1) * L + l]; GB[2 * L + l] += T[(T_CB + 2) * L + l]
            GT[l] += T[T_CC * L + l]; GT[L + l] += T[(T_CC + 1) * L + l]; GT[2 * L + l] += T[(T_CC + 2) * L + l]
            T[T_G2 * L + l] = 0.0
        for j in range(n):       # |dV/dx|^2, for the bound
            g = 3 * j * L
            for l in range(L):
                bx, by, bz = GB[g + l], GB[g + L + l], GB[g + 2 * L + l]
                tx, ty, tz = GT[g + l], GT[g + L + l], GT[g + 2 * L + l]
                T[T_G2 * L + l] += (bx * bx + by * by + bz * bz) + (tx * tx + ty * ty + tz * tz)
        for l in range(L):
            k, iv, cap = kv[b * L + l], 1.0 / v0[b * L + l], capv[b * L + l]
            e = T[T_V * L + l] * iv - 1.0
            g2 = T[T_G2 * L + l] * iv * iv
            T[T_F * L + l] = -k * e * iv * (cap / g2 if cap > 0.0 and g2 > cap else 1.0)
            c = cell[b * L + l]
            if c >= 0:
                energy[c] = 0.5 * k * e * e
        for j in range(n):
            g = 3 * j * L
            for l in range(L):
                w = T[T_F * L + l]
                i = idx[o + j * L + l]
                ff[i] += w * GB[g + l]; ff[i + 1] += w * GB[g + L + l]; ff[i + 2] += w * GB[g + 2 * L + l]
                i = idx[o + (n + j) * L + l]
                ff[i] += w * GT[g + l]; ff[i + 1] += w * GT[g + L + l]; ff[i + 2] += w * GT[g + 2 * L + l]
