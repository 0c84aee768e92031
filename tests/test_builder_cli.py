"""`tissue-sim build-model` / `export`: file formats, JSON summary, and every bad-input case."""
import json

import numpy as np
import pytest
import yaml

from phantoms import make_phantom, write_phantom
from tissue_sim.cli import main
from tissue_sim.core import model as M

TABLE1_KEYS = {'bones', 'muscles', 'muscle_cells', 'muscle_vertices', 'fat_cells', 'fat_vertices', 'shared_vertices'}


@pytest.fixture(scope='module')
def nii(tmp_path_factory):
    d = tmp_path_factory.mktemp('nii')
    return write_phantom('column', d, 'nii')


def run(capsys, *argv):
    argv = [str(a) for a in argv]
    if argv[0] == 'build-model' and not {'--slices', '--slice-mm', '--slice-step'} & set(argv):
        argv += ['--slice-mm', '25']
    if argv[0] == 'build-model' and '--muscle-rays' not in argv:
        argv += ['--muscle-rays', '10']
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_build_model_json_and_file(nii, tmp_path, capsys):
    lab, tab = nii
    out = tmp_path / 'm.npz'
    code, o, e = run(capsys, 'build-model', lab, '--tissues', tab, '-o', out, '--json')
    assert code == 0, e
    d = json.loads(o.strip().splitlines()[-1])
    assert TABLE1_KEYS <= set(d)
    assert d['muscle_cells'] == 16 and d['fat_cells'] == 96 and d['fat_vertices'] == 768
    tm = M.TissueModel.load(out)
    assert tm.n_cells == 16 + 96 and tm.meta['source'].endswith('labels.nii.gz')


def test_build_model_table_output(nii, tmp_path, capsys):
    lab, tab = nii
    code, o, e = run(capsys, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', '--muscle-rays', 8)
    assert code == 0
    assert 'muscle cells' in o and 'shared vertices' in o and '292' in o


@pytest.mark.parametrize('fmt', ['npz', 'png'])
def test_formats_give_the_same_model(fmt, nii, tmp_path, capsys):
    lab, tab = write_phantom('column', tmp_path, fmt)
    code, _, e = run(capsys, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'a.npz')
    assert code == 0, e
    code, _, e = run(capsys, 'build-model', nii[0], '--tissues', nii[1], '-o', tmp_path / 'b.npz')
    a, b = M.TissueModel.load(tmp_path / 'a.npz'), M.TissueModel.load(tmp_path / 'b.npz')
    assert np.allclose(a.rest_positions, b.rest_positions, atol=1e-9)
    assert np.array_equal(a.cell_vertices, b.cell_vertices)


def test_export_glb_ply_vtu(nii, tmp_path, capsys):
    import pyvista as pv
    import trimesh
    from tissue_sim.core.builder.quality import cell_volumes
    lab, tab = nii
    m = tmp_path / 'm.npz'
    assert run(capsys, 'build-model', lab, '--tissues', tab, '-o', m)[0] == 0
    code, o, e = run(capsys, 'export', m, '--glb', tmp_path / 'm.glb', '--ply', tmp_path / 'm.ply', '--vtu', tmp_path / 'm.vtu')
    assert code == 0, e
    tm = M.TissueModel.load(m)
    g = pv.read(tmp_path / 'm.vtu')
    # the model's vertices first, then the cap and side-quad centroids of the polyhedral cells' faces
    assert g.n_cells == tm.n_cells and g.n_points >= tm.n_vertices
    assert np.array_equal(g.points[:tm.n_vertices], tm.rest_positions)
    assert np.array_equal(g.point_data['model_vertex'][:tm.n_vertices], np.arange(tm.n_vertices))
    assert np.all(g.point_data['model_vertex'][tm.n_vertices:] == -1)
    vol = g.compute_cell_sizes()['Volume']
    assert np.allclose(vol, cell_volumes(tm), rtol=1e-6)          # VTK agrees: no inverted cell (convex cells here)
    sc = trimesh.load(tmp_path / 'm.glb')
    assert {'muscle/flexor', 'muscle/extensor', 'skin', 'bone/upper_bone'} <= set(sc.geometry)
    ply = trimesh.load(tmp_path / 'm.ply')
    assert len(ply.faces) == len(tm.surface_triangles) + len(tm.bone_triangles)


# ------------------------------------------------------------------------------- bad input
def _write(tmp_path, lab, aff, table, name='labels.npz'):
    np.savez(tmp_path / name, labels=lab, affine=aff)
    (tmp_path / 'joints.yaml').write_text(yaml.safe_dump(table['joints'], sort_keys=False))
    (tmp_path / 'tissues.yaml').write_text(yaml.safe_dump(dict(table, joints='joints.yaml'), sort_keys=False))
    return tmp_path / name, tmp_path / 'tissues.yaml'


def expect_error(capsys, argv, *words):
    code, o, e = run(capsys, 'build-model', *argv)
    assert code == 2, (o, e)
    assert 'error:' in e and 'Traceback' not in e
    for w in words:
        assert w in e, e
    return e


def test_unknown_label_in_volume(tmp_path, capsys):
    lab, aff, table = make_phantom('column')
    del table['labels'][12]
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], '[12]', 'not in the tissue table')


