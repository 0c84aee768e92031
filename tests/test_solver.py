"""Solver physics tests (docs/method.md sections 2-3): cells, contraction, skeleton, robustness.

Models are the solver's analytic phantoms (tissue_sim.core.solver.phantom): one cell, a two-segment
knee with a hamstring behind and a quadriceps in front of the hinge, and hinge chains.
"""
import math

import numpy as np
import pytest

from tissue_sim.core import solver
from tissue_sim.core.model import TISSUE_FAT
from tissue_sim.core.solver import cells as K, skeleton as SK
from tissue_sim.core.solver import phantom


def _rot(axis, ang):
    R = np.empty((3, 3))
    SK.axis_angle_mat(np.asarray(axis, float) / np.linalg.norm(axis), ang, R)
    return R


def _forces(sim, x, v=None, lam=None, act=None, iters=30):
    f = np.zeros_like(x)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (sim.n_cells, 1))
    M = max(sim.n_muscles, 1)
    e = np.zeros(sim.n_cells)
    bad = K.cell_forces(x, np.zeros_like(x) if v is None else v, f, quat, sim.cell_blocks,
                        np.ones(M) if lam is None else lam, np.zeros(M) if act is None else act,
                        sim.params.volume_mode == 'actual', iters, e, np.zeros(sim.n_cells), 0.0,
                        K.cell_work(sim.cell_blocks), np.empty(sim.n_cells))
    assert bad == -1
    return f, e


@pytest.mark.parametrize('n_ring,tissue', [(4, TISSUE_FAT), (6, 1), (12, 1)])
def test_rigid_motion_gives_zero_force(n_ring, tissue):
    sim = solver.compile_model(phantom.one_cell(n_ring, tissue=tissue), solver.Params.paper())
    R = _rot([0.3, -1.0, 0.5], 2.4)             # large rotation: the warm start begins at identity
    x = sim.rest @ R.T + [0.1, -0.2, 0.3]
    f, e = _forces(sim, x)
    scale = sim.k[0] * 0.02
    assert np.abs(f).max() < 1e-7 * scale
    assert e[0] < 1e-12 * scale * 0.02


@pytest.mark.parametrize('tissue', [TISSUE_FAT, 1])
def test_internal_forces_have_zero_net_force_and_moment(tissue):
    rng = np.random.default_rng(1)
    sim = solver.compile_model(phantom.one_cell(8, tissue=tissue), solver.Params.paper(damping_ratio=0.3))
    x = sim.rest + rng.normal(scale=0.004, size=sim.rest.shape)
    v = rng.normal(scale=0.5, size=sim.rest.shape)
    lam = np.array([0.8]) if tissue == 1 else None
    f, _ = _forces(sim, x, v, lam=lam, act=np.array([1.0]))
    scale = np.abs(f).max()
    assert scale > 100.0                         # the deformation does produce forces
    assert np.linalg.norm(f.sum(0)) < 1e-9 * scale
    moment = np.cross(x, f).sum(0)
    assert np.linalg.norm(moment) < 1e-9 * scale * 0.02


def test_flat_and_inverted_cells_stay_finite():
    sim = solver.compile_model(phantom.one_cell(6), solver.Params.paper())
    flat = sim.rest.copy()
    flat[:, 2] = 0.0                             # collapsed to a plane
    inv = sim.rest * [1.0, 1.0, -1.0]            # mirrored (inverted)
    for x in (flat, inv, np.zeros_like(sim.rest)):
        f, _ = _forces(sim, x)
        assert np.all(np.isfinite(f))
    f, _ = _forces(sim, inv)
    assert np.abs(f).max() > 1e3                 # an inverted cell is pushed back


