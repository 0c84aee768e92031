"""The implicit integrator (integrator: implicit; core/solver/implicit.py, docs/solver.md "Implicit integrator"):
its compiled step against the readable one (reference.reference_step: exact rotations, scipy's sparse solve of the
written-out system), its star-form factor against that system, stability at the parameter set's own step where
the explicit schemes diverge, and a passive run that does not gain energy."""
import numpy as np
import pytest
import scipy.sparse.linalg as sla

from tissue_sim.core import solver
from tissue_sim.core.solver import implicit as IM, phantom


def _implicit(preset='physical', **kw):
    return getattr(solver.Params, preset)(integrator='implicit', substeps=1, **kw)


def _run(sim, n_steps, state=None, ref=None, group='hamstrings', dt=None):
    st = state or solver.make_state(sim)
    ctrl = solver.make_control(sim)
    ctrl.activation[solver.muscle_indices(sim, group)] = 1.0
    for _ in range(n_steps):
        solver.step(sim, st, ctrl, dt=dt)
        if ref is not None:
            solver.reference_step(sim, ref, ctrl.activation, dt=dt)
    return st


def test_the_star_form_factor_solves_the_written_out_system(default_tm):
    """One unknown per cell (its centroid) instead of the cells' dense blocks: the same solution (the Schur
    complement is the vertices' matrix), the bones' motion entering through the cells' rows."""
    sim = solver.compile_model(default_tm, _implicit())
    h = sim.params.dt
    imp = IM.make(sim, h)
    A, Lf, free = IM.system_matrix(sim, IM.solve_length(sim.params, h))     # (BDF2: the solve is made at 2h/3)
    rng = np.random.default_rng(0)
    f = rng.standard_normal((sim.n_vertices, 3))
    y = sim.rest + 1e-3 * rng.standard_normal(sim.rest.shape)
    xk = y.copy()
    xk[~free] += 1e-3 * rng.standard_normal((int(np.sum(~free)), 3))      # the bones moved beyond the prediction
    moved = np.where(free[:, None], 0.0, xk - y)
    IM._solve(imp, f, xk, y, True, y, np.zeros_like(y), 0.0, 0.0)
    w = sla.spsolve(A, f[free] - Lf @ moved)
    assert np.abs(w).max() > 0
    assert np.abs((xk - y)[free] - w).max() <= 1e-9 * np.abs(w).max()
    assert np.array_equal(xk[~free] - y[~free], moved[~free])           # the bones are not touched
    assert imp.n_lnz < A.nnz                  # sparser than the vertices' matrix itself (39k against 108k entries)
    for name in IM.SCRATCH:                   # each State's scratch starts on a cache line (z's rows: one line each)
        assert getattr(imp, name).ctypes.data % 64 == 0 or getattr(imp, name).size == 0, name
    assert IM.make(sim, h).z is not imp.z     # and is its own


def test_the_split_factor_solves_the_same_system_in_two_independent_blocks(default_tm, monkeypatch):
    """split_order (the vertices below and above a plane across the limb, the cells coupling both last): the factor's
    two blocks do not read each other (_factor checks it), and the solve is the written-out system's, with the
    sheath's factor split too."""
    monkeypatch.setattr(IM, 'SPLIT_MIN_UNKNOWNS', 500)
    sim = solver.compile_model(default_tm, _implicit())
    h = sim.params.dt
    imp = IM.make(sim, h)
    n = imp.z.shape[0]
    b0, b1, b2 = int(imp.split[1]), int(imp.split[2]) - int(imp.split[1]), n - int(imp.split[2])
    assert min(b0, b1) > 0.3 * n and 0 < b2 < 0.05 * n          # two large blocks, a thin separator
    assert 0 < imp.s_split[1] < imp.s_split[2] < imp.s_split[3]
    Lp, Lj = imp.Lp.astype(np.int64), imp.Lj.astype(np.int64)
    rows = np.repeat(np.arange(n), np.diff(Lp))
    assert not np.any((rows >= b0) & (rows < b0 + b1) & (Lj < b0))    # block 1 reads nothing of block 0
    A, Lf, free = IM.system_matrix(sim, IM.solve_length(sim.params, h))
    rng = np.random.default_rng(1)
    f = rng.standard_normal((sim.n_vertices, 3))
    y = sim.rest.copy()
    xk = y.copy()
    IM._solve(imp, f, xk, y, True, y, np.zeros_like(y), 0.0, 0.0)
    w = sla.spsolve(A, f[free])
    assert np.abs((xk - y)[free] - w).max() <= 1e-9 * np.abs(w).max()


