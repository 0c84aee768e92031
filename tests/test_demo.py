"""`make demo` end to end, as a user runs it (scripts/demo.sh): real nodes over DDS on the bundled
anatomy, the recording read back, analysis tables, pictures; only shortened to 2 s of sim time. Each run in a ROS
domain the tests' lock files hold (rosutil.isolated_domain; the demo takes ROS_DOMAIN_ID from the environment): left
to pick its own (1 + its pid % 101), a demo's activation node once reached a test running beside it in the same
domain (CI, 2026-12-01: the probe of test_foundation received the demo's 28 muscle names)."""
import json
import os
import subprocess
from pathlib import Path

import pytest

import rosutil  # noqa: F401  (activates the workspace; skips if not built)

pytestmark = [pytest.mark.ros, pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[1]


def test_demo_default_flexes_the_knee_and_writes_analysis_and_figures(tmp_path):
    from tissue_sim.core import builder
    try:
        builder.default_inputs()
    except Exception as e:  # the bundled anatomy is part of the repo; say so if it is missing
        pytest.fail(f'bundled anatomy missing: {e}')
    env = dict(os.environ, TISSUE_SIM_RUNS=str(tmp_path), DEMO_SECONDS='2', DEMO_TIMEOUT='240')
    with rosutil.isolated_domain() as dom:
        p = subprocess.run(['bash', str(ROOT / 'scripts' / 'demo.sh')], cwd=ROOT,
                           env=dict(env, ROS_DOMAIN_ID=str(dom.id)), capture_output=True, text=True, timeout=280)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    (run,) = [d for d in tmp_path.iterdir() if d.is_dir()]
    s = json.loads((run / 'summary.json').read_text())
    assert s['params'] == 'physical' and '--profile ramp' in s['activation']
    assert s['sim_seconds'] >= 2.0
    assert s['publish_rate_hz'] >= 0.95 * 34.0
    # the ramp reaches a = 0.25 at 2 s: the knee is visibly flexed (about 15 deg), far from the limit
    assert 5.0 < s['final_knee_angle_deg'] < 60.0, s
    a = json.loads((run / 'analysis' / 'summary.json').read_text())
    assert a['joints']['knee_r']['max_deg'] > 5.0
    assert a['muscles']['semitendinosus']['length_min_ratio'] < 0.99       # the hamstrings shortened
    for f in ('fat_cells.csv', 'muscles.csv', 'joints.csv', 'frames.csv', 'joint_angles.png'):
        assert (run / 'analysis' / f).stat().st_size > 0, f
    for v in ('limb', 'knee', 'area', 'd_paper', 'd_rotfree'):
        assert (run / 'figures' / f'{v}_panel.png').stat().st_size > 10_000, v
    assert 'demo: files written under' in p.stdout and 'figures/limb_panel.png' in p.stdout


def test_demo_motion_knob_runs_a_named_motion(tmp_path):
    """`make demo MOTION=heel_raise`: the activation node runs the named motion for its own duration
    (1.5 s of sim time); the ankle plantarflexes (measured -50.0 deg at the end, the stop, as headless) and the
    analysis finds the ankle as the joint that moved."""
    env = dict(os.environ, TISSUE_SIM_RUNS=str(tmp_path), MOTION='heel_raise', DEMO_MARKERS='0', DEMO_TIMEOUT='240')
    env.pop('DEMO_SECONDS', None)
    with rosutil.isolated_domain() as dom:
        p = subprocess.run(['bash', str(ROOT / 'scripts' / 'demo.sh')], cwd=ROOT,
                           env=dict(env, ROS_DOMAIN_ID=str(dom.id)), capture_output=True, text=True, timeout=280)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    (run,) = [d for d in tmp_path.iterdir() if d.is_dir()]
    s = json.loads((run / 'summary.json').read_text())
    assert s['activation'] == '--profile heel_raise' and s['sim_seconds'] >= 1.5
    assert s['final_joint_angles_deg']['ankle_r'] <= -25.0, s
    a = json.loads((run / 'analysis' / 'summary.json').read_text())
    assert a['main_joint'] == 'ankle_r'


def test_demo_unknown_motion_is_one_error_line(tmp_path):
    env = dict(os.environ, TISSUE_SIM_RUNS=str(tmp_path), MOTION='moonwalk')
    p = subprocess.run(['bash', str(ROOT / 'scripts' / 'demo.sh')], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2 and p.stdout == ''
    assert p.stderr.strip().startswith('demo: error: MOTION=moonwalk') and len(p.stderr.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())