def test_single_cell_oscillation_frequency():
    """A non-rigid deformation of one cell (no damping) oscillates at sqrt(k/m)."""
    p = solver.Params.paper(damping='none', volume_stiffness=0.0, volume_relax_time=0.0, substeps=1, integrator='explicit')
    sim = solver.compile_model(phantom.one_cell(4, tissue=TISSUE_FAT), p)
    st = solver.make_state(sim)
    st.x[:] = sim.rest * [1.0, 1.0, 1.01]        # stretch along z: orthogonal to the rigid modes
    ctrl = solver.make_control(sim)
    dt = 2e-5
    zs = []
    for _ in range(2000):
        solver.step(sim, st, ctrl, dt)
        zs.append(np.ptp(st.x[:, 2]) - np.ptp(sim.rest[:, 2]))
    zs = np.array(zs)
    crossings = np.flatnonzero(np.diff(np.sign(zs)) > 0)
    period = (crossings[-1] - crossings[0]) * dt / (len(crossings) - 1)
    expected = 2 * math.pi / math.sqrt(sim.k[0] / sim.mass[0])
    assert period == pytest.approx(expected, rel=5e-3)
    assert np.abs(st.v.sum(0)).max() < 1e-9      # no net momentum appears


def _knee(**kw):
    p = dict(n_gaps=12, knee_range_deg=(0.0, 60.0))
    p.update(kw)
    return phantom.knee(**p)


def test_hamstring_flexes_knee_monotonically_to_the_limit_and_holds():
    sim = solver.compile_model(_knee(), solver.Params.paper())
    ham = solver.muscle_indices(sim, 'hamstrings')
    q, vol, lens = [], [], []
    for t, o in solver.simulate(sim, 2.5, {'hamstrings': [(0.0, 1.0)]}, every=10, output='obs'):
        q.append(o['joint_positions'][0])
        vol.append(o['muscle_volumes'][ham[0]])
        lens.append(o['muscle_lengths'][ham[0]])
    q = np.degrees(q)
    lim = 60.0
    assert q[-1] > lim - 1.0                              # reached the range limit
    assert q.max() < lim + 1.0                            # and the end stop holds
    assert np.all(q[q > 1.0][np.argmax(q > 1.0):] >= 0)
    up_to_limit = q[: int(np.argmax(q > lim - 1.0)) + 1]
    assert np.all(np.diff(up_to_limit) > -0.1)            # monotonic flexion (0.1 deg tolerance)
    assert np.all(np.abs(np.diff(q[-100:])) < 0.05)       # at rest at the limit, no jitter
    vol = np.array(vol) / vol[0]
    assert np.abs(vol - 1).max() < 0.02                   # muscle volume within 2 %
    assert lens[-1] < 0.85 * lens[0]                      # the hamstring did shorten


def test_bone_attached_vertices_move_with_their_segment():
    sim = solver.compile_model(_knee(), solver.Params.paper())
    st = solver.make_state(sim)
    ctrl = solver.make_control(sim)
    ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    for _ in range(300):
        solver.step(sim, st, ctrl)
    assert st.q[0] > 0.2
    a, s = sim.att_idx, sim.att_seg
    expect = np.einsum('aij,aj->ai', st.seg_R[s], sim.rest[a]) + st.seg_t[s]
    assert np.allclose(st.x[a], expect, atol=1e-12)
    obs = solver.observe(sim, st)
    assert obs['segment_poses'].shape == (2, 7)
    assert np.isclose(np.linalg.norm(obs['segment_poses'][1, 3:]), 1.0)
    # the shank's pose is a rotation by q about the knee axis (+y)
    assert np.allclose(st.seg_R[1], _rot([0, 1, 0], st.q[0]), atol=1e-12)


def test_zero_activation_stays_at_rest_for_60_s():
    sim = solver.compile_model(_knee(n_gaps=6), solver.Params.paper())
    st = solver.make_state(sim)
    for t, st in solver.simulate(sim, 60.0, None, every=20000, state=st):
        pass
    assert st.time == pytest.approx(60.0)
    assert np.abs(st.x - sim.rest).max() < 1e-9
    assert abs(st.q[0]) < 1e-9 and np.abs(st.v).max() < 1e-9


def test_quadriceps_extends_the_knee_and_relaxed_muscle_returns_to_rest_length():
    # no patella in the phantom: keep flexion below ~35 deg where the quadriceps is still in front
    sim = solver.compile_model(_knee(knee_range_deg=(0.0, 35.0), quad_arm=0.07), solver.Params.paper())
    st = solver.make_state(sim)
    tl = {'hamstrings': [(0.0, 1.0), (1.0, 1.0), (1.001, 0.0)], 'quadriceps': [(0.0, 0.0), (1.0, 0.0), (1.001, 1.0)]}
    q = {}
    for t, o in solver.simulate(sim, 2.5, tl, every=100, state=st, output='obs'):
        q[round(t, 3)] = o['joint_positions'][0]
        last = o
    assert q[1.0] > math.radians(30)
    assert q[2.5] < q[1.0] - math.radians(20)             # extension under the quadriceps
    ham = solver.muscle_indices(sim, 'hamstrings')[0]
    assert last['muscle_stretch'][ham] == 1.0              # relaxed: rest length restored


