"""Numba kernels of the solver: flat arrays in, flat arrays out, single thread. No fastmath except
floating-point contraction (fused multiply-add) in the two hot kernels: deterministic (the compiled
code fixes the order), no reassociation (it made results depend on what ran before in the process),
NaN/Inf semantics kept (divergence checks rely on them).

Cells are CSR (``off``, ``cv``); ``X0`` (K, 3) holds each cell's rest vertex positions relative to
the cell's rest centroid (unweighted mean), in the same order as ``cv``. All positions in metres,
model frame; forces in N (paper units in the 'paper' preset).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

CAUSE_OK = 0
CAUSE_CELL_FORCE = 1        # non-finite or absurd elastic force in a cell
CAUSE_SPEED = 2             # a vertex exceeded max_speed (energy blow-up)
CAUSE_SKELETON = 3          # non-finite joint acceleration
CAUSES = {CAUSE_CELL_FORCE: 'non-finite or overflowing elastic force', CAUSE_SPEED: 'vertex speed above max_speed (energy blow-up)',
          CAUSE_SKELETON: 'non-finite joint acceleration'}
FORCE_BOUND = 1e150
NEWTON_DONE = 1e-5          # [rad] a Newton rotation correction below this ends the iteration (next one ~1e-10)


# ------------------------------------------------------------------------------------ small math
@njit(cache=True)
def quat_to_mat(q, R):
    """Unit quaternion (x, y, z, w) -> rotation matrix R (3, 3), written in place."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z); R[0, 1] = 2 * (x * y - z * w); R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w); R[1, 1] = 1 - 2 * (x * x + z * z); R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w); R[2, 1] = 2 * (y * z + x * w); R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True)
def axis_angle_mat(ax, ang, R):
    """Rotation by ang [rad] about unit axis ax (Rodrigues), written into R."""
    c, s = math.cos(ang), math.sin(ang)
    t = 1 - c
    x, y, z = ax[0], ax[1], ax[2]
    R[0, 0] = t * x * x + c; R[0, 1] = t * x * y - s * z; R[0, 2] = t * x * z + s * y
    R[1, 0] = t * x * y + s * z; R[1, 1] = t * y * y + c; R[1, 2] = t * y * z - s * x
    R[2, 0] = t * x * z - s * y; R[2, 1] = t * y * z + s * x; R[2, 2] = t * z * z + c


@njit(cache=True)
def _quat_row_to_mat(quat, c, R):
    x, y, z, w = quat[c, 0], quat[c, 1], quat[c, 2], quat[c, 3]
    R[0, 0] = 1 - 2 * (y * y + z * z); R[0, 1] = 2 * (x * y - z * w); R[0, 2] = 2 * (x * z + y * w)
    R[1, 0] = 2 * (x * y + z * w); R[1, 1] = 1 - 2 * (x * x + z * z); R[1, 2] = 2 * (y * z - x * w)
    R[2, 0] = 2 * (x * z - y * w); R[2, 1] = 2 * (y * z + x * w); R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True)
