"""The time step (docs/method.md section 3 order: muscle tension, then skeleton, then soft tissue).

``advance`` is the compiled step over many steps; ``reference.reference_step`` is the same step in plain
numpy. Its arguments are named tuples: the state's arrays (``Arrays``), the cell layout (``cells.CellLayout``),
the vertex constants (``Tissue``), the skeleton (``skeleton.Skeleton``), the scalar parameters (``Numbers``)
and the scratch buffers (``Scratch``, with ``cells.CellWork``), all made once per model and sub-step length
by ``Workspace`` (owned by the State being stepped: the SimModel stays immutable); stage 4, bone contact, reads
the model's grids (``contact.ContactGrids``) and the Workspace's ``contact.ContactWork``.
"""
from __future__ import annotations

import collections
import math

import numba
import numpy as np
from numba import njit


def _drop_stale_advance_cache() -> None:
    """numba validates advance()'s on-disk cache against this file only, but the cached machine code embeds
    the kernels of the modules it calls: drop that cache whenever one of them is newer (in the cache beside the
    sources and in NUMBA_CACHE_DIR's, where numba keeps it in a folder named after this one: solver_<hash>)."""
    import os
    from pathlib import Path
    here = Path(__file__).resolve()
    user = os.environ.get('NUMBA_CACHE_DIR')
    try:
        newest = max(here.with_name(n).stat().st_mtime for n in ('cells.py', 'skeleton.py', 'integration.py', 'contact.py',
                                                                 'muscle.py', 'implicit.py', 'volume.py', 'simd.py'))
        cached = list((here.parent / '__pycache__').glob('step.*advance-*.nb[ic]'))
        if user:
            cached += Path(user).glob(f'{here.parent.name}_*/step.*advance-*.nb[ic]')
        for f in cached:
            if f.stat().st_mtime < newest:
                f.unlink(missing_ok=True)
    except OSError:
        pass


_drop_stale_advance_cache()
from tissue_sim.core.solver import cells as CK, integration as IK, skeleton as SK  # noqa: E402
from tissue_sim.core.solver import contact as CT, implicit as IM, muscle as MU, volume as VO  # noqa: E402
from tissue_sim.core.solver.model import Control, DivergenceError, SimModel, State, substeps_for  # noqa: E402

CAUSE_CELL_FORCE = 1        # non-finite or absurd elastic force in a cell
CAUSE_SPEED = 2             # a vertex exceeded max_speed (energy blow-up)
CAUSE_SKELETON = 3          # non-finite joint acceleration
CAUSE_ACTIVATION = 4        # an activation outside [0, 1] or not finite (input error: nothing is done)
CAUSE_LOCK_TARGET = 5       # a locked joint's target not finite (input error: nothing is done)
CAUSES = {CAUSE_CELL_FORCE: 'non-finite or overflowing elastic force', CAUSE_SPEED: 'vertex speed above max_speed (energy blow-up)',
          CAUSE_SKELETON: 'non-finite joint acceleration'}

Arrays = collections.namedtuple('Arrays', 'x v xb vb f quat q qd seg_R seg_t lam cell_energy pressure cell_length '
                                'muscle_length muscle_velocity joint_lock_torque activation contact_wrench x_prev v_prev '
                                'history_h')   # the State's arrays (xb, vb: back buffers)
Tissue = collections.namedtuple('Tissue', 'rest inv_den att_idx att_seg mlanes mcell_muscle mcell_weight inv_vl0 '
                                'fmax path_muscle path_data path_powers path_coef path_shift l_rest enc_size enc_start enc_cell '
                                'enc_s6 enc_v0 enc_k enc_cap enc_idx off cv cell_muscle k_active rest_length end_cell end_top '
                                'end_free_off end_free end_bound_off end_bound via_off via_idx via_seg via_local')     # enc_*: volume.Enclosed;
                                # end_*: cells.EndRings; via_*: the point via rings (SimModel.via_*)
Numbers = collections.namedtuple('Numbers', 'log_c log_r lam_min h_ref vol_actual iters jdamp lim_wh lim_z vel_damp '
                                 'vol_gain vmax2 fv_on fv_max fv_alpha tau_act tau_deact fl_on fl_gamma pe_on pe_k pe_eps0 pe_curve')
