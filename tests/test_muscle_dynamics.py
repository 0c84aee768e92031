"""Activation dynamics and force-length of the physical set (docs/solver.md "Activation dynamics", "Force-length"):
the first-order response against the analytic solution of Thelen 2003 eq. 1, the curves against Thelen 2003 eqs. 2-3,
the fast step against the readable reference step, the passive fibre force conservative, each muscle's force observed
in newtons on the bundled model as the force it delivers to the shank, the paper set unchanged, the TissueState fields."""
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from tissue_sim.core import solver
from tissue_sim.core.solver import muscle as MU, phantom


def _knee(**kw):
    return solver.compile_model(phantom.knee(n_gaps=12, knee_range_deg=(0.0, 60.0)), solver.Params.physical(**kw))


def _rise(t, tau):
    """Thelen 2003 eq. 1 from a = 0 under u = 1: dt = tau (0.5 + 1.5 a) / (1 - a) da, so t = tau (-1.5 a - 2 ln(1 - a))."""
    return brentq(lambda a: tau * (-1.5 * a - 2.0 * math.log1p(-a)) - t, 0.0, 1.0 - 1e-15) if t > 0 else 0.0


def _fall(t, a0, tau):
    """Under u = 0: da/dt = -a (0.5 + 1.5 a) / tau, so a / (0.5 + 1.5 a) = a0 / (0.5 + 1.5 a0) exp(-t / (2 tau))."""
    r = a0 / (0.5 + 1.5 * a0) * math.exp(-t / (2.0 * tau))
    return 0.5 * r / (1.0 - 1.5 * r)


def test_activation_follows_the_first_order_dynamics_of_thelen_2003():
    sim = _knee()
    p = sim.params
    assert (p.activation_time, p.deactivation_time) == (0.015, 0.05)
    state, ctrl = solver.make_state(sim), solver.make_control(sim)
    m = solver.muscle_indices(sim, 'hamstrings')[0]
    ctrl.activation[m] = 1.0
    ups, downs = [], []
    for i in range(130):                                         # 130 ms of full excitation
        solver.step(sim, state, ctrl)
        ups.append((state.time, state.activation[m]))
    a_top = state.activation[m]
    ctrl.activation[m] = 0.0
    for i in range(200):                                         # then 200 ms of none
        solver.step(sim, state, ctrl)
        downs.append((state.time - 0.13, state.activation[m]))
    err_up = max(abs(a - _rise(t, p.activation_time)) for t, a in ups)
    err_down = max(abs(a - _fall(t, a_top, p.deactivation_time)) for t, a in downs)
    assert err_up < 5e-4 and err_down < 5e-4, (err_up, err_down)
    # the time constants as seen: 63 % of the rise at 15.8 ms (tau_act (0.5 + 1.5 a): 0.5-2 tau_act), the fall
    # to 1/e of its start much slower (tau_deact / (0.5 + 1.5 a))
    t63 = next(t for t, a in ups if a >= 1 - math.exp(-1))
    assert 0.014 < t63 < 0.018
    t37 = next(t for t, a in downs if a <= a_top * math.exp(-1))
    assert 0.03 < t37 < 0.1
    assert ups[-1][1] > 0.99 and 0.0 < downs[-1][1] < 0.05
    assert solver.observe(sim, state)['activations'][m] == state.activation[m]


def test_force_length_curves_are_thelen_2003():
    gamma, k, e0 = 0.45, 5.0, 0.6
    assert MU.active_force_length(1.0, gamma) == 1.0
    half = math.sqrt(gamma * math.log(2.0))                          # exp(-d^2 / gamma) = 1/2
    assert MU.active_force_length(1.0 + half, gamma) == pytest.approx(0.5, abs=1e-12)
    assert MU.active_force_length(1.0 - half, gamma) == pytest.approx(0.5, abs=1e-12)
    assert MU.active_force_length(0.5, gamma) == pytest.approx(math.exp(-0.25 / 0.45), rel=1e-12)
    assert MU.passive_force_length(1.0, k, e0) == 0.0 and MU.passive_force_length(0.7, k, e0) == 0.0
    assert MU.passive_force_length(1.0 + e0, k, e0) == pytest.approx(1.0, rel=1e-12)     # Fmax at strain eps0
    assert MU.passive_force_length(1.3, k, e0) == pytest.approx((math.exp(2.5) - 1) / (math.exp(5) - 1), rel=1e-12)
    for ln in (1.1, 1.4, 1.7):                                       # the energy's derivative is the force
        d = 1e-6
        dE = (MU.passive_energy_density(ln + d, k, e0) - MU.passive_energy_density(ln - d, k, e0)) / (2 * d)
        assert dE == pytest.approx(MU.passive_force_length(ln, k, e0), rel=1e-6)
    assert (solver.Params().fl_width, solver.Params().fl_passive_shape, solver.Params().fl_passive_strain) == (gamma, k, e0)
    p = solver.Params.physical()        # the passive strain calibrated against Riener & Edrich 1999 (docs/solver.md)
    assert (p.fl_width, p.fl_passive_shape, p.fl_passive_strain, p.fl_passive_curve) == (gamma, k, 2.0, 'thelen')
    assert p.passive_force_length and not solver.Params.paper().passive_force_length