def extract_rotation_at(B, quat, c, iters, R):
    """Rotational part of B (3x3), after Mueller et al. 2016 ("A Robust Method to Extract the
    Rotational Part of Deformations"): the quaternion quat[c] (x, y, z, w) is warm-started, updated in
    place, R gets its matrix; always a rotation, robust for flat and inverted B.

    Each iteration maximises tr(R^T B) over a rotation increment omega: gradient g = sum_j r_j x b_j
    (r_j, b_j the columns of R, B). Mueller's step is g / |tr(B R^T)|; here the Newton step
    H^-1 g with H = tr(N) I - sym(N), N = B R^T, is used whenever H is positive definite (it is near
    the solution unless B is degenerate), which converges quadratically also for thin, anisotropic
    cells where Mueller's step crawls; otherwise Mueller's step. Steps are capped at 1 rad. Stops after
    iters iterations, when the correction is below 1e-12 rad, or after a Newton correction below
    NEWTON_DONE (its successor would be of order NEWTON_DONE^2: warm-started, one iteration per step
    is then the usual case)."""
    nrm = 0.0
    for i in range(3):
        for j in range(3):
            nrm += B[i, j] * B[i, j]
    nrm = math.sqrt(nrm)
    _quat_row_to_mat(quat, c, R)
    if not (nrm > 0.0) or not math.isfinite(nrm):
        return
    inv = 1.0 / nrm
    for _ in range(iters):
        gx = gy = gz = 0.0
        n00 = n01 = n02 = n11 = n12 = n22 = 0.0
        for j in range(3):          # g = sum_j R[:, j] x B[:, j];  N = B R^T = sum_j b_j r_j^T (sym part)
            r0, r1, r2 = R[0, j], R[1, j], R[2, j]
            b0, b1, b2 = B[0, j] * inv, B[1, j] * inv, B[2, j] * inv
            gx += r1 * b2 - r2 * b1
            gy += r2 * b0 - r0 * b2
            gz += r0 * b1 - r1 * b0
            n00 += b0 * r0; n11 += b1 * r1; n22 += b2 * r2
            n01 += 0.5 * (b0 * r1 + b1 * r0); n02 += 0.5 * (b0 * r2 + b2 * r0); n12 += 0.5 * (b1 * r2 + b2 * r1)
        tr = n00 + n11 + n22
        h00, h11, h22 = tr - n00, tr - n11, tr - n22
        h01, h02, h12 = -n01, -n02, -n12
        c00 = h11 * h22 - h12 * h12; c01 = h02 * h12 - h01 * h22; c02 = h01 * h12 - h02 * h11
        c11 = h00 * h22 - h02 * h02; c12 = h01 * h02 - h00 * h12; c22 = h00 * h11 - h01 * h01
        det = h00 * c00 + h01 * c01 + h02 * c02
        newton = h00 > 0.0 and c22 > 0.0 and det > 1e-9 * tr * tr * tr   # Sylvester: H positive definite
        if newton:
            idet = 1.0 / det
            ox = (c00 * gx + c01 * gy + c02 * gz) * idet
            oy = (c01 * gx + c11 * gy + c12 * gz) * idet
            oz = (c02 * gx + c12 * gy + c22 * gz) * idet
        else:
            den = abs(tr) + 1e-9
            ox, oy, oz = gx / den, gy / den, gz / den
        w = math.sqrt(ox * ox + oy * oy + oz * oz)
        if w < 1e-12:
            break
        if w > 1.0:
            ox /= w; oy /= w; oz /= w
            w = 1.0
        # dq = (omega/2, 1) normalised with q below: a rotation by 2 atan(w/2) = w - w^3/12 + ... about
        # omega (no sin/cos; the cubic error is removed by the next iteration)
        dx, dy, dz, dw = 0.5 * ox, 0.5 * oy, 0.5 * oz, 1.0
        x, y, z, qw = quat[c, 0], quat[c, 1], quat[c, 2], quat[c, 3]       # q = dq * q
        nx = dw * x + dx * qw + dy * z - dz * y
        ny = dw * y - dx * z + dy * qw + dz * x
        nz = dw * z + dx * y - dy * x + dz * qw
        nw = dw * qw - dx * x - dy * y - dz * z
        n = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
        quat[c, 0], quat[c, 1], quat[c, 2], quat[c, 3] = nx * n, ny * n, nz * n, nw * n
        _quat_row_to_mat(quat, c, R)
        if newton and w < NEWTON_DONE:      # quadratic convergence: the next correction would be ~w^2
            break


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


