"""Hill-type muscle properties of the physical set beyond force-velocity (docs/solver.md "Activation dynamics",
"Force-length"): excitation -> activation dynamics, the fibres' active and passive force-length curves, the passive
fibre tension on the cells, and each muscle's force [N] (observe()'s muscle_forces).

Sources (the numbers are Params fields):
* activation dynamics: Thelen 2003 eq. 1 (after Winters 1995), as OpenSim's Thelen2003Muscle computes it:
  da/dt = (u - a) / tau(a, u), tau = tau_act (0.5 + 1.5 a) while u > a, tau_deact / (0.5 + 1.5 a) otherwise;
  tau_act 15 ms, tau_deact 50 ms (Thelen 2003; OpenSim Thelen2003Muscle's activation_time_constant 0.015,
  deactivation_time_constant 0.050).
* active force-length: Thelen 2003 eq. 2, f_L = exp(-(l - 1)^2 / gamma), gamma = 0.45 (KshapeActive).
* passive force-length: Thelen 2003 eq. 3, f_PE = (exp(k_PE (l - 1) / eps0) - 1) / (exp(k_PE) - 1) for l > 1, 0 below
  (the clamp OpenSim's Thelen2003Muscle::calcfpe applies), k_PE = 5 (KshapePassive), eps0 = 0.6 (FmaxMuscleStrain:
  the fibre strain at which the passive force reaches Fmax).
l is the normalised fibre length (observe()'s fibre_lengths): l = l_rest + (C - C_rest) / L_opt, C the muscle's
attachment chord (chord_lengths: the distance between the centroids of its vertices bound to its proximal and to its
distal bone, a function of the joint angles only), C_rest its rest value, L_opt the anatomy's optimal fibre length,
l_rest its normalised fibre length in the model's rest pose (rest_fibre_lengths: the tissue table's rest_fibre_length,
from the source model; Params.rest_fibre_length > 0 overrides it for every muscle): a rigid tendon (as the source model's DeGrooteFregly2016 muscles,
ignore_tendon_compliance), so the fibres take the whole change of the origin-insertion distance. Not the muscle length the
solver measures along its cells (muscle_lengths): held isometric at the knee, the active hamstrings' cell chains
straighten and shorten by 23-56 mm (semimembranosus: l 0.53 at 0 deg), which is the tissue's deformation, not the
fibres' operating point.
"""
from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit

from tissue_sim.core.solver.cells import force_velocity as _force_velocity


@njit(cache=True)
def activation_step(u, a, h, tau_act, tau_deact):
    """Activation after a sub-step h from a under excitation u (Thelen 2003 eq. 1): over the sub-step the time constant
    is frozen at its value at the midpoint activation (a predictor step with tau(a) gives it; second order) and the
    linear ODE solved exactly, a + (u - a)(1 - exp(-h / tau)): it stays within [min(a, u), max(a, u)]."""
    rising = u > a
    s = 0.5 + 1.5 * a
    a1 = a + (u - a) * (1.0 - math.exp(-h / (tau_act * s if rising else tau_deact / s)))
    s = 0.5 + 1.5 * 0.5 * (a + a1)
    return a + (u - a) * (1.0 - math.exp(-h / (tau_act * s if rising else tau_deact / s)))


@njit(cache=True)
def advance_activation(exc, act, h, tau_act, tau_deact):
    """In place: act (M,) one sub-step h towards the excitations exc (M,); tau_act <= 0: act = exc (instant, the paper)."""
    for m in range(act.shape[0]):
        if tau_act > 0.0:
            act[m] = activation_step(exc[m], act[m], h, tau_act, tau_deact)
        else:
            act[m] = exc[m]


@njit(cache=True)
def active_force_length(ln, gamma):
    """Thelen 2003 eq. 2: the active force at normalised fibre length ln, relative to the optimal length's."""
    return math.exp(-(ln - 1.0) ** 2 / gamma)


@njit(cache=True)
def passive_force_length(ln, k_pe, eps0):
    """Thelen 2003 eq. 3 (OpenSim's clamp): the passive fibre force / Fmax at normalised fibre length ln; 0 for ln <= 1."""
    if ln <= 1.0:
        return 0.0
    return (math.exp(k_pe * (ln - 1.0) / eps0) - 1.0) / (math.exp(k_pe) - 1.0)


@njit(cache=True)
def passive_energy_density(ln, k_pe, eps0):
    """Integral of passive_force_length from 1 to ln (the passive energy / (Fmax L_opt)); 0 for ln <= 1."""
    if ln <= 1.0:
        return 0.0
    return ((eps0 / k_pe) * (math.exp(k_pe * (ln - 1.0) / eps0) - 1.0) - (ln - 1.0)) / (math.exp(k_pe) - 1.0)