def test_determinism_bit_identical():
    def run():
        sim = solver.compile_model(_knee(), solver.Params.paper())
        for t, st in solver.simulate(sim, 0.3, {'hamstrings': [(0, 0.0), (0.1, 1.0)]}, every=100):
            pass
        return st
    a, b = run(), run()
    assert a.x.tobytes() == b.x.tobytes() and a.v.tobytes() == b.v.tobytes() and a.q.tobytes() == b.q.tobytes()


def test_per_cell_state_round_trips_through_the_kernel_lanes():
    """The cell kernel keeps the per-cell state in its own lane order during a call: a call that runs no
    step leaves it as it was, and one that does matches a step taken alone."""
    import importlib
    step_mod = importlib.import_module('tissue_sim.core.solver.step')
    sim = solver.compile_model(phantom.knee(n_gaps=6, fat_sectors=4), solver.Params.paper(volume_relax_time=0.005))
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[:] = 1.0
    solver.step(sim, st, ctrl, n_steps=20)
    before = st.copy()
    assert np.any(before.cell_energy != 0) and np.any(before.pressure != 0) and np.any(before.cell_length != 0)
    step_mod._run(sim, st, np.zeros((0, sim.n_muscles)), sim.params.dt)
    for name in ('quat', 'pressure', 'cell_energy', 'cell_length', 'x', 'v'):
        assert np.array_equal(getattr(st, name), getattr(before, name)), name
    one, two = st.copy(), st.copy()
    solver.step(sim, one, ctrl, n_steps=3)
    for _ in range(3):
        solver.step(sim, two, ctrl)
    for name in ('quat', 'pressure', 'cell_energy', 'cell_length', 'x', 'v'):
        assert np.array_equal(getattr(one, name), getattr(two, name)), name


def test_divergence_is_reported_and_no_nan_leaves_step():
    p = solver.Params.paper(substeps=1, k_muscle=2e7, k_fat=2e7, damping='none', volume_stiffness=0.0,
                            integrator='explicit')
    sim = solver.compile_model(_knee(n_gaps=6), p)               # omega dT >> 2: unstable on purpose
    st = solver.make_state(sim)
    ctrl = solver.make_control(sim)
    ctrl.activation[:] = 1.0
    with pytest.raises(solver.DivergenceError) as ei:
        for _ in range(5000):
            solver.step(sim, st, ctrl)
    e = ei.value
    assert e.step >= 1 and e.cause and str(e.step) in str(e)
    assert np.all(np.isfinite(st.x)) and np.all(np.isfinite(st.v)) and np.all(np.isfinite(st.q))
    assert st.step == e.step - 1 or st.step == e.step      # left at the last good step


def test_pendulum_period_under_gravity():
    """Hinge + gravity, no tissue coupling: small-amplitude period 2 pi sqrt(I_pivot / (m g d))."""
    tm = phantom.chain(1, length=0.4, mass=3.0)
    sim = solver.compile_model(tm, solver.Params.paper(gravity=(0, 0, -9.81), joint_damping=0.0))
    st = solver.set_joint_positions(sim, solver.make_state(sim), [0.05])
    qs = [st.q[0]]
    for t, s in solver.simulate(sim, 3.0, None, dt=1e-4, every=10, state=st):
        qs.append(s.q[0])
    qs = np.array(qs)
    up = np.flatnonzero((qs[:-1] < 0) & (qs[1:] >= 0))
    period = (up[-1] - up[0]) * 1e-3 / (len(up) - 1)
    I_pivot = 3.0 * 0.4 ** 2 / 12 + 3.0 * 0.2 ** 2
    expected = 2 * math.pi * math.sqrt(I_pivot / (3.0 * 9.81 * 0.2))
    assert period == pytest.approx(expected, rel=5e-3)


