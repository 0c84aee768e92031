"""The thread-parallel step (Params.threads): the cell pass (cells.lane_forces_par) bit-identical to the serial kernel
(cells.lane_forces, itself checked against reference.cell_forces in tests/test_solver_kernel.py) and to itself for
1 and 2 threads (real numba runs with numba.set_num_threads; no timing), with the tasks cut at every position (every
ring a cut ring) and every few positions as well as at the default units; the whole step likewise, paper and
physical set (mass_scaled and implicit, the implicit solves whole and split: implicit.split_order); the bone contact's
parallel copy (its broad and narrow phases in two halves) against the serial one on vertices in a random walk about
two moving bones. Speed: bench/solver.py --threads 1,2.

The cell energies (a diagnostic: no force depends on them) are compared within 1e-10 of the largest, everything else
bit for bit: the same kernel loaded from numba's on-disk cache and compiled in the process can give energies that
differ in their last bits (docs/solver.md, "Threads"), and which of the two a kernel here is depends on what ran
before it."""
import numba
import numpy as np
import pytest
import trimesh

from tissue_sim.core import solver
from tissue_sim.core.solver import cells as K, contact as CT, implicit as IM

two_threads = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason='needs NUMBA_NUM_THREADS >= 2')


def _with_tasks(sim, per_task):
    """The model's layout packed with tasks of per_task positions (pack_cells' task_positions): the cut and, with it,
    which vertices one task forces alone (excl) and the per-vertex order of the others' slot forces (gvert/gptr/gsrc).
    (Replacing only the tasks of the default layout leaves excl of the default cut: a vertex it calls one task's may
    then get forces from two tasks, added in task order, not lane_forces' order.)"""
    return K.pack_cells(sim.off, sim.cv, sim.X0, sim.cell_muscle, sim.k, sim.k_active, sim.damp_b, sim.k_volume,
                        sim.q_tr, sim.q_ff, sim.rest_length, sim.fibre, sim.Qinv, task_positions=per_task,
                        volume_cap=sim.volume_cap)


def _pass(kernel, sim, cells, x, v, lam, act, threads=None, calls=3):
    """calls cell passes from the same state (the rotation warm start and pressure carried): (bad, f, quat,
    pressure, energy, axial length) after the last."""
    old = numba.get_num_threads()
    if threads:
        numba.set_num_threads(threads)
    try:
        work = K.cell_work(cells)
        C = sim.n_cells
        q, p, e, ln = np.tile([0.0, 0.0, 0.0, 1.0], (C, 1)), np.zeros(C), np.zeros(C), np.zeros(C)
        K.to_lanes(q, p, e, ln, cells, work)
        f = np.full_like(x, np.nan)             # every entry written (0 for a vertex of no cell)
        for _ in range(calls):
            bad = kernel(x, v, f, cells, lam, act, True, 1, 0.01, work)
        K.from_lanes(work, cells, q, p, e, ln)
        return bad, f, q, p, e, ln
    finally:
        numba.set_num_threads(old)


def _energies_match(a, b):
    """Cell energies equal within 1e-10 of the largest (measured: up to 1.1e-12 of it, the paper set after 15 steps; the
    energy is a difference of larger moment terms, so its last bits show; see the module's note)."""
    return a.shape == b.shape and np.all(np.abs(a - b) <= 1e-10 * np.abs(a).max())


def _same(a, b):
    """Two _pass results: the bad cell, forces, rotations, pressures and lengths bit for bit, the energies matching."""
    return (a[0] == b[0] and all(np.array_equal(a[i], b[i]) for i in (1, 2, 3, 5))
            and _energies_match(a[4], b[4]))


@pytest.fixture(scope='module')
def deformed(default_tm):
    sim = solver.compile_model(default_tm, solver.Params.physical())
    rng = np.random.default_rng(3)
    x = sim.rest + rng.normal(scale=1e-3, size=sim.rest.shape)
    v = rng.normal(scale=0.05, size=sim.rest.shape)
    M = max(sim.n_muscles, 1)
    return sim, x, v, rng.uniform(0.8, 1.0, M), rng.uniform(0.0, 1.0, M)


@two_threads
@pytest.mark.parametrize('per_task', [1, 3, None])
def test_parallel_pass_is_bit_identical_to_the_serial_one_for_1_and_2_threads(deformed, per_task):
    sim, x, v, lam, act = deformed
    cells = _with_tasks(sim, per_task)
    assert set(cells.tasks[:, 3]) == {0, 1}                     # two units
    if per_task:
        assert cells.tasks.shape[0] > cells.groups.shape[0]      # cut rings present
    serial = _pass(K.lane_forces, sim, cells, x, v, lam, act)
    assert serial[0] == -1 and np.abs(serial[1]).max() > 0 and np.all(np.isfinite(serial[1]))
    one = _pass(K.lane_forces_par, sim, cells, x, v, lam, act, threads=1)
    two = _pass(K.lane_forces_par, sim, cells, x, v, lam, act, threads=2)
    assert _same(one, two)
    assert _same(serial, one)


@two_threads
def test_parallel_pass_names_the_same_bad_cell(deformed):
    sim, x, v, lam, act = deformed
    cells = _with_tasks(sim, 2)
    xb = x.copy()
    worst = sim.cv[sim.off[sim.n_cells - 5]]            # a vertex of a late cell, and one of an early cell
    xb[worst] = np.nan
    xb[sim.cv[sim.off[7]]] = 1e200
    serial = _pass(K.lane_forces, sim, cells, xb, v, lam, act, calls=1)
    assert serial[0] >= 0
    for threads in (1, 2):
        assert _pass(K.lane_forces_par, sim, cells, xb, v, lam, act, threads=threads, calls=1)[0] == serial[0]