@njit(cache=True)
def chord_lengths(x, ch_off, ch_idx, lengths, axis):
    """Per muscle m its attachment chord: the distance [m] between the centroid of its cells' vertices attached to its
    proximal segment (ch_idx[ch_off[2m]:ch_off[2m+1]]) and of those attached to its distal one (the next group), into
    lengths (M,), the unit vector proximal -> distal into axis (M, 3). Both groups move rigidly with their bones, so the
    chord is a function of the joint angles alone (the tissue's own deformation does not change it). A muscle without
    two such groups (both ends on one segment): length 0, axis 0."""
    for m in range(lengths.shape[0]):
        a0, a1, b1 = ch_off[2 * m], ch_off[2 * m + 1], ch_off[2 * m + 2]
        lengths[m] = 0.0
        axis[m, 0] = axis[m, 1] = axis[m, 2] = 0.0
        if a1 == a0 or b1 == a1:
            continue
        px = py = pz = dx = dy = dz = 0.0
        for k in range(a0, a1):
            i = ch_idx[k]
            px += x[i, 0]; py += x[i, 1]; pz += x[i, 2]
        for k in range(a1, b1):
            i = ch_idx[k]
            dx += x[i, 0]; dy += x[i, 1]; dz += x[i, 2]
        na, nb = a1 - a0, b1 - a1
        ux, uy, uz = dx / nb - px / na, dy / nb - py / na, dz / nb - pz / na
        n = math.sqrt(ux * ux + uy * uy + uz * uz)
        lengths[m] = n
        if n > 0.0:
            axis[m, 0], axis[m, 1], axis[m, 2] = ux / n, uy / n, uz / n


@njit(cache=True)
def fibre_length(chord, m, ch_rest, inv_lopt, l0):
    """Normalised fibre length of muscle m at attachment chord length chord [m]: l0[m] + (chord - rest chord) / L_opt
    (rigid tendon; no chord: l0[m]); l0 (M,) the rest fibre lengths (rest_fibre_lengths)."""
    return l0[m] + (chord - ch_rest[m]) * inv_lopt[m] if ch_rest[m] > 0.0 else l0[m]


@njit(cache=True)
def passive_tension(x, f, ch_off, ch_idx, ch_rest, inv_lopt, fmax, l0, k_pe, eps0, lengths, axis, tension):
    """The passive fibre force of every muscle, added to f (V, 3) in place: F = Fmax f_PE(l) (l = fibre_length of its
    attachment chord, chord_lengths) pulls its two attachment groups together along the chord, F / n_A on each of the
    n_A proximal vertices, -F / n_B on each distal one: minus the gradient of the energy Fmax L_opt int_1^l f_PE
    (passive_energy_density), which depends on the bones' poses only (the forces act on bone-attached vertices: they
    reach the skeleton as joint torques). tension (M,) gets F [N]; returns the passive energy [J]."""
    chord_lengths(x, ch_off, ch_idx, lengths, axis)
    energy = 0.0
    for m in range(lengths.shape[0]):
        tension[m] = 0.0
        if ch_rest[m] <= 0.0 or lengths[m] <= 0.0:
            continue
        ln = fibre_length(lengths[m], m, ch_rest, inv_lopt, l0)
        F = fmax[m] * passive_force_length(ln, k_pe, eps0)
        tension[m] = F
        energy += fmax[m] / inv_lopt[m] * passive_energy_density(ln, k_pe, eps0)
        if F == 0.0:
            continue
        a0, a1, b1 = ch_off[2 * m], ch_off[2 * m + 1], ch_off[2 * m + 2]
        ga, gb = F / (a1 - a0), F / (b1 - a1)
        for k in range(a0, a1):
            i = ch_idx[k]
            f[i, 0] += ga * axis[m, 0]; f[i, 1] += ga * axis[m, 1]; f[i, 2] += ga * axis[m, 2]
        for k in range(a1, b1):
            i = ch_idx[k]
            f[i, 0] -= gb * axis[m, 0]; f[i, 1] -= gb * axis[m, 1]; f[i, 2] -= gb * axis[m, 2]
    return energy


@njit(cache=True)
def tension_activation_of(a, mvel, inv_vl0, fv_on, fv_max, chord, ch_rest, inv_lopt, l0, fl_on, gamma, out):
    """out (M,) = the active tension's activation: a x the force-velocity factor of the muscle velocity mvel [m/s]
    (cells.force_velocity of mvel / (v_max L0), inv_vl0 = 1 / (v_max L0); fv_on) x the active force-length factor of
    the attachment chord (fl_on). The one definition the step and the observation (tension_activation) use."""
    for m in range(out.shape[0]):
        f = a[m]
        if fv_on:
            f *= _force_velocity(mvel[m] * inv_vl0[m], fv_max)
        if fl_on:
            f *= active_force_length(fibre_length(chord[m], m, ch_rest, inv_lopt, l0), gamma)
        out[m] = f


