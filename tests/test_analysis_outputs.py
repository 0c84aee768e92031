"""The commands end to end on a synthetic bending run: tables, summary, plots, pictures, exports, errors."""
import argparse
import csv
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from tissue_sim.cli import main
from tissue_sim.commands import analyze, export_run, render
from tissue_sim.errors import UserError

import synthetic


@pytest.fixture(scope='module')
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp('run')
    tm = synthetic.tube_model(n_around=12, n_slices=7)
    synthetic.bending_run(tm, d / 'run_0.mcap', n_frames=24, max_angle=np.deg2rad(80))
    return d


def _args(mod, argv):
    p = argparse.ArgumentParser()
    mod.add_arguments(p)
    return p.parse_args(argv)


def test_analyze_writes_tables_summary_plots(run_dir, capsys):
    assert analyze.run(_args(analyze, [str(run_dir), '-q'])) == 0
    out = run_dir / 'analysis'
    for f in ('fat_cells.csv', 'muscles.csv', 'joints.csv', 'frames.csv', 'summary.json',
              'joint_angles.png', 'muscles.png', 'fat_d_distribution.png'):
        assert (out / f).is_file() and (out / f).stat().st_size > 100, f
    rows = list(csv.DictReader(open(out / 'fat_cells.csv')))
    assert len(rows) == 24 * 12 * 6
    assert {float(r['area_ratio']) for r in rows if r['frame'] == '0'} == {1.0}
    s = json.loads((out / 'summary.json').read_text())
    assert s['frames'] == 24 and s['joints']['knee_r']['max_deg'] == pytest.approx(80, abs=1e-6)
    f = s['fat']
    # bending: skin behind the knee shrinks, in front it grows; rotation makes the paper's d larger
    assert f['area_ratio_min'] < 0.9 and f['area_ratio_max'] > 1.1
    assert f['d_paper_max_m'] > f['d_rotfree_max_m'] > 0
    joints = list(csv.DictReader(open(out / 'joints.csv')))
    assert float(joints[-1]['position_deg']) == pytest.approx(80, abs=1e-6)
    assert 'wrote' in capsys.readouterr().out


def test_analyze_and_render_share_one_loaded_run(run_dir, tmp_path, monkeypatch):
    """`analyze --figures` reads the run file once and draws the pictures from the same Run and
    Measurements; the pictures' colour values are the analysis' own numbers."""
    from tissue_sim.core import mcapio
    from tissue_sim.core.analysis import figures
    opened = []
    real = mcapio.iter_messages
    monkeypatch.setattr(mcapio, 'iter_messages', lambda f, *a, **k: (opened.append(f), real(f, *a, **k))[1])
    seen = {}
    real_render = figures.render_run

    def spy(run, out, measures=None, **kw):
        seen['run'], seen['measures'] = run, measures
        return real_render(run, out, measures=measures, size=(160, 120), views=('area',), animation=None, **kw)
    monkeypatch.setattr(figures, 'render_run', spy)
    out = tmp_path / 'a'
    assert analyze.run(_args(analyze, [str(run_dir), '-q', '--no-plots', '--figures', '-o', str(out)])) == 0
    assert len(opened) == 1                                   # one pass over the one file of the run
    assert seen['measures'] is not None and seen['measures'].n_frames == seen['run'].n_frames == 24
    assert (out / 'figures' / 'area_panel.png').is_file()
    rows = list(csv.DictReader(open(out / 'fat_cells.csv')))
    last = [float(r['area_ratio']) for r in rows if r['frame'] == '23']
    np.testing.assert_allclose(last, seen['measures'].area_ratio()[-1], rtol=1e-6)


def test_render_pictures_have_size_and_content(run_dir, tmp_path):
    import imageio.v3 as iio
    out = tmp_path / 'fig'
    assert render.run(_args(render, [str(run_dir), '-o', str(out), '--times', '0,0.6', '--size', '320x240',
                                     '--views', 'limb,knee,area,d_rotfree', '--animation', 'gif',
                                     '--anim-frames', '5'])) == 0
    for view in ('limb', 'knee', 'area', 'd_rotfree'):
        a = iio.imread(out / f'{view}_f00000.png')
        b = iio.imread(out / f'{view}_f00020.png')
        assert a.shape == (240, 320, 3) and b.shape == (240, 320, 3)
        assert a.std() > 5 and b.std() > 5                       # not blank
        assert (a != 255).any(axis=2).mean() > 0.02               # something drawn on the white background
        assert np.abs(a.astype(int) - b.astype(int)).mean() > 1   # the frames differ
        assert iio.imread(out / f'{view}_panel.png').shape[1] == 2 * 320 + 6
    # Fig. 8 colours: at 0 s the skin is unchanged (no saturated red/blue); bent, both appear
    a = iio.imread(out / 'area_f00000.png').astype(int)
    b = iio.imread(out / 'area_f00020.png').astype(int)
    body = (slice(20, 230), slice(0, 250))                        # left of the colour bar

    def red(im):
        return ((im[..., 0] > 180) & (im[..., 1] < 120) & (im[..., 2] < 120))[body].sum()

    def blue(im):
        return ((im[..., 2] > 150) & (im[..., 0] < 120) & (im[..., 1] < 120))[body].sum()
    assert red(a) == 0 and blue(a) == 0
    assert red(b) > 20 and blue(b) > 20
    gif = iio.imread(out / 'animation.gif', index=None)
    assert gif.shape[0] == 5 and gif.shape[1:3] == (360, 480)


