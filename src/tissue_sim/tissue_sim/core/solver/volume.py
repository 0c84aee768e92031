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


@njit(cache=True, inline='always')
def _tri(g, a, b, c, P, w):
    """Add w x the gradient of a . (b x c) (points P[a], P[b], P[c]) to g rows a, b, c; returns w a . (b x c)."""
    ax, ay, az = P[a, 0], P[a, 1], P[a, 2]
    bx, by, bz = P[b, 0], P[b, 1], P[b, 2]
    cx, cy, cz = P[c, 0], P[c, 1], P[c, 2]
    g[a, 0] += w * (by * cz - bz * cy); g[a, 1] += w * (bz * cx - bx * cz); g[a, 2] += w * (bx * cy - by * cx)
    g[b, 0] += w * (cy * az - cz * ay); g[b, 1] += w * (cz * ax - cx * az); g[b, 2] += w * (cx * ay - cy * ax)
    g[c, 0] += w * (ay * bz - az * by); g[c, 1] += w * (az * bx - ax * bz); g[c, 2] += w * (ax * by - ay * bx)
    return w * (ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx))


@njit(cache=True)
def enclosed_forces(x, f, off, cv, sign, v0, kvol, energy):
    """f[i] += -kvol (V/V0 - 1) / V0 dV/dx_i for every cell with kvol > 0 (V = sign x the prism volume of its rings:
    bottom ring the first half of its vertices, top the second); energy[c] = 1/2 kvol (V/V0 - 1)^2 (0 without)."""
    C = off.shape[0] - 1
    nmax = 0
    for c in range(C):
        nmax = max(nmax, off[c + 1] - off[c])
    P = np.empty((nmax + nmax // 2 + 2 + 1, 3))        # ring vertices, then quad centroids, the two cap centroids
    g = np.empty((nmax + nmax // 2 + 2 + 1, 3))
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
        cb, ct = m + n, m + n + 1
        for r in range(3):
            sb = 0.0
            st = 0.0
            for j in range(n):
                sb += P[j, r]
                st += P[n + j, r]
            P[cb, r] = sb / n
            P[ct, r] = st / n
        for j in range(n):
            jn = (j + 1) % n
            for r in range(3):
                P[m + j, r] = 0.25 * (P[j, r] + P[jn, r] + P[n + jn, r] + P[n + j, r])
        g[:m + n + 2] = 0.0
        V = 0.0
        s6 = sign[c] / 6.0
        for j in range(n):
            jn = (j + 1) % n
            V += _tri(g, cb, j, jn, P, -s6)                       # bottom cap, normal -z
            V += _tri(g, ct, n + j, n + jn, P, s6)                # top cap, normal +z
            q = m + j
            V += _tri(g, q, j, jn, P, s6)                         # the side quad about its centroid
            V += _tri(g, q, jn, n + jn, P, s6)
            V += _tri(g, q, n + jn, n + j, P, s6)
            V += _tri(g, q, n + j, j, P, s6)
        # the centroids' gradients go to their vertices
        for j in range(n):
            jn = (j + 1) % n
            q = m + j
            for r in range(3):
                gq = 0.25 * g[q, r]
                g[j, r] += gq; g[jn, r] += gq; g[n + jn, r] += gq; g[n + j, r] += gq
        for r in range(3):
            gb, gt = g[cb, r] / n, g[ct, r] / n
            for j in range(n):
                g[j, r] += gb
                g[n + j, r] += gt
        e = V / v0[c] - 1.0
        energy[c] = 0.5 * k * e * e
        w = -k * e / v0[c]
        for j in range(m):
            i = cv[o + j]
            f[i, 0] += w * g[j, 0]
            f[i, 1] += w * g[j, 1]
            f[i, 2] += w * g[j, 2]
