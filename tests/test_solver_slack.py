"""Passive slack (Params.passive_slack, physical set): a muscle fixed at both ends that its joint shortens below
its rest length goes slack (its rest shape follows its length) instead of pushing back along its fibres."""
import dataclasses
import math

import numpy as np
import pytest

from tissue_sim.core import solver
from tissue_sim.core.solver import phantom


def _phantom():
    tm = phantom.knee(n_gaps=8, knee_range_deg=(0.0, 90.0))
    anchors = {n: {'origin': ['thigh', 6], 'insertion': ['shank', 6]} for n in tm.muscle_names}
    return dataclasses.replace(tm, meta=dict(tm.meta, anchors=anchors))


def _flex(sim, deg=60.0, hold=0.3, reference=False):
    """The knee driven to deg (locked, ramped at 200 deg/s) and held, no activation; returns the state."""
    st, ctl = solver.make_state(sim), solver.make_control(sim)
    ctl.joint_lock[:] = True
    ctl.joint_target[:] = st.q
    dt = sim.params.dt
    n = int(math.ceil(deg / 200.0 / dt))
    for i in range(n + int(hold / dt)):
        ctl.joint_target[0] = math.radians(deg * min(i + 1, n) / n)
        if reference:
            solver.reference_step(sim, st, ctl.activation, joint_lock=ctl.joint_lock, joint_target=ctl.joint_target)
        else:
            solver.step(sim, st, ctl)
    return st


def test_only_muscles_fixed_at_both_ends_and_only_in_the_physical_set():
    tm = _phantom()
    assert solver.Params.physical().passive_slack and not solver.Params.paper().passive_slack
    sim = solver.compile_model(tm, solver.Params.physical())
    assert np.allclose(sim.inv_slack_l0, 1.0 / sim.muscle_rest_length)
    assert not np.any(solver.compile_model(tm, solver.Params.paper()).inv_slack_l0)
    free = dataclasses.replace(tm, meta=dict(tm.meta, anchors={'hamstring': {'origin': ['thigh', 6]}}))
    assert not np.any(solver.compile_model(free, solver.Params.physical()).inv_slack_l0)
    with pytest.raises(ValueError, match='passive_slack'):
        solver.Params.paper(passive_slack=True)


def test_a_passively_shortened_muscle_goes_slack():
    """Flexing the phantom knee shortens the hamstring (behind the axis): with slack its rest shape follows its
    length (lam = L/L0 to 1 %) and it ends shorter, pushing less on the shank; without, lam stays 1."""
    tm = _phantom()
    h = tm.muscle_index('hamstring')
    out = {}
    for slack in (True, False):
        sim = solver.compile_model(tm, solver.Params.physical(passive_slack=slack))
        st = _flex(sim)
        L = solver.observe(sim, st)['muscle_lengths'][h]
        out[slack] = (st.lam[h], L / sim.muscle_rest_length[h])
    lam, ratio = out[True]
    assert ratio < 0.95 and lam == pytest.approx(ratio, abs=0.01)
    assert out[False][0] == 1.0
    assert out[True][1] < out[False][1]


def test_fast_step_matches_the_reference_step_with_slack():
    sim = solver.compile_model(_phantom(), solver.Params.physical(rotation_iterations=50))
    fast, ref = _flex(sim, 40.0, 0.05), _flex(sim, 40.0, 0.05, reference=True)
    assert fast.lam.min() < 0.99
    assert np.allclose(fast.lam, ref.lam, rtol=0, atol=1e-9)
    assert np.abs(fast.x - ref.x).max() <= 1e-8 * np.abs(fast.x - sim.rest).max()
