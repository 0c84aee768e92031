"""The time step (METHOD.md section 3 order: muscle tension, then skeleton, then soft tissue)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from tissue_sim.core.solver import kernels as K


def _drop_stale_advance_cache() -> None:
    """numba validates advance()'s on-disk cache against this file only, but the cached machine
    code embeds the kernels of kernels.py: drop that cache whenever kernels.py is newer."""
    from pathlib import Path
    here = Path(__file__).resolve()
    try:
        kernels_mtime = here.with_name('kernels.py').stat().st_mtime
        for f in (here.parent / '__pycache__').glob('step.advance-*.nb[ic]'):
            if f.stat().st_mtime < kernels_mtime:
                f.unlink(missing_ok=True)
    except OSError:
        pass


_drop_stale_advance_cache()
from tissue_sim.core.solver.model import Control, DivergenceError, SimModel, State, substeps_for


@njit(cache=True)
def advance(n_steps, n_sub, h, acts, st, cells, tissue, skel, num, info):
    """n_steps steps of n_sub sub-steps of length h under activations acts (n_steps, M), in place.

    Tuples of flat arrays (built by ``_arrays``): st = mutable state, cells = the cells in SIMD blocks,
    tissue = vertex constants, skel = skeleton constants, num = scalar parameters. Positions and
    velocities alternate between (x, v) and the back buffers (xb, vb); returns how many swaps
    happened. On failure info = (step, cell, cause) and the state is left at the last good sub-step."""
    x, v, xb, vb, f, quat, q, qd, seg_R, seg_t, lam, cell_e, pres, work, cell_len, mlen, mvel = st
    rest, inv_den, mass, free_idx, att_idx, att_seg, mlanes, mcell_muscle, mcell_weight, inv_vl0 = tissue
    seg_order, seg_parent, seg_joint, seg_mass, seg_com, seg_I, j_parent, j_child, j_type, j_axis, j_centre, \
        j_rest, j_range, anc, grav = skel
    log_c, log_r, lam_min, h_ref, vol_actual, iters, jdamp, lim_wh, lim_z, vel_damp, vol_gain, vmax2, \
        fv_on, fv_max, fv_alpha = num
    swaps = 0
    q0, qd0, lam0, cell_work = q.copy(), qd.copy(), lam.copy(), K.cell_work(cells)
    K.to_lanes(quat, pres, cell_e, cell_len, cells, cell_work)     # the cell kernel's per-cell state, in its lane order
    mlen0, mvel0, act_t, mscratch = mlen.copy(), mvel.copy(), np.empty(lam.shape[0]), np.empty(lam.shape[0])
    for n in range(n_steps):
        act = acts[n]
        for _ in range(n_sub):
            q0[:] = q; qd0[:] = qd; lam0[:] = lam; mlen0[:] = mlen; mvel0[:] = mvel
            # 1. muscle tension: contraction state, the active tension's activation x the force-velocity
            # factor (muscle velocity from the last evaluation), then every cell's elastic + volume + damping force
            K.update_contraction(lam, act, log_c, log_r, lam_min, h / h_ref)
            for m in range(act_t.shape[0]):
                act_t[m] = act[m] * K.force_velocity(mvel[m] * inv_vl0[m], fv_max) if fv_on else act[m]
            bad = K.lane_forces(x, v, f, cells, lam, act_t, vol_actual, iters, vol_gain, cell_work)
            if fv_on:
                K.muscle_velocity(cell_work[K.WORK_LENGTH], mlanes, mcell_muscle, mcell_weight, mlen, mvel, h, fv_alpha, mscratch)
            if bad >= 0:
                info[0], info[1], info[2] = n, bad, K.CAUSE_CELL_FORCE
                lam[:] = lam0; mlen[:] = mlen0; mvel[:] = mvel0
                work[0, work.shape[1] - 1] = K.kinetic_energy(v, mass, free_idx)
                K.from_lanes(cell_work, cells, quat, pres, cell_e, cell_len)
                return swaps
            # 2. skeleton: joint torques from the forces on bone-attached vertices, joint dynamics
            ok = K.skeleton_step(h, q, qd, f, x, att_idx, att_seg, seg_order, seg_parent, seg_joint,
                                 seg_mass, seg_com, seg_I, j_parent, j_child, j_type, j_axis, j_centre, j_rest,
                                 j_range, anc, grav, jdamp, lim_wh, lim_z, seg_R, seg_t, work)
            # 3. soft tissue: free vertices integrate (v += h f inv_den, x += h v), attached ones follow the bones
            fast = K.integrate(h, x, v, f, inv_den, xb, vb, att_idx, att_seg, rest, seg_R, seg_t, grav, vel_damp, vmax2)
            if not ok or fast:
                info[0], info[1], info[2] = n, -1, K.CAUSE_SKELETON if not ok else K.CAUSE_SPEED
                q[:] = q0; qd[:] = qd0; lam[:] = lam0; mlen[:] = mlen0; mvel[:] = mvel0
                K.forward_kinematics(q, seg_order, seg_joint, j_parent, j_axis, j_centre, j_rest, seg_R, seg_t)
                work[0, work.shape[1] - 1] = K.kinetic_energy(v, mass, free_idx)
                K.from_lanes(cell_work, cells, quat, pres, cell_e, cell_len)
                return swaps
            x, xb = xb, x
            v, vb = vb, v
            swaps += 1
    work[0, work.shape[1] - 1] = K.kinetic_energy(v, mass, free_idx)
    K.from_lanes(cell_work, cells, quat, pres, cell_e, cell_len)
    return swaps


def _arrays(sim: SimModel, h: float):
    """The constant tuples ``advance`` reads for sub-step length h (cached on the model per h)."""
    key = ('arrays', h)
    t = sim.cache.get(key)
    if t is None:
        p = sim.params
        cells = sim.cell_blocks
        mcells = np.flatnonzero(sim.cell_muscle >= 0).astype(np.int32)
        vl0 = p.max_contraction_velocity * sim.muscle_rest_length
        inv_vl0 = np.where(vl0 > 0, 1.0 / np.where(vl0 > 0, vl0, 1.0), 0.0)
        mlanes = cells[7][mcells]                       # their lanes (the kernel keeps axial lengths in lane order)
        tissue = (sim.rest, sim.inv_denominator(h), sim.mass, sim.free_idx, sim.att_idx, sim.att_seg, mlanes,
                  sim.cell_muscle[mcells], sim.length_weight[mcells], inv_vl0)
        skel = (sim.seg_order, sim.seg_parent, sim.seg_joint, sim.seg_mass, sim.seg_com, sim.seg_inertia,
                sim.j_parent, sim.j_child, sim.j_type, sim.j_axis, sim.j_centre, sim.j_rest, sim.j_range, sim.anc,
                sim.gravity)
        num = (math.log(p.contraction_rate), math.log(p.relax_rate), float(p.min_stretch), float(p.rate_dt),
               p.volume_mode == 'actual', int(p.rotation_iterations), float(p.joint_damping), float(p.limit_omega_dt),
               float(p.limit_damping_ratio), float(p.velocity_damping),
               h / p.volume_relax_time if p.volume_relax_time > 0 else 0.0, float(p.max_speed) ** 2,
               p.max_contraction_velocity > 0 and p.specific_tension > 0, float(p.fv_max_lengthening),
               h / (p.fv_filter_time + h))
        t = sim.cache[key] = (cells, tissue, skel, num)
    return t


def _run(sim: SimModel, state: State, acts: np.ndarray, dt: float) -> None:
    """Advance state in place by len(acts) steps of dt under per-step activations acts (N, M)."""
    p = sim.params
    n_sub = sim.n_substeps if dt == p.dt else substeps_for(p, sim.omega_max, sim.damp_rate, dt)
    h = dt / n_sub
    info = np.array([-1, -1, 0], np.int64)
    st = (state.x, state.v, state.x_back, state.v_back, state.f, state.quat, state.q, state.qd, state.seg_R,
          state.seg_t, state.lam, state.cell_energy, state.pressure, state.work, state.cell_length,
          state.muscle_length, state.muscle_velocity)
    swaps = advance(acts.shape[0], n_sub, h, acts, st, *_arrays(sim, h), info)
    if swaps % 2:
        state.x, state.x_back = state.x_back, state.x
        state.v, state.v_back = state.v_back, state.v
    done = int(info[0]) if info[0] >= 0 else acts.shape[0]
    state.step += done
    state.time += done * dt
    state.kinetic_energy = float(state.work[0, -1])
    if info[0] >= 0:
        raise DivergenceError(state.step + 1, int(info[1]), K.CAUSES[int(info[2])])


def step(sim: SimModel, state: State, ctrl: Control, dt: float | None = None, n_steps: int = 1) -> State:
    """Advance ``state`` in place by one step of ``dt`` seconds (None: params.dt) under ``ctrl``
    (``n_steps`` > 1: that many steps under the same activation in one kernel call, e.g. one frame).

    Raises DivergenceError (state left at the last good sub-step). Returns state."""
    dt = sim.params.dt if dt is None else float(dt)
    if not dt > 0:
        raise ValueError(f'dt must be > 0, got {dt}')
    if n_steps < 1:
        raise ValueError(f'n_steps must be >= 1, got {n_steps}')
    a = np.asarray(ctrl.activation, np.float64)
    # min and max propagate NaN, so the range test also rejects non-finite values (one pass each: this
    # runs every step(), where numpy's per-call overhead on a few values is a noticeable share)
    if a.shape != (sim.n_muscles,) or (a.size and not (a.min() >= 0.0 and a.max() <= 1.0)):
        raise ValueError(f'activation must be {sim.n_muscles} finite values in [0, 1]')
    acts = np.empty((int(n_steps), a.size))
    acts[:] = a
    _run(sim, state, acts, dt)
    return state
