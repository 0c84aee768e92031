"""The analysis over any motion, several joints (issue 22 item 5): a recorded ankle motion of the
bundled limb (the named ``ankle_pump``, physical set without its passive fibre force) analysed and drawn: angles per joint in the
tables and summary, the main joint found (the ankle, not the knee), and the Fig. 8-9 style maps drawn
at the frames of its extremes; frame picking on synthetic joint curves."""
import json

import numpy as np
import pytest

from tissue_sim.core.analysis.plots import main_joint, pick_motion_frames


def test_pick_motion_frames_takes_the_extremes_of_the_main_joint():
    t = np.linspace(0, 3, 61)
    knee = np.deg2rad(2 * np.sin(t))                         # moves little
    ankle = np.deg2rad(20 * np.sin(2 * np.pi * t / 3))        # +20 at 0.75 s, -20 at 2.25 s
    q = np.stack([knee, ankle], axis=1)
    assert main_joint(q) == 1
    f = pick_motion_frames(t, q, 4)
    assert list(f) == sorted({0, 60, int(np.argmax(ankle)), int(np.argmin(ankle))})
    assert list(pick_motion_frames(t, q, 2)) == sorted({int(np.argmax(ankle)), int(np.argmin(ankle))})
    assert len(pick_motion_frames(t, q, 6)) == 6
    flexion = np.stack([np.deg2rad(np.minimum(120, 100 * t)), 0 * t], axis=1)     # paper-like: to the stop, held
    f = pick_motion_frames(t, flexion, 4)
    assert f[0] == 0 and f[-1] == 60 and int(np.argmax(flexion[:, 0])) in f
    assert main_joint(np.zeros((5, 2))) is None
    assert list(pick_motion_frames(t, np.zeros((61, 2)), 4)) == [0, 20, 40, 60]     # nothing moves: evenly spread


@pytest.fixture(scope='module')
def ankle_run(default_tm, tmp_path_factory):
    from tissue_sim.core import activation, runio, solver
    path = tmp_path_factory.mktemp('ankle') / 'run.mcap'
    # (without the passive fibre force: with it the tibialis anterior at 0.5 no longer lifts the foot past neutral,
    # docs/ros.md, and the motion has no dorsal extreme to draw; this test is about the analysis of a two-way motion)
    runio.record_simulation(path, default_tm, solver.Params.physical(passive_force_length=False), duration=1.3,
                            timeline=activation.motion_timeline('ankle_pump'), rate_hz=20.0)
    return path


@pytest.mark.slow
def test_analyze_and_render_an_ankle_motion(ankle_run, tmp_path):
    """ankle_pump's first 1.3 s: dorsiflexion to the +20-deg stop, then plantarflexion (measured
    -34 deg at 1.3 s)."""
    from tissue_sim.cli import main
    out = tmp_path / 'analysis'
    assert main(['analyze', str(ankle_run), '-o', str(out), '-q']) == 0
    s = json.loads((out / 'summary.json').read_text())
    a, k = s['joints']['ankle_r'], s['joints']['knee_r']
    assert s['main_joint'] == 'ankle_r'
    assert a['max_deg'] >= 12.0 and a['min_deg'] <= -20.0, a
    assert a['range_deg'] > k['range_deg'] and a['time_of_max_s'] < a['time_of_min_s']
    header = (out / 'frames.csv').read_text().splitlines()[0]
    assert 'knee_r_deg' in header and 'ankle_r_deg' in header
    frames = s['picture_frames']
    assert {int(round(a['time_of_max_s'] / 0.05)), int(round(a['time_of_min_s'] / 0.05))} <= set(frames), frames  # 20 Hz
    fig = tmp_path / 'figures'
    assert main(['render', str(ankle_run), '-o', str(fig), '--views', 'area,d_rotfree,knee', '--size', '320x240',
                 '--animation', 'none']) == 0
    for f in frames:
        for v in ('area', 'd_rotfree', 'knee'):
            assert (fig / f'{v}_f{f:05d}.png').is_file(), (v, f)
    assert (fig / 'area_panel.png').stat().st_size > 5_000
