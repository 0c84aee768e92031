"""`tissue-sim simulate`: headless runs, saved results, clear errors."""
import json

import numpy as np

from tissue_sim.cli import main


def test_simulate_phantom_writes_run(tmp_path, capsys):
    out = tmp_path / 'run.npz'
    rc = main(['simulate', 'phantom:knee', '--duration', '0.4', '--activate', 'hamstrings=1', '-o', str(out), '--json'])
    assert rc == 0
    s = json.loads(capsys.readouterr().out)
    assert s['joints']['knee_r']['end_deg'] > 10 and s['diverged'] is None
    with np.load(out) as z:
        assert z['joint_positions'].shape[1] == 1 and z['time'][-1] > 0.39
        assert z['activation'][-1, 0] == 1.0 and z['activation'][-1, 1] == 0.0
        assert np.all(np.diff(z['time']) > 0)


def test_simulate_bad_input_is_one_error_line(capsys):
    assert main(['simulate', 'phantom:knee', '--activate', 'biceps=1']) == 2
    assert 'unknown muscle or group' in capsys.readouterr().err
    assert main(['simulate', 'phantom:knee', '--activate', 'hamstrings=3']) == 2
    assert main(['simulate', 'missing.npz']) == 2
    assert 'no such model file' in capsys.readouterr().err
    assert main(['simulate', 'phantom:knee', '--params', 'nope.yaml']) == 2
    assert 'no such parameter file' in capsys.readouterr().err


def test_simulate_divergence_exit_code(tmp_path, capsys):
    p = tmp_path / 'p.yaml'
    p.write_text('substeps: 1\nk_muscle: 3.0e7\nk_fat: 3.0e7\ndamping: none\nvolume_stiffness: 0.0\n')
    rc = main(['simulate', 'phantom:knee', '--params', str(p), '--duration', '0.5', '--activate', 'all=1'])
    assert rc == 1
    assert 'diverged at step' in capsys.readouterr().err


def test_simulate_reads_the_activation_nodes_timeline_format(tmp_path, capsys):
    """One timeline file format for the activation node and the headless run."""
    tl = tmp_path / 'tl.yaml'
    tl.write_text('muscles:\n  hamstrings: [[0.0, 0.0], [0.1, 1.0]]\n')
    out = tmp_path / 'run.npz'
    assert main(['simulate', 'phantom:knee', '--duration', '0.3', '--timeline', str(tl), '-o', str(out)]) == 0
    with np.load(out) as z:
        assert z['activation'][0, 0] == 0.0 and z['activation'][-1, 0] == 1.0 and z['activation'][-1, 1] == 0.0
    capsys.readouterr()
    tl.write_text('muscles:\n  hamstrings: [[0.0, 2.0]]\n')
    assert main(['simulate', 'phantom:knee', '--duration', '0.1', '--timeline', str(tl)]) == 2
    assert 'activations must be in [0, 1]' in capsys.readouterr().err