def test_units_end_between_groups_or_cut_one_where_their_costs_meet():
    """pack_cells' units (cells._tasks): two groups of about equal cost split between them (no cut ring); one group
    that dominates is cut where the costs meet; with task_positions every group is cut into runs and the units
    between runs. Each unit's tasks are consecutive."""
    g = lambda n, L: (n, L, 0, 0, 0)                            # (n, positions, first blocks, kind: unused)
    even = K._tasks([g(8, 306), g(66, 70)])                     # the 3x limb's fat and muscle groups
    assert even.tolist() == [[0, 0, 306, 0], [1, 0, 70, 1]]
    cut = K._tasks([g(8, 40), g(66, 70)])
    assert cut.shape[0] == 3 and cut[1, 0] == cut[2, 0] == 1 and cut[1, 2] == cut[2, 1]
    cost = lambda t: sum(K.BLK * ((66 if gi == 1 else 8) // 2 * K.COST_SLOT + K.COST_CELL) * (j1 - j0)
                         for gi, j0, j1, u in cut if u == t)
    assert abs(cost(0) - cost(1)) <= 0.02 * (cost(0) + cost(1))
    runs = K._tasks([g(8, 40), g(66, 70)], 8)
    assert np.all(np.diff(runs[:, 3]) >= 0) and set(runs[:, 3]) == {0, 1} and runs.shape[0] == 5 + 9


def _run(tm, params, steps=15):
    sim = solver.compile_model(tm, params)
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[[m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]] = 1.0
    solver.step(sim, st, ctrl, n_steps=steps)
    assert np.all(np.isfinite(st.x)) and np.abs(st.x - sim.rest).max() > 1e-6      # it moved
    return st


@two_threads
@pytest.mark.parametrize('kw', [dict(preset='paper'), dict(preset='physical'),
                                dict(preset='physical', integrator='implicit', substeps=1)],
                         ids=['paper', 'physical', 'physical-implicit'])
def test_step_does_not_depend_on_the_threads(default_tm, kw, monkeypatch):
    kw = dict(kw)
    if kw.get('integrator') == 'implicit':      # the solves split in two blocks, as a finer model's are
        monkeypatch.setattr(IM, 'SPLIT_MIN_UNKNOWNS', 500)
    make = solver.Params.physical if kw.pop('preset') == 'physical' else solver.Params.paper
    runs = [_run(default_tm, make(threads=n, **kw)) for n in (1, 2, 0)]
    for other in runs[1:]:
        for name in ('x', 'v', 'q', 'qd', 'quat', 'pressure', 'muscle_velocity'):
            assert np.array_equal(getattr(runs[0], name), getattr(other, name)), name
        assert _energies_match(runs[0].cell_energy, other.cell_energy)


def test_threads_parameter_is_checked():
    with pytest.raises(ValueError, match='threads'):
        solver.Params.paper(threads=-1)
    with pytest.raises(ValueError, match='threads'):
        solver.Params.from_dict({'threads': 1.5})
    assert solver.Params.from_dict({'threads': 2}).threads == 2


@two_threads
def test_parallel_bone_contact_is_bit_identical_to_the_serial_one():
    """Vertices in a random walk about two bones on two segments, one turning (every sub-step many of them projected):
    the parallel copy of the bone contact (implicit.parallel_kernels) on 2 threads gives the serial kernel's
    positions, velocities, reactions and list of moved vertices bit for bit, sub-step after sub-step."""
    rng = np.random.default_rng(7)
    meshes = [tuple(np.asarray(a) for a in (m.vertices, m.faces)) for m in
              (trimesh.creation.icosphere(3, 0.015), trimesh.creation.box((0.02, 0.02, 0.03)))]
    meshes[1] = (meshes[1][0] + [0.04, 0.0, 0.0], meshes[1][1])
    x0 = rng.normal(0, 0.012, (1000, 3)) * [2, 1, 1] + [0.02, 0, 0]
    in_box = np.all(np.abs(x0 - [0.04, 0.0, 0.0]) < [0.012, 0.012, 0.017], axis=1)
    x0 = x0[(np.linalg.norm(x0, axis=1) > 0.017) & ~in_box]       # 2 mm outside both bones
    par = IM.parallel_kernels()[5]
    runs, old = [], numba.get_num_threads()
    numba.set_num_threads(2)
    try:
        for kernel in (CT.bone_contact, par):
            cg = CT.build_grids(meshes, np.array([0, 1]), 5e-4, 0.2, 1.5e-3, x0, -np.ones(len(x0), np.int32))
            cw = CT.work(cg, 2, len(x0))
            seg_R, seg_t = np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3))
            x, v, wr = x0.copy(), np.zeros_like(x0), np.zeros((2, 6))
            r, hits, trace = np.random.default_rng(5), 0, []
            for k in range(300):
                cw.R0[:] = seg_R
                cw.t0[:] = seg_t
                a = 0.004 * k
                seg_R[1] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
                v += r.normal(0, 0.3, v.shape)
                x += 1e-3 * v
                CT.unmark(cw)
                hits += kernel(1e-3, x, v, seg_R, seg_t, cg, cw, np.ones(len(x)), wr)
                trace.append((x.copy(), v.copy(), wr.copy(), cw.moved[:cw.n_moved[0]].copy()))
            runs.append((hits, trace))
    finally:
        numba.set_num_threads(old)
    (ha, ta), (hb, tb) = runs
    assert ha == hb and ha > 300                  # vertices were projected, on both sides of the halves
    for a, b in zip(ta, tb):
        assert all(np.array_equal(p, q) for p, q in zip(a, b))
