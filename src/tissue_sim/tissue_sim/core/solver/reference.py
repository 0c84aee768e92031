"""The readable step: the solver's physics in plain numpy (docs/method.md sections 2-3, docs/solver.md).

``reference_step(sim, state, activation)`` advances a State like ``step()`` does, in the paper's order:
1. muscle tension (contraction state, every cell's force), 2. skeleton, 3. soft tissue, 4. bone contact. Cells are rows of a
padded array (one cell per row), the rotation of each cell is the exact polar factor by a batched SVD.
It is the definition the fast kernels (cells.py: SIMD lanes along chains of cells, a warm-started Newton
rotation) are tested against (tests/test_solver_reference.py); it is ~150x slower (bench/solver.py).
"""
from __future__ import annotations

import collections

import numpy as np

from tissue_sim.core.solver import cells as CK, contact as CT, implicit as IM, muscle as MU, skeleton as SK
from tissue_sim.core.solver.measures import via_pulls
from tissue_sim.core.solver.model import SimModel, State, substeps_for

Padded = collections.namedtuple('Padded', 'idx mask bottom X0')   # (C, P) vertex, real slot, bottom ring; (C, P, 3)


def padded(cells) -> Padded:
    """The cells (CSR ``off``, ``cv``, ``X0``) as rows of P = the largest cell size, padding repeating vertex 0."""
    sizes = np.diff(cells.off)
    slot = np.arange(sizes.max(initial=1))[None, :]
    mask = slot < sizes[:, None]
    at = np.where(mask, cells.off[:-1, None] + slot, 0)
    return Padded(np.where(mask, cells.cv[at], 0), mask, slot < (sizes // 2)[:, None],
                  np.where(mask[..., None], cells.X0[at], 0.0))


def polar_rotation(B: np.ndarray) -> np.ndarray:
    """(C, 3, 3) the rotation R maximising tr(R^T B) (the polar factor of B; a proper rotation also for
    inverted B), by SVD."""
    U, _, Vt = np.linalg.svd(B)
    U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
    return U @ Vt


def bound_scale(g2, cap):
    """The volume terms' bound (SimModel.volume_cap; docs/solver.md "The volume term's bound"): per cell the factor
    cap / g2 of its volume force where its squared gradient norm g2 exceeds a bound cap > 0, else 1."""
    return np.where((cap > 0) & (g2 > cap), cap / np.where(g2 > 0, g2, 1.0), 1.0)


def cell_forces(cells, pad: Padded, x, v, lam, act, pressure, vol_gain, volume_actual):
    """Force (V, 3) [N] of every cell on its vertices: shape matching to the contracted rest shape, volume,
    deformation damping, active axial tension (docs/solver.md "Elastic cells", "Contraction"). ``cells``: a
    SimModel (or anything with its cell arrays); lam, act (M,) the contraction state and the tension's
    activation; pressure (C,) the integral volume term, updated in place (vol_gain = h / volume_relax_time);
    the volume force scaled by volume_cap / |grad det D|^2 where that is above a cell's volume_cap > 0.
    Returns f, cell energy (C,) [J], axial length (C,) [m] (ring-centroid distance), rotations (C, 3, 3)."""
    m = pad.mask[..., None]
    n = pad.mask.sum(1)
    xc, vc = x[pad.idx] * m, v[pad.idx] * m
    c = xc.sum(1) / n[:, None]                                   # centroid
    r = (xc - c[:, None]) * m                                    # vertices about it
    A = np.einsum('cpi,cpj->cij', r, pad.X0)                     # A = sum r X0^T
    D = A @ cells.Qinv                                           # best-fit affine deformation
    mus = cells.cell_muscle >= 0
    la = np.where(mus, lam[np.maximum(cells.cell_muscle, 0)] if lam.size else 1.0, 1.0)
    fib = cells.fibre
    mu = np.clip(np.linalg.norm(np.einsum('cij,cj->ci', D, fib), axis=1), 0.25, 4.0)   # current fibre stretch
    s = np.where(mus, 1.0 / np.sqrt(mu if volume_actual else la), 1.0)                # cross-section factor
    F = (la - s)[:, None, None] * fib[:, :, None] * fib[:, None, :] + s[:, None, None] * np.eye(3)
    R = polar_rotation(A @ F)
    T = R @ F                                                    # goal G_i = c + T X0_i
    gap = np.einsum('cij,cpj->cpi', T, pad.X0) - r               # G_i - x_i
    f = cells.k[:, None, None] * gap
    # volume energy 1/2 kv (det D - 1)^2 (+ the integral term): force g cof(D) Qinv X0_i (the cells whose volume energy
    # is on their enclosed volume instead, k_enclosed > 0: enclosed_forces, below)
    J = np.linalg.det(D)
    kv = np.where(cells.k_enclosed > 0, 0.0, cells.k_volume)
    g = -kv * (J - 1.0)
    pressure += vol_gain * g
    g = np.where(kv > 0, g + pressure, 0.0)
    cof = np.stack([np.cross(D[:, 1], D[:, 2]), np.cross(D[:, 2], D[:, 0]), np.cross(D[:, 0], D[:, 1])], axis=1)
    grad = np.einsum('cij,cpj->cpi', cof @ cells.Qinv, pad.X0)          # grad det D: one row per vertex
    # the volume term's bound (volume_cap > 0): beyond it the force scaled by volume_cap / |grad det D|^2
    g = g * bound_scale((grad * grad * m).sum((1, 2)), cells.volume_cap)
    f += g[:, None, None] * grad
    # deformation damping: -b (v_i - vbar - w x r_i), w = I^-1 L the cell's rigid angular velocity
    vbar = vc.sum(1) / n[:, None]
    Y = np.einsum('cpi,cpj->cij', r, r)
    tr = np.trace(Y, axis1=1, axis2=2)
    inertia = (tr * (1 + 1e-9) + 1e-300)[:, None, None] * np.eye(3) - Y
    w = np.linalg.solve(inertia, np.cross(r, vc).sum(1)[..., None])[..., 0]
    f -= cells.damp_b[:, None, None] * (vc - vbar[:, None] - np.cross(w[:, None], r)) * m
    # active tension T = a ka n/4 max(l - lam L, 0) between the ring centroids, along their axis u
    half = n // 2
    u = ((xc * (~pad.bottom & pad.mask)[..., None]).sum(1) - (xc * pad.bottom[..., None]).sum(1)) / half[:, None]
    ln = np.linalg.norm(u, axis=1)
    stretch = np.maximum(ln - la * cells.rest_length, 0.0)
    ka = np.where(mus, act[np.maximum(cells.cell_muscle, 0)] if act.size else 0.0, 0.0) * cells.k_active * 0.25 * n
    pull = (ka * stretch * 2.0 / (n * np.where(ln > 0, ln, 1.0)))[:, None] * u            # on each bottom vertex
    f += np.where(pad.bottom[..., None], 1.0, -1.0) * pull[:, None] * m
    energy = 0.5 * cells.k * (gap * gap * m).sum((1, 2)) + 0.5 * kv * (J - 1) ** 2 + 0.5 * ka * stretch ** 2
    out = np.zeros_like(x)
    np.add.at(out, pad.idx[pad.mask], f[pad.mask])
    if np.any(cells.k_enclosed > 0):
        fe, ee = enclosed_forces(cells, x)
        out += fe
        energy = energy + ee
    er = cells.end_rings
    for e, (c, top) in enumerate(zip(er.cell, er.top)):    # end_ring_pull 'bound': on a partly bound end ring the
        free = er.free[er.free_off[e]:er.free_off[e + 1]]   # tension's pull on its free vertices acts on its bound ones
        bound = er.bound[er.bound_off[e]:er.bound_off[e + 1]]
        p = (-1.0 if top else 1.0) * pull[c]
        out[free] -= p
        out[bound] += p * len(free) / len(bound)
    return out, energy, ln, R


def enclosed_forces(cells, x):
    """The volume energy on the enclosed volume (Params.volume_measure 'enclosed'; volume.enclosed_lanes is the same
    compiled): per cell with k_enclosed > 0, V = its sign x the prism volume of core.geometry.prism_volumes (caps as
    fans about the ring centroids, side quads as four triangles about their centroids), E = 1/2 k (V/V0 - 1)^2 and
    the force -k (V/V0 - 1) / V0 dV/dx, dV/dx from d(a . b x c) = (b x c, c x a, a x b) per triangle, each centroid's
    share going to its vertices, times min(1, cap / |dV/dx / V0|^2) where the cell's bound cap (SimModel.volume_cap)
    is > 0. Returns (forces (V, 3), energies (C,))."""
    f, energy = np.zeros_like(x), np.zeros(len(cells.k_enclosed))
    sizes = np.diff(cells.off)
    on = cells.k_enclosed > 0
    for size in np.unique(sizes[on]):
        cs = np.flatnonzero(on & (sizes == size))
        n = size // 2
        idx = cells.cv[cells.off[cs][:, None] + np.arange(size)]
        P = x[idx] - x[idx[:, :1]]                                   # (c, 2n, 3), about the first vertex
        B, T = P[:, :n], P[:, n:]
        Bn, Tn = np.roll(B, -1, axis=1), np.roll(T, -1, axis=1)
        cb, ct = B.mean(1, keepdims=True) + 0 * B, T.mean(1, keepdims=True) + 0 * T
        qc = (B + Bn + Tn + T) / 4.0
        gB, gBn, gT, gTn = (np.zeros_like(B) for _ in range(4))
        gcb, gct, gq = np.zeros_like(B), np.zeros_like(T), np.zeros_like(B)
        V = np.zeros(len(cs))
        for w, (a, ga), (b, gb), (c, gc) in (
                (-1.0, (cb, gcb), (B, gB), (Bn, gBn)), (1.0, (ct, gct), (T, gT), (Tn, gTn)),
                (1.0, (qc, gq), (B, gB), (Bn, gBn)), (1.0, (qc, gq), (Bn, gBn), (Tn, gTn)),
                (1.0, (qc, gq), (Tn, gTn), (T, gT)), (1.0, (qc, gq), (T, gT), (B, gB))):
            V += w * np.einsum('cij,cij->c', a, np.cross(b, c))
            ga += w * np.cross(b, c)
            gb += w * np.cross(c, a)
            gc += w * np.cross(a, b)
        gB += np.roll(gBn, 1, axis=1) + gq / 4.0 + np.roll(gq, 1, axis=1) / 4.0 + gcb.sum(1, keepdims=True) / n
        gT += np.roll(gTn, 1, axis=1) + gq / 4.0 + np.roll(gq, 1, axis=1) / 4.0 + gct.sum(1, keepdims=True) / n
        sign, v0, k = cells.cell_sign[cs], cells.rest_volume[cs], cells.k_enclosed[cs]
        V = sign * V / 6.0
        e = V / v0 - 1.0
        energy[cs] = 0.5 * k * e * e
        grad = np.concatenate([gB, gT], axis=1) * (sign / 6.0)[:, None, None]      # dV/dx
        scale = bound_scale(np.sum(grad * grad, axis=(1, 2)) / (v0 * v0), cells.volume_cap[cs])
        np.add.at(f, idx, (-k * e / v0 * scale)[:, None, None] * grad)
    return f, energy


def reference_step(sim: SimModel, state: State, activation, dt: float | None = None, joint_lock=None,
                   joint_target=None) -> State:
    """One step of dt (None: params.dt) in n_substeps sub-steps, in place, as step() (no divergence check).
    joint_lock (J,) bool, joint_target (J,) [rad]: Control's joint lock (None: no joint locked)."""
    p, pad = sim.params, padded(sim)
    dt = p.dt if dt is None else float(dt)
    n_sub = sim.n_substeps if dt == p.dt else substeps_for(p, sim.omega_max, sim.damp_rate, dt)
    h = dt / n_sub
    a = np.asarray(activation, np.float64)
    vol_gain = h / p.volume_relax_time if p.volume_relax_time > 0 else 0.0
    inv_den, free = sim.inv_denominator(h), sim.inv_mass > 0
    J = sim.n_joints
    lock = np.zeros(J, bool) if joint_lock is None else np.asarray(joint_lock, bool)
    q_target = sim.j_rest.copy() if joint_target is None else np.asarray(joint_target, np.float64)
    if state.joint_lock_torque is None:
        state.joint_lock_torque = np.zeros(J)
    if state.activation is None:
        state.activation = np.zeros(sim.n_muscles)
    if state.contact_wrench is None:
        state.contact_wrench = np.zeros((sim.n_segments, 6))
    u = a                             # the commands: excitations when activation dynamics is on
    fl_on = p.force_length and p.specific_tension > 0
    pe_on = p.passive_force_length and p.specific_tension > 0
    for _ in range(n_sub):
        R0, t0 = state.seg_R.copy(), state.seg_t.copy()        # the segment poses at the sub-step's start (stage 4)
        # 0. activation dynamics (Thelen 2003 eq. 1): da/dt = (u - a) / tau, tau = tau_act (0.5 + 1.5 a) while u > a,
        # else tau_deact / (0.5 + 1.5 a), tau frozen over the sub-step at the midpoint activation of a predictor
        # step; activation_time 0: a = u (the paper)
        if p.activation_time > 0:
            a0, rising = state.activation.copy(), u > state.activation
            tau = lambda act: np.where(rising, p.activation_time * (0.5 + 1.5 * act),        # noqa: E731
                                       p.deactivation_time / (0.5 + 1.5 * act))
            a1 = a0 + (u - a0) * (1.0 - np.exp(-h / tau(a0)))
            state.activation[:] = a0 + (u - a0) * (1.0 - np.exp(-h / tau(0.5 * (a0 + a1))))
        else:
            state.activation[:] = u
        a = state.activation
        # 1. muscle tension: contraction state towards 1 - a (1 - min_stretch), the tension's activation x
        # the force-velocity factor of the last measured muscle velocity x the active force-length factor of the
        # last measured fibre length, every cell's force
        target = 1.0 - a * (1.0 - p.min_stretch)
        shrink = np.maximum(state.lam * p.contraction_rate ** (a * h / p.rate_dt), target)
        state.lam[:] = np.where(state.lam > target, shrink, np.minimum(state.lam / p.relax_rate ** (h / p.rate_dt), target))
        fv_on = p.max_contraction_velocity > 0 and p.specific_tension > 0
        vl0 = p.max_contraction_velocity * sim.muscle_rest_length        # [m/s] v_max L0 of each muscle
        vn = np.divide(state.muscle_velocity, vl0, out=np.zeros_like(vl0), where=vl0 > 0)
        act_t = a * np.array([CK.force_velocity(w, p.fv_max_lengthening) for w in vn]) if fv_on else a.copy()
        # (integrator implicit: every force at the inertial prediction y, bone-attached vertices at x + h v; the solve is
        # backward Euler's over hs from (xs, vs): (x, v) and h, or with BDF2 (4 x - x_prev)/3, (4 v - v_prev)/3 and 2h/3,
        # the past at constant velocity where there is none at h)
        implicit = p.integrator == 'implicit'
        hs, xs, vs = h, state.x.copy(), state.v.copy()
        if implicit and p.implicit_scheme == 'bdf2':
            if state.x_prev is None or state.history_h is None or state.history_h[0] != h:
                state.x_prev, state.v_prev, state.history_h = state.x - h * state.v, state.v.copy(), np.array([h])
            hs, xs, vs = IM.solve_length(p, h), (4 * state.x - state.x_prev) / 3, (4 * state.v - state.v_prev) / 3
        y = np.where(free[:, None], xs + hs * (1.0 - hs * p.velocity_damping) * (vs + hs * sim.gravity),
                     xs + hs * vs) if implicit else state.x
        if fl_on:            # normalised fibre length l of each muscle's source-model path at the joint coordinates
            act_t = act_t * np.exp(-(path_fibres(sim, state.q)[0] - 1.0) ** 2 / p.fl_width)
        # the passive fibre force as joint torques (minus the gradient of its energy in the joint coordinates)
        tau_pe = passive_joint_torques(sim, state.q) if pe_on else np.zeros(J)
        f, state.cell_energy[:], state.cell_length[:], R = cell_forces(
            sim, pad, y, vs, state.lam, act_t, state.pressure, vol_gain, p.volume_mode == 'actual')
        if fv_on:            # each muscle's length (sum of w_c l_c), its filtered lengthening velocity
            mc = sim.cell_muscle >= 0
            length = np.bincount(sim.cell_muscle[mc], (sim.length_weight * state.cell_length)[mc], sim.n_muscles)
            seen = state.muscle_length >= 0
            state.muscle_velocity[seen] += h / (p.fv_filter_time + h) * (
                (length - state.muscle_length)[seen] / h - state.muscle_velocity[seen])
            state.muscle_length[:] = length
        # 2. skeleton: joint torques from the forces on the bone-attached vertices, the point via rings' net forces at
        # their centroids' places, tau_pe and the last sub-step's contact reaction (state.contact_wrench), joint dynamics
        # (a locked hinge is driven to its target, its torque in state.joint_lock_torque), poses
        for s_, where, pull in zip(*via_pulls(sim, f, state.seg_R, state.seg_t)):
            state.contact_wrench[s_] += np.concatenate([pull, np.cross(where, pull)])
        SK.skeleton_step(h, state.q, state.qd, f, y, sim.skeleton, sim.att_idx, sim.att_seg,
                         p.joint_damping, p.limit_omega_dt, p.limit_damping_ratio, state.seg_R, state.seg_t,
                         np.zeros((max(J, 1), 8 + J)), lock, q_target, state.joint_lock_torque, tau_pe,
                         state.contact_wrench)
        state.contact_wrench[:] = 0.0      # (applied: the sheath correction and stage 4 write this sub-step's)
        # 3. soft tissue: symplectic Euler for the free vertices (implicit: implicit.py's correction of y, its
        # local/global iterations from the forces at the last iterate), the bone-attached ones follow their segment
        i, s = sim.att_idx, sim.att_seg
        xa = np.einsum('aij,aj->ai', state.seg_R[s], sim.rest[i]) + state.seg_t[s]
        if implicit:
            past = state.x.copy(), state.v.copy()
            moved = np.zeros_like(state.x)
            moved[i] = xa - y[i]
            state.x[free] = IM.reference_solve(sim, hs, f, y, y, moved)
            state.x[i] = xa
            state.v[:] = (state.x - xs) / hs
            for _ in range(1, p.implicit_iterations):
                f, state.cell_energy[:], state.cell_length[:], R = cell_forces(
                    sim, pad, state.x, state.v, state.lam, act_t, state.pressure, vol_gain, p.volume_mode == 'actual')
                state.x[free] = IM.reference_solve(sim, hs, f, state.x, y, np.zeros_like(state.x))
                state.v[:] = (state.x - xs) / hs
            if sim.contact.s_idx.size:        # the sheath (docs/solver.md "Implicit integrator": the sheath)
                sheath_correction(sim, hs, state.x, state.seg_R, state.seg_t, state.contact_wrench)
                state.v[:] = (state.x - xs) / hs
            if sim.via_seg.size and p.implicit_via_correction:    # the point via rings inside the solve
                _, places, _ = via_pulls(sim, state.x, state.seg_R, state.seg_t)        # (implicit.via_correct)
                state.x[free] += IM.reference_via_solve(sim, hs, state.x, places)
                state.v[:] = (state.x - xs) / hs
            if p.implicit_scheme == 'bdf2':   # this sub-step is the next one's history (stage 4's vertices: below)
                state.x_prev, state.v_prev, state.history_h = past[0], past[1], np.array([h])
        else:
            state.v[:] = (state.v + h * (f * inv_den[:, None] + sim.gravity)) * (1.0 - h * p.velocity_damping)
            state.x[free] += h * state.v[free]
            state.v[i], state.x[i] = (xa - state.x[i]) / h, xa
        # 3b. point via rings: each ring's centroid moved onto its place on its bone by moving its free vertices alike
        if sim.via_seg.size:
            via_stage(sim, hs, state.x, state.v, state.seg_R, state.seg_t, inv_den)
        # 4. fold contact (Params.fold_contact), then bone contact: free vertices closer to a bone than their floor are
        # projected out (Params.bone_contact); the segments take the reaction of each velocity change, for the next sub-step
        if sim.contact.g_seg.size or sim.contact.f_seg.size or sim.contact.w_seg.size:
            before = state.x.copy(), state.v.copy()
            m = np.divide(1.0, inv_den, out=np.zeros_like(inv_den), where=inv_den > 0)
            fold_stage(sim.contact, state.x, state.v, state.seg_R, state.seg_t, R0, t0, h, m, state.contact_wrench)
            wrap_stage(sim.contact, state.x, state.v, state.seg_R, state.seg_t, R0, t0, h, m, state.contact_wrench)
            contact_stage(sim.contact, state.x, state.v, state.seg_R, state.seg_t, R0, t0, h, m, state.contact_wrench)
            if implicit and p.implicit_scheme == 'bdf2':     # a projection is not motion: BDF2 restarts there
                jump = np.any((state.x != before[0]) | (state.v != before[1]), axis=1)
                state.x_prev[jump] = state.x[jump] - h * state.v[jump]
                state.v_prev[jump] = state.v[jump]
        state.f[:] = f
    state.quat[:] = rotation_quaternions(R)
    state.step += 1
    state.time += dt
    return state


def path_fibres(sim, q):
    """The source-model paths at joint coordinates q (docs/solver.md "Force-length"): per muscle part its musculotendon
    length L (P,) = coef . prod_j q_j^powers [m], dL/dq (P, J), the fibre's length along the tendon d = max(L - L_TS, 0)
    and its length lf = sqrt(d^2 + (L_opt sin a)^2) [m], the normalised fibre length lp = lf / L_opt (+ the override's
    shift); per muscle ln (M,): the Fmax-weighted mean of its parts' lp (rest_fibre_lengths without a path).
    Returns ln, lp, L, dL, d, lf."""
    pm, pdata, powers, coef, shift, l0 = MU.path_constants(sim)
    q = np.asarray(q, np.float64)
    qe = q[None, :] ** powers                                              # (T, J); 0^0 = 1
    L = coef @ qe.prod(1)
    dmono = np.stack([powers[:, j] * q[j] ** np.maximum(powers[:, j] - 1, 0) * np.delete(qe, j, axis=1).prod(1)
                      for j in range(q.size)], 1) if q.size else np.zeros((powers.shape[0], 0))
    dL = coef @ dmono
    d = np.maximum(L - pdata[:, 2], 0.0)
    lf = np.sqrt(d ** 2 + pdata[:, 3] ** 2)
    lp = lf / pdata[:, 1] + shift[pm]
    has = np.isin(np.arange(sim.n_muscles), pm)
    ln = np.where(has, np.bincount(pm, pdata[:, 0] * lp, sim.n_muscles), l0)
    return ln, lp, L, dL, d, lf


def passive_joint_torques(sim, q):
    """(J,) [N m] the passive fibre force as joint torques: per part F = Fmax share f_PE(lp) (Params.fl_passive_curve:
    Thelen 2003 eq. 3, 0 for lp <= 1; or De Groote et al. 2016, 0 below 0.2), along the tendon F d / lf, torque
    -F d / lf dL/dq."""
    p = sim.params
    pm, pdata = MU.path_constants(sim)[:2]
    fmax = MU.muscle_constants(sim)[0]
    ln, lp, L, dL, d, lf = path_fibres(sim, q)
    k, e0 = p.fl_passive_shape, p.fl_passive_strain
    if p.fl_passive_curve == 'thelen':
        f = np.where(lp > 1.0, (np.exp(k * (lp - 1.0) / e0) - 1.0) / (np.exp(k) - 1.0), 0.0)
    else:
        o = np.exp(k * (MU.DGF_MIN_LENGTH - 1.0) / e0)
        f = np.where(lp > MU.DGF_MIN_LENGTH, (np.exp(k * (lp - 1.0) / e0) - o) / (np.exp(k) - o), 0.0)
    Ft = fmax[pm] * pdata[:, 0] * f * np.divide(d, lf, out=np.zeros_like(d), where=lf > 0)
    return -(Ft @ dL)


def grid_sample(cg, b, P):
    """Trilinear value [m] of bone grid b of ContactGrids cg at rest-frame points P (n, 3) and its gradient (n, 3)
    in grid units; +inf and 0 outside the grid's box."""
    dims = cg.g_dims[b]
    phi = cg.g_phi[cg.g_off[b]:cg.g_off[b + 1]].reshape(dims).astype(np.float64)
    g = (P - cg.g_origin[b]) * cg.g_inv_h[b]                               # grid coordinates
    inside = np.all((g >= 0) & (g <= dims - 1), axis=1)
    ijk = np.minimum(np.floor(np.where(inside[:, None], g, 0)).astype(np.int64), dims - 2)   # the cell's lower corner
    fr = np.where(inside[:, None], g - ijk, 0.0)                          # position in the cell, [0, 1]^3
    value, grad = np.zeros(len(P)), np.zeros((len(P), 3))
    for corner in np.ndindex(2, 2, 2):                                     # weights prod (1 - f) or f per axis
        c = phi[ijk[:, 0] + corner[0], ijk[:, 1] + corner[1], ijk[:, 2] + corner[2]]
        w = np.where(np.array(corner) == 1, fr, 1.0 - fr)                  # (n, 3) per-axis weights
        sign = np.where(np.array(corner) == 1, 1.0, -1.0)
        value += c * w.prod(1)
        for a in range(3):
            grad[:, a] += c * sign[a] * np.prod(np.delete(w, a, axis=1), axis=1)
    return np.where(inside, value, np.inf), grad * inside[:, None]


def react(wr, s, share, x, m, dv, h):
    """Segment s takes the reaction of the velocity changes dv (N, 3) of vertices at x (N, 3) with masses m (N,) (the
    integrator's 1/inv_den), share of it (0.5: a bisector plane's two segments): wr[s] += (sum of F = -share m dv / h,
    sum of x x F) (contact._react)."""
    F = -share * m[:, None] * dv / h
    wr[s, :3] += F.sum(axis=0)
    wr[s, 3:] += np.cross(x, F).sum(axis=0)


def via_stage(sim, h, x, v, seg_R, seg_t, inv_den):
    """Stage 3b, the point via rings (SimModel.via_*; integration.hold_via_points compiled), in place: ring r's
    centroid onto p = R_s local_r + t_s by moving its free vertices by d = (p - c) n / n_free (velocities by d / h).
    (Its bone took the ring's net force in stage 2.)"""
    _, places, _ = via_pulls(sim, x, seg_R, seg_t)
    for r in range(sim.via_seg.size):
        ring = sim.via_idx[sim.via_off[r]:sim.via_off[r + 1]]
        free = ring[inv_den[ring] > 0]
        if not free.size:
            continue
        d = (places[r] - x[ring].mean(axis=0)) * ring.size / free.size
        x[free] += d
        v[free] += d / h


def contact_stage(cg, x, v, seg_R, seg_t, R0, t0, h, m=None, wr=None):
    """Stage 4, bone contact (docs/contact.md), in place on the positions and velocities stage 3 wrote: grid by grid
    (cg: the SimModel's ContactGrids; none: nothing), every free vertex whose sampled distance d is below its floor
    moves by (floor - d) along the grid's gradient direction n (world frame), again from there while it is still
    below (by more than contact.PROJECTION_TOL; at most contact.PROJECTIONS times), and its velocity relative to the
    bone (whose velocity there is (x - (R0 p + t0)) / h, p the vertex in the bone's rest frame before the projection,
    R0 t0 the pose at the sub-step's start) loses its inward part along the last n; with friction mu its tangential
    part shrinks by mu x that; the bone takes the reaction (react, with the masses m (V,) into wr (S, 6); None: not
    recorded). No broad phase: every vertex is tested every sub-step (contact.bone_contact gives the same result faster)."""
    free = cg.free_idx
    floor, mu = cg.floor[free], cg.par[1]
    for b, s in enumerate(cg.g_seg):
        p = (x[free] - seg_t[s]) @ seg_R[s]                                 # rest-frame points R^T (x - t)
        d, grad = grid_sample(cg, b, p)
        gn = np.linalg.norm(grad, axis=1)
        hit = (d < floor) & (gn > 0)
        i = free[hit]
        v_bone = (x[i] - (p[hit] @ R0[s].T + t0[s])) / h
        u = np.zeros((len(p), 3))                                           # the last projection's rest-frame normal
        todo = hit.copy()
        for _ in range(CT.PROJECTIONS):
            if not todo.any():
                break
            u[todo] = grad[todo] / gn[todo, None]
            push = (floor[todo] - d[todo])[:, None]
            x[free[todo]] += push * (u[todo] @ seg_R[s].T)
            p[todo] += push * u[todo]
            d[todo], grad[todo] = grid_sample(cg, b, p[todo])               # (outside the box: +inf, done)
            gn[todo] = np.linalg.norm(grad[todo], axis=1)
            todo[todo] = (d[todo] < floor[todo] - CT.PROJECTION_TOL) & (gn[todo] > 0)
        n = u[hit] @ seg_R[s].T                                             # world normals
        rel = v[i] - v_bone
        vn = np.sum(rel * n, axis=1)
        tang = rel - vn[:, None] * n
        vt = np.linalg.norm(tang, axis=1)
        keep = np.maximum(0.0, 1.0 - mu * -vn / np.where(vt > 0, vt, 1.0)) if mu > 0 else np.ones_like(vn)
        keep = np.where((vt > 0) | (mu == 0), keep, 0.0)
        v_new = np.where((vn < 0)[:, None], v_bone + keep[:, None] * tang, v[i])
        if wr is not None:
            react(wr, s, 1.0, x[i], m[i], v_new - v[i], h)
        v[i] = v_new


def wrap_stage(cg, x, v, seg_R, seg_t, R0, t0, h, m=None, wr=None):
    """Stage 4b, the wrap surfaces (docs/contact.md "Wrap surfaces"), in place: cylinder by cylinder (cg.w_*; none:
    nothing), each of its vertices within its length, on its quadrant's side and nearer its axis than its floor moves
    radially onto the floor; its velocity relative to the cylinder (the segment's velocity there, from its pose R0 t0 at
    the sub-step's start) loses its inward radial part; the segment takes the reaction (react, masses m, into wr).
    contact.wrap_contact is the same stage compiled."""
    for w, s in enumerate(cg.w_seg):
        c, a, q, half = cg.w_geo[w, :3], cg.w_geo[w, 3:6], cg.w_geo[w, 6:9], cg.w_geo[w, 10]
        i = cg.w_idx[cg.w_off[w]:cg.w_off[w + 1]]
        floor = cg.w_floor[cg.w_off[w]:cg.w_off[w + 1]]
        p = (x[i] - seg_t[s]) @ seg_R[s]                                    # rest-frame points R^T (x - t)
        along, d, rho = CT.cylinder_coordinates(p, c, a)
        hit = (np.abs(along) <= half) & (d @ q >= 0.0) & (rho < floor) & (rho > 0.0)
        i, p, d, rho, floor = i[hit], p[hit], d[hit], rho[hit], floor[hit]
        v_surf = (x[i] - (p @ R0[s].T + t0[s])) / h
        n = (d / rho[:, None]) @ seg_R[s].T                                 # world radial directions
        x[i] += (floor - rho)[:, None] * n
        vn = np.sum((v[i] - v_surf) * n, axis=1)
        dv = np.where((vn < 0)[:, None], -vn[:, None] * n, 0.0)
        if wr is not None:
            react(wr, s, 1.0, x[i], m[i], dv, h)
        v[i] += dv


def fold_plane(cg, k, seg_R, seg_t):
    """Folding hinge k's bisector plane in the pose (seg_R, seg_t): (unit normal n, point c on the axis, the parent's
    and the child's proximal directions R_p n0 and R_c n0, the flexion -(R_c n0) . (R_p e))."""
    ps, cs = cg.f_seg[k]
    c0, n0, e = cg.f_geo[k, :3], cg.f_geo[k, 3:6], cg.f_geo[k, 6:]
    up_p, up_c = seg_R[ps] @ n0, seg_R[cs] @ n0
    n = (up_p + up_c) / np.linalg.norm(up_p + up_c)
    return n, seg_R[ps] @ c0 + seg_t[ps], up_p, up_c, -up_c @ (seg_R[ps] @ e)


def sheath_offsets(cg, k, x, seg_R, seg_t):
    """The sheath of folding hinge k (Params.sheath_group, docs/contact.md) at positions x: per side (held in the
    parent's frame, then the child's), (i, p, seg, push, u) of its vertices beyond s_r across n0 from their rest
    position in that segment's rest frame: their ids, rest-frame points p = R^T (x - t), the segment, how far they
    move (s_r - |lateral offset|, < 0) along the outward unit u (world) to be back on the radius."""
    n0 = cg.f_geo[k, 3:6]
    out_ = []
    for side, ps in ((1.0, cg.f_seg[k, 0]), (-1.0, cg.f_seg[k, 1])):   # held in the parent's / the child's frame
        sl = np.arange(cg.s_off[k], cg.s_off[k + 1])
        sl = sl[cg.s_side[sl] == side]
        i = cg.s_idx[sl]
        p = (x[i] - seg_t[ps]) @ seg_R[ps]                             # rest-frame points R^T (x - t)
        e = p - cg.s_X[sl]
        lat = e - (e @ n0)[:, None] * n0
        ll = np.linalg.norm(lat, axis=1)
        out = ll > cg.s_r[0]
        i, p, lat, ll = i[out], p[out], lat[out], ll[out]
        out_.append((i, p, ps, cg.s_r[0] - ll, (lat / ll[:, None]) @ seg_R[ps].T))
    return out_


def sheath_correction(sim, h, x, seg_R, seg_t, wr=None):
    """The implicit integrator's sheath correction (implicit.sheath_correct, docs/solver.md "Implicit integrator"):
    the sheathed vertices beyond the radius moved back onto it and the tissue of implicit.sheath_region following
    them, A' w = r with A' = A + diag(k_s) (implicit.sheath_weights) over that region (the rest held) and r = k_s times
    each one's way back (implicit.reference_sheath_solve: scipy's solve of the written-out system). In place on x.
    The segment of each sheathed vertex moved takes the reaction of the force that held it, k_s (d - w) (w: how far
    the solve moved it), into wr (S, 6) (None: not recorded; contact.sheath_reaction)."""
    cg = sim.contact
    d = np.zeros_like(x)
    held = []
    for k in range(cg.f_seg.shape[0]):
        for i, _, seg, push, u in sheath_offsets(cg, k, x, seg_R, seg_t):
            d[i] = push[:, None] * u
            held.append((i, seg))
    if np.any(d):
        x0 = x.copy()
        x[sim.inv_mass > 0] += IM.reference_sheath_solve(sim, h, d)
        if wr is not None:
            ks = IM.sheath_weights(sim, h)
            for i, seg in held:
                react(wr, seg, 1.0, x[i], ks[i], d[i] - (x[i] - x0[i]), 1.0)


def fold_stage(cg, x, v, seg_R, seg_t, R0, t0, h, m=None, wr=None):
    """Stage 4a, the fold contact (docs/contact.md), in place on the positions and velocities stage 3 wrote: for each
    folding hinge k while it is flexed, its vertices i (side s: +1 proximal, -1 distal) with s n . (x_i - c) below their
    floor move onto it along their own segment's proximal direction times s (n the unit normal of the plane through
    the axis bisecting the segments, c a point of the axis; along s n where that direction's s n-component is below
    contact.FOLD_MIN_COS), and their velocity loses the inward part of s (n . v + the plane's rate at x), the plane's
    rate from its pose at the sub-step's start (R0, t0) and now; then each keeps to the flexion side of its own
    segment's plane through the axis (below). First, whatever the angle, the sheath (Params.sheath_group). Each velocity
    change's reaction (react, masses m (V,), into wr (S, 6); None: not recorded) goes to the segment whose plane or
    sheath made it, half to each of the two for the bisector plane. contact.fold_contact is the same stage compiled."""
    if wr is None:
        m, wr = np.zeros(len(x)), np.zeros((int(np.max(cg.f_seg, initial=0)) + 1, 6))
    for k in range(cg.f_seg.shape[0]):
        # the sheath: its vertices keep their offset across n0 from their rest position, in the parent's rest frame,
        # within s_r (scaled back onto it, the axial part kept); their outward velocity relative to the parent goes
        for i, p, ps, push, u in sheath_offsets(cg, k, x, seg_R, seg_t):
            v_seg = (x[i] - (p @ R0[ps].T + t0[ps])) / h
            x[i] += push[:, None] * u
            vn = np.sum((v[i] - v_seg) * u, axis=1)
            dv = -np.maximum(vn, 0.0)[:, None] * u
            react(wr, ps, 1.0, x[i], m[i], dv, h)
            v[i] += dv
        n, c, up_p, up_c, flex = fold_plane(cg, k, seg_R, seg_t)
        if flex <= 0:
            continue
        n_start, c_start = fold_plane(cg, k, R0, t0)[:2]
        sl = slice(cg.f_off[k], cg.f_off[k + 1])
        i, s, lim = cg.f_idx[sl], cg.f_side[sl], cg.f_floor[sl]
        phi = s * ((x[i] - c) @ n)
        hit = (phi < lim) & bool(cg.f_plane[0])                         # (Params.fold_plane)
        i, s, lim, phi = i[hit], s[hit], lim[hit], phi[hit]
        d = s[:, None] * np.where((s > 0)[:, None], up_p, up_c)        # own segment's long axis, away from the plane
        dn = s * (d @ n)
        weak = dn < CT.FOLD_MIN_COS
        d[weak], dn[weak] = s[weak, None] * n, 1.0
        x[i] += ((lim - phi) / dn)[:, None] * d
        rate = ((x[i] - c) @ n - (x[i] - c_start) @ n_start) / h      # the plane's own rate of n . (x - c) at x
        vn = s * (v[i] @ n + rate)
        dv = -np.where(vn < 0, vn * s, 0.0)[:, None] * n
        for seg in cg.f_seg[k]:
            react(wr, seg, 0.5, x[i], m[i], dv, h)
        v[i] += dv
        # the flexion side: each vertex keeps e_own . (x - c) >= its floor (e_own: the flexion direction e in its own
        # segment's pose), moved along e_own, its velocity relative to that plane losing its inward part
        e = cg.f_geo[k, 6:]
        for sgn, seg in ((1.0, cg.f_seg[k, 0]), (-1.0, cg.f_seg[k, 1])):
            sel = cg.f_side[sl] == sgn
            i, lim = cg.f_idx[sl][sel], cg.f_wfloor[sl][sel]
            E, E_start = seg_R[seg] @ e, R0[seg] @ e
            w = (x[i] - c) @ E
            hit = w < lim
            i, lim, w = i[hit], lim[hit], w[hit]
            x[i] += (lim - w)[:, None] * E
            vn = v[i] @ E + ((x[i] - c) @ E - (x[i] - c_start) @ E_start) / h
            dv = -np.minimum(vn, 0.0)[:, None] * E
            react(wr, seg, 1.0, x[i], m[i], dv, h)
            v[i] += dv


def rotation_quaternions(R: np.ndarray) -> np.ndarray:
    """(C, 3, 3) rotations -> (C, 4) unit quaternions x y z w (w >= 0)."""
    w = 0.5 * np.sqrt(np.maximum(1.0 + np.trace(R, axis1=1, axis2=2), 0.0))
    xyz = 0.5 * np.sqrt(np.maximum(1.0 + 2.0 * np.diagonal(R, axis1=1, axis2=2) - np.trace(R, axis1=1, axis2=2)[:, None], 0.0))
    xyz *= np.where(np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1) < 0, -1.0, 1.0)
    return np.concatenate([xyz, w[:, None]], axis=1)
