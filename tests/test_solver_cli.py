"""`tissue-sim simulate`: headless runs, saved results, clear errors."""
import json

import numpy as np
import pytest

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
    err = capsys.readouterr().err
    assert 'diverged at step' in err
    # the message names the way out: the implicit integrator, as the --set that selects it; and that way runs
    assert '--set integrator=implicit --set substeps=1' in err and len(err.strip().splitlines()) == 1
    rc = main(['simulate', 'phantom:knee', '--params', str(p), '--duration', '0.5', '--activate', 'all=1',
               '--set', 'integrator=implicit', '--set', 'substeps=1', '--json'])
    assert rc == 0 and json.loads(capsys.readouterr().out)['diverged'] is None


def test_simulate_set_changes_fields_of_the_parameter_set(tmp_path, capsys):
    """--set NAME=VALUE (repeatable) changes the named set's fields, as validate's --set; the run's parameters record
    it. A bad one is one error line, exit 2, and nothing is written."""
    import yaml
    out = tmp_path / 'obs.npz'
    rc = main(['simulate', 'phantom:knee', '--params', 'physical', '--set', 'integrator=implicit',
               '--set', 'substeps=1', '--set', 'gravity=[0, 0, -9.81]', '--duration', '0.05', '-o', str(out), '--json'])
    assert rc == 0
    assert json.loads(capsys.readouterr().out)['substeps'] == 1
    with np.load(out) as z:
        p = yaml.safe_load(str(z['params_yaml']))
    assert (p['preset'], p['integrator'], p['substeps'], p['gravity']) == ('physical', 'implicit', 1, [0, 0, -9.81])
    bad = tmp_path / 'bad.npz'
    for arg, msg in (('nope=1', 'unknown field(s) nope'), ('integrator=bogus', 'integrator must be one of'),
                     ('substeps', 'expected NAME=VALUE')):
        assert main(['simulate', 'phantom:knee', '--set', arg, '-o', str(bad)]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1, err
        assert not bad.exists()


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


def test_simulate_to_mcap_is_a_run_that_analyze_and_rosbags_read(tmp_path, capsys):
    """One run format: `simulate -o x.mcap` writes what the recorder writes (topology once, a
    TissueState per recorded step), `analyze` reads it, and so does the independent rosbags reader."""
    run = tmp_path / 'x.mcap'
    assert main(['simulate', 'phantom:knee', '--duration', '0.3', '--activate', 'hamstrings=1', '--every', '20',
                 '-o', str(run), '--json']) == 0
    s = json.loads(capsys.readouterr().out)
    assert main(['analyze', str(run), '-q', '--no-plots', '-o', str(tmp_path / 'a')]) == 0
    summary = json.loads((tmp_path / 'a' / 'summary.json').read_text())
    assert summary['joints']['knee_r']['max_deg'] == pytest.approx(s['joints']['knee_r']['max_deg'], abs=1e-3)
    assert summary['frames'] >= 10

    from rosbags.highlevel import AnyReader
    with AnyReader([run]) as r:
        msgs = [(c.topic, r.deserialize(d, c.msgtype)) for c, t, d in r.messages()]
    assert [t for t, _ in msgs].count('/tissue/topology') == 1
    states = [m for t, m in msgs if t == '/tissue/state']
    topo = next(m for t, m in msgs if t == '/tissue/topology')
    assert len(states) == summary['frames'] and topo.model_name == s['model']
    assert len(states[-1].vertex_positions) == len(topo.rest_positions) and states[-1].sim_time > 0.29
    assert list(states[-1].muscle_names) == list(topo.muscle_names)
    assert np.rad2deg(states[-1].joint_positions[0]) == pytest.approx(s['joints']['knee_r']['end_deg'], abs=1e-3)


def test_npz_output_is_observations_not_a_run(tmp_path, capsys):
    obs = tmp_path / 'obs.npz'
    assert main(['simulate', 'phantom:knee', '--duration', '0.05', '-o', str(obs)]) == 0
    capsys.readouterr()
    assert main(['analyze', str(obs)]) == 2
    err = capsys.readouterr().err
    assert 'observation arrays only' in err and 'Traceback' not in err
    assert main(['simulate', 'phantom:knee', '--duration', '0.05', '-o', str(tmp_path / 'x.csv')]) == 2
    assert 'expected RUN.mcap' in capsys.readouterr().err and not (tmp_path / 'x.csv').exists()