def attachment_groups(sim):
    """(ch_off (2M+1,) int64, ch_idx int32) the CSR groups of chord_lengths: per muscle the bone-attached vertices of its
    cells on its most proximal segment (fewest joints from the root), then those on its most distal one (most joints;
    among equals the one with more of its vertices); both empty when all its attached vertices lie on one segment."""
    depth = np.zeros(sim.n_segments, np.int64)
    for s in range(sim.n_segments):
        t = s
        while sim.seg_parent[t] >= 0:
            depth[s] += 1
            t = sim.seg_parent[t]
    groups = []
    for m in range(sim.n_muscles):
        cells = np.flatnonzero(sim.cell_muscle == m)
        verts = np.unique(np.concatenate([sim.cv[sim.off[c]:sim.off[c + 1]] for c in cells])) if cells.size else np.zeros(0, int)
        seg = sim.vertex_segment[verts]
        verts, seg = verts[seg >= 0], seg[seg >= 0]
        segs, counts = np.unique(seg, return_counts=True)
        if segs.size < 2 or depth[segs].min() == depth[segs].max():
            groups += [np.zeros(0, np.int32), np.zeros(0, np.int32)]
            continue
        key = lambda i: (depth[segs[i]], counts[i])             # noqa: E731
        prox = segs[min(range(segs.size), key=lambda i: (depth[segs[i]], -counts[i]))]
        dist = segs[max(range(segs.size), key=key)]
        groups += [verts[seg == prox].astype(np.int32), verts[seg == dist].astype(np.int32)]
    off = np.zeros(len(groups) + 1, np.int64)
    off[1:] = np.cumsum([g.size for g in groups])
    return off, (np.concatenate(groups) if groups else np.zeros(0, np.int32)).astype(np.int32)


_CONSTANTS = weakref.WeakKeyDictionary()     # SimModel -> its muscle constants (the model is immutable)


def muscle_constants(sim):
    """(ch_rest (M,) [m], inv_lopt (M,) [1/m], fmax (M,) [N], ch_off, ch_idx) of a SimModel: each muscle's attachment
    chord at rest (chord_lengths; 0: none), 1 / its optimal fibre length (the anatomy's; unknown: the muscle's measured
    rest length, the whole muscle taken as fibre), its maximum isometric force (the active tension's calibration force,
    model.muscle_max_forces), the chord's vertex groups (attachment_groups)."""
    c = _constants(sim)
    return c[0], c[1], c[2], c[5], c[6]


def _constants(sim):
    c = _CONSTANTS.get(sim)
    if c is None:
        from tissue_sim.core.solver.model import muscle_max_forces
        lrest = np.asarray(sim.muscle_rest_length, np.float64)
        lopt = np.asarray(sim.tissue.muscle_fibre_length, np.float64)
        lopt = np.where(np.isfinite(lopt) & (lopt > 0), lopt, lrest)
        inv = np.where(lopt > 0, 1.0 / np.where(lopt > 0, lopt, 1.0), 0.0)
        # the muscle cells, each one's slice gap (numbered over all muscles), and per muscle its gaps as a row of
        # a (M, G) table padded with the index of a NaN (G = most gaps of a muscle; a muscle without any: a 0)
        cells = np.flatnonzero(sim.cell_muscle >= 0)
        key = sim.cell_muscle[cells].astype(np.int64) * (int(sim.tissue.cell_slice.max(initial=0)) + 1) \
            + sim.tissue.cell_slice[cells]
        ukey, gaps = np.unique(key, return_inverse=True)
        gm = ukey // (int(sim.tissue.cell_slice.max(initial=0)) + 1)
        counts = np.bincount(gm, minlength=sim.n_muscles)
        table = np.full((sim.n_muscles, max(int(counts.max(initial=0)), 1)), ukey.size, np.int64)   # NaN slot
        for m in range(sim.n_muscles):
            table[m, :counts[m]] = np.flatnonzero(gm == m)
        table[counts == 0, 0] = ukey.size + 1                                                 # the 0 slot
        gaps = (gaps, table, ukey.size)
        ch_off, ch_idx = attachment_groups(sim)
        ch_rest, axis = np.zeros(sim.n_muscles), np.zeros((sim.n_muscles, 3))
        chord_lengths(sim.rest, ch_off, ch_idx, ch_rest, axis)
        c = _CONSTANTS[sim] = (ch_rest, inv, muscle_max_forces(sim.tissue, sim.params, sim.rest_volume, sim.rest_length),
                               cells, gaps, ch_off, ch_idx)
    return c