# ------------------------------------------------------------------------------------ cell forces
@njit(cache=True, fastmath={'contract'})
def cell_forces(x, v, f, quat, off, cv, X0, Qinv, fibre, cell_muscle, lam, act, kc, kact, damp_b,
                volume_actual, iters, cell_energy, kvol, pressure, vol_gain, q_tr, q_ff, rest_len):
    """Elastic (+ volume, + deformation-damping) forces of all cells, accumulated into f (V, 3)
    (zeroed here). Returns the first cell whose force is non-finite or overflowing, else -1.

    Per cell (one gather pass, one scatter pass): centroid c = mean x_i; A = sum (x_i - c) X0_i^T;
    rest shape X'_i = F X0_i with F = lam f f^T + s (I - f f^T) for muscle cells (fibre f, s the
    cross-section factor), F = I for fat; R = rotation of A F (warm-started from quat); goal
    G_i = c + R F X0_i; force k (G_i - x_i). R being the polar factor, this satisfies eq. (1):
    zero net force and moment. Volume (kvol[c] > 0): with D = A Qinv the cell's best-fit affine
    deformation, energy 0.5 kvol (det D - 1)^2 adds -kvol (det D - 1) cof(D) Qinv X0_i (internal:
    rotation and translation invariant), plus an integral term: pressure[c] += vol_gain * (-kvol
    (det D - 1)) each call acts the same way, so a cell held from reaching its volume (e.g. by
    bone-attached vertices) builds up pressure until det D = 1 (vol_gain = h / volume_relax_time;
    0 = off). Damping: -b (v_i - v_rigid_i) with v_rigid the cell's mean
    linear + angular velocity (momentum conserving, rigid motion undamped). cell_energy[c] gets
    0.5 k sum |G_i - x_i|^2 + the volume energy, the first from the cell's moments:
    tr(F^2 Q) - 2 tr(T^T A) + tr(Y) with q_tr = tr Q, q_ff = f^T Q f (Q = sum X0 X0^T), Y = sum r r^T.

    Active tension (kact[c] > 0, muscle cells): a contractile force along the cell's axis only, between
    the centroids of its bottom ring (first n/2 vertices) and top ring (last n/2): with l the current
    centroid distance, u its direction and rest_len[c] the rest distance, T = a kact n/4 max(l - lam
    rest_len, 0) pulls the rings together (-2T/n u on each top vertex, +2T/n u on each bottom vertex:
    zero net force and moment). At l = rest_len, lam = lam_min that is n_ring kact (1 - lam_min) L / 2,
    the force the calibration (model.active_stiffness) sets. Being axial, it does not stiffen the
    cell against bending or shear (a muscle pulls, it does not hold its shape).

    Per cell-vertex entry the scatter applies one affine map: f_i = (k T + P) X0_i + (b [w]x - k I) r_i
    - b v_i + b vbar (elastic + volume + damping together)."""
    f[:] = 0.0
    A = np.empty((3, 3))
    B = np.empty((3, 3))
    F = np.empty((3, 3))
    R = np.empty((3, 3))
    T = np.empty((3, 3))
    D = np.empty((3, 3))
    P = np.zeros((3, 3))
    for c in range(off.shape[0] - 1):
        a0, a1 = off[c], off[c + 1]
        n = a1 - a0
        i0 = cv[a0]
        ox, oy, oz = x[i0, 0], x[i0, 1], x[i0, 2]          # local origin (precision)
        b = damp_b[c]
        sx = sy = sz = 0.0
        svx = svy = svz = 0.0
        lx = ly = lz = 0.0
        yxx = yyy = yzz = yxy = yxz = yyz = 0.0
        a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = 0.0   # scalars: no aliasing with x, f
        for p in range(a0, a1):                             # gather
            i = cv[p]
            dx, dy, dz = x[i, 0] - ox, x[i, 1] - oy, x[i, 2] - oz
            sx += dx; sy += dy; sz += dz
            X, Y, Z = X0[p, 0], X0[p, 1], X0[p, 2]
            a00 += dx * X; a01 += dx * Y; a02 += dx * Z
            a10 += dy * X; a11 += dy * Y; a12 += dy * Z
            a20 += dz * X; a21 += dz * Y; a22 += dz * Z
            yxx += dx * dx; yyy += dy * dy; yzz += dz * dz
            yxy += dx * dy; yxz += dx * dz; yyz += dy * dz
            if b > 0.0:
                ux, uy, uz = v[i, 0], v[i, 1], v[i, 2]
                svx += ux; svy += uy; svz += uz
                lx += dy * uz - dz * uy; ly += dz * ux - dx * uz; lz += dx * uy - dy * ux
        A[0, 0] = a00; A[0, 1] = a01; A[0, 2] = a02
        A[1, 0] = a10; A[1, 1] = a11; A[1, 2] = a12
        A[2, 0] = a20; A[2, 1] = a21; A[2, 2] = a22
        inv_n = 1.0 / n
        mx, my, mz = sx * inv_n, sy * inv_n, sz * inv_n
        cx, cy, cz = ox + mx, oy + my, oz + mz
        m = cell_muscle[c]
        k = kc[c]
        kv = kvol[c]
        if m >= 0 or kv > 0.0:
            for r in range(3):
                for s in range(3):
                    D[r, s] = A[r, 0] * Qinv[c, 0, s] + A[r, 1] * Qinv[c, 1, s] + A[r, 2] * Qinv[c, 2, s]
        if m >= 0:
            fx, fy, fz = fibre[c, 0], fibre[c, 1], fibre[c, 2]
            la = lam[m]
            if volume_actual:          # current fibre stretch mu = |D f|
                ux = D[0, 0] * fx + D[0, 1] * fy + D[0, 2] * fz
                uy = D[1, 0] * fx + D[1, 1] * fy + D[1, 2] * fz
                uz = D[2, 0] * fx + D[2, 1] * fy + D[2, 2] * fz
                mu = min(max(math.sqrt(ux * ux + uy * uy + uz * uz), 0.25), 4.0)
                sl = 1.0 / math.sqrt(mu)
            else:
                sl = 1.0 / math.sqrt(la)
            F[0, 0] = (la - sl) * fx * fx + sl; F[0, 1] = (la - sl) * fx * fy; F[0, 2] = (la - sl) * fx * fz
            F[1, 0] = F[0, 1]; F[1, 1] = (la - sl) * fy * fy + sl; F[1, 2] = (la - sl) * fy * fz
            F[2, 0] = F[0, 2]; F[2, 1] = F[1, 2]; F[2, 2] = (la - sl) * fz * fz + sl
            for r in range(3):
                for s in range(3):
                    B[r, s] = A[r, 0] * F[0, s] + A[r, 1] * F[1, s] + A[r, 2] * F[2, s]
            extract_rotation_at(B, quat, c, iters, R)
            for r in range(3):
                for s in range(3):
                    T[r, s] = R[r, 0] * F[0, s] + R[r, 1] * F[1, s] + R[r, 2] * F[2, s]
        else:
            extract_rotation_at(A, quat, c, iters, T)
        ev = 0.0
        P[:, :] = 0.0
        if kv > 0.0:                   # P = -kvol (det D - 1) cof(D) Qinv
            c00 = D[1, 1] * D[2, 2] - D[1, 2] * D[2, 1]; c01 = D[1, 2] * D[2, 0] - D[1, 0] * D[2, 2]
            c02 = D[1, 0] * D[2, 1] - D[1, 1] * D[2, 0]
            c10 = D[0, 2] * D[2, 1] - D[0, 1] * D[2, 2]; c11 = D[0, 0] * D[2, 2] - D[0, 2] * D[2, 0]
            c12 = D[0, 1] * D[2, 0] - D[0, 0] * D[2, 1]
            c20 = D[0, 1] * D[1, 2] - D[0, 2] * D[1, 1]; c21 = D[0, 2] * D[1, 0] - D[0, 0] * D[1, 2]
            c22 = D[0, 0] * D[1, 1] - D[0, 1] * D[1, 0]
            det = D[0, 0] * c00 + D[0, 1] * c01 + D[0, 2] * c02
            g = -kv * (det - 1.0)
            pressure[c] += vol_gain * g
            g += pressure[c]
            ev = 0.5 * kv * (det - 1.0) ** 2
            for s in range(3):
                P[0, s] = g * (c00 * Qinv[c, 0, s] + c01 * Qinv[c, 1, s] + c02 * Qinv[c, 2, s])
                P[1, s] = g * (c10 * Qinv[c, 0, s] + c11 * Qinv[c, 1, s] + c12 * Qinv[c, 2, s])
                P[2, s] = g * (c20 * Qinv[c, 0, s] + c21 * Qinv[c, 1, s] + c22 * Qinv[c, 2, s])
        # second moments of the current vertices about the centroid: Y = sum r r^T
        qxx = yxx - n * mx * mx; qyy = yyy - n * my * my; qzz = yzz - n * mz * mz
        qxy = yxy - n * mx * my; qxz = yxz - n * mx * mz; qyz = yyz - n * my * mz
        wx = wy = wz = 0.0
        vx = vy = vz = 0.0
        if b > 0.0:                    # rigid velocity of the cell: mean + angular (I^-1 L) about c
            vx, vy, vz = svx * inv_n, svy * inv_n, svz * inv_n
            Lx = lx - n * (my * vz - mz * vy)
            Ly = ly - n * (mz * vx - mx * vz)
            Lz = lz - n * (mx * vy - my * vx)
            tr = qxx + qyy + qzz
            eps = 1e-9 * tr + 1e-300
            I00 = tr - qxx + eps; I11 = tr - qyy + eps; I22 = tr - qzz + eps
            I01 = -qxy; I02 = -qxz; I12 = -qyz
            c00 = I11 * I22 - I12 * I12; c01 = I02 * I12 - I01 * I22; c02 = I01 * I12 - I02 * I11
            c11 = I00 * I22 - I02 * I02; c12 = I01 * I02 - I00 * I12; c22 = I00 * I11 - I01 * I01
            det = I00 * c00 + I01 * c01 + I02 * c02
            if det > 0.0 and math.isfinite(det):
                idet = 1.0 / det
                wx = (c00 * Lx + c01 * Ly + c02 * Lz) * idet
                wy = (c01 * Lx + c11 * Ly + c12 * Lz) * idet
                wz = (c02 * Lx + c12 * Ly + c22 * Lz) * idet
        # elastic energy from the moments (R orthogonal, F symmetric, sum X0 = 0):
        # sum |T X0_i - r_i|^2 = tr(F^2 Q) - 2 tr(T^T A) + tr(Y), Q = sum X0 X0^T (q_tr = tr Q, q_ff = f^T Q f)
        if m >= 0:
            fqf = q_ff[c]
            tf2q = la * la * fqf + sl * sl * (q_tr[c] - fqf)
        else:
            tf2q = q_tr[c]
        tta = (T[0, 0] * a00 + T[0, 1] * a01 + T[0, 2] * a02 + T[1, 0] * a10 + T[1, 1] * a11 + T[1, 2] * a12
               + T[2, 0] * a20 + T[2, 1] * a21 + T[2, 2] * a22)
        e = max(tf2q - 2.0 * tta + (qxx + qyy + qzz), 0.0)
        # active axial tension between the ring centroids (muscle cells with active stiffness)
        tax = tay = taz = 0.0
        ea = 0.0
        half = n // 2
        if m >= 0 and kact[c] > 0.0 and act[m] > 0.0:
            ux = uy = uz = 0.0
            for p in range(a0, a1):
                i = cv[p]
                if p - a0 < half:
                    ux -= x[i, 0]; uy -= x[i, 1]; uz -= x[i, 2]
                else:
                    ux += x[i, 0]; uy += x[i, 1]; uz += x[i, 2]
            ux /= half; uy /= half; uz /= half
            ln = math.sqrt(ux * ux + uy * uy + uz * uz)
            stretch = ln - la * rest_len[c]
            if stretch > 0.0 and ln > 0.0:
                ka = act[m] * kact[c] * 0.25 * n
                tt = ka * stretch * 2.0 / (n * ln)           # per-vertex force / l, along u
                tax, tay, taz = tt * ux, tt * uy, tt * uz
                ea = 0.5 * ka * stretch * stretch
        # force on vertex i, elastic + volume + damping in one affine map of (X0_i, r_i, v_i):
        # k (T X0 - r) + P X0 - b (v - vbar - w x r) = (k T + P) X0 + (b [w]x - k I) r - b v + b vbar
        m00 = k * T[0, 0] + P[0, 0]; m01 = k * T[0, 1] + P[0, 1]; m02 = k * T[0, 2] + P[0, 2]
        m10 = k * T[1, 0] + P[1, 0]; m11 = k * T[1, 1] + P[1, 1]; m12 = k * T[1, 2] + P[1, 2]
        m20 = k * T[2, 0] + P[2, 0]; m21 = k * T[2, 1] + P[2, 1]; m22 = k * T[2, 2] + P[2, 2]
        bwx, bwy, bwz = b * wx, b * wy, b * wz
        # f0 = m X0 - k r - b v + b (vbar + w x (x_i - c)) with r = x_i - c: the constant part uses the
        # local origin o: w x (x_i - c) = w x d_i - w x mm (d_i = x_i - o, mm = c - o)
        kx0 = -k * mx; ky0 = -k * my; kz0 = -k * mz
        cx0 = b * vx - (bwy * mz - bwz * my) - kx0
        cy0 = b * vy - (bwz * mx - bwx * mz) - ky0
        cz0 = b * vz - (bwx * my - bwy * mx) - kz0
        for p in range(a0, a1):                             # scatter
            i = cv[p]
            X, Y, Z = X0[p, 0], X0[p, 1], X0[p, 2]
            dx, dy, dz = x[i, 0] - ox, x[i, 1] - oy, x[i, 2] - oz
            fx_ = m00 * X + m01 * Y + m02 * Z - k * dx + (bwy * dz - bwz * dy) + cx0
            fy_ = m10 * X + m11 * Y + m12 * Z - k * dy + (bwz * dx - bwx * dz) + cy0
            fz_ = m20 * X + m21 * Y + m22 * Z - k * dz + (bwx * dy - bwy * dx) + cz0
            if b > 0.0:
                fx_ -= b * v[i, 0]; fy_ -= b * v[i, 1]; fz_ -= b * v[i, 2]
            if p - a0 < half:
                fx_ += tax; fy_ += tay; fz_ += taz
            else:
                fx_ -= tax; fy_ -= tay; fz_ -= taz
            f[i, 0] += fx_; f[i, 1] += fy_; f[i, 2] += fz_
        cell_energy[c] = 0.5 * k * e + ev + ea
        if not (e * k * k < FORCE_BOUND) or not (ev < FORCE_BOUND) or not (abs(m00) + abs(cx0) < FORCE_BOUND):
            return c                   # catches NaN and overflow
    return -1


