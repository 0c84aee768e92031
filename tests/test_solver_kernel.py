"""The cell kernel (kernels.cell_forces: SIMD across cells, in blocks of cells of one size) against the
plain per-cell loop it replaced, kept below verbatim as the reference: the same forces, energies,
rotations and pressures to rounding, on the bundled anatomy (both parameter sets) and on synthetic
cells of mixed sizes (odd sizes, partial blocks, muscle and fat, damped and undamped, with and
without volume term or active tension in one block); bit-identical results across processes; the
divergence check naming the lowest bad cell."""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from tissue_sim.core import solver
from tissue_sim.core.solver import kernels as K
from tissue_sim.core.solver.kernels import FORCE_BOUND, NEWTON_DONE


# ------------------------------------------------------------------------------------ reference (the per-cell kernel)
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


@njit(cache=True, fastmath={'contract'})
def _reference_cell_forces(x, v, f, quat, off, cv, X0, Qinv, fibre, cell_muscle, lam, act, kc, kact, damp_b,
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


# ------------------------------------------------------------------------------------ helpers
def _run_both(x, v, quat, lam, act, pressure, vol_gain, volume_actual, iters, csr, cells):
    """(new, reference) results of one call each on copies of the mutable inputs: (bad, f, quat,
    pressure, cell_energy)."""
    off, cv, X0, Qinv, fibre, cell_muscle, k, k_active, damp_b, k_volume, q_tr, q_ff, rest_length = csr
    out = []
    for new in (True, False):
        f, q, p, e = np.zeros_like(x), quat.copy(), pressure.copy(), np.zeros(off.size - 1)
        if new:
            ln = np.full(off.size - 1, np.nan)
            bad = K.cell_forces(x, v, f, q, cells, lam, act, volume_actual, iters, e, p, vol_gain, K.cell_work(cells), ln)
            # the axial length it reports: the ring-centroid distance (even sizes; odd: |sum top - sum bottom| / half)
            sizes = np.diff(off)
            ref = np.empty(off.size - 1)
            K.cell_axial_lengths(x, off, cv, ref)
            even = sizes % 2 == 0
            assert np.allclose(ln[even], ref[even], rtol=1e-12, atol=1e-15, equal_nan=True), 'cell_length'
            fin = np.array([np.isfinite(x[cv[off[c]:off[c + 1]]]).all() for c in range(off.size - 1)])
            assert np.all(np.isfinite(ln[fin])), 'cell_length'
        else:
            bad = _reference_cell_forces(x, v, f, q, off, cv, X0, Qinv, fibre, cell_muscle, lam, act, k, k_active,
                                         damp_b, volume_actual, iters, e, k_volume, p, vol_gain, q_tr, q_ff,
                                         rest_length)
        out.append((bad, f, q, p, e))
    return out


def _assert_agree(new, ref):
    bad, f, q, p, e = new
    rbad, rf, rq, rp, re = ref
    assert bad == rbad == -1
    scale = np.abs(rf).max()
    assert scale > 0
    assert np.abs(f - rf).max() <= 1e-12 * scale
    assert np.abs(q - rq).max() <= 1e-12
    assert np.abs(p - rp).max() <= 1e-12 * max(np.abs(rp).max(), 1e-300)
    assert np.abs(e - re).max() <= 1e-10 * np.abs(re).max()


def _csr(sim):
    return (sim.off, sim.cv, sim.X0, sim.Qinv, sim.fibre, sim.cell_muscle, sim.k, sim.k_active, sim.damp_b,
            sim.k_volume, sim.q_tr, sim.q_ff, sim.rest_length)


def _mixed_cells(rng, sizes_counts, n_vertices=400, n_muscles=3, fat_sizes=()):
    """Random cells (vertices drawn from a shared pool, so cells share vertices, but no two share a ring)
    of the given sizes: CSR arrays and per-cell constants as compile_model computes them, and a packed
    layout. Cells of a size in fat_sizes are all fat (no volume, no tension)."""
    rest = rng.normal(scale=0.02, size=(n_vertices, 3))
    sizes = np.concatenate([np.full(c, n) for n, c in sizes_counts])
    rng.shuffle(sizes)                                   # sizes interleaved in cell order
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    cv = np.concatenate([rng.choice(n_vertices, n, replace=False) for n in sizes]).astype(np.int32)
    return (rest,) + _cells(rng, rest, off, cv, n_muscles, np.isin(sizes, fat_sizes))


def _stacked_cells(rng, columns, ring=6, n_muscles=3):
    """Prisms stacked in columns, each cell's top ring the next one's bottom ring (shared vertices), as
    the model builder makes them: columns = [(number of cells, closed), ...]; a closed column is a loop of
    cells around an axis (its last cell's top ring is its first cell's bottom ring: a cycle of rings)."""
    rest, off, cv, nv = [], [0], [], 0
    for c, (cells, closed) in enumerate(columns):
        n_rings = cells if closed else cells + 1
        angle = np.arange(ring) * 2 * np.pi / ring
        first = nv
        for r in range(n_rings):
            if closed:                  # rings around the z axis of this column, radius 0.1
                phi = 2 * np.pi * r / n_rings
                centre = np.array([0.1 * np.cos(phi), 0.1 * np.sin(phi), 0.2 * c])
                radial, up = np.array([np.cos(phi), np.sin(phi), 0.0]), np.array([0.0, 0.0, 1.0])
            else:
                centre, radial, up = np.array([0.05 * c, 0.0, 0.01 * r]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
            rest.append(centre + 0.004 * (np.cos(angle)[:, None] * radial + np.sin(angle)[:, None] * up)
                        + rng.normal(scale=3e-4, size=(ring, 3)))
            nv += ring
        for k in range(cells):
            bottom = first + ring * k
            top = first + ring * ((k + 1) % n_rings)
            cv += list(range(bottom, bottom + ring)) + list(range(top, top + ring))
            off.append(off[-1] + 2 * ring)
    rest = np.concatenate(rest)
    off, cv = np.array(off, np.int64), np.array(cv, np.int32)
    return (rest,) + _cells(rng, rest, off, cv, n_muscles, np.zeros(off.size - 1, bool))


def _cells(rng, rest, off, cv, n_muscles, fat):
    """Per-cell constants (random, as compile_model computes them from rest) and the packed layout."""
    sizes = np.diff(off)
    C = sizes.size
    cell_of = np.repeat(np.arange(C), sizes)
    cent = np.zeros((C, 3))
    np.add.at(cent, cell_of, rest[cv])
    cent /= sizes[:, None]
    X0 = rest[cv] - cent[cell_of]
    Q = np.zeros((C, 3, 3))
    np.add.at(Q, cell_of, X0[:, :, None] * X0[:, None, :])
    fibre = rng.normal(size=(C, 3))
    fibre /= np.linalg.norm(fibre, axis=1)[:, None]
    muscle = np.where((rng.random(C) < 0.6) & ~fat, rng.integers(0, n_muscles, C), -1).astype(np.int32)
    k = rng.uniform(50.0, 200.0, C)
    k_active = np.where((muscle >= 0) & (rng.random(C) < 0.7), rng.uniform(10.0, 80.0, C), 0.0)
    damp_b = np.where(rng.random(C) < 0.7, rng.uniform(0.1, 2.0, C), 0.0)
    k_volume = np.where((muscle >= 0) & (rng.random(C) < 0.8), rng.uniform(1.0, 20.0, C), 0.0)
    rest_length = np.zeros(C)
    K.cell_axial_lengths(rest, off, cv, rest_length)
    csr = (off, cv, X0, np.linalg.inv(Q), fibre, muscle, k, k_active, damp_b, k_volume, np.trace(Q, axis1=1, axis2=2),
           np.einsum('ci,cij,cj->c', fibre, Q, fibre), rest_length)
    return csr, K.pack_cells(off, cv, X0, muscle, k, k_active, damp_b, k_volume, csr[10], csr[11],
                             rest_length, fibre, csr[3])


def _ring_entries(cells):
    """How many ring-vertex entries the layout computes (real slots of real lanes)."""
    rings = cells[2]
    return int((rings[:, 0] * rings[:, 3]).sum())


def _random_state(rng, rest, C):
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    x = rest @ R.T * 1.05 + rng.normal(scale=0.002, size=rest.shape) + [0.1, -0.2, 0.3]
    v = rng.normal(scale=0.3, size=rest.shape)
    quat = rng.normal(size=(C, 4))                       # warm starts away from the answer: several iterations
    quat /= np.linalg.norm(quat, axis=1)[:, None]
    return x, v, quat


# ------------------------------------------------------------------------------------ tests
@pytest.mark.parametrize('preset', ['paper', 'physical'])
def test_matches_the_per_cell_kernel_on_the_default_model(default_tm, preset):
    sim = solver.compile_model(default_tm, getattr(solver.Params, preset)(volume_relax_time=0.005))   # (pressures too)
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    solver.step(sim, st, ctrl, n_steps=60)               # contracting: lam < 1, deformed, moving, pressures built up
    rng = np.random.default_rng(3)
    v = st.v + rng.normal(scale=0.01, size=st.v.shape)
    p = sim.params
    assert np.any(st.lam < 1) and np.any(st.pressure != 0)
    new, ref = _run_both(st.x, v, st.quat, st.lam, ctrl.activation, st.pressure, 0.01, p.volume_mode == 'actual',
                         p.rotation_iterations, _csr(sim), sim.cell_blocks)
    _assert_agree(new, ref)


@pytest.mark.parametrize('volume_actual,iters', [(True, 1), (False, 20), (True, 0)])
def test_matches_the_per_cell_kernel_on_mixed_cell_sizes(volume_actual, iters):
    rng = np.random.default_rng(7)
    # sizes: odd (rings of two sizes, a padding slot), small, several blocks, a single cell, an all-fat size
    # (the kernel's version compiled without muscle, volume and tension)
    rest, csr, cells = _mixed_cells(rng, [(5, 7), (8, 2 * K.BLK + 3), (12, K.BLK - 1), (24, 9), (9, 1), (6, 20)],
                                    fat_sizes=(6,))
    C = csr[0].size - 1
    groups, ids = cells[0], cells[1]
    assert np.array_equal(np.sort(ids[ids >= 0]), np.arange(C))          # every cell in exactly one lane
    assert sorted(groups[:, 0]) == [5, 6, 8, 9, 12, 24]                  # one group of lanes per size
    assert groups[groups[:, 0] == 6, 4].tolist() == [1] and groups[groups[:, 0] != 6, 4].sum() == 0   # plain
    assert _ring_entries(cells) == csr[0][-1]                            # nothing shared: every ring once per cell
    x, v, quat = _random_state(rng, rest, C)
    lam, act = np.array([0.7, 1.0, 0.85]), np.array([1.0, 0.0, 0.4])
    pressure = rng.normal(scale=0.5, size=C)
    new, ref = _run_both(x, v, quat, lam, act, pressure, 0.05, volume_actual, iters, csr, cells)
    _assert_agree(new, ref)
    assert iters == 0 or np.abs(new[2] - quat).max() > 0.1               # the rotations did move


def test_shared_rings_are_computed_once_and_agree():
    """Columns of prisms (the builder's shape): each shared ring is summed and forced once for its two
    cells. Columns longer than a lane (cut: the ring at a cut twice), shorter ones (lanes pass from one
    column to the next through a dummy position) and a closed loop of cells (a cycle of rings)."""
    rng = np.random.default_rng(5)
    columns = [(120, False), (3, False), (1, False), (60, True), (47, False), (29, False)]
    rest, csr, cells = _stacked_cells(rng, columns)
    C = csr[0].size - 1
    ids = cells[1]
    assert np.array_equal(np.sort(ids[ids >= 0]), np.arange(C))
    distinct_rings = sum(n if closed else n + 1 for n, closed in columns)
    entries = _ring_entries(cells)
    assert entries < 0.6 * csr[0][-1]                                     # vs 12 entries per cell
    assert distinct_rings * 6 <= entries <= (distinct_rings + K.BLK + 1) * 6     # at most one extra ring per cut
    x, v, quat = _random_state(rng, rest, C)
    lam, act = np.array([0.75, 1.0, 0.9]), np.array([1.0, 0.3, 0.0])
    pressure = rng.normal(scale=0.5, size=C)
    for volume_actual, iters in ((True, 1), (False, 20)):
        new, ref = _run_both(x, v, quat, lam, act, pressure, 0.05, volume_actual, iters, csr, cells)
        _assert_agree(new, ref)


def test_divergence_names_the_lowest_bad_cell():
    rng = np.random.default_rng(11)
    rest, csr, cells = _mixed_cells(rng, [(8, 40), (6, 20)])
    off, cv = csr[0], csr[1]
    x = rest.copy()
    i = cv[off[30]]                                      # a vertex of cell 30 (and maybe of lower cells)
    x[i] = np.nan
    first = int(np.flatnonzero([i in cv[off[c]:off[c + 1]] for c in range(off.size - 1)])[0])
    C = off.size - 1
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (C, 1))
    lam, act = np.ones(3), np.ones(3)
    (bad, *_), (rbad, *_) = _run_both(x, np.zeros_like(x), quat, lam, act, np.zeros(C), 0.0, True, 1, csr, cells)
    assert bad == rbad == first


_RUN = """
import hashlib, sys
sys.path.insert(0, {src!r})
from tissue_sim.core import solver
from tissue_sim.core.solver import phantom
sim = solver.compile_model(phantom.knee(n_gaps=6, fat_sectors=4), solver.Params.{preset}())
for t, st in solver.simulate(sim, 0.05, {{'hamstrings': [(0, 0.0), (0.02, 1.0)]}}, every=10):
    pass
digest = hashlib.sha256(st.x.tobytes() + st.v.tobytes() + st.q.tobytes() + st.quat.tobytes()).hexdigest()
"""


@pytest.mark.parametrize('preset', ['paper', 'physical'])
def test_bit_identical_across_processes(preset):
    """The same run in this process (after whatever ran before it) and in a fresh one."""
    code = _RUN.format(src=str(Path(__file__).resolve().parents[1] / 'src' / 'tissue_sim'), preset=preset)
    here = {}
    exec(code, here)
    there = subprocess.run([sys.executable, '-c', code + 'print(digest)'], capture_output=True, text=True, check=True)
    assert here['digest'] == there.stdout.strip()


def test_the_fused_gather_is_compiled_noalias():
    """The pinned numba takes the noalias option (else the fused gather silently stays scalar: right
    results, ~10 % slower), and _ring_moments is compiled with it: every array argument noalias in its IR."""
    assert K.NOALIAS == {'_noalias': True}
    from numba.core import compiler
    assert 'noalias' in compiler.Flags.options              # the flag the option maps to still exists
    fn = K._ring_moments.py_func
    ir = njit(fastmath={'contract'}, error_model='numpy', **K.NOALIAS)(fn)
    rs, gv = np.zeros(K.N_R * K.BLK), np.zeros(6 * 2 * K.BLK)
    x = np.arange(30.0)
    ir(rs, gv, np.zeros(2 * 3 * K.BLK), 2, 2, x, x, np.zeros((2, K.BLK), np.uint32) + 9)    # vertex 3: offset 3 * 3
    text = next(iter(ir.inspect_llvm().values()))
    define = next(line for line in text.splitlines() if line.startswith('define') and '_ring_moments' in line)
    assert define.count('noalias') >= 8                     # retptr, excinfo + the data pointers of the arrays
    assert rs[K.R_O * K.BLK] == 9.0 and gv[0] == 9.0         # gathered x[3 * 3] through the slot offset


def test_lanes_per_block_follow_the_cpu():
    """32 lanes where LLVM emits 512-bit vectors by default (AMD Zen 4 and later), else 16; the module's
    BLK is the choice for the CPU numba compiles for, and a whole number of 8-double vectors."""
    assert K.lanes_for_cpu('znver4') == K.lanes_for_cpu('znver5') == 32
    for name in ('znver3', 'znver2', 'skylake-avx512', 'haswell', 'generic', 'neoverse-n1'):
        assert K.lanes_for_cpu(name) == 16, name
    assert K.BLK == K.lanes_for_cpu() and K.BLK % 8 == 0


@pytest.mark.slow
def test_the_other_lane_width_matches_the_reference_too():
    """On a CPU that runs 32 lanes, the 16-lane layout (what every other CPU runs) passes this file's
    tests too: a fresh process compiling for NUMBA_CPU_NAME=generic (a CPU name of its own in numba's
    cache index, so the two layouts never share cached code)."""
    if K.BLK == 16:
        pytest.skip('this CPU runs the 16-lane layout already (the tests above cover it)')
    import os
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, NUMBA_CPU_NAME='generic')
    probe = subprocess.run([sys.executable, '-c', 'import sys; sys.path.insert(0, sys.argv[1]); '
                            'from tissue_sim.core.solver import kernels as K; print(K.BLK)', str(root / 'src' / 'tissue_sim')],
                           capture_output=True, text=True, env=env, check=True)
    assert probe.stdout.strip() == '16'
    run = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-m', 'not slow', '-p', 'no:cacheprovider',
                          str(Path(__file__).resolve())], capture_output=True, text=True, env=env, cwd=root)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert ' passed' in run.stdout and 'failed' not in run.stdout
