"""Knee stiffness under co-contraction (tissue_sim.core.stiffness, `tissue-sim stiffness`; issue 22
item 2) on the bundled limb, physical set, the real solver with its joint lock: co-contraction of the
hamstrings and the quadriceps balancing them stiffens the knee, and the released knee stays near
where it was held while the hamstrings alone flex it away. Measured (docs/solver.md, co-contraction
stiffness; 0.3-s holds): k 4.6 N m/rad passive, 84.8 N m/rad at full hamstring activation (quadriceps
0.41); free drift 1.7 deg (hamstrings alone: 90 deg, to the stop)."""
import json

import pytest

from tissue_sim.cli import main


@pytest.mark.parametrize('argv, msg', [
    (['--levels', '0,1.5'], 'must be in'), (['--levels', 'a,b'], 'comma-separated'),
    (['--angle', '119'], 'range'), (['--delta', '0'], '--delta'), (['--settle', 'nan'], '--settle'),
    (['--params', 'nope.yaml'], 'nope.yaml'), (['--jobs', '0'], 'argument --jobs: 0 must be >= 1'),
])
def test_bad_arguments(tmp_path, capsys, argv, msg):
    out = tmp_path / 'st'
    assert main(['stiffness', '-o', str(out), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('tissue-sim stiffness: error:') and msg in err[0], err
    assert not out.exists()


@pytest.mark.slow
def test_co_contraction_stiffens_the_knee_without_moving_it(tmp_path):
    """Reduced run (levels 0 and 1, 0.15-s holds, 0.3 s free): k at full co-contraction at least 5x
    the passive one (measured 84.8 / 4.6 N m/rad with 0.3-s holds), its net torque balanced to within
    5 N m of the passive one, the released knee within 5 deg of the held angle while the hamstrings
    alone move it by more than 20 deg."""
    out = tmp_path / 'st'
    assert main(['stiffness', '-o', str(out), '--levels', '0,1', '--settle', '0.15', '--free', '0.3']) == 0
    res = json.loads((out / 'stiffness_physical.json').read_text())
    assert (out / 'stiffness_physical.png').stat().st_size > 10_000
    passive, full = res['levels']
    print({k: full[k] for k in ('activations', 'torque_nm', 'stiffness_nm_per_rad', 'free_drift_max_deg')},
          passive['stiffness_nm_per_rad'], full['hamstrings_only'])
    assert passive['stiffness_nm_per_rad'] > 0
    assert full['stiffness_nm_per_rad'] >= 5 * passive['stiffness_nm_per_rad']
    assert 0.1 < full['activations']['quadriceps'] < 1.0
    assert abs(full['torque_nm'] - res['passive_torque_nm']) < 5.0
    assert full['free_drift_max_deg'] < 5.0
    assert full['hamstrings_only']['free_drift_max_deg'] > 20.0
    # the levels measured on threads at once (the default) give what they give one after the other
    one = tmp_path / 'one'
    assert main(['stiffness', '-o', str(one), '--levels', '0,1', '--settle', '0.15', '--free', '0.3', '--jobs', '1']) == 0
    serial = json.loads((one / 'stiffness_physical.json').read_text())
    assert {k: v for k, v in serial.items() if k != 'wall_s'} == {k: v for k, v in res.items() if k != 'wall_s'}


def test_published_passive_stiffness_is_the_slope_of_riener_and_edrich():
    """The relaxed-knee reference the command prints beside level 0: the central difference of Riener & Edrich 1999's
    passive moment equals the formula's analytic derivative (hip and ankle 0), 5.4 N m/rad at 30 deg."""
    import math
    from tissue_sim.core.stiffness import published_passive_stiffness
    for k in (15.0, 30.0, 60.0, 90.0):
        dm = (-0.0352 * math.exp(1.800 - 0.0352 * k) - 0.0495 * math.exp(-3.971 + 0.0495 * k)
              - 0.150 * math.exp(2.220 - 0.150 * k))                         # N m per degree
        assert published_passive_stiffness(k, 0.5) == pytest.approx(-dm * 180.0 / math.pi, rel=2e-3)
    assert published_passive_stiffness(30.0, 2.0) == pytest.approx(5.4, abs=0.05)
