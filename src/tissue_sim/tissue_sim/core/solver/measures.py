"""Measures of a state: axial cell lengths, cell volumes, kinetic and skeleton energies (observe() reports them)."""
from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit

from tissue_sim.core.geometry import prism_volumes
from tissue_sim.core.model import JOINT_COUPLED
from tissue_sim.core.solver.skeleton import coupled_eval



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


def cell_volumes(sim, x: np.ndarray, cells: str = 'all') -> np.ndarray:
    """(C,) volume [m^3] of every cell at positions x: core.geometry.prism_volumes (the one definition: cap
    fans about each ring's centroid, side quads as four triangles about the quad centroid), signed so that
    it is positive at rest (sim.cell_sign: the rest orientation of each cell's rings). cells='muscle': the
    muscle cells' only, (number of muscle cells,) in cell order (each cell's volume is computed alone: the same
    values as the whole array's; observe() needs no others, and the fat cells are a third of the work)."""
    if cells == 'all':
        return prism_volumes(x, sim.off, sim.cv) * sim.cell_sign
    sel, off, cv = _muscle_layout(sim)
    return prism_volumes(x, off, cv) * sim.cell_sign[sel]


_LAYOUTS = weakref.WeakKeyDictionary()      # SimModel -> (muscle cells, their offsets, their vertices)


def _muscle_layout(sim):
    t = _LAYOUTS.get(sim)
    if t is None:
        sel = np.flatnonzero(sim.cell_muscle >= 0)
        sizes = np.diff(sim.off)[sel]
        off = np.concatenate([[0], np.cumsum(sizes)]).astype(sim.off.dtype)
        cv = (np.concatenate([sim.cv[sim.off[c]:sim.off[c + 1]] for c in sel]) if sel.size
              else np.zeros(0, sim.cv.dtype)).astype(sim.cv.dtype)
        t = _LAYOUTS[sim] = (sel, off, cv)
    return t


def kinetic_energy(sim, state) -> float:
    """Kinetic energy [J] of the free vertices (true masses)."""
    free = sim.inv_mass > 0
    return 0.5 * float(np.dot(sim.mass[free], np.einsum('ij,ij->i', state.v[free], state.v[free])))


def joint_torques(sim, state, f: np.ndarray, idx=None) -> np.ndarray:
    """(J,) [N m] generalized force on each hinge of forces f (V, 3) on bone-attached vertices (idx: which;
    default all), by virtual work as the skeleton kernel applies them: a hinge j gets a_j . (x - p_j) x f
    from the vertices of the segments it moves; the driver of a coupled joint gets (W x (x - P) + R_p d') . f
    from the vertices of its child (docs/solver.md "Coupled joints"). 0 for a fixed or coupled joint."""
    idx = sim.att_idx if idx is None else np.asarray(idx)
    seg = sim.vertex_segment[idx]
    x, F = state.x[idx], f[idx]
    tau = np.zeros(sim.n_joints)
    ev = np.empty((4, 3))
    for j in range(sim.n_joints):
        Rp, tp = state.seg_R[sim.j_parent[j]], state.seg_t[sim.j_parent[j]]
        a = Rp @ sim.j_axis[j]
        if sim.j_type[j] == JOINT_COUPLED:
            sel = seg == sim.j_child[j]
            coupled_eval(j, state.q[sim.j_driver[j]], sim.skeleton, ev)
            P = Rp @ (sim.j_centre[j] + ev[1:, 0]) + tp
            tau[sim.j_driver[j]] += float(np.sum((np.cross(a * ev[0, 1], x[sel] - P) + Rp @ ev[1:, 1]) * F[sel]))
        elif sim.j_type[j] == 1:
            sel = sim.anc[j][seg]
            tau[j] += float(a @ np.cross(x[sel] - (Rp @ sim.j_centre[j] + tp), F[sel]).sum(0))
    return tau


def skeleton_energy(sim, state) -> float:
    """Kinetic + gravitational potential energy [J] of the segments (masses incl. attached vertices
    when params.attached_mass_to_segment), potential relative to the rest pose."""
    e = 0.0
    S, J = sim.n_segments, sim.n_joints
    a = np.empty((J, 3))
    p = np.empty((J, 3))
    for j in range(J):
        Rp, tp = state.seg_R[sim.j_parent[j]], state.seg_t[sim.j_parent[j]]
        a[j] = Rp @ sim.j_axis[j]
        p[j] = Rp @ sim.j_centre[j] + tp
    for s in range(S):
        com = state.seg_R[s] @ sim.seg_com[s] + state.seg_t[s]
        w = np.zeros(3)
        v = np.zeros(3)
        for j in range(J):
            if sim.anc[j, s]:
                w += a[j] * state.qd[j]
                v += np.cross(a[j], com - p[j]) * state.qd[j]
        j = sim.seg_joint[s]
        if j >= 0 and sim.j_type[j] == JOINT_COUPLED:       # + the coupling's motion (skeleton.coupled_eval)
            Rp, tp = state.seg_R[sim.j_parent[j]], state.seg_t[sim.j_parent[j]]
            ev = np.empty((4, 3))
            coupled_eval(j, state.q[sim.j_driver[j]], sim.skeleton, ev)
            W = Rp @ sim.j_axis[j] * ev[0, 1]
            P = Rp @ (sim.j_centre[j] + ev[1:, 0]) + tp
            w += W * state.qd[sim.j_driver[j]]
            v += (np.cross(W, com - P) + Rp @ ev[1:, 1]) * state.qd[sim.j_driver[j]]
        Iw = state.seg_R[s] @ sim.seg_inertia[s] @ state.seg_R[s].T
        e += 0.5 * sim.seg_mass[s] * v @ v + 0.5 * w @ Iw @ w - sim.seg_mass[s] * sim.gravity @ (com - sim.seg_com[s])
    return float(e)