def test_missing_label(tmp_path, capsys):
    lab, aff, table = make_phantom('column')
    table['labels'][13] = {'name': 'ghost', 'tissue': 'muscle'}
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], 'missing labels', 'ghost', '--allow-missing')
    code, o, e = run(capsys, 'build-model', l, '--tissues', t, '-o', tmp_path / 'm.npz', '--allow-missing')
    assert code == 0 and 'ghost' in o


def test_empty_slice(tmp_path, capsys):
    lab, aff, table = make_phantom('column')
    lab[:, :, 20] = 0
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t, '--slice-step', 5], 'empty slice', '[20]')


def test_inconsistent_png_slices(tmp_path, capsys):
    import imageio.v3 as iio
    lab, tab = write_phantom('column', tmp_path, 'png')
    iio.imwrite(lab / 'slice_0003.png', np.zeros((10, 12), np.uint8))
    expect_error(capsys, [lab, '--tissues', tab], 'inconsistent slices', 'slice_0003.png')


def test_wrong_spacing(tmp_path, capsys):
    lab, tab = write_phantom('column', tmp_path, 'png')
    (lab / 'spacing.yaml').write_text('pixel_mm: [1.0, -1.0]\nslice_mm: 5\n')
    expect_error(capsys, [lab, '--tissues', tab], 'wrong spacing')
    (lab / 'spacing.yaml').write_text('pixel_mm: [1.0, 1.0]\nslice_mm: 5\n')
    expect_error(capsys, [lab, '--tissues', tab, '--slice-mm', 2], 'wrong spacing', 'finer')
    lab2, aff, table = make_phantom('column')
    aff = aff.copy(); aff[2, 0] = 0.5          # oblique slices
    l, t = _write(tmp_path, lab2, aff, table)
    expect_error(capsys, [l, '--tissues', t], 'perpendicular')


def test_unreadable_files(tmp_path, capsys):
    lab, aff, table = make_phantom('column')
    l, t = _write(tmp_path, lab, aff, table)
    bad = tmp_path / 'bad.nii.gz'
    bad.write_bytes(b'not a nifti file at all')
    expect_error(capsys, [bad, '--tissues', t], 'unreadable', 'bad.nii.gz')
    expect_error(capsys, [tmp_path / 'nope.nii', '--tissues', t], 'no such file')
    (tmp_path / 'x.txt').write_text('x')
    expect_error(capsys, [tmp_path / 'x.txt', '--tissues', t], 'unknown label file type')
    (tmp_path / 'bad.yaml').write_text('labels: [unclosed')
    expect_error(capsys, [l, '--tissues', tmp_path / 'bad.yaml'], 'not valid YAML')
    expect_error(capsys, [l], '--tissues')


def test_bad_tissue_tables(tmp_path, capsys):
    lab, aff, table = make_phantom('column')
    table['labels'][1]['segment'] = 'femur_segment'
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], 'femur_segment', 'not in the joints file')
    lab, aff, table = make_phantom('column')
    table['labels'][11]['tissue'] = 'muscel'
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], 'muscel', 'bone, muscle, fat')
    lab, aff, table = make_phantom('column')
    table['joints']['joints'][0]['child'] = 'upper'
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], "joint 'knee'")