def test_split_solves_change_the_motion_only_by_rounding(default_tm, monkeypatch):
    """The bundled limb stepped with its factors split (as a finer model's are) and whole: the same motion to
    rounding (20 steps of a full hamstring contraction)."""
    whole = _run(solver.compile_model(default_tm, _implicit()), 20)
    monkeypatch.setattr(IM, 'SPLIT_MIN_UNKNOWNS', 500)
    sim = solver.compile_model(default_tm, _implicit())
    split = _run(sim, 20)
    assert split.workspace.implicit(sim.params.dt).split[1] < split.workspace.implicit(sim.params.dt).split[3]
    motion = np.abs(whole.x - sim.rest).max()
    assert motion > 1e-3
    assert np.abs(split.x - whole.x).max() <= 1e-9 * motion and not np.array_equal(split.x, whole.x)
    assert np.allclose(split.q, whole.q, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize('scheme', ['bdf2', 'euler'])
@pytest.mark.parametrize('iterations', [1, 2])
def test_fast_step_matches_the_reference_step_on_the_knee_phantom(iterations, scheme):
    """Both formulas; the last 20 steps at half the step (BDF2 starts again: its history is at the old h)."""
    tm = phantom.knee(n_gaps=12, knee_range_deg=(0.0, 60.0))
    sim = solver.compile_model(tm, _implicit('paper', rotation_iterations=50, implicit_iterations=iterations,
                                             gravity=(0.0, 0.0, -9.81), velocity_damping=0.5, implicit_scheme=scheme))
    fast, ref = solver.make_state(sim), solver.make_state(sim)
    _run(sim, 130, fast, ref)
    _run(sim, 20, fast, ref, dt=0.5 * sim.params.dt)
    assert fast.history_h[0] == (0.5 * sim.params.dt if scheme == 'bdf2' else 0.0)
    motion = np.abs(fast.x - sim.rest).max()
    assert fast.q[0] > 0.1 and motion > 1e-2
    assert np.abs(fast.x - ref.x).max() <= 1e-9 * motion
    assert np.abs(fast.v - ref.v).max() <= 1e-9 * np.abs(ref.v).max()
    assert np.allclose(fast.q, ref.q, rtol=1e-9, atol=1e-12)


def test_fast_step_matches_the_reference_step_on_the_default_model(default_tm):
    """The physical set (force-velocity, bone contact) with the implicit integrator, 20 steps of 1 ms."""
    sim = solver.compile_model(default_tm, _implicit(rotation_iterations=50))
    fast, ref = solver.make_state(sim), solver.make_state(sim)
    _run(sim, 20, fast, ref)
    motion = np.abs(fast.x - sim.rest).max()
    assert motion > 1e-3
    assert np.abs(fast.x - ref.x).max() <= 1e-8 * motion
    assert np.allclose(fast.q, ref.q, rtol=1e-8, atol=1e-12)
    assert np.allclose(fast.muscle_velocity, ref.muscle_velocity, rtol=0, atol=1e-8 * np.abs(ref.muscle_velocity).max())


def test_bdf2_lags_the_converged_motion_less_than_backward_euler(default_tm):
    """The demo's experiment (physical set, the hamstrings fully active from rest; bench/convergence.py), 0.3 s: the knee
    at the set's 1-ms step against the same formula at 16 sub-steps. Both reach the same knee at 16 sub-steps; at 1 ms
    BDF2 (second order, less numerical damping) lags it less. Measured: backward Euler 69.2 against 72.6 deg (3.4),
    BDF2 70.9 against 72.6 (1.7); on the 3x limb 14.1 against 10.1 deg (docs/convergence.md)."""
    knee = {}
    for scheme in ('euler', 'bdf2'):
        for n_sub in (1, 16):
            sim = solver.compile_model(default_tm, solver.Params.physical(integrator='implicit', substeps=n_sub,
                                                                          implicit_scheme=scheme))
            knee[scheme, n_sub] = np.degrees(_run(sim, 300).q[0])
    assert knee['bdf2', 16] > 60.0
    assert abs(knee['bdf2', 16] - knee['euler', 16]) < 0.5
    lag = {scheme: knee[scheme, 16] - knee[scheme, 1] for scheme in ('euler', 'bdf2')}
    assert 0.0 <= lag['bdf2'] < 0.7 * lag['euler'], knee


def test_bad_implicit_scheme_is_refused():
    with pytest.raises(ValueError, match='implicit_scheme'):
        solver.Params.physical(integrator='implicit', implicit_scheme='rk4')


@pytest.mark.parametrize('stiffness', [1.0, 16.0])
def test_one_pass_per_step_follows_the_sub_stepped_explicit_motion(stiffness):
    """Knee phantom, paper set (x16: stiff cells, explicit needs 5 sub-steps): one implicit pass per step of 1 ms
    follows explicit at true masses within 3 % of the motion (measured 0.7 deg of 56, 0.9 deg of 54)."""
    tm = phantom.knee(n_gaps=8)
    q = {}
    for name in ('explicit', 'implicit'):
        sim = solver.compile_model(tm, solver.Params.paper(integrator=name, k_fat=5e5 * stiffness,
                                                           k_muscle=1e6 * stiffness))
        assert (sim.n_substeps == 1) == (name == 'implicit')
        q[name] = np.array([o['joint_positions'][0] for _, o in solver.simulate(
            sim, 0.12, {'hamstrings': [(0.0, 1.0)]}, every=20, output='obs')])
    assert q['explicit'][-1] > np.radians(40)
    assert np.abs(q['implicit'] - q['explicit']).max() < 0.03 * q['explicit'][-1]


def test_stable_at_one_ms_with_one_sub_step_where_the_explicit_schemes_diverge(default_tm):
    """The physical set at its own step (1 ms), one sub-step: explicit diverges (it needs ~40 sub-steps; measured at
    step 2); implicit flexes the knee towards its 120-deg stop with the true masses. (Every fibre at its optimum at
    rest, rest_fibre_length 1.0: the stronger drive. mass_scaled at one sub-step buys its stability with added mass:
    measured, it survives this run, knee at its stop, so it is not part of this test.) With the physical set's
    hamstring sheath (implicit.sheath_correct)."""
    sim = solver.compile_model(default_tm, solver.Params.physical(integrator='explicit', substeps=1, rest_fibre_length=1.0))
    with pytest.raises(solver.DivergenceError):
        _run(sim, 1500)
    sim = solver.compile_model(default_tm, _implicit(rest_fibre_length=1.0))
    st = _run(sim, 1500)
    # (measured 115.3 deg at 1.5 s with the physical set's BDF2, 115.5 with backward Euler, below the 120-deg stop: the
    # quadriceps stretched past their optimum resist with their passive fibre force, the physical set's)
    assert 105.0 <= np.degrees(st.q[0]) <= 121.0, np.degrees(st.q[0])
    assert np.all(np.isfinite(st.x)) and np.abs(st.v).max() < 5.0


def test_a_passive_run_does_not_gain_energy(default_tm):
    """No activation, the free tissue released from a random deformation (0.5 mm per vertex): the total energy
    (tissue kinetic + elastic + skeleton + the passive fibres') never rises, in every 10-step window (the physical set's
    implicit formula, BDF2, takes energy out as backward Euler does, less of it; bone contact off: its projection is a
    separate stage)."""
    sim = solver.compile_model(default_tm, _implicit(bone_contact=False))
    st = solver.make_state(sim)
    free = sim.inv_mass > 0
    st.x[free] += 5e-4 * np.random.default_rng(1).standard_normal((int(free.sum()), 3))
    ctrl = solver.make_control(sim)
    energies = []
    for _ in range(50):
        solver.step(sim, st, ctrl, n_steps=10)
        energies.append(solver.kinetic_energy(sim, st) + float(st.cell_energy.sum()) + solver.skeleton_energy(sim, st)
                        + solver.observe(sim, st)['passive_energy'])
    e = np.array(energies)
    assert e[0] > 0
    assert np.all(np.diff(e) <= 1e-9 * e[0])
    assert e[-1] < 0.5 * e[0]


def test_bad_implicit_iterations_are_refused():
    for bad in (0, 21, 1.5):
        with pytest.raises(ValueError, match='implicit_iterations'):
            solver.Params.paper(integrator='implicit', implicit_iterations=bad)


def test_the_volume_bound_follows_the_integrator():
    """Params.implicit_volume_cap and explicit_volume_cap: finite numbers >= 0 (0: off), anything else refused;
    compile_model sets the bound from the first under the implicit integrator and from the second under mass_scaled and
    explicit (the physical set's 1.0; the paper set's 0, unbounded), at keff's stiffness: |grad det D|^2 <= (1 + vol) /
    vol x its rest value (2x for muscle cells, 1.05x for the physical set's fat)."""
    for name in ('implicit_volume_cap', 'explicit_volume_cap'):
        for bad in (-0.5, float('nan'), float('inf')):
            with pytest.raises(ValueError, match=name):
                solver.Params.physical(**{name: bad})
    assert solver.Params.physical().explicit_volume_cap == 1.0 and solver.Params.paper().explicit_volume_cap == 0.0
    tm = phantom.knee(n_gaps=8)
    for integrator in ('mass_scaled', 'explicit', 'implicit'):
        for cap in (0.0, 1.0):
            other = 'explicit_volume_cap' if integrator == 'implicit' else 'implicit_volume_cap'
            own = 'implicit_volume_cap' if integrator == 'implicit' else 'explicit_volume_cap'
            sim = solver.compile_model(tm, solver.Params.physical(integrator=integrator, substeps=1,
                                                                  **{own: cap, other: 1.0 - cap}))
            assert np.any(sim.k_volume > 0)
            assert np.any(sim.volume_cap > 0) == (cap > 0)
    assert not np.any(solver.compile_model(tm, solver.Params.paper(volume_stiffness=1.0)).volume_cap)
    sim = solver.compile_model(tm, _implicit(implicit_volume_cap=0.0))
    assert not np.any(sim.volume_cap)
    for sim in (solver.compile_model(tm, _implicit()), solver.compile_model(tm, solver.Params.physical())):
        g2 = np.einsum('cii->c', sim.Qinv)                    # |grad det D|^2 at rest
        vol = sim.k_volume > 0
        ratio = sim.volume_cap[vol] / g2[vol]
        muscle = (sim.cell_muscle >= 0)[vol]
        assert np.allclose(ratio[muscle], 2.0) and np.allclose(ratio[~muscle], 21.0 / 20.0)


@pytest.mark.slow
@pytest.mark.parametrize('settings', [dict(slices=140, muscle_rays=24, fat_rays=36, allow_broken=True),
                                      dict(refine=3.0), dict(refine=2.0)], ids=['26k', 'refine3', 'refine2'])
def test_a_fine_model_is_stable_at_one_ms_with_one_iteration(settings):
    """~26k vertices (the builder at 140 slices, 24 muscle and 36 fat rays), the bundled limb refined 3x (32k) and 2x
    (15k): physical set with its sheath (hamstrings, sartorius, gracilis), every fibre at its optimum at rest (rest_fibre_length 1.0, the
    stronger drive), full hamstring activation from rest, 1 ms, one sub-step, ONE local/global iteration (BDF2, the
    physical set's): 1 s without divergence, no vertex faster than 5 m/s at its end, the knee past 90 deg (measured 117.3 /
    98.1 / 111.8 deg at 2x / 3x / 26k: on the 3x limb the knee stops at ~100 deg, where semitendinosus' moment arm, its tendon passing its via
    point on the tibia, is the source model's order, 13-23 mm at 100-110 deg on the 1x limb, and the finer mesh's
    passive tissue is stiffer, docs/convergence.md; with the ring free, point_vias false, its bowstringing tendon took
    the knee to its 120-deg stop). Without the volume term's bound (implicit_volume_cap 0) the
    runs diverged at steps 487 (26k), 256 (refine 3: a semimembranosus cell sheared to singular values 6.5 / 0.8 /
    0.19, its volume term ~27x its rest stiffness) and 564 (refine 2); docs/solver.md "Implicit integrator"."""
    from tissue_sim.core.builder import default_model
    tm = default_model(**settings)
    assert tm.n_vertices >= 14000
    sim = solver.compile_model(tm, _implicit(rest_fibre_length=1.0))
    assert sim.params.implicit_iterations == 1 and sim.params.sheath_group == solver.Params.physical().sheath_group
    assert sim.contact.s_idx.size and np.all(sim.contact.s_side > 0)      # sheathed above the knee (none below)
    assert np.all(sim.volume_cap[sim.k_volume > 0] > 0)
    st = _run(sim, 1000)
    assert np.degrees(st.q[0]) > 90.0
    assert np.all(np.isfinite(st.x)) and np.abs(st.v).max() < 5.0


@pytest.mark.slow
def test_the_demo_motion_agrees_with_mass_scaled(default_tm):
    """The demo's motion (physical set, hamstrings ramped 0 -> 1 over 8 s, 10 s), the same physics in both (the
    sheath and the contact's reaction on the skeleton in both, and the affine volume measure, the one the implicit
    integrator holds): the implicit knee trajectory within 5 deg of mass_scaled's. Measured: 4.28 deg at worst (BDF2), at
    8.4 s, where the knee swings up to its stop (within 0.5 deg to 7 s, 1.9 deg at 8 s; mass_scaled's added mass, 7.3 ->
    24.5 kg of tissue, slows that swing), the knees ending at 117.5 / 119.0 deg; 2.13 deg with sartorius, gracilis and
    semitendinosus also sheathed below the knee (docs/solver.md). """
    q = {}
    for name, params in (('mass_scaled', solver.Params.physical(volume_measure='affine')), ('implicit', _implicit())):
        sim = solver.compile_model(default_tm, params)
        q[name] = np.degrees([o['joint_positions'][0] for _, o in solver.simulate(
            sim, 10.0, {'hamstrings': [(0.0, 0.0), (8.0, 1.0)]}, every=50, output='obs')])
    d = np.abs(q['implicit'] - q['mass_scaled'])
    print(f"max diff {d.max():.2f} deg at frame {int(d.argmax())}; end {q['mass_scaled'][-1]:.1f} / {q['implicit'][-1]:.1f} deg")
    assert q['mass_scaled'][-1] >= 105.0
    assert d.max() < 5.0


def test_the_implicit_physical_set_keeps_the_sheath():
    """The sheath runs under the implicit integrator (its correction solve, implicit.sheath_correct): the physical
    preset keeps it (above the knee), a parameter file asking for both is accepted, and the factor of
    A' = A + diag(k_s) is made only where there is a sheath."""
    phys = solver.Params.physical()
    p = solver.Params.physical(integrator='implicit', substeps=1)
    assert (p.sheath_group, p.sheath_below) == (phys.sheath_group, phys.sheath_below) and 'hamstrings' in p.sheath_group
    d = phys.to_dict()
    d['integrator'] = 'implicit'
    assert (solver.Params.from_dict(d).sheath_group, solver.Params.from_dict(d).sheath_below) == (phys.sheath_group,
                                                                                                  phys.sheath_below)
    tm = phantom.knee(n_gaps=8)
    sim = solver.compile_model(tm, _implicit('paper'))
    assert IM.make(sim, sim.params.dt).sd.shape[0] == 0          # no sheath: no second factor


def test_fast_step_matches_the_reference_step_with_the_sheath_correction(default_tm, monkeypatch):
    """The physical set with a 20-um sheath (so that it acts within a few steps of a full hamstring contraction),
    20 steps: the compiled correction (contact.sheath_offsets, the A' factor) against reference.sheath_correction
    (numpy offsets, scipy's solve of the written-out A')."""
    sim = solver.compile_model(default_tm, _implicit(rotation_iterations=50, sheath_radius=2e-5))
    calls = []
    real = IM.reference_sheath_solve
    monkeypatch.setattr(IM, 'reference_sheath_solve', lambda *a: calls.append(1) or real(*a))
    fast, ref = solver.make_state(sim), solver.make_state(sim)
    _run(sim, 20, fast, ref)
    assert len(calls) >= 10                  # the correction acted in most steps
    motion = np.abs(fast.x - sim.rest).max()
    assert motion > 1e-3
    assert np.abs(fast.x - ref.x).max() <= 1e-8 * motion
    assert np.abs(fast.v - ref.v).max() <= 1e-8 * np.abs(ref.v).max()
    assert np.allclose(fast.q, ref.q, rtol=1e-8, atol=1e-12)


def test_a_full_hamstring_contraction_with_the_sheath_is_stable(default_tm):
    """Full hamstring activation from rest with the physical set's 1-mm sheath, one 1-ms sub-step: the plain
    projection after the solve diverged at step 149 (the sartorius vertices next to the projected ones vibrating);
    with the correction solve the knee flexes (measured 87.2 deg at 0.4 s) and every sheathed vertex ends within the
    radius of its rest line."""
    from tissue_sim.core.solver import reference
    sim = solver.compile_model(default_tm, _implicit())
    assert sim.contact.s_idx.size > 200
    st = _run(sim, 400)
    assert np.degrees(st.q[0]) > 60.0
    assert np.all(np.isfinite(st.x)) and np.abs(st.v).max() < 10.0
    beyond = [push for k in range(sim.contact.f_seg.shape[0])
              for _, _, _, push, _ in reference.sheath_offsets(sim.contact, k, st.x, st.seg_R, st.seg_t)]
    assert max((np.abs(b).max() for b in beyond if b.size), default=0.0) <= 1e-9


def test_the_via_correction_is_the_constrained_solve_and_moves_the_tissue_round_the_ring(default_tm):
    """implicit.via_correct (Params.implicit_via_correction, the default): after the solve, the least A-norm
    correction that puts each point via ring's centroid on its place. Against the KKT system written out (scipy:
    A w + C^T l = 0, C w = -g): the same correction; the ring's centroid lands on its place; the tissue round the
    ring moves with it (hold_via_points would move the ring's free vertices only); off, nothing is precomputed."""
    sim = solver.compile_model(default_tm, _implicit())
    assert sim.via_seg.size >= 1                         # semitendinosus' ring at the tibia (builder: point_vias)
    h = IM.solve_length(sim.params, sim.params.dt)
    imp = IM.make(sim, sim.params.dt)
    st = solver.make_state(sim)
    rng = np.random.default_rng(3)
    free = sim.inv_mass > 0
    x0 = st.x.copy()
    xn = x0 + np.where(free[:, None], 1e-3 * rng.standard_normal(x0.shape), 0.0)
    vn = np.zeros_like(xn)
    before = xn.copy()
    assert IM.via_correct(h, x0, xn, vn, imp, sim.via_off, sim.via_idx, sim.via_seg, sim.via_local, st.seg_R,
                          st.seg_t, 1e12) == 0
    w = (xn - before)[free]
    # the KKT system over the free vertices
    A, _, _ = IM.system_matrix(sim, h)
    C = IM.via_matrix(sim, np.flatnonzero(free))
    places = np.einsum('rij,rj->ri', st.seg_R[sim.via_seg], sim.via_local) + st.seg_t[sim.via_seg]
    rings = [sim.via_idx[sim.via_off[r]:sim.via_off[r + 1]] for r in range(sim.via_seg.size)]
    g = np.array([before[ring].mean(axis=0) for ring in rings]) - places
    AiCt = sla.spsolve(A.tocsc(), C.T).reshape(-1, len(rings))
    expected = -AiCt @ np.linalg.solve(C @ AiCt, g)
    assert np.abs(g).max() > 1e-4
    assert np.abs(w - expected).max() <= 1e-9 * np.abs(expected).max()
    assert np.allclose(IM.reference_via_solve(sim, h, before, places), expected, rtol=0, atol=1e-12)
    for ring, p in zip(rings, places):
        assert np.abs(xn[ring].mean(axis=0) - p).max() < 1e-12
    in_ring = np.zeros(sim.n_vertices, bool)
    in_ring[np.concatenate(rings)] = True
    moved = np.linalg.norm(xn - before, axis=1)
    assert np.sum(moved[free & ~in_ring] > 0.05 * moved[in_ring].max()) >= 10     # the tissue round it follows
    assert np.allclose(vn[free], (xn - x0)[free] / h)
    off = IM.make(solver.compile_model(default_tm, _implicit(implicit_via_correction=False)), sim.params.dt)
    assert off.via_sinv.shape == (0, 0)


def test_row_dot4_is_the_plain_sum_over_the_row():
    """simd.row_dot4 (the solves' one LLVM kernel) against the plain loop: rows of every length round its four
    accumulators (0 to 11 entries), unsigned column indices, a fourth column of z that is only carried along."""
    from numba import njit
    from tissue_sim.core.solver.simd import row_dot4

    @njit
    def rows(Lx, Lj, z, Lp):
        out = np.empty((Lp.size - 1, 4))
        for p in range(Lp.size - 1):
            out[p, 0], out[p, 1], out[p, 2], out[p, 3] = row_dot4(Lx, Lj, z, Lp[p], Lp[p + 1])
        return out

    rng = np.random.default_rng(3)
    lengths = np.arange(12)
    Lp = np.concatenate([[0], np.cumsum(lengths)]).astype(np.uint64)
    Lj = rng.integers(0, 50, int(Lp[-1])).astype(np.uint32)
    Lx = rng.standard_normal(int(Lp[-1]))
    z = rng.standard_normal((50, 4))
    got = rows(Lx, Lj, z, Lp)
    want = np.array([Lx[a:b] @ z[Lj[a:b]] for a, b in zip(Lp[:-1], Lp[1:])]).reshape(-1, 4)
    assert np.abs(got - want).max() <= 1e-13 * np.abs(want).max()
    assert np.all(got[0] == 0.0)


def test_row_axpy4_is_the_plain_scatter_of_a_row():
    """simd.row_axpy4 (the backward pass's scatter) against the plain loop: z[Lj[q]] -= Lx[q] (w0, w1, w2) over rows
    of 0 to 11 distinct columns (one fused multiply-add per entry: compared to a tolerance), the fourth column and the
    rows not named untouched."""
    from numba import njit
    from tissue_sim.core.solver.simd import row_axpy4

    @njit
    def scatter(Lx, Lj, z, q0, q1, w0, w1, w2):
        row_axpy4(Lx, Lj, z, q0, q1, w0, w1, w2)

    rng = np.random.default_rng(4)
    for n in range(12):
        Lj = rng.permutation(50)[:n].astype(np.uint32)
        Lx = rng.standard_normal(n)
        w = rng.standard_normal(3)
        z = rng.standard_normal((50, 4))
        want = z.copy()
        for q in range(n):
            want[Lj[q], :3] -= Lx[q] * w
        got = z.copy()
        scatter(Lx, Lj, got, np.uint64(0), np.uint64(n), w[0], w[1], w[2])
        assert np.abs(got - want).max() <= 1e-14 * max(1.0, np.abs(want).max())
        assert np.array_equal(got[:, 3], z[:, 3])
        untouched = np.setdiff1d(np.arange(50), Lj)
        assert np.array_equal(got[untouched], z[untouched])
