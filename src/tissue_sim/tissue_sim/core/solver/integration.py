"""Time integration of the soft tissue: symplectic Euler for the free vertices, the segment pose for the
bone-attached ones (docs/solver.md "Time integration and stability"). numba."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath={'contract'})
def integrate(h, x, v, f, inv_den, xn, vn, att_idx, att_seg, rest, seg_R, seg_t, gravity, vel_damp, vmax2):
    """Symplectic Euler for the free vertices (v += h (f inv_den + g); v *= 1 - h c_v; x += h v; inv_den
    = 1/m explicit, 1/(m + h b + h^2 kappa) diagonally implicit) and the segment pose for bone-attached
    ones (x = R_s X + t_s, v = dx/h). Reads x, v, writes xn, vn (double buffer: a discarded step leaves
    x, v untouched). Returns how many vertices are faster than sqrt(vmax2) or not finite.

    The first loop runs over every vertex in order on flat views (no index list: LLVM vectorises it);
    a bone-attached vertex (inv_den 0) is computed there too, not counted, and overwritten by pose_attached."""
    nfast = 0
    damp = 1.0 - h * vel_damp
    g0, g1, g2 = h * gravity[0], h * gravity[1], h * gravity[2]
    xf, vf, ff, xnf, vnf = x.reshape(-1), v.reshape(-1), f.reshape(-1), xn.reshape(-1), vn.reshape(-1)
    for i in range(inv_den.shape[0]):
        hm = h * inv_den[i]
        a = (vf[3 * i] + hm * ff[3 * i] + g0) * damp
        b = (vf[3 * i + 1] + hm * ff[3 * i + 1] + g1) * damp
        c = (vf[3 * i + 2] + hm * ff[3 * i + 2] + g2) * damp
        vnf[3 * i] = a; vnf[3 * i + 1] = b; vnf[3 * i + 2] = c
        xnf[3 * i] = xf[3 * i] + h * a; xnf[3 * i + 1] = xf[3 * i + 1] + h * b; xnf[3 * i + 2] = xf[3 * i + 2] + h * c
        sp = a * a + b * b + c * c
        nfast += 0 if sp <= vmax2 or hm == 0.0 else 1      # (NaN counts)
    return nfast + pose_attached(h, x, xn, vn, att_idx, att_seg, rest, seg_R, seg_t, vmax2)


@njit(cache=True, fastmath={'contract'})
def pose_attached(h, x, xn, vn, att_idx, att_seg, rest, seg_R, seg_t, vmax2):
    """The bone-attached vertices in their segments' poses: xn = R_s X + t_s, vn = (xn - x)/h (integrate; the
    implicit integrator's integration, implicit.integrate). By runs of one segment (compile_model sorts them by
    segment): the pose in registers, flat views and unsigned indices (no negative-index wrap-around). Returns how
    many are faster than sqrt(vmax2) or not finite."""
    nfast = 0
    xf, xnf, vnf = x.reshape(-1), xn.reshape(-1), vn.reshape(-1)
    ih = 1.0 / h
    rf = rest.reshape(-1)
    k = 0
    while k < att_idx.shape[0]:
        s = att_seg[k]
        e = k + 1
        while e < att_idx.shape[0] and att_seg[e] == s:
            e += 1
        r00, r01, r02, t0 = seg_R[s, 0, 0], seg_R[s, 0, 1], seg_R[s, 0, 2], seg_t[s, 0]
        r10, r11, r12, t1 = seg_R[s, 1, 0], seg_R[s, 1, 1], seg_R[s, 1, 2], seg_t[s, 1]
        r20, r21, r22, t2 = seg_R[s, 2, 0], seg_R[s, 2, 1], seg_R[s, 2, 2], seg_t[s, 2]
        for kk in range(k, e):
            i = 3 * np.uint32(att_idx[kk])
            X, Y, Z = rf[i], rf[i + 1], rf[i + 2]
            a = r00 * X + r01 * Y + r02 * Z + t0
            b = r10 * X + r11 * Y + r12 * Z + t1
            c = r20 * X + r21 * Y + r22 * Z + t2
            da, db, dc = (a - xf[i]) * ih, (b - xf[i + 1]) * ih, (c - xf[i + 2]) * ih
            vnf[i] = da; vnf[i + 1] = db; vnf[i + 2] = dc
            xnf[i] = a; xnf[i + 1] = b; xnf[i + 2] = c
            nfast += 0 if da * da + db * db + dc * dc <= vmax2 else 1
        k = e
    return nfast


@njit(cache=True, inline='always')
def _via_place(r, via_seg, via_local, seg_R, seg_t):
    """Point via ring r's centroid place p = R_s local_r + t_s in its segment's pose (seg_R, seg_t)."""
    s = via_seg[r]
    lx, ly, lz = via_local[r, 0], via_local[r, 1], via_local[r, 2]
    return (seg_R[s, 0, 0] * lx + seg_R[s, 0, 1] * ly + seg_R[s, 0, 2] * lz + seg_t[s, 0],
            seg_R[s, 1, 0] * lx + seg_R[s, 1, 1] * ly + seg_R[s, 1, 2] * lz + seg_t[s, 1],
            seg_R[s, 2, 0] * lx + seg_R[s, 2, 1] * ly + seg_R[s, 2, 2] * lz + seg_t[s, 2])


@njit(cache=True, fastmath={'contract'})
def via_forces(f, via_off, via_idx, via_seg, via_local, seg_R, seg_t, inv_den, wr):
    """The point via rings' pull on their bones (before the skeleton step, with the forces f of this sub-step's
    evaluation): the bone holds each ring's centroid, so it takes the net force on the ring's free vertices (inv_den >
    0), applied at the centroid's place p (no moment about p: the ring turns freely), into wr (S, 6) (force, its moment
    about the world origin), as a bound vertex's force reaches its segment. The same with either integrator: the ring's
    projection (hold_via_points) then only moves it."""
    for r in range(via_seg.shape[0]):
        fx = fy = fz = 0.0
        for k in range(via_off[r], via_off[r + 1]):
            i = via_idx[k]
            if inv_den[i] > 0.0:
                fx += f[i, 0]; fy += f[i, 1]; fz += f[i, 2]
        px, py, pz = _via_place(r, via_seg, via_local, seg_R, seg_t)
        s = via_seg[r]
        wr[s, 0] += fx
        wr[s, 1] += fy
        wr[s, 2] += fz
        wr[s, 3] += py * fz - pz * fy
        wr[s, 4] += pz * fx - px * fz
        wr[s, 5] += px * fy - py * fx


@njit(cache=True, fastmath={'contract'})
def hold_via_points(h, xn, vn, via_off, via_idx, via_seg, via_local, seg_R, seg_t, inv_den):
    """Point via rings (SimModel.via_*; docs/solver.md "Point vias"), after the integration: ring r's centroid c (the
    mean of its vertices at xn, bone-attached ones where their segments put them) is moved onto its place in segment
    s = via_seg[r]'s new pose, p = R_s via_local[r] + t_s, by moving each of its free vertices (inv_den > 0) by
    d = (p - c) n / n_free and its velocity by d / h: only the centroid is held, the ring turns and deforms with its
    cells (a tendon passing a bone-fixed point, as the source model's path at its via point). The bone took the ring's
    net force in the skeleton step (via_forces)."""
    ih = 1.0 / h
    for r in range(via_seg.shape[0]):
        a, b = via_off[r], via_off[r + 1]
        cx = cy = cz = 0.0
        nfree = 0
        for k in range(a, b):
            i = via_idx[k]
            cx += xn[i, 0]; cy += xn[i, 1]; cz += xn[i, 2]
            if inv_den[i] > 0.0:
                nfree += 1
        if nfree == 0:
            continue
        n = b - a
        px, py, pz = _via_place(r, via_seg, via_local, seg_R, seg_t)
        sc = n / nfree
        dx, dy, dz = (px - cx / n) * sc, (py - cy / n) * sc, (pz - cz / n) * sc
        for k in range(a, b):
            i = via_idx[k]
            if inv_den[i] > 0.0:
                xn[i, 0] += dx; xn[i, 1] += dy; xn[i, 2] += dz
                vn[i, 0] += dx * ih; vn[i, 1] += dy * ih; vn[i, 2] += dz * ih