def test_double_pendulum_conserves_energy():
    """Two hinges in a tree (Coriolis and centrifugal terms matter): energy drift stays small."""
    tm = phantom.chain(2, length=0.4, mass=3.0)
    sim = solver.compile_model(tm, solver.Params.paper(gravity=(0, 0, -9.81), joint_damping=0.0))
    st = solver.set_joint_positions(sim, solver.make_state(sim), [1.2, -0.5])
    e0 = solver.skeleton_energy(sim, st)
    es = []
    for t, s in solver.simulate(sim, 2.0, None, dt=1e-4, every=500, state=st):
        es.append(solver.skeleton_energy(sim, s))
    span = 3.0 * 9.81 * 0.4 * 3                    # scale of the energy exchanged
    assert abs(e0 - solver.skeleton_energy(sim, solver.make_state(sim))) > 1.0
    assert np.abs(np.array(es) - e0).max() < 2e-3 * span
    assert np.ptp(st.q[1]) >= 0 and abs(st.q[1]) > 0      # the second joint moved


def test_fixed_joint_does_not_move():
    tm = phantom.chain(2, length=0.4, mass=3.0, fixed_last=True)
    sim = solver.compile_model(tm, solver.Params.paper(gravity=(0, 0, -9.81)))
    st = solver.set_joint_positions(sim, solver.make_state(sim), [0.5, 0.0])
    for t, s in solver.simulate(sim, 0.2, None, every=100, state=st):
        pass
    assert st.q[1] == 0.0 and st.qd[1] == 0.0 and st.q[0] < 0.5


def test_physical_preset_runs_and_flexes():
    sim = solver.compile_model(_knee(knee_range_deg=(0.0, 120.0)), solver.Params.physical())
    assert sim.n_substeps >= 1 and np.all(sim.k_active[sim.cell_muscle >= 0] > 0)
    assert sim.mass.sum() < 5.0                     # SI masses: grams per vertex, not 1 kg
    for t, o in solver.simulate(sim, 0.5, {'hamstrings': 1.0}, every=50, output='obs'):
        pass
    assert o['joint_positions'][0] > math.radians(10)
    assert np.isfinite(o['elastic_energy'])


def test_timeline_and_control_validation():
    sim = solver.compile_model(_knee(n_gaps=4), solver.Params.paper())
    fn = solver.timeline_function(sim, {'hamstrings': [(0, 0), (1, 1)], 'quadriceps': 0.25})
    assert np.allclose(fn(0.5), [0.5, 0.25]) and np.allclose(fn(5.0), [1.0, 0.25])
    with pytest.raises(KeyError, match='unknown muscle or group'):
        solver.timeline_function(sim, {'biceps': [(0, 1)]})
    with pytest.raises(ValueError, match=r'\[0, 1\]'):
        solver.timeline_function(sim, {'hamstring': [(0, 2.0)]})
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[0] = 1.5
    with pytest.raises(ValueError, match='activation'):
        solver.step(sim, st, ctrl)
    ctrl.activation[0] = np.nan
    with pytest.raises(ValueError, match='activation'):
        solver.step(sim, st, ctrl)
    ctrl.activation[0] = 0.5
    ctrl.activation[-1] = -0.25
    rest = st.copy()
    with pytest.raises(ValueError, match=rf"muscle {sim.n_muscles - 1} \('{sim.tissue.muscle_names[-1]}'\) has -0.25"):
        solver.step(sim, st, ctrl, n_steps=5)
    assert st.step == 0 and st.x.tobytes() == rest.x.tobytes() and st.lam.tobytes() == rest.lam.tobytes()   # nothing done
    with pytest.raises(ValueError, match='shape'):
        solver.step(sim, st, solver.Control(np.zeros(sim.n_muscles + 1)))