def test_export_run_meshes_and_vtu_series(run_dir, tmp_path):
    import pyvista as pv
    import trimesh
    out = tmp_path / 'exp'
    assert export_run.run(_args(export_run, [str(run_dir), '-o', str(out), '--times', '0.3', '--stride', '6'])) == 0
    scene = trimesh.load(out / 'frame_00010.glb')
    names = set(scene.geometry)
    assert 'skin' in names and 'muscle/biceps_femoris_long_head' in names and 'bone/tibia' in names
    assert trimesh.load(out / 'frame_00010.ply').vertices.shape[0] > 100
    root = ET.parse(out / 'vtu' / 'cells.pvd').getroot()
    ds = root.findall('./Collection/DataSet')
    assert len(ds) == 2 * 4                              # frames 0, 6, 12, 18: cells + bones each
    g = pv.read(out / 'vtu' / ds[0].get('file'))
    assert g.n_cells == len(np.asarray(g.cell_data['cell'])) and np.all(g.cell_data['cell'] == np.arange(g.n_cells))
    last = pv.read(out / 'vtu' / ds[-2].get('file'))
    # the cells are the solver's, frame by frame: each VTK cell (one per model cell) encloses the
    # geometry.prism_volumes volume of that frame's positions (polyhedra by VTK's own volume)
    from tissue_sim.core import model as M
    from tissue_sim.core.geometry import prism_volumes
    from tissue_sim.core.runio import load_run
    run = load_run(run_dir)
    k = int(np.flatnonzero(run.frame_index == 18)[0])
    ref = prism_volumes(run.frames[k].astype(np.float64), run.model.cell_offsets, run.model.cell_vertices,
                        np.asarray(run.model.cell_tissue) == M.TISSUE_FAT)
    poly = last.celltypes == pv.CellType.POLYHEDRON
    vol = np.array([last.GetCell(c).ComputeVolume() if poly[c] else np.nan for c in range(last.n_cells)])
    vol[~poly] = last.compute_cell_sizes(length=False, area=False)['Volume'][~poly]
    assert poly.any() and np.allclose(vol, ref, rtol=1e-6, atol=1e-12), np.abs(vol / ref - 1).max()
    assert set(np.unique(g.cell_data['tissue'])) == {1, 2}
    fat = g.cell_data['tissue'] == 2
    assert np.all(np.isfinite(g.cell_data['area_ratio'][fat])) and np.all(np.isnan(g.cell_data['d_paper_m'][~fat]))
    assert float(ds[-2].get('timestep')) == pytest.approx(18 / 34.0)
    assert np.abs(last.point_data['displacement_m']).max() > 0.01


def test_bad_input_is_one_error_line(tmp_path, capsys):
    bad = tmp_path / 'x.mcap'
    bad.write_text('hello')
    assert main(['analyze', str(bad)]) == 2
    err = capsys.readouterr().err
    assert 'error:' in err and 'not an MCAP' in err and 'Traceback' not in err
    assert main(['render', str(tmp_path / 'missing')]) == 2
    assert 'no such file' in capsys.readouterr().err
    with pytest.raises(UserError, match='--views'):
        render.run(_args(render, [str(bad), '--views', 'nonsense']))
    with pytest.raises(UserError, match='--size'):
        render.run(_args(render, [str(bad), '--size', 'big']))


@pytest.mark.slow
def test_real_headless_run_on_phantom(tmp_path):
    """A short real solver run on the builder's column phantom (hamstring 'flexor' active), recorded
    to MCAP with the numpy encoder, then analysed: the knee flexes, the flexor shortens, the fat deforms."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from phantoms import make_phantom_model
    from tissue_sim.core import runio
    from tissue_sim.core.analysis import measure, tables
    tm = make_phantom_model('column')
    p = runio.record_simulation(tmp_path / 'run.mcap', tm, duration=0.6, timeline={'hamstrings': [(0, 0), (0.1, 1)]})
    m = measure.measure_run(p)
    assert abs(m.n_frames - (0.6 * 34 + 1)) <= 1                # 34 Hz of simulated time
    knee = np.rad2deg(m.joint_positions[:, 0])
    assert knee.max() > 2.0                                   # flexion
    k = m.muscle_names.index('flexor')
    assert m.muscle_lengths[-1, k] < m.muscle_lengths[0, k]   # the active muscle shortened
    # the simulator's volumes and ours from the same meshes agree
    np.testing.assert_allclose(m.muscle_volumes, m.muscle_volumes_mesh, rtol=1e-3)
    s = tables.summary(m)
    assert s['fat']['d_rotfree_max_m'] > 0 and s['fat']['d_paper_max_m'] >= s['fat']['d_rotfree_max_m']