Scratch = collections.namedtuple('Scratch', 'cell_work skel_work q0 qd0 lam0 mlen0 mvel0 act_t muscle_sums act0 passive '
                                 'fibre path_mono path_dmono path_len path_dlen part_l tau_pe enc_p enc_gb enc_gt enc_t enc_energy')


_cell_pass = CK.lane_forces     # the cell pass of advance (parallel_advance: cells.lane_forces_par)
_im_bdf2_start, _im_integrate, _im_correct, _im_sheath_correct, _im_via_correct, _bone_contact = (
    IM.bdf2_start, IM.integrate, IM.correct, IM.sheath_correct, IM.via_correct, CT.bone_contact)
# (parallel_advance: implicit.parallel_kernels, BDF2's start, the triangular passes, the via rings' moves and the bone
# contact's broad and narrow phases on the threads)


@njit(inline='always')
def muscle_tension(q, a_st, mvel, tissue, num, scratch):
    """Stage 1 before the cell pass: the active force-length's fibre lengths of the source-model paths at the joint
    coordinates q, the passive fibre force as joint torques (scratch.tau_pe), and each muscle's active tension factor
    (activation x force-velocity x force-length) into scratch.act_t."""
    if num.fl_on or num.pe_on:
        MU.fibre_lengths(q, tissue.path_muscle, tissue.path_data, tissue.path_powers, tissue.path_coef,
                         tissue.path_shift, tissue.l_rest, scratch.path_mono, scratch.path_dmono, scratch.path_len,
                         scratch.path_dlen, scratch.part_l, scratch.fibre)
        if num.pe_on:
            MU.passive_torques(tissue.path_muscle, tissue.path_data, scratch.path_len, scratch.path_dlen,
                               scratch.part_l, tissue.path_shift, tissue.fmax, num.pe_k, num.pe_eps0, num.pe_curve,
                               scratch.tau_pe, scratch.passive)
    MU.tension_activation_of(a_st, mvel, tissue.inv_vl0, num.fv_on, num.fv_max, scratch.fibre, num.fl_on,
                             num.fl_gamma, scratch.act_t)


@njit(inline='always')
def after_cells(x, f, h, lam, mlen, mvel, tissue, num, scratch, velocity):
    """Stage 1 after the cell pass at x: the muscle cells' enclosed-volume forces, the partly bound end rings' shift,
    and (velocity) the muscles' length and velocity from the cell pass's axial lengths."""
    if tissue.enc_size.shape[0] > 0:
        VO.enclosed_lanes(x, f, tissue.enc_size, tissue.enc_start, tissue.enc_cell, tissue.enc_s6, tissue.enc_v0,
                          tissue.enc_k, tissue.enc_cap, tissue.enc_idx, scratch.enc_p, scratch.enc_gb, scratch.enc_gt,
                          scratch.enc_t, scratch.enc_energy)
    if tissue.end_cell.shape[0] > 0:
        CK.end_ring_shift(x, f, tissue.off, tissue.cv, tissue.cell_muscle, tissue.k_active, tissue.rest_length,
                          tissue.end_cell, tissue.end_top, tissue.end_free_off, tissue.end_free,
                          tissue.end_bound_off, tissue.end_bound, lam, scratch.act_t)
    if velocity and num.fv_on:
        CK.muscle_velocity(scratch.cell_work.ll, tissue.mlanes, tissue.mcell_muscle, tissue.mcell_weight, mlen, mvel, h,
                           num.fv_alpha, scratch.muscle_sums)


