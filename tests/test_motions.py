"""Named motions (tissue_sim.core.activation.MOTIONS, issue 22 item 4) on the bundled limb.

Each motion is run for its own duration with ``Params.physical()`` and the real solver, from rest:
the joint it is about moves in the right direction by at least the stated amount (knee: + =
flexion; ankle: + = dorsiflexion, joints.yaml), no DivergenceError, every joint inside its range
(the end stops hold within 1 deg), and muscle volumes within the physical set's documented bounds:
the muscles a motion drives within 6 % for the ankle motions (docs/anatomy.md, free ankle) and 14 %
for the knee motions (the full hamstring contraction's bound, tests/test_solver_default_model.py),
every muscle (driven or passive) within 14 %. Measured figures (docs/ros.md, named motions) are in
the comments; the bounds leave margin.
"""
import math

import numpy as np
import pytest

from tissue_sim.core import activation as act
from tissue_sim.core import solver
from tissue_sim.core.model import JOINT_COUPLED

KNEE_BOUND, ANKLE_BOUND, ANY_BOUND = 0.14, 0.06, 0.14
KE_BOUND = 20.0          # [J] kinetic energy of the free tissue (measured at most 10.4 J: the kick)


def test_motions_resolve_on_the_bundled_limb(default_tm):
    """Every motion names muscles of the bundled model, starts at rest, keeps activations in [0, 1]
    and ends inside its duration; level scales it and start shifts it; a muscle selection is refused."""
    m = act.Muscles.of(default_tm)
    for name, mo in act.MOTIONS.items():
        assert mo.joint in default_tm.joint_names
        plan = act.Activations(act.profile_entries(name, m), m)
        assert plan.names == m.names                          # every other muscle published passive (0)
        ts = np.linspace(0.0, mo.duration, 301)
        vals = np.array([plan.full(t) for t in ts])
        assert np.all(vals[0] == 0.0) and vals.max() > 0.4 and np.all((vals >= 0) & (vals <= 1))
        half = act.Activations(act.profile_entries(name, m, level=0.5, start=1.0), m)
        assert np.allclose([half.full(t + 1.0) for t in ts], vals * 0.5)
        assert np.all(half.full(0.99) == 0.0)
    with pytest.raises(act.ActivationError, match='no muscle selection'):
        act.profile_entries('kick', m, selectors=['hamstrings'])
    with pytest.raises(act.ActivationError, match='unknown motion'):
        act.motion_timeline('moonwalk')
    assert set(act.MOTIONS) <= set(act.PROFILES)


@pytest.fixture(scope='module')
def physical_sim(default_tm):
    return solver.compile_model(default_tm, solver.Params.physical())


def _run(sim, name):
    """Joint angles [deg] (F, J), kinetic energy (F,), |volume change| (F, M) of a motion from rest."""
    mo = act.MOTIONS[name]
    q, ke, dv, v0 = [], [], [], None
    for t, o in solver.simulate(sim, mo.duration, act.motion_timeline(name), every=20, output='obs'):
        v0 = o['muscle_volumes'].copy() if v0 is None else v0
        q.append(np.degrees(o['joint_positions']))
        ke.append(o['kinetic_energy'])
        dv.append(np.abs(o['muscle_volumes'] / v0 - 1))
    return np.array(q), np.array(ke), np.array(dv)


def _check(sim, name, run, bound):
    q, ke, dv = run
    tm = sim.tissue
    for j in range(len(tm.joint_names)):
        lo, hi = np.degrees(sim.j_range[j])
        if hi > lo and tm.joint_type[j] != JOINT_COUPLED:     # (a coupled joint's pose follows its driver: no end stops)
            assert q[:, j].min() >= lo - 1.0 and q[:, j].max() <= hi + 1.0, (tm.joint_names[j], q[:, j].min(), q[:, j].max())
    assert np.all(np.isfinite(ke)) and ke.max() < KE_BOUND, ke.max()
    driven = _driven(tm, name)
    worst = dv.max(axis=0)
    assert worst[driven].max() < bound, {tm.muscle_names[i]: round(float(worst[i]), 4) for i in driven}
    assert worst.max() < ANY_BOUND, (tm.muscle_names[int(worst.argmax())], worst.max())
    print(f'{name}: driven muscles max |dV/V| {worst[driven].max():.1%}, any muscle {worst.max():.1%} '
          f'({tm.muscle_names[int(worst.argmax())]}), max kinetic energy {ke.max():.2f} J')


def _driven(tm, name):
    """Indices of the muscles a motion activates at some time."""
    m = act.Muscles.of(tm)
    plan = act.Activations(act.profile_entries(name, m), m)
    a = np.array([plan.full(t) for t in np.linspace(0, act.MOTIONS[name].duration, 301)])
    return np.flatnonzero(a.max(axis=0) > 0)


def _joint(sim, name):
    return list(sim.tissue.joint_names).index(name)


@pytest.mark.slow
def test_knee_flexion(physical_sim):
    """Hamstrings ramped to 1 over 1 s: the knee flexes to its 120-deg stop (measured 120.0 deg at 1.3 s, 113.5 at
    the end: the stretched quadriceps' passive fibre force pulls it back a little; hamstrings 3.7 %, any muscle 9.8 %:
    the passive triceps surae bent round the knee)."""
    run = _run(physical_sim, 'knee_flexion')
    k = run[0][:, _joint(physical_sim, 'knee_r')]
    assert k[-1] >= 110.0, k[-1]
    _check(physical_sim, 'knee_flexion', run, KNEE_BOUND)