def test_bad_settings(nii, capsys):
    lab, tab = nii
    expect_error(capsys, [lab, '--tissues', tab, '--muscle-rays', 2], 'muscle_rays')
    expect_error(capsys, [lab, '--tissues', tab, '--slice-mm', 500], 'at least 2')


def test_export_errors(tmp_path, capsys):
    code = main(['export', str(tmp_path / 'none.npz'), '--glb', str(tmp_path / 'x.glb')])
    assert code == 2
    (tmp_path / 'junk.npz').write_bytes(b'junk')
    assert main(['export', str(tmp_path / 'junk.npz'), '--vtu', str(tmp_path / 'x.vtu')]) == 2
    assert 'not a tissue_sim model' in capsys.readouterr().err


def test_bone_mesh_file_from_table(tmp_path, capsys):
    import trimesh
    lab, aff, table = make_phantom('column')
    cyl = trimesh.creation.cylinder(radius=0.01, height=0.0875, sections=24)
    cyl.apply_translation([0, 0, 0.05625])                 # the upper bone: z 12.5 .. 100 mm
    cyl.export(tmp_path / 'upper.stl')
    table['labels'][1]['mesh'] = 'upper.stl'
    l, t = _write(tmp_path, lab, aff, table)
    code, o, e = run(capsys, 'build-model', l, '--tissues', t, '-o', tmp_path / 'm.npz')
    assert code == 0, e
    tm = M.TissueModel.load(tmp_path / 'm.npz')
    v, f = tm.bone_mesh(0)
    assert len(v) == len(cyl.vertices) and np.allclose(np.sort(v[:, 2]), np.sort(cyl.vertices[:, 2]))
    assert len(tm.bone_mesh(1)[0]) != len(cyl.vertices)    # the other bone: marching cubes
    from tissue_sim.core.builder import build_model
    _, rep = build_model(l, t, slice_mm=25.0)
    assert rep['bones'][0]['label_inside_mesh'] > 0.9 and not any('mesh' in w for w in rep['warnings'])
    cyl.apply_scale(1000.0)                                 # a mesh in millimetres: reported
    cyl.export(tmp_path / 'upper.stl')
    _, rep = build_model(l, t, slice_mm=25.0)
    assert rep['bones'][0]['label_inside_mesh'] < 0.1
    assert any('upper_bone' in w and 'model frame, in metres' in w for w in rep['warnings'])
    table['labels'][1]['mesh'] = 'missing.stl'
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], 'missing.stl', 'not found')
    (tmp_path / 'broken.stl').write_bytes(b'solid x\nfacet nonsense\n')
    table['labels'][1]['mesh'] = 'broken.stl'
    l, t = _write(tmp_path, lab, aff, table)
    expect_error(capsys, [l, '--tissues', t], 'broken.stl')


def test_png_first_slice_superior(nii, tmp_path, capsys):
    import imageio.v3 as iio
    lab, aff, table = make_phantom('tapered')               # not symmetric in z
    d = tmp_path / 'png'
    d.mkdir()
    K = lab.shape[2]
    for k in range(K):                                      # slice_0000 is the most superior slice
        iio.imwrite(d / f'slice_{k:04d}.png', lab[:, :, K - 1 - k].T.astype(np.uint8))
    top = aff[:3, :3] @ [0, 0, K - 1] + aff[:3, 3]
    (d / 'spacing.yaml').write_text(yaml.safe_dump({'pixel_mm': [1.0, 1.0], 'slice_mm': 5.0, 'first_slice_superior': True,
                                                    'origin_mm': [float(x) for x in top]}))
    l, t = _write(tmp_path, lab, aff, table)
    assert run(capsys, 'build-model', d, '--tissues', t, '-o', tmp_path / 'a.npz')[0] == 0
    assert run(capsys, 'build-model', l, '--tissues', t, '-o', tmp_path / 'b.npz')[0] == 0
    a, b = M.TissueModel.load(tmp_path / 'a.npz'), M.TissueModel.load(tmp_path / 'b.npz')
    assert np.allclose(a.slice_z, b.slice_z) and a.n_cells == b.n_cells
    assert np.allclose(np.sort(a.rest_positions, axis=0), np.sort(b.rest_positions, axis=0), atol=1e-9)