@njit(cache=True, nogil=True)     # nogil: the simulator node steps in a thread of its own (core/realtime.py)
def advance(n_steps, n_sub, h, acts, lock, target, st, cells, tissue, sk, num, scratch, contact, imp, info):
    """n_steps steps of n_sub sub-steps of length h under activations acts (n_steps, M) or (1, M) (the
    same for every step) and the joint lock (lock (J,) bool, target (J,) [rad]: Control.joint_lock/joint_target),
    in place. Positions and velocities alternate between (x, v) and the back buffers
    (xb, vb) (with BDF2 the two rotate with its history (x_prev, v_prev): (x, xb, x_prev) <- (xb, x_prev, x));
    returns how many swaps (rotations) happened. On failure info = (step, cell, cause) and the state is left
    at the last good sub-step (an activation outside [0, 1] or not finite: nothing is done,
    info = (-1, muscle, CAUSE_ACTIVATION)).

    The arguments come as plain tuples in the order of the named tuples (numba's dispatcher types a plain
    tuple of arrays in its C fast path, a named tuple through Python: ~7 us more per call) and are named here;
    contact = (the model's contact.ContactGrids, the Workspace's contact.ContactWork); imp = implicit.Implicit (the
    implicit integrator's factor and buffers; on = False for the others)."""
    st, cells, tissue, sk, num = Arrays(*st), CK.CellLayout(*cells), Tissue(*tissue), SK.Skeleton(*sk), Numbers(*num)
    scratch, imp = Scratch(CK.CellWork(*scratch[0]), *scratch[1:]), IM.Implicit(*imp)
    cgrid, cwork = CT.ContactGrids(*contact[0]), CT.ContactWork(*contact[1])
    x, v, xb, vb, f, q, qd, lam, mlen, mvel = st.x, st.v, st.xb, st.vb, st.f, st.q, st.qd, st.lam, st.muscle_length, st.muscle_velocity
    xp, vp = st.x_prev, st.v_prev  # (BDF2's history: a third buffer, rotated with the other two)
    a_st = st.activation          # the activation state (the commands are its excitations when tau_act > 0)
    work, act_t = scratch.cell_work, scratch.act_t
    for n in range(acts.shape[0]):
        for m in range(acts.shape[1]):
            if not (acts[n, m] >= 0.0 and acts[n, m] <= 1.0):      # (NaN fails both)
                info[1], info[2] = m, CAUSE_ACTIVATION
                return 0
    for j in range(lock.shape[0]):
        if lock[j] and not math.isfinite(target[j]):
            info[1], info[2] = j, CAUSE_LOCK_TARGET
            return 0
    swaps = 0
    CK.to_lanes(st.quat, st.pressure, st.cell_energy, st.cell_length, cells, work)   # per-cell state in lane order
    for n in range(n_steps):
        act = acts[n if acts.shape[0] > 1 else 0]
        for _ in range(n_sub):
            scratch.q0[:] = q; scratch.qd0[:] = qd; scratch.lam0[:] = lam; scratch.mlen0[:] = mlen; scratch.mvel0[:] = mvel
            scratch.act0[:] = a_st
            # 0. activation dynamics: the activation state one sub-step towards the commanded excitation
            # (tau_act 0: the activation is the command, the paper's instant activation)
            MU.advance_activation(act, a_st, h, num.tau_act, num.tau_deact)
            # 1. muscle tension: contraction state, the active tension's activation x the force-velocity
            # factor (muscle velocity from the last evaluation) x the active force-length factor (the fibre
            # length of the source-model path at the joint coordinates now), the passive fibre force as joint torques
            # (conservative, muscle.py), then every cell's elastic + volume + damping force; integrator
            # implicit: all of them at the inertial prediction y = x + h v (+ h^2 g) with velocity v (BDF2: at
            # y = xh + (2h/3) vh with vh, the velocity its solve corrects: v1 = vh + w / (2h/3))
            CK.update_contraction(lam, a_st, num.log_c, num.log_r, num.lam_min, h / num.h_ref)
            xe = x
            hs, xs, vs = h, x, v       # the implicit solve's step length and start (BDF2: 2h/3 from its combination)
            if imp.on and imp.bdf2:    # (its start and the prediction y in one pass)
                _im_bdf2_start(h, x, v, xp, vp, st.history_h, imp.xh, imp.vh, imp.y, imp.yc, imp.yg, imp.hs)
                hs, xs, vs = imp.hs, imp.xh, imp.vh      # (implicit.solve_length)
            elif imp.on:
                IM.predict(x, v, imp.y, imp.yc, imp.yg, imp.hs)
            if imp.on:
                xe = imp.y
            muscle_tension(q, a_st, mvel, tissue, num, scratch)
            bad = _cell_pass(xe, vs, f, cells, lam, act_t, num.vol_actual, num.iters, num.vol_gain, work)
            after_cells(xe, f, h, lam, mlen, mvel, tissue, num, scratch, True)
            if bad >= 0:
                info[0], info[1], info[2] = n, bad, CAUSE_CELL_FORCE
                lam[:] = scratch.lam0; mlen[:] = scratch.mlen0; mvel[:] = scratch.mvel0; a_st[:] = scratch.act0
                CK.from_lanes(work, cells, st.quat, st.pressure, st.cell_energy, st.cell_length)
                return swaps
            # 2. skeleton: joint torques from the forces on bone-attached vertices, the point via rings' net forces
            # (integration.via_forces), the passive fibre force and the last sub-step's contact reaction (stage 4), joint dynamics
            if tissue.via_seg.shape[0] > 0:
                IK.via_forces(f, tissue.via_off, tissue.via_idx, tissue.via_seg, tissue.via_local, st.seg_R, st.seg_t,
                              tissue.inv_den, st.contact_wrench)
            ok = SK.skeleton_step(h, q, qd, f, xe, sk, tissue.att_idx, tissue.att_seg, num.jdamp, num.lim_wh, num.lim_z,
                                  st.seg_R, st.seg_t, scratch.skel_work, lock, target, st.joint_lock_torque, scratch.tau_pe,
                                  st.contact_wrench)
            st.contact_wrench[:] = 0.0    # (applied: stage 3's sheath correction and stage 4 write this sub-step's)
            # 3. soft tissue: free vertices integrate (v += h f inv_den, x += h v), attached ones follow the bones
            if imp.on:             # implicit: x1 = y + A^-1 (f - Lhat_fa dxa); further local/global iterations
                fast = _im_integrate(hs, xs, f, xb, vb, imp, tissue.att_idx, tissue.att_seg, tissue.rest, st.seg_R,
                                    st.seg_t, num.vmax2)
                for _ in range(1, imp.iters):
                    if fast or not ok:
                        break
                    if _cell_pass(xb, vb, f, cells, lam, act_t, num.vol_actual, num.iters, num.vol_gain, work) >= 0:
                        fast = 1       # (reported as a blow-up: the iterate is not finite)
                        break
                    after_cells(xb, f, h, lam, mlen, mvel, tissue, num, scratch, False)
                    fast = _im_correct(hs, xs, f, xb, vb, imp, num.vmax2)
                if ok and not fast:    # the sheath inside the implicit step (implicit.sheath_correct)
                    fast = _im_sheath_correct(hs, xs, xb, vb, imp, st.seg_R, st.seg_t, cgrid, num.vmax2, st.contact_wrench)
                if ok and not fast:    # the point via rings inside it (implicit.via_correct; none: nothing done)
                    fast = _im_via_correct(hs, xs, xb, vb, imp, tissue.via_off, tissue.via_idx, tissue.via_seg,
                                          tissue.via_local, st.seg_R, st.seg_t, num.vmax2)
            else:
                fast = IK.integrate(h, x, v, f, tissue.inv_den, xb, vb, tissue.att_idx, tissue.att_seg, tissue.rest,
                                    st.seg_R, st.seg_t, sk.gravity, num.vel_damp, num.vmax2)
            if not ok or fast:
                info[0], info[1], info[2] = n, -1, CAUSE_SKELETON if not ok else CAUSE_SPEED
                q[:] = scratch.q0; qd[:] = scratch.qd0; lam[:] = scratch.lam0; mlen[:] = scratch.mlen0; mvel[:] = scratch.mvel0
                a_st[:] = scratch.act0
                SK.forward_kinematics(q, sk, st.seg_R, st.seg_t)
                CK.from_lanes(work, cells, st.quat, st.pressure, st.cell_energy, st.cell_length)
                return swaps
            # 3b. point via rings: each one's centroid moved onto its place on its bone (integration.hold_via_points;
            # a move d changes the velocity by d / hs: v1 = (x1 - xs) / hs)
            if tissue.via_seg.shape[0] > 0:
                IK.hold_via_points(hs, xb, vb, tissue.via_off, tissue.via_idx, tissue.via_seg, tissue.via_local,
                                   st.seg_R, st.seg_t, tissue.inv_den)
            # 4. bone contact: free vertices closer to a bone than the margin are projected out, their inward
            # velocity relative to the bone removed (the bone's pose at the sub-step's start: forward kinematics of q0)
            # (4a: first the fold contact keeps flexion-side tissue on its side of each folding hinge's bisector plane,
            # 4b: the wrap cylinders keep the muscles that wrap over them outside);
            # each velocity change's reaction goes to the segment that made it, for the next sub-step's skeleton step
            if imp.on and imp.bdf2:    # (stage 4 lists the vertices it moves: BDF2's history, implicit.bdf2_history)
                CT.unmark(cwork)
            if cgrid.g_seg.shape[0] > 0 or cgrid.f_seg.shape[0] > 0 or cgrid.w_seg.shape[0] > 0:
                SK.forward_kinematics(scratch.q0, sk, cwork.R0, cwork.t0)
                CT.fold_contact(h, xb, vb, st.seg_R, st.seg_t, cgrid, cwork, tissue.inv_den, st.contact_wrench)
                CT.wrap_contact(h, xb, vb, st.seg_R, st.seg_t, cgrid, cwork, tissue.inv_den, st.contact_wrench)
                _bone_contact(h, xb, vb, st.seg_R, st.seg_t, cgrid, cwork, tissue.inv_den, st.contact_wrench)
            if imp.on and imp.bdf2:    # the sub-step is taken: it is BDF2's history for the next one, and the
                IM.bdf2_history(h, xb, vb, x, v, st.history_h, cwork.moved, cwork.n_moved)     # buffers rotate
                x, xb, xp = xb, xp, x
                v, vb, vp = vb, vp, v
            else:
                x, xb = xb, x
                v, vb = vb, v
            swaps += 1
    CK.from_lanes(work, cells, st.quat, st.pressure, st.cell_energy, st.cell_length)
    if tissue.enc_size.shape[0] > 0:        # (the enclosed-volume energy of the last force evaluation)
        st.cell_energy[:] += scratch.enc_energy
    return swaps


