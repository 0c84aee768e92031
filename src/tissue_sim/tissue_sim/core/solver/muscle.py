"""Hill-type muscle properties of the physical set beyond force-velocity (docs/solver.md "Activation dynamics",
"Force-length"): excitation -> activation dynamics, the fibres' active and passive force-length curves, the fibre
lengths of the source model's muscle paths, the passive fibre force as joint torques, and each muscle's force [N]
(observe()'s muscle_forces).

Sources (the numbers are Params fields):
* activation dynamics: Thelen 2003 eq. 1 (after Winters 1995), as OpenSim's Thelen2003Muscle computes it:
  da/dt = (u - a) / tau(a, u), tau = tau_act (0.5 + 1.5 a) while u > a, tau_deact / (0.5 + 1.5 a) otherwise;
  tau_act 15 ms, tau_deact 50 ms (Thelen 2003; OpenSim Thelen2003Muscle's activation_time_constant 0.015,
  deactivation_time_constant 0.050).
* active force-length: Thelen 2003 eq. 2, f_L = exp(-(l - 1)^2 / gamma), gamma = 0.45 (KshapeActive).
* passive force-length (fl_passive_curve): Thelen 2003 eq. 3, f_PE = (exp(k_PE (l - 1) / eps0) - 1) / (exp(k_PE) - 1)
  for l > 1, 0 below (the clamp OpenSim's Thelen2003Muscle::calcfpe applies), k_PE = 5 (KshapePassive), eps0 = 0.6
  (FmaxMuscleStrain: the fibre strain at which the passive force reaches Fmax; the physical set: 2.0, a calibration,
  docs/solver.md); or De Groote et al. 2016 (the source model's DeGrooteFregly2016Muscle).
l is the normalised fibre length (observe()'s fibre_lengths), per muscle part the rigid-tendon fibre length of its
source-model path, sqrt((L_MT - L_TS)^2 + (L_opt sin a_opt)^2) / L_opt, L_MT(q) the tissue model's path polynomial of
the joint coordinates (muscle_paths.yaml, fitted by tools/anatomy/paths.py to OpenSim's wrapped paths), a muscle's the
Fmax-weighted mean of its parts' (a muscle without a path: its rest_fibre_lengths). The passive force acts as joint
torques -F cos(a) dL_MT/dq (conservative: minus the gradient of its energy). Not the muscle length the solver
measures along its cells (muscle_lengths): held isometric at the knee, the active hamstrings' cell chains straighten
and shorten by 23-56 mm, which is the tissue's deformation, not the fibres' operating point.
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
def passive_force_length_curve(ln, k_pe, eps0, curve):
    """The passive force-length curve of Params.fl_passive_curve: 0 Thelen 2003 (passive_force_length), 1 De Groote et
    al. 2016 (OpenSim DeGrooteFregly2016Muscle::calcPassiveForceMultiplier: (exp(k (l - 1)/eps0) - o) / (exp(k) - o),
    o = exp(k (l_min - 1)/eps0), l_min = 0.2; 0 below l_min)."""
    if curve == 0:
        return passive_force_length(ln, k_pe, eps0)
    if ln <= DGF_MIN_LENGTH:
        return 0.0
    o = math.exp(k_pe * (DGF_MIN_LENGTH - 1.0) / eps0)
    return (math.exp(k_pe * (ln - 1.0) / eps0) - o) / (math.exp(k_pe) - o)


@njit(cache=True)
def passive_energy_curve(ln, k_pe, eps0, curve):
    """Integral of passive_force_length_curve from its zero (1 for Thelen, l_min for De Groote-Fregly) to ln."""
    if curve == 0:
        return passive_energy_density(ln, k_pe, eps0)
    if ln <= DGF_MIN_LENGTH:
        return 0.0
    o = math.exp(k_pe * (DGF_MIN_LENGTH - 1.0) / eps0)
    return ((eps0 / k_pe) * (math.exp(k_pe * (ln - 1.0) / eps0) - o) - o * (ln - DGF_MIN_LENGTH)) / (math.exp(k_pe) - o)


DGF_MIN_LENGTH = 0.2           # De Groote et al. 2016: minimum normalised fibre length (OpenSim's default)
PASSIVE_CURVES = ('thelen', 'degroote')


@njit(cache=True)
def path_lengths(q, powers, coef, mono, dmono, L, dL):
    """Each muscle part's musculotendon length L (P,) [m] and its derivative dL (P, J) [m/rad] at the joint coordinates
    q (J,): L = sum_t coef[p, t] prod_j q_j^powers[t, j] (the tissue model's path polynomials, fitted to the source
    model's wrapped paths; tools/anatomy/paths.py). mono (T,), dmono (T, J): scratch."""
    T, J = powers.shape
    for t in range(T):
        v = 1.0
        for j in range(J):
            if powers[t, j] > 0:
                v *= q[j] ** powers[t, j]
        mono[t] = v
        for j in range(J):
            e = powers[t, j]
            if e == 0:
                dmono[t, j] = 0.0
                continue
            d = e * q[j] ** (e - 1)
            for k in range(J):
                if k != j and powers[t, k] > 0:
                    d *= q[k] ** powers[t, k]
            dmono[t, j] = d
    for p in range(coef.shape[0]):
        acc = 0.0
        for t in range(T):
            acc += coef[p, t] * mono[t]
        L[p] = acc
        for j in range(J):
            acc = 0.0
            for t in range(T):
                acc += coef[p, t] * dmono[t, j]
            dL[p, j] = acc


@njit(cache=True)
def fibre_lengths(q, pm, pdata, powers, coef, shift, l0, mono, dmono, L, dL, lpart, ln):
    """The normalised fibre lengths at the joint coordinates q: per part (lpart (P,)) the rigid-tendon fibre length
    sqrt((L_MT - L_TS)^2 + (L_opt sin a_opt)^2) / L_opt of its path (path_lengths; a path shorter than its tendon: the
    fibre height alone) + its muscle's shift (Params.rest_fibre_length's override; else 0); per muscle (ln (M,)) the
    Fmax-weighted mean over its parts, l0[m] (rest_fibre_lengths) for a muscle without a path. L, dL: the paths."""
    path_lengths(q, powers, coef, mono, dmono, L, dL)
    for m in range(ln.shape[0]):
        ln[m] = -1.0
    for p in range(pm.shape[0]):
        m = pm[p]
        d = max(L[p] - pdata[p, 2], 0.0)
        lpart[p] = math.sqrt(d * d + pdata[p, 3] * pdata[p, 3]) / pdata[p, 1] + shift[m]
        ln[m] = (0.0 if ln[m] == -1.0 else ln[m]) + pdata[p, 0] * lpart[p]
    for m in range(ln.shape[0]):
        if ln[m] == -1.0:
            ln[m] = l0[m]


@njit(cache=True)
def passive_torques(pm, pdata, L, dL, lpart, shift, fmax, k_pe, eps0, curve, tau, tension):
    """The passive fibre force of every muscle part, F = Fmax_m share_p f_PE(l_p), as joint torques into tau (J,)
    (overwritten): tau_j = -sum_p F_p cos(a_p) dL_p/dq_j (cos a = (L_MT - L_TS) / fibre length: the force along the
    tendon; minus the gradient of the energy Fmax share L_opt int f_PE dl, a function of q alone: conservative);
    tension (M,) gets each muscle's passive force along its tendons [N]. Returns the passive energy [J]."""
    for j in range(tau.shape[0]):
        tau[j] = 0.0
    for m in range(tension.shape[0]):
        tension[m] = 0.0
    energy = 0.0
    for p in range(pm.shape[0]):
        m = pm[p]
        ln = lpart[p]
        fm = fmax[m] * pdata[p, 0]
        energy += fm * pdata[p, 1] * passive_energy_curve(ln, k_pe, eps0, curve)
        F = fm * passive_force_length_curve(ln, k_pe, eps0, curve)
        d = L[p] - pdata[p, 2]
        if F == 0.0 or d <= 0.0:
            continue
        Ft = F * d / ((ln - shift[m]) * pdata[p, 1])           # along the tendon: F cos(a)
        tension[m] += Ft
        for j in range(tau.shape[0]):
            tau[j] -= Ft * dL[p, j]
    return energy


@njit(cache=True)
def tension_activation_of(a, mvel, inv_vl0, fv_on, fv_max, ln, fl_on, gamma, out):
    """out (M,) = the active tension's activation: a x the force-velocity factor of the muscle velocity mvel [m/s]
    (cells.force_velocity of mvel / (v_max L0), inv_vl0 = 1 / (v_max L0); fv_on) x the active force-length factor of
    the normalised fibre length ln (M,) (fibre_lengths; fl_on). The one definition the step and the observation
    (tension_activation) use."""
    for m in range(out.shape[0]):
        f = a[m]
        if fv_on:
            f *= _force_velocity(mvel[m] * inv_vl0[m], fv_max)
        if fl_on:
            f *= active_force_length(ln[m], gamma)
        out[m] = f


_CONSTANTS = weakref.WeakKeyDictionary()     # SimModel -> its muscle constants (the model is immutable)


def path_constants(sim):
    """(path_muscle, path_data, path_powers, path_coef, shift (M,), l0 (M,)) of a SimModel: the tissue model's muscle
    paths, the per-muscle shift of the fibre length (Params.rest_fibre_length > 0: the override minus the path's own
    rest value, so that the muscle's fibre length in the rest pose is the override; else 0) and rest_fibre_lengths."""
    return _constants(sim)[3]


def muscle_constants(sim):
    """(fmax (M,) [N], path_constants) of a SimModel: each muscle's maximum isometric force (the active tension's
    calibration force, model.muscle_max_forces)."""
    c = _constants(sim)
    return c[0], c[3]


def _constants(sim):
    c = _CONSTANTS.get(sim)
    if c is None:
        from tissue_sim.core.solver.model import muscle_max_forces
        tm = sim.tissue
        # the muscle cells, each one's slice gap (numbered over all muscles), and per muscle its gaps as a row of
        # a (M, G) table padded with the index of a NaN (G = most gaps of a muscle; a muscle without any: a 0)
        cells = np.flatnonzero(sim.cell_muscle >= 0)
        key = sim.cell_muscle[cells].astype(np.int64) * (int(tm.cell_slice.max(initial=0)) + 1) + tm.cell_slice[cells]
        ukey, gaps = np.unique(key, return_inverse=True)
        gm = ukey // (int(tm.cell_slice.max(initial=0)) + 1)
        counts = np.bincount(gm, minlength=sim.n_muscles)
        table = np.full((sim.n_muscles, max(int(counts.max(initial=0)), 1)), ukey.size, np.int64)   # NaN slot
        for m in range(sim.n_muscles):
            table[m, :counts[m]] = np.flatnonzero(gm == m)
        table[counts == 0, 0] = ukey.size + 1                                                 # the 0 slot
        gaps = (gaps, table, ukey.size)
        pm = np.ascontiguousarray(tm.path_muscle, np.int32)
        pdata = np.ascontiguousarray(tm.path_data, np.float64)
        powers = np.ascontiguousarray(tm.path_powers, np.int64)
        coef = np.ascontiguousarray(tm.path_coef, np.float64)
        l0 = rest_fibre_lengths(sim)
        shift = np.zeros(sim.n_muscles)
        if sim.params.rest_fibre_length > 0 and pm.size:
            w = PathWork(sim.n_muscles, pm.size, powers.shape)
            fibre_lengths(np.array(sim.j_rest, np.float64), pm, pdata, powers, coef, shift, l0, *w)
            shift = np.where(np.isin(np.arange(sim.n_muscles), pm), sim.params.rest_fibre_length - w[-1], 0.0)
        c = _CONSTANTS[sim] = (muscle_max_forces(tm, sim.params, sim.rest_volume, sim.rest_length), cells, gaps,
                               (pm, pdata, powers, coef, shift, l0))
    return c


def PathWork(M, P, pshape):
    """Scratch for fibre_lengths: (mono (T,), dmono (T, J), L (P,), dL (P, J), lpart (P,), ln (M,))."""
    T, J = pshape
    return (np.zeros(T), np.zeros((T, J)), np.zeros(P), np.zeros((P, J)), np.zeros(P), np.zeros(M))


def fibre_state(sim, q):
    """(ln (M,), lpart (P,), L (P,), dL (P, J)) at joint coordinates q: fibre_lengths of the model's paths."""
    pm, pdata, powers, coef, shift, l0 = path_constants(sim)
    w = PathWork(sim.n_muscles, pm.size, powers.shape)
    fibre_lengths(np.array(q, np.float64), pm, pdata, powers, coef, shift, l0, *w)     # (a writable copy: one signature)
    return w[5], w[4], w[2], w[3]


def passive_state(sim, q):
    """(tau (J,) [N m], tension (M,) [N], energy [J]) of the passive fibre force at joint coordinates q (passive_torques
    with the Params' curve; whether or not passive_force_length is on)."""
    p = sim.params
    fmax, (pm, pdata, powers, coef, shift, l0) = muscle_constants(sim)
    ln, lpart, L, dL = fibre_state(sim, q)
    tau, ten = np.zeros(sim.n_joints), np.zeros(sim.n_muscles)
    e = passive_torques(pm, pdata, L, dL, lpart, shift, fmax, float(p.fl_passive_shape), float(p.fl_passive_strain),
                        PASSIVE_CURVES.index(p.fl_passive_curve), tau, ten)
    return tau, ten, e


def rest_fibre_lengths(sim) -> np.ndarray:
    """(M,) each muscle's normalised fibre length in the model's rest pose: Params.rest_fibre_length where > 0 (an
    override for every muscle), else the model's muscle_rest_fibre_length (the tissue table's rest_fibre_length; 1.0
    where the table has none). A muscle with a path (fibre_lengths) starts at its path's value instead, which is the
    table's to the fit error (the table's value comes from the same source-model path)."""
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
    vl0 = p.max_contraction_velocity * np.asarray(sim.muscle_rest_length, np.float64)
    inv_vl0 = np.divide(1.0, vl0, out=np.zeros_like(vl0), where=vl0 > 0)
    out = np.empty(M)
    tension_activation_of(a, np.asarray(state.muscle_velocity, np.float64), inv_vl0, p.max_contraction_velocity > 0,
                          float(p.fv_max_lengthening), fibre_state(sim, state.q)[0], bool(p.force_length),
                          float(p.fl_width), out)
    return out


def muscle_forces(sim, state) -> dict:
    """Each muscle's force [N] at the state (observe()'s muscle_forces and its parts; physical set; 0 with specific_tension
    0, the paper's set, whose muscles pull only by their cells' elastic recovery):
    active (M,): per slice gap the sum over the muscle's cells of the active tension T = a' k_a n/4 max(l - lam L, 0)
    (a' = tension_activation, l the cell's ring-centroid distance at the state's positions; docs/solver.md "Active
    tension"), the median over the muscle's gaps (cells in series carry one force); passive (M,): the passive fibre force
    along its tendons (passive_torques; passive_force_length on, else 0); total = active + passive; fibre_length (M,):
    the normalised fibre length l of its source-model path at the state's joint coordinates (fibre_lengths);
    passive_energy [J]."""
    from tissue_sim.core.solver.measures import cell_axial_lengths
    p = sim.params
    M = sim.n_muscles
    alen = np.empty(sim.n_cells)
    cell_axial_lengths(state.x, sim.off, sim.cv, alen)
    _, mcells, (mgap, table, ng), _ = _constants(sim)
    passive, energy = np.zeros(M), 0.0
    if p.passive_force_length and p.specific_tension > 0:
        _, passive, energy = passive_state(sim, state.q)
    ln = fibre_state(sim, state.q)[0].copy()
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
