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
l is the normalised fibre length (muscle_fibre_lengths): rigid tendon, so the fibres take every change of the muscle's
measured length: l = l_rest + (L - L_rest) / L_opt (L the muscle length the solver measures, muscle_lengths of observe,
L_rest its rest value, L_opt the optimal fibre length of the anatomy, l_rest = Params.rest_fibre_length).
"""
from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit


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
def fibre_length(mlen, m, lrest, inv_lopt, l0):
    """Normalised fibre length of muscle m at measured muscle length mlen [m] (< 0: not measured yet: l0)."""
    return l0 + (mlen - lrest[m]) * inv_lopt[m] if mlen >= 0.0 else l0


@njit(cache=True)
def passive_tension(x, f, off, cv, mcells, mcell_muscle, mcell_weight, lrest, inv_lopt, fmax, l0, k_pe, eps0,
                    lengths, tension):
    """The passive fibre force of every muscle on its cells, added to f (V, 3) in place: with L = sum_c w_c l_c the
    muscle's length (l_c the cell's ring-centroid distance at x, w_c its length weight) and F = Fmax f_PE(l(L)), each
    muscle cell gets -F w_c dl_c/dx: F w_c (2/n) u on each bottom-ring vertex, minus that on each top-ring vertex
    (u the unit axis bottom -> top, n the cell's vertex count). This is minus the gradient of the energy
    Fmax L_opt int_1^l f_PE (passive_energy_density): conservative, zero net force and moment on the cell.
    lengths (M,) gets the muscle lengths, tension (M,) the forces F [N]; returns the passive energy [J]."""
    lengths[:] = 0.0
    for k in range(mcells.shape[0]):
        c = mcells[k]
        a0 = off[c]
        n = (off[c + 1] - a0) // 2
        bx = by = bz = tx = ty = tz = 0.0
        for t in range(n):
            i, j = cv[a0 + t], cv[a0 + n + t]
            bx += x[i, 0]; by += x[i, 1]; bz += x[i, 2]
            tx += x[j, 0]; ty += x[j, 1]; tz += x[j, 2]
        lengths[mcell_muscle[k]] += mcell_weight[k] * math.sqrt((tx - bx) ** 2 + (ty - by) ** 2 + (tz - bz) ** 2) / n
    energy = 0.0
    for m in range(lengths.shape[0]):
        ln = fibre_length(lengths[m], m, lrest, inv_lopt, l0)
        tension[m] = fmax[m] * passive_force_length(ln, k_pe, eps0)
        if inv_lopt[m] > 0.0:
            energy += fmax[m] / inv_lopt[m] * passive_energy_density(ln, k_pe, eps0)
    for k in range(mcells.shape[0]):
        F = tension[mcell_muscle[k]]
        if F == 0.0:
            continue
        c = mcells[k]
        a0 = off[c]
        n = (off[c + 1] - a0) // 2
        ux = uy = uz = 0.0
        for t in range(n):
            i, j = cv[a0 + t], cv[a0 + n + t]
            ux += x[j, 0] - x[i, 0]; uy += x[j, 1] - x[i, 1]; uz += x[j, 2] - x[i, 2]
        norm = math.sqrt(ux * ux + uy * uy + uz * uz)
        if norm <= 0.0:
            continue
        g = F * mcell_weight[k] / (n * norm)        # F w_c (1/n) u / |u| per vertex, u = n (top - bottom centroid)
        for t in range(n):
            i, j = cv[a0 + t], cv[a0 + n + t]
            f[i, 0] += g * ux; f[i, 1] += g * uy; f[i, 2] += g * uz
            f[j, 0] -= g * ux; f[j, 1] -= g * uy; f[j, 2] -= g * uz
    return energy


_CONSTANTS = weakref.WeakKeyDictionary()     # SimModel -> its muscle constants (the model is immutable)


def muscle_constants(sim):
    """(lrest (M,) [m], inv_lopt (M,) [1/m], fmax (M,) [N]) of a SimModel: each muscle's measured rest length, 1 / its
    optimal fibre length (the anatomy's; unknown: the muscle's rest length, the whole muscle taken as fibre), its
    maximum isometric force (the active tension's calibration force, model.muscle_max_forces)."""
    return _constants(sim)[:3]


def _constants(sim):
    c = _CONSTANTS.get(sim)
    if c is None:
        from tissue_sim.core.solver.model import muscle_max_forces
        lrest = np.asarray(sim.muscle_rest_length, np.float64)
        lopt = np.asarray(sim.tissue.muscle_fibre_length, np.float64)
        lopt = np.where(np.isfinite(lopt) & (lopt > 0), lopt, lrest)
        inv = np.where(lopt > 0, 1.0 / np.where(lopt > 0, lopt, 1.0), 0.0)
        # per muscle: its cells, and each cell's slice gap among the muscle's gaps (for the median over gaps)
        cells = [np.flatnonzero(sim.cell_muscle == m) for m in range(sim.n_muscles)]
        gaps = [np.unique(sim.tissue.cell_slice[cm], return_inverse=True)[1] for cm in cells]
        c = _CONSTANTS[sim] = (lrest, inv, muscle_max_forces(sim.tissue, sim.params, sim.rest_volume, sim.rest_length),
                               cells, gaps)
    return c


def tension_activation(sim, state) -> np.ndarray:
    """(M,) the active tension's activation factor at the state: the activation state x the force-velocity factor of
    its muscle velocity (max_contraction_velocity > 0) x the active force-length factor of its fibre length
    (force_length on), as the step applies them (specific_tension 0: the activation, unused)."""
    from tissue_sim.core.solver import cells as CK
    p = sim.params
    a = np.asarray(state.activation if state.activation is not None else np.zeros(sim.n_muscles), np.float64).copy()
    if p.specific_tension <= 0:
        return a
    lrest, inv_lopt, _ = muscle_constants(sim)
    if p.max_contraction_velocity > 0:
        vl0 = p.max_contraction_velocity * np.asarray(sim.muscle_rest_length)
        vn = np.divide(state.muscle_velocity, vl0, out=np.zeros_like(vl0), where=vl0 > 0)
        a *= np.array([CK.force_velocity(w, p.fv_max_lengthening) for w in vn])
    if p.force_length:
        a *= np.array([active_force_length(fibre_length(state.muscle_length[m], m, lrest, inv_lopt, p.rest_fibre_length),
                                           p.fl_width) for m in range(sim.n_muscles)])
    return a


def muscle_forces(sim, state) -> dict:
    """Each muscle's force [N] at the state (observe()'s muscle_forces and its parts; physical set; 0 with specific_tension
    0, the paper's set, whose muscles pull only by their cells' elastic recovery):
    active (M,): per slice gap the sum over the muscle's cells of the active tension T = a' k_a n/4 max(l - lam L, 0)
    (a' = tension_activation, l the cell's ring-centroid distance at the state's positions; docs/solver.md "Active
    tension"), the median over the muscle's gaps (cells in series carry one force); passive (M,): Fmax f_PE(l) of the
    passive force-length (passive_force_length on, else 0); total = active + passive; fibre_length (M,): the normalised
    fibre length l (rest_fibre_length + (L - L_rest) / L_opt at the measured lengths L); passive_energy [J]."""
    from tissue_sim.core.solver.measures import cell_axial_lengths
    p = sim.params
    M = sim.n_muscles
    alen = np.empty(sim.n_cells)
    cell_axial_lengths(state.x, sim.off, sim.cv, alen)
    lrest, inv_lopt, fmax, mcells, mgaps = _constants(sim)
    mus = sim.cell_muscle
    sel = mus >= 0
    L = np.bincount(mus[sel], weights=(alen * sim.length_weight)[sel], minlength=M)[:M]
    ln = p.rest_fibre_length + (L - lrest) * inv_lopt
    act = tension_activation(sim, state)
    n = np.diff(sim.off)
    active = np.zeros(M)
    for m in range(M):
        c = mcells[m]
        if c.size == 0 or not np.any(sim.k_active[c] > 0):
            continue
        T = act[m] * sim.k_active[c] * n[c] / 4.0 * np.maximum(alen[c] - state.lam[m] * sim.rest_length[c], 0.0)
        active[m] = float(np.median(np.bincount(mgaps[m], weights=T)))
    passive, energy = np.zeros(M), 0.0
    if p.passive_force_length and p.specific_tension > 0:
        passive = fmax * np.array([passive_force_length(v, p.fl_passive_shape, p.fl_passive_strain) for v in ln])
        energy = float(sum(fmax[m] / inv_lopt[m] * passive_energy_density(ln[m], p.fl_passive_shape, p.fl_passive_strain)
                           for m in range(M) if inv_lopt[m] > 0))
    return dict(active=active, passive=passive, total=active + passive, fibre_length=ln, passive_energy=energy)