_PARALLEL = []


def parallel_advance():
    """advance with the thread-parallel kernels (Params.threads != 1): the same code, compiled from it with
    _cell_pass bound to cells.lane_forces_par and the implicit integrator's kernels and the bone contact to
    implicit.parallel_kernels', once per process and not cached on disk. (numba caches parallel kernels, but a
    cached function that calls one segfaulted when loaded in a later process if it had been compiled against a callee
    loaded from the cache: measured with advance itself; so advance, cached, never calls a parallel kernel.) The first
    call compiles it (about as long as advance's cold compile)."""
    if not _PARALLEL:
        g = dict(globals())
        g['_cell_pass'] = CK.lane_forces_par
        (g['_im_bdf2_start'], g['_im_integrate'], g['_im_correct'], g['_im_sheath_correct'], g['_im_via_correct'],
         g['_bone_contact']) = IM.parallel_kernels()
        _PARALLEL.append(IM.recompiled(advance, g, 'advance_parallel', nogil=True))
    return _PARALLEL[0]


class Workspace:
    """What ``advance`` reads besides the state, for one model: per sub-step length h the constants
    (Tissue, Numbers) and the scratch buffers (Scratch; their contents on entry do not matter). Owned by
    the State it steps (``state.workspace``, made on its first step, rebuilt for another model). The bone
    contact's buffers (``contact``: the broad phase's records, the poses at a sub-step's start) are one
    ``contact.ContactWork`` for every h."""

    def __init__(self, sim: SimModel):
        self.sim = sim
        self._by_h = {}
        self._imp = {}
        self.no_lock = (np.zeros(sim.n_joints, np.bool_), np.zeros(sim.n_joints))    # (lock, target): no joint locked
        self.contact = CT.work(sim.contact, sim.n_segments,      # (BDF2 reads the moved vertices)
                               sim.n_vertices if sim.params.integrator == 'implicit' and sim.params.implicit_scheme == 'bdf2' else 0)

    def arrays(self, h: float):
        """(cells, tissue, skeleton, numbers, scratch, (contact grids, contact work)) for sub-step length h, as
        named tuples."""
        return self._get(h)[0]

    def plain(self, h: float):
        """The same as plain tuples (what advance() is called with)."""
        return self._get(h)[1]

    def _get(self, h: float):
        t = self._by_h.get(h)
        if t is None:
            if len(self._by_h) > 8:
                self._by_h.clear(); self._imp.clear()
            named = self._make(h)
            cells, tissue, sk, num, scratch, (cgrid, cwork) = named
            plain = (tuple(cells), tuple(tissue), tuple(sk), tuple(num), (tuple(scratch.cell_work),) + tuple(scratch)[1:],
                     (tuple(cgrid), tuple(cwork)), tuple(self.implicit(h)))
            t = self._by_h[h] = (named, plain)
        return t

    def implicit(self, h: float):
        """The implicit integrator's implicit.Implicit for sub-step length h (its factor made once per h)."""
        imp = self._imp.get(h)
        if imp is None:
            imp = self._imp[h] = IM.make(self.sim, h)
        return imp

    def _make(self, h: float):
        sim, p = self.sim, self.sim.params
        cells = sim.cell_blocks
        mcells = np.flatnonzero(sim.cell_muscle >= 0).astype(np.int32)
        vl0 = p.max_contraction_velocity * sim.muscle_rest_length
        enc = VO.pack_enclosed(sim.off, sim.cv, sim.cell_sign, sim.rest_volume, sim.k_enclosed, sim.volume_cap)
        tissue = Tissue(sim.rest, sim.inv_denominator(h), sim.att_idx, sim.att_seg,
                        cells.lane_of[mcells],             # the muscle cells' lanes (the kernel keeps axial lengths in lane order)
                        sim.cell_muscle[mcells], sim.length_weight[mcells],
                        np.where(vl0 > 0, 1.0 / np.where(vl0 > 0, vl0, 1.0), 0.0),
                        MU.muscle_constants(sim)[0], *MU.path_constants(sim),   # the force-length's constants (muscle.py)
                        *enc, sim.off, sim.cv, sim.cell_muscle, sim.k_active, sim.rest_length, *sim.end_rings,
                        sim.via_off, sim.via_idx, sim.via_seg, sim.via_local)
        num = Numbers(math.log(p.contraction_rate), math.log(p.relax_rate), float(p.min_stretch), float(p.rate_dt),
                      p.volume_mode == 'actual', int(p.rotation_iterations), float(p.joint_damping),
                      float(p.limit_omega_dt), float(p.limit_damping_ratio), float(p.velocity_damping),
                      h / p.volume_relax_time if p.volume_relax_time > 0 else 0.0, float(p.max_speed) ** 2,
                      p.max_contraction_velocity > 0 and p.specific_tension > 0, float(p.fv_max_lengthening),
                      h / (p.fv_filter_time + h),
                      float(p.activation_time), float(p.deactivation_time), p.force_length and p.specific_tension > 0,
                      float(p.fl_width), p.passive_force_length and p.specific_tension > 0, float(p.fl_passive_shape),
                      float(p.fl_passive_strain), MU.PASSIVE_CURVES.index(p.fl_passive_curve))
        M, J = sim.n_muscles, sim.n_joints
        pw = MU.PathWork(M, sim.tissue.path_muscle.size, sim.tissue.path_powers.shape)
        scratch = Scratch(CK.cell_work(cells), np.zeros((max(J, 1), 8 + J)), np.empty(J), np.empty(J), np.empty(M),
                          np.empty(M), np.empty(M), np.empty(M), np.empty(M), np.empty(M), np.zeros(M),
                          MU.fibre_state(sim, sim.j_rest)[0].copy(), pw[0], pw[1], pw[2], pw[3], pw[4], np.zeros(J),
                          *VO.enclosed_work(enc), np.zeros(sim.n_cells))
        return cells, tissue, sim.skeleton, num, scratch, (sim.contact, self.contact)