# ------------------------------------------------------------------------------------ skeleton
@njit(cache=True)
def forward_kinematics(q, seg_order, seg_joint, j_parent, j_axis, j_centre, j_rest, seg_R, seg_t):
    """Pose (R_s, t_s) of every non-root segment from the joint coordinates q; a point p_rest of
    segment s is at R_s p_rest + t_s. Joint j rotates its child by q_j - rest_j about its rest axis
    through its rest centre, then the parent's pose applies. seg_order lists parents first."""
    Rj = np.empty((3, 3))
    for s in seg_order:
        j = seg_joint[s]
        if j < 0:
            continue
        p = j_parent[j]
        axis_angle_mat(j_axis[j], q[j] - j_rest[j], Rj)
        cx, cy, cz = j_centre[j, 0], j_centre[j, 1], j_centre[j, 2]
        # local transform: x -> Rj (x - c) + c ; world: R_p (Rj (x - c) + c) + t_p
        lx = cx - (Rj[0, 0] * cx + Rj[0, 1] * cy + Rj[0, 2] * cz)
        ly = cy - (Rj[1, 0] * cx + Rj[1, 1] * cy + Rj[1, 2] * cz)
        lz = cz - (Rj[2, 0] * cx + Rj[2, 1] * cy + Rj[2, 2] * cz)
        for r in range(3):
            for c in range(3):
                seg_R[s, r, c] = seg_R[p, r, 0] * Rj[0, c] + seg_R[p, r, 1] * Rj[1, c] + seg_R[p, r, 2] * Rj[2, c]
            seg_t[s, r] = seg_R[p, r, 0] * lx + seg_R[p, r, 1] * ly + seg_R[p, r, 2] * lz + seg_t[p, r]


