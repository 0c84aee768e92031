"""A muscle's end ring partly bound to a bone across a joint (Params.end_ring_pull, cells.end_rings, cells.end_ring_shift;
docs/solver.md "Partly bound end rings")."""
import dataclasses

import numpy as np
import pytest

from tissue_sim.core import solver
from tissue_sim.core.solver import phantom

from test_solver_reference import _assert_same, _both


def _knee_with_a_half_bound_insertion():
    """The knee phantom with half of the hamstring's insertion ring (on the shank) left free."""
    tm = phantom.knee(n_gaps=12, knee_range_deg=(0.0, 60.0))
    vs = np.array(tm.vertex_segment)
    c = int(np.flatnonzero(np.asarray(tm.cell_muscle) == 0)[0])            # its lowest cell: the insertion ring
    n = (tm.cell_offsets[c + 1] - tm.cell_offsets[c]) // 2
    ring = np.asarray(tm.cell_vertices)[tm.cell_offsets[c]:tm.cell_offsets[c] + n]
    vs[ring[: n // 2]] = -1
    return dataclasses.replace(tm, vertex_segment=vs), c, ring


def test_which_end_rings_pass_their_pull_to_their_bound_vertices(default_tm):
    """Physical set: on the bundled limb, only the vastus medialis' insertion ring on the patella (6 of its 11
    vertices bound: the others lie round the femur's medial condyle, where bound to the patella they would go 12 mm
    into the femur in flexion); muscles whose partly bound end rings lie on the bone of their other end (the long
    toe extensors and flexors on the shank) are left as they are. The paper set: none. A bad value is refused."""
    sim = solver.compile_model(default_tm, solver.Params.physical())
    er = sim.end_rings
    assert [default_tm.muscle_names[sim.cell_muscle[c]] for c in er.cell] == ['vastus_medialis']
    patella = list(default_tm.segment_names).index('patella')
    bound = er.bound[er.bound_off[0]:er.bound_off[1]]
    free = er.free[er.free_off[0]:er.free_off[1]]
    assert np.all(sim.vertex_segment[bound] == patella) and np.all(sim.vertex_segment[free] == -1)
    assert len(bound) == 6 and len(free) == 5
    assert solver.compile_model(default_tm, solver.Params.paper()).end_rings.cell.size == 0
    with pytest.raises(ValueError, match='end_ring_pull'):
        solver.Params.physical(end_ring_pull='free').validate()


def test_fast_step_matches_the_reference_step_with_a_partly_bound_end_ring():
    """The knee phantom with half of the hamstring's insertion ring free, physical set (end_ring_pull 'bound'), 150
    steps of a full contraction: the compiled step (cells.end_ring_shift after the cell pass) against reference_step;
    and the shift acts: the free half of the ring ends elsewhere with 'ring'."""
    tm, c, ring = _knee_with_a_half_bound_insertion()
    params = solver.Params.physical(rotation_iterations=50)
    sim, fast, ref = _both(tm, params, 150)
    assert list(sim.end_rings.cell) == [c] and fast.q[0] > 0.05
    _assert_same(sim, fast, ref, 1e-9)
    _, other, _ = _both(tm, solver.Params.physical(rotation_iterations=50, end_ring_pull='ring'), 150)
    free = ring[: len(ring) // 2]
    assert np.abs(other.x[free] - fast.x[free]).max() > 1e-3 * np.abs(fast.x - sim.rest).max()


def test_the_shift_moves_the_pull_of_the_free_vertices_onto_the_bound_ones():
    """One force evaluation on the phantom stretched along the muscle, fully active: with end_ring_pull 'bound' the
    ring's free vertices lose exactly the tension's pull (t u per vertex, the cell kernel's), the bound ones gain it
    in proportion, the ring's net force is unchanged, and no other vertex's force changes."""
    tm, c, ring = _knee_with_a_half_bound_insertion()
    out = {}
    for mode in ('ring', 'bound'):
        sim = solver.compile_model(tm, solver.Params.physical(end_ring_pull=mode))
        st = solver.make_state(sim)
        x = sim.rest.copy()
        x[:, 2] *= 1.05                                        # every cell 5 % longer: the tension pulls
        from tissue_sim.core.solver import reference
        lam, act = np.full(sim.n_muscles, 0.8), np.ones(sim.n_muscles)
        f, *_ = reference.cell_forces(sim, reference.padded(sim), x, np.zeros_like(x), lam, act, st.pressure.copy(), 0.0,
                                      True)
        out[mode] = f
    d = out['bound'] - out['ring']
    free, bound = ring[: len(ring) // 2], ring[len(ring) // 2:]
    others = np.setdiff1d(np.arange(len(d)), ring)
    assert np.abs(d[others]).max() == 0.0
    assert np.abs(d[ring].sum(0)).max() < 1e-9 * np.abs(d).max()
    assert np.abs(d[free]).max() > 0 and np.allclose(d[free], d[free][0]) and np.allclose(d[bound], d[bound][0])
    assert np.allclose(d[bound][0], -d[free][0] * len(free) / len(bound))
    # the pull removed from each free vertex points up the muscle (from the bottom ring to the top ring)
    assert d[free][0][2] < 0


@pytest.mark.slow
def test_the_vastus_medialis_pulls_on_the_patella(default_tm):
    """Physical set, the knee and ankle held at rest, the vastus medialis alone fully active for 0.5 s: with its
    insertion ring's pull on the bound vertices it keeps its length and its tension (measured 1,272 N, 46 % of its
    2,748 N; with end_ring_pull 'ring' 179 N: the ring's free half was pulled 55 mm up the thigh and the muscle went
    slack, 253 -> 213 mm)."""
    out = {}
    for mode in ('ring', 'bound'):
        sim = solver.compile_model(default_tm, solver.Params.physical(end_ring_pull=mode))
        m = list(default_tm.muscle_names).index('vastus_medialis')
        st, ctrl = solver.make_state(sim), solver.make_control(sim)
        ctrl.joint_lock[:] = True
        ctrl.joint_target[:] = st.q
        ctrl.activation[m] = 1.0
        solver.step(sim, st, ctrl, n_steps=500)
        o = solver.observe(sim, st)
        out[mode] = (o['muscle_active_forces'][m], o['muscle_lengths'][m])
    assert out['bound'][0] > 0.35 * 2747.8 > 3 * out['ring'][0], out
    assert out['bound'][1] > out['ring'][1] + 0.02, out