def _run(sim: SimModel, state: State, acts: np.ndarray, dt: float, n_steps: int | None = None, lock=None,
         target=None) -> None:
    """Advance state in place by n_steps (None: len(acts)) steps of dt under per-step activations
    acts (n_steps, M), or (1, M): the same for every step, and the joint lock (lock (J,) bool, target (J,)
    [rad]; None: no joint locked). Raises ValueError for an activation outside
    [0, 1] or not finite (nothing done), DivergenceError (state left at the last good sub-step)."""
    n_steps = acts.shape[0] if n_steps is None else n_steps
    if acts.ndim != 2 or acts.shape[1] != sim.n_muscles or acts.shape[0] not in (1, n_steps):
        raise ValueError(f'activation must be {sim.n_muscles} finite values in [0, 1] per step')
    p = sim.params
    n_sub = sim.n_substeps if dt == p.dt else substeps_for(p, sim.omega_max, sim.damp_rate, dt)
    h = dt / n_sub
    info = np.array([-1, -1, 0], np.int64)
    ws = state.workspace
    if ws is None or ws.sim is not sim:
        ws = state.workspace = Workspace(sim)
    if state.joint_lock_torque is None:
        state.joint_lock_torque = np.zeros(sim.n_joints)
    if state.activation is None:
        state.activation = np.zeros(sim.n_muscles)
    if state.contact_wrench is None:
        state.contact_wrench = np.zeros((sim.n_segments, 6))
    if state.x_prev is None or state.x_prev.shape != state.x.shape:
        state.x_prev, state.v_prev, state.history_h = np.zeros_like(state.x), np.zeros_like(state.x), np.zeros(1)
    st = (state.x, state.v, state.x_back, state.v_back, state.f, state.quat, state.q, state.qd, state.seg_R,
          state.seg_t, state.lam, state.cell_energy, state.pressure, state.cell_length, state.muscle_length,
          state.muscle_velocity, state.joint_lock_torque, state.activation, state.contact_wrench, state.x_prev,
          state.v_prev, state.history_h)   # (the fields of Arrays)
    if lock is None:
        lock, target = ws.no_lock
    run = advance
    if p.threads != 1:          # (numba's setting is per Python thread: set where the step runs)
        set_threads(p.threads)
        run = parallel_advance()
    swaps = run(n_steps, n_sub, h, acts, lock, target, st, *ws.plain(h), info)
    if info[2] == CAUSE_ACTIVATION:
        m = int(info[1])
        raise ValueError(f'activation must be {sim.n_muscles} finite values in [0, 1]; muscle {m} '
                         f'({sim.tissue.muscle_names[m]!r}) has {acts[np.flatnonzero(~((acts[:, m] >= 0) & (acts[:, m] <= 1)))[0], m]}')
    if info[2] == CAUSE_LOCK_TARGET:
        raise ValueError(f'joint_target must be finite where joint_lock is set; joint {int(info[1])} '
                         f'({sim.tissue.joint_names[int(info[1])]!r}) has {target[int(info[1])]}')
    if p.integrator == 'implicit' and p.implicit_scheme == 'bdf2':     # (the buffers rotate: advance)
        for _ in range(swaps % 3):
            state.x, state.x_back, state.x_prev = state.x_back, state.x_prev, state.x
            state.v, state.v_back, state.v_prev = state.v_back, state.v_prev, state.v
    elif swaps % 2:
        state.x, state.x_back = state.x_back, state.x
        state.v, state.v_back = state.v_back, state.v
    done = int(info[0]) if info[0] >= 0 else n_steps
    state.step += done
    state.time += done * dt
    if info[0] >= 0:
        raise DivergenceError(state.step + 1, int(info[1]), CAUSES[int(info[2])])


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
    lock, target = joint_lock_of(sim, ctrl)
    _run(sim, state, a.reshape(1, -1), dt, int(n_steps), lock, target)
    return state