@njit(cache=True)
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True)
def skeleton_step(h, q, qd, f, x, att_idx, att_seg, seg_order, seg_parent, seg_joint, seg_mass, seg_com,
                  seg_inertia, j_parent, j_child, j_type, j_axis, j_centre, j_rest, j_range, anc,
                  gravity, joint_damping, limit_wh, limit_zeta, seg_R, seg_t, work):
    """One step of the skeleton (a tree of rigid segments, hinge or fixed joints, fixed root).

    tau_j = a_j . sum over attached vertices of segments below joint j of (x - p_j) x f (the
    tissue's reaction on the bone). Joint-space mass matrix M from segment masses/inertias by
    Jacobians; bias (Coriolis, centrifugal, gravity) by recursive Newton-Euler with qdd = 0;
    range limits as an implicit stiff, critically damped end stop (no jolt). Symplectic Euler:
    qd += h qdd, q += h qd; then forward kinematics. Returns False if qdd is not finite."""
    S = seg_mass.shape[0]
    J = q.shape[0]
    # world axes and centres of the joints, world COM and inertia of the segments (current pose)
    a = work[0:J, 0:3]
    pj = work[0:J, 3:6]
    com = np.empty((S, 3))
    Iw = np.empty((S, 3, 3))
    for j in range(J):
        p = j_parent[j]
        for r in range(3):
            a[j, r] = seg_R[p, r, 0] * j_axis[j, 0] + seg_R[p, r, 1] * j_axis[j, 1] + seg_R[p, r, 2] * j_axis[j, 2]
            pj[j, r] = (seg_R[p, r, 0] * j_centre[j, 0] + seg_R[p, r, 1] * j_centre[j, 1]
                        + seg_R[p, r, 2] * j_centre[j, 2] + seg_t[p, r])
    for s in range(S):
        for r in range(3):
            com[s, r] = seg_R[s, r, 0] * seg_com[s, 0] + seg_R[s, r, 1] * seg_com[s, 1] + seg_R[s, r, 2] * seg_com[s, 2] + seg_t[s, r]
        for r in range(3):
            for c in range(3):
                acc = 0.0
                for k in range(3):
                    for l in range(3):
                        acc += seg_R[s, r, k] * seg_inertia[s, k, l] * seg_R[s, c, l]
                Iw[s, r, c] = acc
    # tissue wrench per segment (force, moment about the world origin), summed up the tree
    Fs = np.zeros((S, 3))
    Ns = np.zeros((S, 3))
    for k in range(att_idx.shape[0]):
        i = att_idx[k]
        s = att_seg[k]
        Fs[s, 0] += f[i, 0]; Fs[s, 1] += f[i, 1]; Fs[s, 2] += f[i, 2]
        Ns[s, 0] += x[i, 1] * f[i, 2] - x[i, 2] * f[i, 1]
        Ns[s, 1] += x[i, 2] * f[i, 0] - x[i, 0] * f[i, 2]
        Ns[s, 2] += x[i, 0] * f[i, 1] - x[i, 1] * f[i, 0]
    # recursive Newton-Euler, qdd = 0, base acceleration -g (gravity), forward pass
    w = np.zeros((S, 3))
    al = np.zeros((S, 3))
    acom = np.zeros((S, 3))
    tmp = np.empty(3)
    tmp2 = np.empty(3)
    vk = np.empty(3)
    d = np.empty(3)
    acc_p = np.empty(3)
    Iwv = np.empty(3)
    Ial = np.empty(3)
    for s in seg_order:
        j = seg_joint[s]
        if j < 0:
            for r in range(3):
                acom[s, r] = -gravity[r]
            continue
        p = j_parent[j]
        wq = qd[j] if j_type[j] == 1 else 0.0
        for r in range(3):
            w[s, r] = w[p, r] + a[j, r] * wq
        # alpha_s = alpha_p + w_p x (a_j qd_j)
        _cross(w[p], a[j], tmp)
        for r in range(3):
            al[s, r] = al[p, r] + tmp[r] * wq
        # acceleration of the joint point on the parent, then of the child's COM
        for r in range(3):
            d[r] = pj[j, r] - com[p, r]
        _cross(al[p], d, tmp); _cross(w[p], d, tmp2)
        for r in range(3):
            acc_p[r] = acom[p, r] + tmp[r]
        _cross(w[p], tmp2, tmp)
        for r in range(3):
            acc_p[r] += tmp[r]
            d[r] = com[s, r] - pj[j, r]
        _cross(al[s], d, tmp); _cross(w[s], d, tmp2)
        for r in range(3):
            acom[s, r] = acc_p[r] + tmp[r]
        _cross(w[s], tmp2, tmp)
        for r in range(3):
            acom[s, r] += tmp[r]
    # backward pass: wrench (force, moment about the world origin) each subtree needs
    Fb = np.zeros((S, 3))
    Nb = np.zeros((S, 3))
    for kk in range(seg_order.shape[0] - 1, -1, -1):
        s = seg_order[kk]
        for r in range(3):
            Fb[s, r] += seg_mass[s] * acom[s, r]
        for r in range(3):
            Iwv[r] = Iw[s, r, 0] * w[s, 0] + Iw[s, r, 1] * w[s, 1] + Iw[s, r, 2] * w[s, 2]
            Ial[r] = Iw[s, r, 0] * al[s, 0] + Iw[s, r, 1] * al[s, 1] + Iw[s, r, 2] * al[s, 2]
        _cross(w[s], Iwv, tmp)
        for r in range(3):
            tmp2[r] = seg_mass[s] * acom[s, r]
        _cross(com[s], tmp2, Iwv)
        for r in range(3):
            Nb[s, r] += Ial[r] + tmp[r] + Iwv[r]
        ps = seg_parent[s]
        if ps >= 0:
            for r in range(3):
                Fb[ps, r] += Fb[s, r]; Nb[ps, r] += Nb[s, r]
                Fs[ps, r] += Fs[s, r]; Ns[ps, r] += Ns[s, r]
    # joint-space equations M qdd = tau - bias
    M = work[0:J, 6:6 + J]
    rhs = work[0:J, 6 + J]
    for j in range(J):
        c = j_child[j]
        # moment about p_j: N - p_j x F
        _cross(pj[j], Fs[c], tmp)
        _cross(pj[j], Fb[c], tmp2)
        tau = 0.0
        bias = 0.0
        for r in range(3):
            tau += a[j, r] * (Ns[c, r] - tmp[r])
            bias += a[j, r] * (Nb[c, r] - tmp2[r])
        rhs[j] = tau - bias - joint_damping * qd[j]       # viscous joint damping, implicit (M += h c below)
        for k in range(J):
            acc = 0.0
            for s in range(S):
                if anc[j, s] and anc[k, s]:
                    for r in range(3):
                        d0 = com[s, r] - pj[j, r]
                        tmp[r] = d0
                    _cross(a[j], tmp, tmp2)      # J_v column of j at COM of s
                    for r in range(3):
                        tmp[r] = com[s, r] - pj[k, r]
                    _cross(a[k], tmp, vk)
                    acc += seg_mass[s] * (tmp2[0] * vk[0] + tmp2[1] * vk[1] + tmp2[2] * vk[2])
                    for r in range(3):
                        acc += a[j, r] * (Iw[s, r, 0] * a[k, 0] + Iw[s, r, 1] * a[k, 1] + Iw[s, r, 2] * a[k, 2])
            M[j, k] = acc
    for j in range(J):
        if j_type[j] != 1:                       # fixed joint: no motion
            for k in range(J):
                M[j, k] = 0.0
                M[k, j] = 0.0
            M[j, j] = 1.0
            rhs[j] = 0.0
            continue
        # end stop: implicit spring-damper on the predicted coordinate (stiffness from the joint's inertia)
        mjj = M[j, j]
        M[j, j] += h * joint_damping
        wl = limit_wh / h
        kl = mjj * wl * wl
        bl = 2.0 * limit_zeta * mjj * wl
        qp = q[j] + h * qd[j]
        pen = 0.0
        if qp > j_range[j, 1]:
            pen = qp - j_range[j, 1]
        elif qp < j_range[j, 0]:
            pen = qp - j_range[j, 0]
        if pen != 0.0:
            M[j, j] += h * h * kl + h * bl
            rhs[j] += -kl * pen - bl * qd[j]
    # solve (Gaussian elimination with partial pivoting; J is small)
    qdd = work[0:J, 7 + J]
    for i in range(J):
        piv = i
        for r in range(i + 1, J):
            if abs(M[r, i]) > abs(M[piv, i]):
                piv = r
        if piv != i:
            for c in range(J):
                t_ = M[i, c]; M[i, c] = M[piv, c]; M[piv, c] = t_
            t_ = rhs[i]; rhs[i] = rhs[piv]; rhs[piv] = t_
        for r in range(i + 1, J):
            fac = M[r, i] / M[i, i]
            for c in range(i, J):
                M[r, c] -= fac * M[i, c]
            rhs[r] -= fac * rhs[i]
    for i in range(J - 1, -1, -1):
        acc = rhs[i]
        for c in range(i + 1, J):
            acc -= M[i, c] * qdd[c]
        qdd[i] = acc / M[i, i]
    for j in range(J):
        if not math.isfinite(qdd[j]):
            return False
    for j in range(J):
        if j_type[j] == 1:
            qd[j] += h * qdd[j]
            q[j] += h * qd[j]
    forward_kinematics(q, seg_order, seg_joint, j_parent, j_axis, j_centre, j_rest, seg_R, seg_t)
    return True