def test_fast_step_matches_the_reference_step_with_muscle_dynamics():
    """Activation dynamics, active and passive force-length on (the passive fibre force acting: the fibres start
    stretched), excitations switched on and off."""
    sim = _knee(rotation_iterations=50, passive_force_length=True, rest_fibre_length=1.15)
    fast, ref = solver.make_state(sim), solver.make_state(sim)
    ctrl = solver.make_control(sim)
    for i in range(160):
        ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0 if i < 100 else 0.2
        solver.step(sim, fast, ctrl)
        solver.reference_step(sim, ref, ctrl.activation)
    motion = np.abs(fast.x - sim.rest).max()
    assert motion > 1e-3 and fast.q[0] > 0.01
    assert np.abs(fast.x - ref.x).max() <= 1e-9 * motion
    assert np.allclose(fast.q, ref.q, rtol=1e-9, atol=0)
    assert np.allclose(fast.activation, ref.activation, rtol=0, atol=1e-14)
    assert np.allclose(fast.muscle_length, ref.muscle_length, rtol=1e-12, atol=0)
    obs = solver.observe(sim, fast)
    assert np.all(obs['muscle_passive_forces'] > 0)                   # both columns stretched beyond optimal
    assert 0.2 < obs['activations'][0] < 0.5                          # falling from ~1 towards 0.2


def test_passive_fibre_force_is_the_gradient_of_its_energy():
    """The passive fibre force acts as joint torques tau = -F cos(a) dL_MT/dq along each muscle's path and is
    conservative: its virtual work over a small knee rotation is minus the change of the reported passive energy (so a
    passive run does not gain energy from it). On the knee phantom (paths L = length -+ arm q, no tendon, no pennation)
    the torque is the analytic F_ham arm - F_quad arm."""
    sim = _knee(passive_force_length=True, rest_fibre_length=1.2)
    p = sim.params
    state = solver.make_state(sim)
    fmax = MU.muscle_constants(sim)[0]
    length, arm = 0.3, 0.04

    def at(deg):
        solver.set_joint_positions(sim, state, [math.radians(deg)])
        tau, F, e = MU.passive_state(sim, state.q)
        assert e == pytest.approx(solver.observe(sim, state)['passive_energy'], rel=1e-12)
        return tau, F, e

    for deg in (5.0, 25.0, 45.0):
        d = 1e-3
        tau, F, e = at(deg)
        q = math.radians(deg)
        ln = np.array([1.2 - arm * q / length, 1.2 + arm * q / length])     # the override 1.2 at rest, then the paths
        want = fmax * np.array([MU.passive_force_length(v, p.fl_passive_shape, p.fl_passive_strain) for v in ln])
        assert np.allclose(F, want, rtol=1e-12) and np.all(F > 0)
        assert tau[0] == pytest.approx((F[0] - F[1]) * arm, rel=1e-12)
        _, _, ep = at(deg + d)
        _, _, em = at(deg - d)
        assert tau[0] * math.radians(2 * d) == pytest.approx(-(ep - em), rel=1e-5)
        assert abs(ep - em) > 1e-6 * e