def test_states_sharing_a_model_do_not_interfere():
    """The kernel's buffers belong to the model and are reused by every call: two states stepped in
    turn with one model end bit for bit where each ends alone (the buffers' contents on entry do not
    matter), and solver.kinetic_energy agrees with observe()."""
    def fresh():
        sim = solver.compile_model(phantom.knee(n_gaps=6, fat_sectors=4))
        return sim, solver.make_state(sim), solver.make_state(sim)
    on, off = np.ones(2), np.zeros(2)
    sim, a, b = fresh()
    for _ in range(15):
        solver.step(sim, a, solver.Control(on), n_steps=2)
        solver.step(sim, b, solver.Control(off + 0.3))
    sim1, a1, _ = fresh()
    sim2, b1, _ = fresh()
    solver.step(sim1, a1, solver.Control(on), n_steps=30)
    solver.step(sim2, b1, solver.Control(off + 0.3), n_steps=15)
    for name in ('x', 'v', 'quat', 'pressure', 'cell_energy', 'cell_length', 'q', 'qd', 'lam'):
        assert getattr(a, name).tobytes() == getattr(a1, name).tobytes(), name
        assert getattr(b, name).tobytes() == getattr(b1, name).tobytes(), name
    ke = solver.kinetic_energy(sim, a)
    assert ke > 0 and ke == solver.observe(sim, a)['kinetic_energy']
    assert solver.kinetic_energy(sim, a.copy()) == ke and solver.kinetic_energy(sim, solver.make_state(sim)) == 0.0


def test_reset_restores_rest():
    sim = solver.compile_model(_knee(n_gaps=4), solver.Params.paper())
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[:] = 1.0
    for _ in range(50):
        solver.step(sim, st, ctrl)
    solver.reset(sim, st)
    assert st.step == 0 and st.time == 0.0 and np.array_equal(st.x, sim.rest) and st.q[0] == 0.0


def test_params_yaml_round_trip_and_errors(tmp_path):
    p = solver.Params.physical(dt=5e-4)
    f = tmp_path / 'p.yaml'
    p.to_yaml(f)
    q = solver.Params.from_yaml(f)
    assert q == p
    f.write_text('k_muscle: 1.0\nbogus: 3\n')
    with pytest.raises(ValueError, match='bogus'):
        solver.Params.from_yaml(f)
    f.write_text('min_stretch: 0.01\n')
    with pytest.raises(ValueError, match='min_stretch'):
        solver.Params.from_yaml(f)
    with pytest.raises(ValueError, match='no such'):
        solver.Params.from_yaml(tmp_path / 'missing.yaml')


def test_params_from_assignments_reads_each_value_as_yaml_and_names_a_bad_one():
    p = solver.Params.from_assignments('physical', ['bone_contact=false', "fold_contact=''", 'sheath_group=',
                                                    'volume_stiffness_fat=2.5', 'substeps=1', 'gravity=[0, 0, -9.81]'],
                                       integrator='implicit')
    assert p == solver.Params.physical(bone_contact=False, fold_contact='', sheath_group='', volume_stiffness_fat=2.5,
                                       substeps=1, gravity=(0.0, 0.0, -9.81), integrator='implicit')
    assert solver.Params.from_assignments('paper', []) == solver.Params.paper()
    for bad, msg in (('bone_contact', 'expected NAME=VALUE'), ('=3', 'expected NAME=VALUE'),
                     ('bone_contact=maybe', 'bone_contact must be a bool'), ('bogus=1', 'unknown field'),
                     ('substeps=[1', 'not a YAML'), ('min_stretch=0.01', 'min_stretch')):
        with pytest.raises(ValueError, match=msg):
            solver.Params.from_assignments('physical', [bad])


def test_bundled_parameter_files_load():
    from importlib import resources
    for name in ('params_paper.yaml', 'params_physical.yaml'):
        path = resources.files('tissue_sim') / 'config' / name
        p = solver.Params.from_yaml(path)
        assert p == (solver.Params.paper() if 'paper' in name else solver.Params.physical())


def test_step_n_steps_equals_repeated_steps():
    sim = solver.compile_model(_knee(n_gaps=4), solver.Params.paper())
    a, b = solver.make_state(sim), solver.make_state(sim)
    ctrl = solver.make_control(sim)
    ctrl.activation[0] = 0.7
    for _ in range(30):
        solver.step(sim, a, ctrl)
    solver.step(sim, b, ctrl, n_steps=30)
    assert a.step == b.step == 30 and a.x.tobytes() == b.x.tobytes() and a.q.tobytes() == b.q.tobytes()