# ------------------------------------------------------------------------------------ integration
@njit(cache=True, fastmath={'contract'})
def integrate(h, x, v, f, inv_den, mass, xn, vn, free_idx, att_idx, att_seg, rest, seg_R, seg_t, gravity, vel_damp):
    """Symplectic Euler for the free vertices (v += h (f inv_den + g); v *= 1 - h c_v; x += h v; inv_den
    = 1/m explicit, 1/(m + h b + h^2 kappa) diagonally implicit) and the
    segment pose for bone-attached ones (x = R_s X + t_s, v = dx/h). Reads x, v, writes xn, vn (double
    buffer: a discarded step leaves x, v untouched). Returns (max speed^2, kinetic energy of the free
    vertices)."""
    vmax2 = 0.0
    ke = 0.0
    damp = 1.0 - h * vel_damp
    g0, g1, g2 = h * gravity[0], h * gravity[1], h * gravity[2]
    for k in range(free_idx.shape[0]):
        i = free_idx[k]
        hm = h * inv_den[i]
        a = (v[i, 0] + hm * f[i, 0] + g0) * damp
        b = (v[i, 1] + hm * f[i, 1] + g1) * damp
        c = (v[i, 2] + hm * f[i, 2] + g2) * damp
        vn[i, 0] = a; vn[i, 1] = b; vn[i, 2] = c
        xn[i, 0] = x[i, 0] + h * a; xn[i, 1] = x[i, 1] + h * b; xn[i, 2] = x[i, 2] + h * c
        sp = a * a + b * b + c * c
        ke += sp * mass[i]
        if not (sp <= vmax2):
            vmax2 = sp if sp == sp else np.inf
    ih = 1.0 / h
    for k in range(att_idx.shape[0]):
        i = att_idx[k]
        s = att_seg[k]
        X, Y, Z = rest[i, 0], rest[i, 1], rest[i, 2]
        sp = 0.0
        for r in range(3):
            xr = seg_R[s, r, 0] * X + seg_R[s, r, 1] * Y + seg_R[s, r, 2] * Z + seg_t[s, r]
            d = (xr - x[i, r]) * ih
            vn[i, r] = d
            xn[i, r] = xr
            sp += d * d
        if not (sp <= vmax2):
            vmax2 = sp if sp == sp else np.inf
    return vmax2, 0.5 * ke