@pytest.mark.parametrize('curve', ['thelen', 'degroote'])
def test_passive_torques_on_the_bundled_paths(default_tm, curve):
    """Bundled limb, every source-model path: the compiled passive torques (knee and ankle: the gastrocnemii cross both)
    equal the readable reference's (reference.passive_joint_torques) and are minus the gradient of the passive energy
    in both joint coordinates (central differences, 1e-5); the curves' energies are their forces' integrals."""
    from tissue_sim.core.solver import reference
    sim = solver.compile_model(default_tm, solver.Params.physical(passive_force_length=True, fl_passive_curve=curve))
    names = list(default_tm.joint_names)
    k, a = names.index('knee_r'), names.index('ankle_r')
    for knee, ankle in ((0.0, 0.0), (35.0, -20.0), (80.0, 10.0), (115.0, -40.0)):
        q = np.array(sim.j_rest, float)
        q[k], q[a] = math.radians(knee), math.radians(ankle)
        tau, F, e = MU.passive_state(sim, q)
        assert np.allclose(tau, reference.passive_joint_torques(sim, q), rtol=1e-10, atol=1e-9)
        for j in (k, a):
            d = np.zeros_like(q)
            d[j] = 1e-6
            ep, em = MU.passive_state(sim, q + d)[2], MU.passive_state(sim, q - d)[2]
            assert tau[j] == pytest.approx(-(ep - em) / 2e-6, rel=1e-5, abs=1e-6), (knee, ankle, j)
    for ln in (0.5, 1.1, 1.4, 1.7):
        c = MU.PASSIVE_CURVES.index(curve)
        dE = (MU.passive_energy_curve(ln + 1e-6, 4.0, 0.7, c) - MU.passive_energy_curve(ln - 1e-6, 4.0, 0.7, c)) / 2e-6
        assert dE == pytest.approx(MU.passive_force_length_curve(ln, 4.0, 0.7, c), rel=1e-6, abs=1e-9)


def test_observed_force_is_the_force_delivered_to_the_shank(default_tm):
    """Bundled model, physical set, knee held at 0 deg, the hamstrings excited: each hamstring's observed force [N]
    is the force its cells put on the bones below the knee (the validation's 'delivered force', docs/validation.md)
    within 10 %, and of the order of its Fmax."""
    from tissue_sim.core import validation as V
    sim = solver.compile_model(default_tm, solver.Params.physical())
    state, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.joint_lock[:] = True
    ham = solver.muscle_indices(sim, 'hamstrings')
    ctrl.activation[ham] = 1.0
    solver.step(sim, state, ctrl, n_steps=300)
    obs = solver.observe(sim, state)
    j = list(sim.tissue.joint_names).index(V.KNEE_JOINT)
    att = sim.att_idx[V._below_knee(sim, j)]
    forces = V._Forces(sim)
    act = MU.tension_activation(sim, state)
    for name in ('biceps_femoris_long_head', 'semitendinosus'):
        m = list(sim.tissue.muscle_names).index(name)
        delivered = np.linalg.norm(forces(state, act, m)[att].sum(0))
        assert obs['muscle_forces'][m] == pytest.approx(delivered, rel=0.1), name
        assert 0.4 < obs['muscle_forces'][m] / default_tm.muscle_max_force[m] < 1.3, name
    assert obs['activations'][ham].min() > 0.99
    others = np.setdiff1d(np.arange(sim.n_muscles), ham)
    assert np.all(obs['muscle_active_forces'][others] == 0)           # not excited: their force is the passive fibres'
    assert np.array_equal(obs['muscle_forces'][others], obs['muscle_passive_forces'][others])
    soleus = list(sim.tissue.muscle_names).index('soleus')            # stretched at ankle 0 on its source path (l 1.74)
    assert obs['muscle_passive_forces'][soleus] > 0


def test_the_paper_set_keeps_instant_activation_and_has_no_tension():
    p = solver.Params.paper()
    assert p.activation_time == 0 and not p.force_length and not p.passive_force_length
    sim = solver.compile_model(phantom.knee(n_gaps=12, knee_range_deg=(0.0, 60.0)), p)
    state, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[0] = 0.7
    solver.step(sim, state, ctrl)
    assert state.activation[0] == 0.7                                  # the command, at once
    obs = solver.observe(sim, state)
    assert np.all(obs['muscle_forces'] == 0) and obs['passive_energy'] == 0
    copy = state.copy()
    assert copy.activation is not state.activation and np.array_equal(copy.activation, state.activation)
    solver.reset(sim, state)
    assert np.all(state.activation == 0)