def test_mass_scaled_integrator_one_pass_and_agrees_with_explicit():
    """The paper set's default integrator: one force evaluation per step; a vertex's mass is raised
    only where its cells' summed stiffness needs it (h^2 kappa / m <= stability_limit^2); on the knee
    phantom no vertex needs it at dT = 1 ms and the motion matches the sub-stepped explicit one."""
    tm = _knee(n_gaps=8)
    ex = solver.compile_model(tm, solver.Params.paper(integrator='explicit'))
    ms = solver.compile_model(tm, solver.Params.paper())
    assert ms.params.integrator == 'mass_scaled' and ms.n_substeps == 1 and ex.n_substeps >= 2
    h, L = ms.params.dt, ms.params.stability_limit
    free = ms.inv_mass > 0
    m_eff = 1.0 / ms.inv_denominator(h)[free]
    assert np.all(m_eff >= ms.mass[free]) and np.all(h * h * ms.vertex_stiffness[free] / m_eff <= L * L * (1 + 1e-12))
    stiff = solver.compile_model(tm, solver.Params.paper(k_fat=4e6, k_muscle=4e6))   # needs scaling at 1 ms
    m_st = 1.0 / stiff.inv_denominator(h)[free]
    assert np.any(m_st > stiff.mass[free]) and stiff.n_substeps == 1
    q = {}
    for name, sim in (('ex', ex), ('ms', ms), ('stiff', stiff)):
        for t, o in solver.simulate(sim, 0.12, {'hamstrings': [(0.0, 1.0)]}, every=120, output='obs'):
            pass
        q[name] = math.degrees(o['joint_positions'][0])
    assert q['ex'] > 10.0 and abs(q['ms'] - q['ex']) < 0.05 * q['ex']
    assert q['stiff'] > 10.0                       # stable and flexing with 4x the paper's stiffness, one pass per step


def test_force_velocity_curve():
    """Hill's hyperbola when shortening (a/F0 = 0.25), 0 at and beyond v_max, 1 at rest with one slope
    (5) on both sides, rising monotonically to the eccentric plateau when lengthening."""
    fv = K.force_velocity
    assert fv(0.0, 1.4) == 1.0 and fv(-1.0, 1.4) == 0.0 and fv(-3.0, 1.4) == 0.0
    assert fv(-0.5, 1.4) == pytest.approx(0.5 / 3.0)            # (1 - 0.5) / (1 + 0.5 / 0.25)
    vs = np.linspace(-1.2, 5.0, 2001)
    f = np.array([fv(x, 1.4) for x in vs])
    assert np.all(np.diff(f) >= 0) and f.min() == 0.0 and f.max() < 1.4 and fv(1e6, 1.4) == pytest.approx(1.4, rel=1e-6)
    e = 1e-7
    assert (fv(e, 1.4) - 1.0) / e == pytest.approx(5.0, rel=1e-4)
    assert (1.0 - fv(-e, 1.4)) / e == pytest.approx(5.0, rel=1e-4)
    assert fv(0.3, 1.0) == 1.0                                  # no eccentric gain: flat when lengthening


def test_the_model_stays_immutable_and_the_state_holds_no_model_constant():
    """Issue 18: SimModel is immutable (read-only arrays, nothing cached on it by a step); the step's scratch
    buffers belong to the State's workspace (not copied); the State holds no model constant (the vertex
    masses are read from the model: solver.kinetic_energy)."""
    import dataclasses
    sim = solver.compile_model(_knee(n_gaps=6))
    before = {f.name: getattr(sim, f.name) for f in dataclasses.fields(sim)}

    def arrays(v):
        return [v] if isinstance(v, np.ndarray) else [a for x in v for a in arrays(x)] if isinstance(v, tuple) else []
    for name, v in before.items():
        for a in arrays(v):
            assert not a.flags.writeable, name
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[:] = 1.0
    solver.step(sim, st, ctrl, n_steps=5)
    assert all(getattr(sim, n) is v for n, v in before.items()) and set(vars(sim)) == set(before)   # (no cache)
    assert st.workspace is not None and st.workspace.sim is sim and st.copy().workspace is None
    for f in dataclasses.fields(st):
        v = getattr(st, f.name)
        assert not any(v is a for a in arrays(tuple(before.values()))), f.name
    assert 'free_mass' not in {f.name for f in dataclasses.fields(st)}