# ------------------------------------------------------------------------------------ measures
@njit(cache=True)
def cell_volumes(x, off, cv, out):
    """Signed volume of each prism cell [m^3] by the divergence theorem on its triangulated surface:
    bottom ring (fan, outward = down), top ring (fan), each side quad split along b_i - t_{i+1}.
    Positive for the model's convention (rings counter-clockwise seen from +z)."""
    for c in range(off.shape[0] - 1):
        a0 = off[c]
        n = (off[c + 1] - a0) // 2
        vol = 0.0
        for t in range(1, n - 1):      # bottom: (b0, b_{t+1}, b_t); top: (t0, t_t, t_{t+1})
            vol += _tri(x, cv[a0], cv[a0 + t + 1], cv[a0 + t])
            vol += _tri(x, cv[a0 + n], cv[a0 + n + t], cv[a0 + n + t + 1])
        for t in range(n):
            u = (t + 1) % n
            b0, b1, t0, t1 = cv[a0 + t], cv[a0 + u], cv[a0 + n + t], cv[a0 + n + u]
            vol += _tri(x, b0, b1, t1)
            vol += _tri(x, b0, t1, t0)
        out[c] = vol


@njit(cache=True)
def _tri(x, i, j, k):
    return (x[i, 0] * (x[j, 1] * x[k, 2] - x[j, 2] * x[k, 1])
            + x[i, 1] * (x[j, 2] * x[k, 0] - x[j, 0] * x[k, 2])
            + x[i, 2] * (x[j, 0] * x[k, 1] - x[j, 1] * x[k, 0])) / 6.0


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