def test_muscle_parameters_are_validated():
    for bad in (dict(activation_time=-0.01), dict(deactivation_time=0.0), dict(fl_width=0.0),
                dict(fl_passive_strain=-1.0), dict(rest_fibre_length=5.0), dict(rest_fibre_length=0.1)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            solver.Params.physical(**bad)
    with pytest.raises(ValueError, match='force_length'):
        solver.Params.from_dict({'preset': 'physical', 'force_length': 'yes'})


def test_tissue_state_carries_excitations_and_forces():
    from tissue_sim.core import tissue_cdr
    base = dict(stamp_ns=5, step=3, sim_time=0.003, joint_names=['knee'], joint_positions=[0.1], joint_velocities=[0.0],
                muscle_names=['a', 'b'], activations=[0.25, 0.0], muscle_lengths=[0.3, 0.2], muscle_volumes=[1e-4, 2e-4],
                segment_poses=np.zeros((1, 7)), vertex_positions=np.zeros((2, 3)))
    s = tissue_cdr.decode_state(tissue_cdr.encode_state(**base, excitations=[1.0, 0.0], muscle_forces=[812.5, 0.0]))
    assert np.allclose(s.activations, [0.25, 0.0]) and np.allclose(s.excitations, [1.0, 0.0])
    assert np.allclose(s.muscle_forces, [812.5, 0.0])
    assert tissue_cdr.decode_state(tissue_cdr.encode_state_obj(s)).muscle_forces.tolist() == [812.5, 0.0]
    # a message without the two fields (recorded before them): the commands were the activations, no forces
    old = tissue_cdr.encode_state(**base)[:-16]       # without the excitations (length + 2 float32) and empty forces
    s0 = tissue_cdr.decode_state(old)
    assert np.allclose(s0.excitations, [0.25, 0.0]) and s0.muscle_forces.size == 0


def test_a_recorded_run_tabulates_each_muscles_force_and_excitation(tmp_path):
    """tissue-sim simulate -> run.mcap -> analyze: muscles.csv has the excitation (the command) and force_n, the
    force observe() gives for the same headless run (float32 in the message), the activation its dynamic state."""
    import csv

    from tissue_sim.cli import main
    assert main(['simulate', 'phantom:knee', '--duration', '0.1', '--activate', 'hamstring=1', '--params', 'physical',
                 '-o', str(tmp_path / 'run.mcap')]) == 0
    assert main(['analyze', str(tmp_path / 'run.mcap'), '-q', '--no-plots', '-o', str(tmp_path / 'an')]) == 0
    rows = [r for r in csv.DictReader(open(tmp_path / 'an' / 'muscles.csv')) if r['muscle'] == 'hamstring']
    last = rows[-1]
    sim = solver.compile_model(phantom.knee(n_gaps=12), solver.Params.physical())      # what phantom:knee loads
    *_, (t, obs) = solver.simulate(sim, 0.1, {'hamstring': 1.0}, every=100, output='obs')
    assert float(last['time_s']) == pytest.approx(t)
    assert float(last['excitation']) == 1.0 and float(rows[0]['activation']) == 0.0
    assert float(last['activation']) == pytest.approx(obs['activations'][0], rel=1e-6) and 0.9 < obs['activations'][0] < 1
    assert float(last['force_n']) == pytest.approx(obs['muscle_forces'][0], rel=1e-5) and obs['muscle_forces'][0] > 50


def test_muscle_paths_file_is_checked_and_mapped_onto_the_joints():
    """The muscle paths (docs/FORMATS.md): parts map onto the model's joints (one monomial table for all parts, the
    Fmax shares of a merged muscle summing to 1, the fibre height L_opt sin a); bad entries are one UserError naming
    the muscle."""
    from tissue_sim.core.builder.table import load_muscle_paths, path_arrays
    from tissue_sim.errors import UserError
    part = dict(max_isometric_force=300.0, optimal_fibre_length=0.1, tendon_slack_length=0.2,
                pennation_at_optimal_rad=0.3, joints=['ankle_r'], powers=[[0], [1]], coefficients_m=[0.3, -0.04])
    two = dict(part, max_isometric_force=100.0, joints=['knee_r', 'ankle_r'], powers=[[0, 0], [1, 1]],
               coefficients_m=[0.31, 0.01])
    paths = load_muscle_paths({'muscles': {'soleus': [part, two]}}, ['knee_r', 'ankle_r'], {'soleus', 'tib'}, 'x')
    pm, pdata, powers, coef = path_arrays(paths, ['tib', 'soleus'], 2)
    assert pm.tolist() == [1, 1] and np.allclose(pdata[:, 0], [0.75, 0.25])
    assert np.allclose(pdata[0, 1:], [0.1, 0.2, 0.1 * math.sin(0.3)])
    assert powers.tolist() == [[0, 0], [0, 1], [1, 1]]
    assert np.allclose(coef, [[0.3, -0.04, 0.0], [0.31, 0.0, 0.01]])
    for bad, msg in ((dict(part, joints=['hip_r']), 'needs joints'), (dict(part, powers=[[0]]), 'one row'),
                     (dict(part, optimal_fibre_length=-1.0), 'lengths > 0')):
        with pytest.raises(UserError, match=msg):
            load_muscle_paths({'muscles': {'soleus': [bad]}}, ['knee_r', 'ankle_r'], {'soleus'}, 'x')
    with pytest.raises(UserError, match="'calf' is not a muscle"):
        load_muscle_paths({'muscles': {'calf': [part]}}, ['knee_r', 'ankle_r'], {'soleus'}, 'x')
