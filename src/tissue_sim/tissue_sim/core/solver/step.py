"""The time step (docs/method.md section 3 order: muscle tension, then skeleton, then soft tissue)."""
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
def advance(n_steps, n_sub, h, acts, st, cells, tissue, skel, num, scratch, info):
    """n_steps steps of n_sub sub-steps of length h under activations acts (n_steps, M) or (1, M) (the
    same for every step), in place.

    Tuples of flat arrays (built by ``_arrays``): st = mutable state, cells = the cells in SIMD blocks,
    tissue = vertex constants, skel = skeleton constants, num = scalar parameters, scratch = buffers
    (their contents on entry do not matter). Positions and velocities alternate between (x, v) and the
    back buffers (xb, vb); returns how many swaps happened. On failure info = (step, cell, cause) and
    the state is left at the last good sub-step (an activation outside [0, 1] or not finite: nothing
    is done, info = (-1, muscle, CAUSE_ACTIVATION))."""
    x, v, xb, vb, f, quat, q, qd, seg_R, seg_t, lam, cell_e, pres, cell_len, mlen, mvel = st
    rest, inv_den, att_idx, att_seg, mlanes, mcell_muscle, mcell_weight, inv_vl0 = tissue
    seg_order, seg_parent, seg_joint, seg_mass, seg_com, seg_I, j_parent, j_child, j_type, j_axis, j_centre, \
        j_rest, j_range, anc, grav = skel
    log_c, log_r, lam_min, h_ref, vol_actual, iters, jdamp, lim_wh, lim_z, vel_damp, vol_gain, vmax2, \
        fv_on, fv_max, fv_alpha = num
    cell_work, work, q0, qd0, lam0, mlen0, mvel0, act_t, mscratch = scratch
    for n in range(acts.shape[0]):
        for m in range(acts.shape[1]):
            if not (acts[n, m] >= 0.0 and acts[n, m] <= 1.0):      # (NaN fails both)
                info[1], info[2] = m, K.CAUSE_ACTIVATION
                return 0
    swaps = 0
    K.to_lanes(quat, pres, cell_e, cell_len, cells, cell_work)     # the cell kernel's per-cell state, in its lane order
    for n in range(n_steps):
        act = acts[n if acts.shape[0] > 1 else 0]
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
                K.from_lanes(cell_work, cells, quat, pres, cell_e, cell_len)
                return swaps
            x, xb = xb, x
            v, vb = vb, v
            swaps += 1
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
        tissue = (sim.rest, sim.inv_denominator(h), sim.att_idx, sim.att_seg, mlanes,
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
        M, J = sim.n_muscles, sim.n_joints
        scratch = (K.cell_work(cells), np.zeros((max(J, 1), 9)), np.empty(J), np.empty(J), np.empty(M),
                   np.empty(M), np.empty(M), np.empty(M), np.empty(M))
        t = sim.cache[key] = (cells, tissue, skel, num, scratch)
    return t


def _run(sim: SimModel, state: State, acts: np.ndarray, dt: float, n_steps: int | None = None) -> None:
    """Advance state in place by n_steps (None: len(acts)) steps of dt under per-step activations
    acts (n_steps, M), or (1, M): the same for every step. Raises ValueError for an activation outside
    [0, 1] or not finite (nothing done), DivergenceError (state left at the last good sub-step)."""
    n_steps = acts.shape[0] if n_steps is None else n_steps
    if acts.ndim != 2 or acts.shape[1] != sim.n_muscles or acts.shape[0] not in (1, n_steps):
        raise ValueError(f'activation must be {sim.n_muscles} finite values in [0, 1] per step')
    p = sim.params
    n_sub = sim.n_substeps if dt == p.dt else substeps_for(p, sim.omega_max, sim.damp_rate, dt)
    h = dt / n_sub
    info = np.array([-1, -1, 0], np.int64)
    st = (state.x, state.v, state.x_back, state.v_back, state.f, state.quat, state.q, state.qd, state.seg_R,
          state.seg_t, state.lam, state.cell_energy, state.pressure, state.cell_length,
          state.muscle_length, state.muscle_velocity)
    swaps = advance(n_steps, n_sub, h, acts, st, *_arrays(sim, h), info)
    if info[2] == K.CAUSE_ACTIVATION:
        m = int(info[1])
        raise ValueError(f'activation must be {sim.n_muscles} finite values in [0, 1]; muscle {m} '
                         f'({sim.tissue.muscle_names[m]!r}) has {acts[np.flatnonzero(~((acts[:, m] >= 0) & (acts[:, m] <= 1)))[0], m]}')
    if swaps % 2:
        state.x, state.x_back = state.x_back, state.x
        state.v, state.v_back = state.v_back, state.v
    done = int(info[0]) if info[0] >= 0 else n_steps
    state.step += done
    state.time += done * dt
    if info[0] >= 0:
        raise DivergenceError(state.step + 1, int(info[1]), K.CAUSES[int(info[2])])


def step(sim: SimModel, state: State, ctrl: Control, dt: float | None = None, n_steps: int = 1) -> State:
    """Advance ``state`` in place by one step of ``dt`` seconds (None: params.dt) under ``ctrl``
    (``n_steps`` > 1: that many steps under the same activation in one kernel call, e.g. one frame).

    Raises ValueError for a bad dt, n_steps or activation (finite, in [0, 1]; nothing done) and
    DivergenceError (state left at the last good sub-step). Returns state."""
    dt = sim.params.dt if dt is None else float(dt)
    if not dt > 0:
        raise ValueError(f'dt must be > 0, got {dt}')
    if n_steps < 1:
        raise ValueError(f'n_steps must be >= 1, got {n_steps}')
    # the activation's range is checked in advance() (compiled: numpy's per-call overhead on a few values
    # is a noticeable share of a step)
    a = np.asarray(ctrl.activation, np.float64)
    if a.shape != (sim.n_muscles,):
        raise ValueError(f'activation must be {sim.n_muscles} finite values in [0, 1], got shape {a.shape}')
    _run(sim, state, a.reshape(1, -1), dt, int(n_steps))
    return state