def rest_fibre_lengths(sim) -> np.ndarray:
    """(M,) each muscle's normalised fibre length in the model's rest pose: Params.rest_fibre_length where > 0 (an
    override for every muscle), else the model's muscle_rest_fibre_length (the tissue table's rest_fibre_length; 1.0
    where the table has none)."""
    p = sim.params
    if p.rest_fibre_length > 0:
        return np.full(sim.n_muscles, float(p.rest_fibre_length))
    return np.asarray(sim.tissue.muscle_rest_fibre_length, np.float64).copy()


def tension_activation(sim, state) -> np.ndarray:
    """(M,) the active tension's activation factor at the state: the activation state x the force-velocity factor of
    its muscle velocity (max_contraction_velocity > 0) x the active force-length factor of its fibre length
    (force_length on), as the step applies them (specific_tension 0: the activation, unused)."""
    p = sim.params
    M = sim.n_muscles
    a = np.asarray(state.activation if state.activation is not None else np.zeros(M), np.float64).copy()
    if p.specific_tension <= 0:
        return a
    ch_rest, inv_lopt, _, ch_off, ch_idx = muscle_constants(sim)
    vl0 = p.max_contraction_velocity * np.asarray(sim.muscle_rest_length, np.float64)
    inv_vl0 = np.divide(1.0, vl0, out=np.zeros_like(vl0), where=vl0 > 0)
    chord, axis = np.zeros(M), np.zeros((M, 3))
    if p.force_length:
        chord_lengths(state.x, ch_off, ch_idx, chord, axis)
    out = np.empty(M)
    tension_activation_of(a, np.asarray(state.muscle_velocity, np.float64), inv_vl0, p.max_contraction_velocity > 0,
                          float(p.fv_max_lengthening), chord, ch_rest, inv_lopt, rest_fibre_lengths(sim),
                          bool(p.force_length), float(p.fl_width), out)
    return out


def muscle_forces(sim, state) -> dict:
    """Each muscle's force [N] at the state (observe()'s muscle_forces and its parts; physical set; 0 with specific_tension
    0, the paper's set, whose muscles pull only by their cells' elastic recovery):
    active (M,): per slice gap the sum over the muscle's cells of the active tension T = a' k_a n/4 max(l - lam L, 0)
    (a' = tension_activation, l the cell's ring-centroid distance at the state's positions; docs/solver.md "Active
    tension"), the median over the muscle's gaps (cells in series carry one force); passive (M,): Fmax f_PE(l) of the
    passive force-length (passive_force_length on, else 0); total = active + passive; fibre_length (M,): the normalised
    fibre length l (rest_fibre_lengths + (C - C_rest) / L_opt of the attachment chords C); passive_energy [J]."""
    from tissue_sim.core.solver.measures import cell_axial_lengths
    p = sim.params
    M = sim.n_muscles
    alen = np.empty(sim.n_cells)
    cell_axial_lengths(state.x, sim.off, sim.cv, alen)
    ch_rest, inv_lopt, fmax, mcells, (mgap, table, ng), ch_off, ch_idx = _constants(sim)
    chord, axis, passive = np.zeros(M), np.zeros((M, 3)), np.zeros(M)
    energy = 0.0
    l0 = rest_fibre_lengths(sim)
    if p.passive_force_length and p.specific_tension > 0:
        energy = passive_tension(state.x, np.zeros_like(state.x), ch_off, ch_idx, ch_rest, inv_lopt, fmax,
                                 l0, p.fl_passive_shape, p.fl_passive_strain, chord, axis, passive)
    else:
        chord_lengths(state.x, ch_off, ch_idx, chord, axis)
    ln = np.array([fibre_length(chord[m], m, ch_rest, inv_lopt, l0) for m in range(M)])
    act = tension_activation(sim, state)
    n = np.diff(sim.off)[mcells]
    cm = sim.cell_muscle[mcells]
    T = act[cm] * sim.k_active[mcells] * n / 4.0 * np.maximum(alen[mcells] - state.lam[cm] * sim.rest_length[mcells], 0.0)
    gap_sums = np.concatenate([np.bincount(mgap, weights=T, minlength=ng), [np.nan, 0.0]])
    rows = np.sort(gap_sums[table], axis=1)                          # NaN padding last
    k = np.sum(~np.isnan(rows), axis=1)                              # >= 1 per row
    idx = np.arange(M)
    active = 0.5 * (rows[idx, (k - 1) // 2] + rows[idx, k // 2])     # the median over the muscle's gaps
    return dict(active=active, passive=passive, total=active + passive, fibre_length=ln, passive_energy=energy)
