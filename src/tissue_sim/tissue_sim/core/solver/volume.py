"""The volume energy on each cell's enclosed volume (Params.volume_measure 'enclosed'; docs/solver.md "Volume"):
E_c = 1/2 kvol_c (V_c / V0_c - 1)^2, V_c the signed volume of the cell's closed surface as core.geometry.prism_volumes
defines it (each ring cap a fan about its centroid, each side quad four triangles about its centroid), its force the
exact gradient -kvol (V/V0 - 1) / V0 dV/dx_i. A prism deformed unevenly (half its vertices bound, the other half
moved) keeps the determinant of its best-fit affine map but not its volume; this energy holds the volume itself.
Thin cells (tendons, whose rings are ~5-mm discs: rest ring radius below THIN_RADIUS) keep the affine measure: held on
their enclosed volume, the semitendinosus' tendon cells behind the knee, their rings splayed by the fold and sheath
projections, and the soleus' above the calcaneus drove runs to diverge (docs/solver.md "What the volume energy holds")."""
from __future__ import annotations

import numpy as np
from numba import njit


THIN_RADIUS = 6e-3      # [m] cells whose rest bottom ring's mean radius is below this keep the affine measure (tendons)


def ring_radii(rest, off, cv) -> np.ndarray:
    """(C,) [m] the mean distance of each cell's bottom-ring vertices (the first half of its vertices) from their centroid."""
    out = np.zeros(len(off) - 1)
    for c in range(len(off) - 1):
        ring = rest[cv[off[c]:off[c] + (off[c + 1] - off[c]) // 2]]
        out[c] = np.linalg.norm(ring - ring.mean(0), axis=1).mean()
    return out


@njit(cache=True)
def enclosed_forces(x, f, off, cv, sign, v0, kvol, energy):
    """f[i] += -kvol (V/V0 - 1) / V0 dV/dx_i for every cell with kvol > 0 (V = sign x the prism volume of its rings:
    bottom ring the first half of its vertices, top the second); energy[c] = 1/2 kvol (V/V0 - 1)^2 (0 without)."""
    C = off.shape[0] - 1
    nmax = 0
    for c in range(C):
        nmax = max(nmax, off[c + 1] - off[c])
    P = np.empty((nmax, 3))
    g = np.empty((nmax, 3))
    for c in range(C):
        k = kvol[c]
        energy[c] = 0.0
        if not k > 0.0:
            continue
        o = off[c]
        m = off[c + 1] - o
        n = m // 2
        # positions relative to the cell's first vertex (the volume of a closed surface does not depend on it)
        rx, ry, rz = x[cv[o], 0], x[cv[o], 1], x[cv[o], 2]
        for j in range(m):
            i = cv[o + j]
            P[j, 0], P[j, 1], P[j, 2] = x[i, 0] - rx, x[i, 1] - ry, x[i, 2] - rz
            g[j, 0] = 0.0; g[j, 1] = 0.0; g[j, 2] = 0.0
        s6 = sign[c] / 6.0
        V = 0.0
        # the caps, fans about their centroids z: sum_j z . (v_j x v_j+1) = z . S; d/dv_k = S/n + z x (v_k-1 - v_k+1)
        for cap in range(2):
            b0 = cap * n
            w = s6 if cap else -s6                      # bottom cap normal -z, top +z
            zx = zy = zz = 0.0
            for j in range(n):
                zx += P[b0 + j, 0]; zy += P[b0 + j, 1]; zz += P[b0 + j, 2]
            zx /= n; zy /= n; zz /= n
            sx = sy = sz = 0.0
            for j in range(n):
                a, b = b0 + j, b0 + (j + 1) % n
                sx += P[a, 1] * P[b, 2] - P[a, 2] * P[b, 1]
                sy += P[a, 2] * P[b, 0] - P[a, 0] * P[b, 2]
                sz += P[a, 0] * P[b, 1] - P[a, 1] * P[b, 0]
            V += w * (zx * sx + zy * sy + zz * sz)
            for j in range(n):
                a = b0 + j
                p, q = b0 + (j - 1) % n, b0 + (j + 1) % n
                dx, dy, dz = P[p, 0] - P[q, 0], P[p, 1] - P[q, 1], P[p, 2] - P[q, 2]
                g[a, 0] += w * (sx / n + zy * dz - zz * dy)
                g[a, 1] += w * (sy / n + zz * dx - zx * dz)
                g[a, 2] += w * (sz / n + zx * dy - zy * dx)
        # the side quads (a, b, c, d) = (j, j+1, n+j+1, n+j), four triangles about their centroid q: q . X / 6 with
        # X = (c - a) x (d - b); d/da = X/4 - u x q, d/dc = X/4 + u x q (u = d - b), d/db = X/4 - q x w, d/dd = X/4 + q x w
        # (w = c - a)
        for j in range(n):
            jn = (j + 1) % n
            a, b, cc, d = j, jn, n + jn, n + j
            wx, wy, wz = P[cc, 0] - P[a, 0], P[cc, 1] - P[a, 1], P[cc, 2] - P[a, 2]
            ux, uy, uz = P[d, 0] - P[b, 0], P[d, 1] - P[b, 1], P[d, 2] - P[b, 2]
            qx = 0.25 * (P[a, 0] + P[b, 0] + P[cc, 0] + P[d, 0])
            qy = 0.25 * (P[a, 1] + P[b, 1] + P[cc, 1] + P[d, 1])
            qz = 0.25 * (P[a, 2] + P[b, 2] + P[cc, 2] + P[d, 2])
            Xx, Xy, Xz = wy * uz - wz * uy, wz * ux - wx * uz, wx * uy - wy * ux
            V += s6 * (qx * Xx + qy * Xy + qz * Xz)
            uqx, uqy, uqz = uy * qz - uz * qy, uz * qx - ux * qz, ux * qy - uy * qx
            qwx, qwy, qwz = qy * wz - qz * wy, qz * wx - qx * wz, qx * wy - qy * wx
            hx, hy, hz = 0.25 * Xx, 0.25 * Xy, 0.25 * Xz
            g[a, 0] += s6 * (hx - uqx); g[a, 1] += s6 * (hy - uqy); g[a, 2] += s6 * (hz - uqz)
            g[cc, 0] += s6 * (hx + uqx); g[cc, 1] += s6 * (hy + uqy); g[cc, 2] += s6 * (hz + uqz)
            g[b, 0] += s6 * (hx - qwx); g[b, 1] += s6 * (hy - qwy); g[b, 2] += s6 * (hz - qwz)
            g[d, 0] += s6 * (hx + qwx); g[d, 1] += s6 * (hy + qwy); g[d, 2] += s6 * (hz + qwz)
        e = V / v0[c] - 1.0
        energy[c] = 0.5 * k * e * e
        w = -k * e / v0[c]
        for j in range(m):
            i = cv[o + j]
            f[i, 0] += w * g[j, 0]
            f[i, 1] += w * g[j, 1]
            f[i, 2] += w * g[j, 2]
