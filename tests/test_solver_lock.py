"""The joint lock (Control.joint_lock / joint_target, State.joint_lock_torque; docs/solver.md "Joint lock"):
a locked hinge holds its coordinate inside the compiled step and reports the torque it applies.

Analytic: a known external torque (a force on a shank vertex, gravity on the segments) on a locked knee is
balanced by the reported lock torque; a locked knee does not move under full muscle activation and its lock
torque is minus the tissue's torque on the shank; the fast step matches the reference step with a lock."""
import numpy as np
import pytest

from tissue_sim.core import solver
from tissue_sim.core.solver import phantom, skeleton as SK


def _sim(**kw):
    return solver.compile_model(phantom.knee(n_gaps=8, knee_range_deg=(0.0, 120.0)), solver.Params.paper(**kw))


def _knee_frame(sim, state, j=0):
    p = sim.j_parent[j]
    return state.seg_R[p] @ sim.j_axis[j], state.seg_R[p] @ sim.j_centre[j] + state.seg_t[p]


def _locked_control(sim, deg):
    ctrl = solver.make_control(sim)
    ctrl.joint_lock[0] = True
    ctrl.joint_target[0] = np.radians(deg)
    return ctrl


def test_the_lock_balances_a_known_external_torque():
    """The skeleton kernel alone: a 7 N force on one shank vertex plus gravity on the segments, knee locked at
    40 deg and at rest: the lock torque is minus (a . (x - p) x F + a . sum_s (com_s - p) x m_s g)."""
    g = np.array([0.0, 0.0, -9.81])
    sim = _sim(gravity=tuple(g))
    state = solver.make_state(sim)
    solver.set_joint_positions(sim, state, [np.radians(40.0)])
    j = 0
    below = np.flatnonzero(sim.anc[j][sim.att_seg])
    i = int(sim.att_idx[below[len(below) // 2]])
    F = np.array([3.0, -2.0, 6.0])
    f = np.zeros_like(state.x)
    f[i] = F
    axis, centre = _knee_frame(sim, state, j)
    com = np.einsum('sij,sj->si', state.seg_R, sim.seg_com) + state.seg_t
    tau_ext = axis @ np.cross(state.x[i] - centre, F)
    tau_ext += sum(axis @ np.cross(com[s] - centre, sim.seg_mass[s] * g) for s in np.flatnonzero(sim.anc[j]))
    assert abs(tau_ext) > 0.1
    lock_tau = np.zeros(sim.n_joints)
    q = state.q.copy()
    qd = np.zeros(sim.n_joints)
    ok = SK.skeleton_step(1e-3, q, qd, f, state.x, sim.skeleton, sim.att_idx, sim.att_seg, 0.0, 0.5, 1.0,
                          state.seg_R, state.seg_t, np.zeros((sim.n_joints, 8 + sim.n_joints)),
                          np.array([True]), np.array([np.radians(40.0)]), lock_tau, np.zeros(1),
                          np.zeros((sim.n_segments, 6)))
    assert ok
    assert lock_tau[0] == pytest.approx(-tau_ext, rel=1e-9)
    assert q[0] == np.radians(40.0) and qd[0] == 0.0
    # unlocked, the same torque accelerates the knee and no lock torque is reported
    q2, qd2 = state.q.copy(), np.zeros(1)
    SK.skeleton_step(1e-3, q2, qd2, f, state.x, sim.skeleton, sim.att_idx, sim.att_seg, 0.0, 0.5, 1.0,
                     state.seg_R.copy(), state.seg_t.copy(), np.zeros((1, 9)), np.array([False]), np.zeros(1), lock_tau, np.zeros(1),
                     np.zeros((sim.n_segments, 6)))
    assert lock_tau[0] == 0.0 and np.sign(qd2[0]) == np.sign(tau_ext)


def test_a_locked_knee_does_not_move_under_full_activation_and_its_torque_is_the_tissue_torque():
    sim = _sim()
    ctrl = _locked_control(sim, 30.0)
    ctrl.activation[:] = 1.0
    state = solver.make_state(sim)
    solver.set_joint_positions(sim, state, ctrl.joint_target)
    free = solver.make_state(sim)
    solver.set_joint_positions(sim, free, ctrl.joint_target)
    unlocked = solver.Control(activation=ctrl.activation.copy())
    for _ in range(400):
        solver.step(sim, state, ctrl)
        solver.step(sim, free, unlocked)
    assert state.q[0] == np.radians(30.0) and state.qd[0] == 0.0
    assert abs(free.q[0] - np.radians(30.0)) > 0.1                 # the same contraction swings a free knee
    obs = solver.observe(sim, state)
    # the torque of the tissue's forces (last sub-step) on the shank's attached vertices about the knee axis
    below = np.flatnonzero(sim.anc[0][sim.att_seg])
    att = sim.att_idx[below]
    axis, centre = _knee_frame(sim, state, 0)
    tau_tissue = axis @ np.cross(state.x[att] - centre, state.f[att]).sum(0)
    assert abs(tau_tissue) > 1.0
    assert obs['joint_lock_torque'][0] == pytest.approx(-tau_tissue, rel=1e-6)
    assert free.joint_lock_torque[0] == 0.0
    # released, it moves
    ctrl.joint_lock[0] = False
    for _ in range(50):
        solver.step(sim, state, ctrl)
    assert abs(state.q[0] - np.radians(30.0)) > 1e-3


def test_a_moving_target_is_followed_exactly():
    sim = _sim()
    ctrl = _locked_control(sim, 0.0)
    state = solver.make_state(sim)
    dt = sim.params.dt
    for n in range(1, 101):
        ctrl.joint_target[0] = np.radians(0.2 * n)
        solver.step(sim, state, ctrl)
        assert state.q[0] == ctrl.joint_target[0]
    assert state.qd[0] == pytest.approx(np.radians(0.2) / dt, rel=1e-9)


def test_fast_step_matches_the_reference_step_with_a_locked_knee():
    sim = _sim(rotation_iterations=50, volume_relax_time=0.005)
    ctrl = _locked_control(sim, 0.0)
    ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    fast, ref = solver.make_state(sim), solver.make_state(sim)
    for n in range(200):
        ctrl.joint_target[0] = np.radians(min(20.0, 0.1 * (n + 1)))       # ramp to 20 deg, then hold
        solver.step(sim, fast, ctrl)
        solver.reference_step(sim, ref, ctrl.activation, joint_lock=ctrl.joint_lock, joint_target=ctrl.joint_target)
    motion = np.abs(fast.x - sim.rest).max()
    assert motion > 1e-3
    assert np.abs(fast.x - ref.x).max() <= 1e-9 * motion
    assert fast.q[0] == ref.q[0] == np.radians(20.0)
    assert abs(ref.joint_lock_torque[0]) > 1.0
    assert fast.joint_lock_torque[0] == pytest.approx(ref.joint_lock_torque[0], rel=1e-8)


@pytest.mark.parametrize('lock, target, what', [(np.zeros(2, bool), None, 'joint_lock'),
                                                (np.array([1]), None, 'joint_lock'),
                                                (np.array([True]), np.array([np.nan]), 'joint_target')])
def test_a_bad_lock_is_rejected_naming_it(lock, target, what):
    sim = _sim()
    state = solver.make_state(sim)
    with pytest.raises(ValueError, match=what):
        solver.step(sim, state, solver.Control(np.zeros(sim.n_muscles), lock, target))
    assert state.step == 0