def joint_lock_of(sim: SimModel, ctrl: Control):
    """(lock, target) of a Control for advance(): (None, None) when it has no joint_lock; ValueError naming the
    field for a joint_lock that is not J booleans or a joint_target that is not J numbers (a target that is
    not finite where locked is refused by advance(): nothing done). Kept to attribute checks: it runs on
    every step() call."""
    lk, tg = ctrl.joint_lock, ctrl.joint_target
    if lk is None:
        return None, None
    J = sim.n_joints
    if not (type(lk) is np.ndarray and lk.dtype is _BOOL and lk.shape == (J,) and lk.flags.c_contiguous):
        lk = np.ascontiguousarray(lk)
        if lk.shape != (J,) or lk.dtype != _BOOL:
            raise ValueError(f'joint_lock must be {J} booleans (one per joint), got {lk.dtype} of shape {lk.shape}')
    if tg is None:
        tg = sim.j_rest
    elif not (type(tg) is np.ndarray and tg.dtype is _F64 and tg.shape == (J,) and tg.flags.c_contiguous):
        try:
            tg = np.ascontiguousarray(tg, np.float64)
        except (TypeError, ValueError):
            raise ValueError(f'joint_target must be {J} joint coordinates [rad]') from None
        if tg.shape != (J,):
            raise ValueError(f'joint_target must be {J} joint coordinates [rad], got shape {tg.shape}')
    return lk, tg


_BOOL, _F64 = np.dtype(np.bool_), np.dtype(np.float64)
_MAX_THREADS = int(numba.config.NUMBA_NUM_THREADS)


def set_threads(n: int) -> int:
    """numba's threads for the parallel step (Params.threads): n, at most NUMBA_NUM_THREADS; 0: all of them. Returns
    the number set. Only the speed depends on it (parallel_advance is bit-identical for any number)."""
    n = _MAX_THREADS if n <= 0 else min(int(n), _MAX_THREADS)
    if numba.get_num_threads() != n:
        numba.set_num_threads(n)
    return n