@pytest.mark.slow
def test_knee_extension(physical_sim):
    """Hamstrings flex the knee (measured peak 88.6 deg, physical set), then the quadriceps extend it to its
    0-deg stop (measured 0.0 deg at the end): >= 40 deg of flexion, then >= 35 deg of extension,
    ending within 10 deg of straight."""
    run = _run(physical_sim, 'knee_extension')
    k = run[0][:, _joint(physical_sim, 'knee_r')]
    peak = int(np.argmax(k))
    assert k[peak] >= 40.0, k[peak]
    assert k[peak] - k[-1] >= 35.0 and k[-1] <= 10.0, (k[peak], k[-1])
    _check(physical_sim, 'knee_extension', run, KNEE_BOUND)


@pytest.mark.slow
def test_kick(physical_sim):
    """Wind-up flexion (measured peak 101.8 deg), then a fast extension back to straight (measured 0.0 deg
    at the end)."""
    run = _run(physical_sim, 'kick')
    k = run[0][:, _joint(physical_sim, 'knee_r')]
    peak = int(np.argmax(k))
    assert k[peak] >= 60.0, k[peak]
    assert k[peak:].min() <= 10.0 and k[-1] <= 15.0, (k[peak:].min(), k[-1])
    _check(physical_sim, 'kick', run, KNEE_BOUND)


@pytest.mark.slow
def test_heel_raise(physical_sim):
    """Triceps surae ramped to 0.5: the ankle plantarflexes (measured -50.0 deg at 1.5 s, the stop, beyond the relaxed
    foot's passive equilibrium, -36 deg (test_solver_default_model.py)); the quadriceps at 0.3 hold the knee (measured
    at most 0.1 deg; without them the gastrocnemii, crossing it, flex it 50.0 deg)."""
    run = _run(physical_sim, 'heel_raise')
    a = run[0][:, _joint(physical_sim, 'ankle_r')]
    k = run[0][:, _joint(physical_sim, 'knee_r')]
    assert a[-1] <= -35.0 and a.max() < 1.0, (a[-1], a.max())
    assert k.max() <= 10.0, k.max()
    _check(physical_sim, 'heel_raise', run, ANKLE_BOUND)


@pytest.mark.slow
def test_ankle_pump(physical_sim):
    """Tibialis anterior (0.8), then the triceps surae (0.5), twice. With the passive fibre force (physical set) the
    relaxed foot hangs plantarflexed (-36 deg at rest) and the tibialis anterior is weak (the source model has it at
    l = 1.42 at ankle 0, 1.6 plantarflexed, far on the descending limb; at 0.5 it held the foot at -15 deg, at 1.0 it
    changed its volume by 11 %). Measured: dorsiflexion to +11.4 deg, plantarflexion to -39.9, dorsiflexion again to
    +3.9 (a 43.7-deg swing), plantarflexion to -39.8; the tibialis anterior's volume within 4.3 %."""
    run = _run(physical_sim, 'ankle_pump')
    a = run[0][:, _joint(physical_sim, 'ankle_r')]
    F = len(a)
    first, second = a[: F // 2], a[F // 2:]
    assert first.max() >= 5.0 and second.max() >= 0.0, (first.max(), second.max())            # dorsiflexed
    assert first.min() <= -30.0 and second.min() <= -30.0, (first.min(), second.min())        # plantarflexed
    assert second.max() - first.min() >= 35.0, (second.max(), first.min())                   # the second swing
    assert int(np.argmax(first)) < int(np.argmin(first))                        # dorsiflexion first
    _check(physical_sim, 'ankle_pump', run, ANKLE_BOUND)


def test_simulate_motion_cli(tmp_path):
    """`tissue-sim simulate --motion NAME`: the motion's timeline, the physical set by default; a bad
    name or --motion with --timeline: one error line, exit 2, nothing written."""
    from tissue_sim.cli import main
    out = tmp_path / 'obs.npz'
    for argv in (['--motion', 'moonwalk'], ['--motion', 'kick', '--timeline', str(tmp_path / 't.yaml')]):
        assert main(['simulate', *argv, '-o', str(out)]) == 2 and not out.exists()
    assert main(['simulate', '--motion', 'heel_raise', '--duration', '0.2', '--every', '50', '-o', str(out), '--json']) == 0
    d = np.load(out)
    names = list(d['muscle_names'])
    a = d['activation'][-1]
    assert a[names.index('soleus')] == pytest.approx(0.2, abs=0.01)          # 0.5 at 0.5 s: 0.2 at 0.2 s
    assert a[names.index('semitendinosus')] == 0.0
    assert 'physical' in str(d['params_yaml'])


def test_activation_node_takes_a_motion():
    from tissue_sim.nodes.activation import build_parser, check_args
    a = check_args(build_parser().parse_args(['--profile', 'ankle_pump', '--level', '0.8']))
    assert a.profile == 'ankle_pump'
    with pytest.raises(act.ActivationError, match='named motion'):
        check_args(build_parser().parse_args(['--profile', 'kick', '--muscles', 'hamstrings']))
