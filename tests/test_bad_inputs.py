"""Bad input to the real command line (a subprocess, as a user runs it): one `error:` line naming the
problem, exit code 2, no traceback, and nothing written or changed (issue 20)."""
import gzip
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from conftest import SRC
from phantoms import make_phantom, write_phantom

SLICE = ['--slice-mm', '25', '--muscle-rays', '10']


def cli(*argv, cwd, peak_rss=False):
    """Run `tissue-sim ARGV` in a fresh interpreter; (exit code, stdout, stderr[, peak RSS in bytes])."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get('PYTHONPATH', '')]),
               TISSUE_SIM_CACHE=str(cwd / '.cache_unused'))
    cmd = [sys.executable, '-m', 'tissue_sim.cli', *map(str, argv)]
    if peak_rss:   # run it as the child of a small wrapper that reports the child's peak resident memory
        wrap = ('import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); '
                'print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024, file=sys.stderr); sys.exit(r.returncode)')
        cmd = [sys.executable, '-c', wrap, *cmd]
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    if not peak_rss:
        return r.returncode, r.stdout, r.stderr
    lines = r.stderr.splitlines()
    return r.returncode, r.stdout, '\n'.join(lines[:-1]) + ('\n' if len(lines) > 1 else ''), int(lines[-1])


def snapshot(folder):
    """Every file under folder (not the unused cache) with its size and modification time."""
    out = {}
    for root, dirs, files in os.walk(folder):
        dirs[:] = [d for d in dirs if d != '.cache_unused']
        for f in files:
            st = os.stat(os.path.join(root, f))
            out[os.path.relpath(os.path.join(root, f), folder)] = (st.st_size, st.st_mtime_ns)
        for d in dirs:
            out[os.path.relpath(os.path.join(root, d), folder) + '/'] = None
    return out


def expect_error(tmp_path, *argv, words=()):
    """The command fails with exit 2 and one `error:` line containing every word; nothing changes."""
    before = snapshot(tmp_path)
    code, out, err = cli(*argv, cwd=tmp_path)
    assert code == 2, (code, out, err)
    assert 'Traceback' not in err, err
    assert snapshot(tmp_path) == before, 'the failed command wrote or changed files'
    lines = err.strip().splitlines()
    assert len(lines) == 1 and ': error: ' in lines[0], err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.fixture(scope='module')
def phantom(tmp_path_factory):
    """A built phantom model and its inputs: (labels.nii.gz, tissues.yaml, model.npz)."""
    d = tmp_path_factory.mktemp('ph')
    lab, tab = write_phantom('column', d, 'nii')
    code, out, err = cli('build-model', lab, '--tissues', tab, '-o', d / 'model.npz', '--json', *SLICE, cwd=d)
    assert code == 0, err
    return lab, tab, d / 'model.npz'


# ------------------------------------------------------------------------------------ NIfTI
def _raw_nifti(path, pixdim=None, shape=None, sform=True, extra=b''):
    """Write the column phantom as a NIfTI file with raw header fields set after nibabel's checks."""
    import nibabel as nib
    lab, aff, table = make_phantom('column')
    img = nib.Nifti1Image(lab, aff)
    if not sform:
        img.header.set_sform(None, code=0)
        img.header.set_qform(None, code=0)
    img.header['vox_offset'] = 352
    raw = bytearray(img.header.binaryblock)
    if pixdim is not None:
        ax, val = pixdim
        raw[76 + 4 * ax:80 + 4 * ax] = np.float32(val).tobytes()
    if shape is not None:
        raw[40:56] = np.array([len(shape), *shape, 1, 1, 1, 1][:8], '<i2').tobytes()
    data = b'\0' * 4 + (lab.astype(np.int16).tobytes(order='F') if shape is None else extra)
    blob = bytes(raw) + data
    path.write_bytes(gzip.compress(blob) if path.name.endswith('.gz') else blob)
    (path.parent / 'joints.yaml').write_text(yaml.safe_dump(table['joints'], sort_keys=False))
    (path.parent / 'tissues.yaml').write_text(yaml.safe_dump(dict(table, joints='joints.yaml'), sort_keys=False))
    return path, path.parent / 'tissues.yaml'


@pytest.mark.parametrize('axis', [1, 2, 3])
@pytest.mark.parametrize('value', [0.0, -5.0, float('nan'), float('inf')])
def test_nifti_without_sform_and_bad_pixdim(tmp_path, axis, value):
    """pixdim dz = 0 and no sform/qform: nibabel turns it into 1 mm and a model 6x too short was built."""
    lab, tab = _raw_nifti(tmp_path / 'labels.nii', pixdim=(axis, value), sform=False)
    e = expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', *SLICE,
                     words=['labels.nii', 'wrong spacing', 'pixdim'])
    assert 'no sform' in e


def test_nifti_without_sform_and_good_pixdim_builds(tmp_path):
    """The same file with valid pixdim builds (the check does not reject what it should accept)."""
    lab, tab = _raw_nifti(tmp_path / 'labels.nii.gz', sform=False)
    code, out, err = cli('build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', '--json', *SLICE, cwd=tmp_path)
    assert code == 0, err
    assert json.loads(out)['muscle_cells'] == 16


@pytest.mark.parametrize('name', ['labels.nii', 'labels.nii.gz'])
def test_nifti_declaring_2_gib_in_a_small_file(tmp_path, name):
    """A header declaring 1024^3 int16 voxels in a ~1.4 KB file: refused before anything is allocated."""
    lab, tab = _raw_nifti(tmp_path / name, shape=(1024, 1024, 1024), extra=b'\1' * 1000)
    assert lab.stat().st_size < 1500
    before = snapshot(tmp_path)
    code, out, err, rss = cli('build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', *SLICE, cwd=tmp_path,
                              peak_rss=True)
    assert code == 2 and 'Traceback' not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and 'truncated NIfTI file' in lines[0] and '2.0 GiB' in lines[0], err
    assert rss < 1 << 30, f'peak memory {rss / 2**30:.2f} GiB'
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------- tissue table
@pytest.mark.parametrize('label, key, value, words', [
    (11, 'group', ['a', 'b'], ['label 11', '"group"', 'text string', "['a', 'b']"]),
    (11, 'name', 42, ['label 11', '"name"', 'text string', '42']),
    (12, 'name', ['x'], ['label 12', '"name"', 'a list']),
    (1, 'segment', 7, ['label 1', '"segment"', 'text string', '7']),
])
def test_tissue_table_wrong_types(tmp_path, label, key, value, words):
    lab, aff, table = make_phantom('column')
    table['labels'][label][key] = value
    np.savez(tmp_path / 'labels.npz', labels=lab, affine=aff)
    (tmp_path / 'tissues.yaml').write_text(yaml.safe_dump(table, sort_keys=False))
    expect_error(tmp_path, 'build-model', tmp_path / 'labels.npz', '--tissues', tmp_path / 'tissues.yaml',
                 '-o', tmp_path / 'm.npz', *SLICE, words=['tissues.yaml', *words])


def test_tissue_table_non_integer_label_key(tmp_path):
    lab, aff, table = make_phantom('column')
    table['labels'][1.5] = table['labels'].pop(1)
    np.savez(tmp_path / 'labels.npz', labels=lab, affine=aff)
    (tmp_path / 'tissues.yaml').write_text(yaml.safe_dump(table, sort_keys=False))
    expect_error(tmp_path, 'build-model', tmp_path / 'labels.npz', '--tissues', tmp_path / 'tissues.yaml',
                 '-o', tmp_path / 'm.npz', *SLICE, words=['label 1.5', 'not an integer'])


# ------------------------------------------------------------------------------- model files
def _rewrite_model(src, dst, header=None, arrays=None):
    """Copy a model file, replacing its raw header bytes and/or some arrays."""
    with np.load(src) as z:
        a = {k: z[k] for k in z.files}
    if header is not None:
        a['__header__'] = np.frombuffer(header, np.uint8)
    a.update(arrays or {})
    np.savez_compressed(dst, **a)
    return dst


def _header(model, **change):
    with np.load(model) as z:
        h = json.loads(z['__header__'].tobytes().decode())
    for k, v in change.items():
        if v is None:
            h.pop(k)
        else:
            h[k] = v
    return json.dumps(h).encode()


def _inverted(model, tissue=1):
    """The model with one cell's bottom and top rings swapped (an inverted cell)."""
    with np.load(model) as z:
        off, cv, tis = z['cell_offsets'], z['cell_vertices'].copy(), z['cell_tissue']
    c = int(np.nonzero(tis == tissue)[0][3])
    cell = cv[off[c]:off[c + 1]]
    n = len(cell) // 2
    cv[off[c]:off[c + 1]] = np.concatenate([cell[n:], cell[:n]])
    return {'cell_vertices': cv}


BAD_MODELS = {
    'header not UTF-8': (lambda m: dict(header=b'\xff\xfe{"format": 1}'), ['damaged model header', 'UTF-8']),
    'header not JSON': (lambda m: dict(header=b'{"format": '), ['damaged model header']),
    'header without name': (lambda m: dict(header=_header(m, name=None)), ['damaged model header', '"name"']),
    'version as a string': (lambda m: dict(header=_header(m, version='1')), ["version '1' (str)", 'integer']),
    'inverted cell': (lambda m: dict(arrays=_inverted(m)), ['1 inverted cell', 'muscle', 'against the contract']),
    'inverted fat cell': (lambda m: dict(arrays=_inverted(m, 2)), ['1 inverted cell', 'fat',
                                                                   'against the other fat cells']),
    'float indices': (lambda m: dict(arrays={'cell_vertices': np.load(m)['cell_vertices'].astype(float)}),
                      ["'cell_vertices'", 'integer']),
}


@pytest.mark.parametrize('command', ['simulate', 'export'])
@pytest.mark.parametrize('case', list(BAD_MODELS))
def test_damaged_model_files(phantom, tmp_path, command, case):
    make, words = BAD_MODELS[case]
    bad = _rewrite_model(phantom[2], tmp_path / 'bad.npz', **make(phantom[2]))
    if command == 'simulate':
        argv = ['simulate', bad, '--duration', '0.01', '-o', tmp_path / 'run.npz']
    else:
        argv = ['export', bad, '--glb', tmp_path / 'x.glb', '--vtu', tmp_path / 'x.vtu']
    expect_error(tmp_path, *argv, words=['bad.npz', *words])


def test_the_unchanged_model_loads(phantom, tmp_path):
    """The rewrite itself keeps a good model good (so the failures above are the changes')."""
    ok = _rewrite_model(phantom[2], tmp_path / 'ok.npz')
    code, out, err = cli('export', ok, '--glb', tmp_path / 'x.glb', cwd=tmp_path)
    assert code == 0 and (tmp_path / 'x.glb').is_file(), err


# ------------------------------------------------------------------------ outputs and options
def test_report_into_a_missing_folder_writes_no_model(phantom, tmp_path):
    lab, tab, _ = phantom
    expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', '--report',
                 tmp_path / 'nodir' / 'r.json', *SLICE, words=['nodir/r.json', 'does not exist'])


def test_vtu_under_a_file_is_one_line(phantom, tmp_path):
    """A VTU path whose folder is a file: one line (VTK printed ~25 lines of its own errors) and no model."""
    lab, tab, _ = phantom
    (tmp_path / 'afile').write_text('x')
    expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', '--vtu',
                 tmp_path / 'afile' / 'x.vtu', *SLICE, words=['afile/x.vtu', 'not a folder'])
    expect_error(tmp_path, 'export', phantom[2], '--glb', tmp_path / 'x.glb', '--vtu', tmp_path / 'afile' / 'x.vtu',
                 words=['afile/x.vtu', 'not a folder'])


@pytest.mark.skipif(os.geteuid() == 0, reason='root can write into a read-only folder')
def test_vtu_into_a_read_only_folder(phantom, tmp_path):
    lab, tab, _ = phantom
    ro = tmp_path / 'ro'
    ro.mkdir()
    ro.chmod(0o555)
    try:
        expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', '--vtu', ro / 'x.vtu',
                     *SLICE, words=['ro/x.vtu', 'not writable'])
    finally:
        ro.chmod(0o755)


@pytest.mark.parametrize('argv, words', [
    (['--bone-mesh-step', '0'], ['--bone-mesh-step', '>= 1', 'got 0']),
    (['--bone-mesh-step', '-2'], ['--bone-mesh-step', 'got -2']),
    (['--glb', 'same.out', '--vtu', 'same.out'], ['--glb and --vtu name the same file']),
])
def test_bad_options_before_any_work(phantom, tmp_path, argv, words):
    lab, tab, _ = phantom
    expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', *argv, *SLICE, words=words)


def test_output_over_the_input_is_refused(phantom, tmp_path):
    expect_error(tmp_path, 'export', phantom[2], '--glb', phantom[2], words=['model.npz', 'the input'])


def test_a_failed_build_keeps_the_old_model(phantom, tmp_path):
    """An existing model file is neither replaced nor truncated when a later output fails."""
    lab, tab, model = phantom
    old = tmp_path / 'm.npz'
    old.write_bytes(b'the previous model')
    expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', old, '--report', tmp_path / 'no' / 'r.json',
                 *SLICE, words=['does not exist'])
    assert old.read_bytes() == b'the previous model'


def test_good_outputs_are_all_written(phantom, tmp_path):
    lab, tab, _ = phantom
    code, out, err = cli('build-model', lab, '--tissues', tab, '-o', 'm.npz', '--report', 'r.json', '--glb', 'm.glb',
                         '--vtu', 'm.vtu', '--json', *SLICE, cwd=tmp_path)
    assert code == 0, err
    names = {p.name for p in tmp_path.iterdir() if not p.name.startswith('.cache')}
    assert names == {'m.npz', 'r.json', 'm.glb', 'm.vtu'}, names      # no staging file left behind
    assert oct((tmp_path / 'm.npz').stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m


def test_nifti_in_metres_is_read_in_millimetres(tmp_path):
    """xyzt_units = metre: the affine is converted (nibabel leaves it in the file's unit)."""
    import nibabel as nib
    from tissue_sim.core.builder.io import load_labels
    lab, aff, table = make_phantom('column')
    img = nib.Nifti1Image(lab, aff / np.array([[1000.0], [1000.0], [1000.0], [1.0]]))
    img.header.set_xyzt_units('meter')
    nib.save(img, str(tmp_path / 'm.nii.gz'))
    assert np.allclose(load_labels(tmp_path / 'm.nii.gz').affine, aff, atol=1e-3)


@pytest.mark.parametrize('spacing, words', [
    ({'pixel_mm': [1.0, 1.0], 'slice_mm': 5.0, 'first_slice_superior': 'no'}, ['first_slice_superior', 'true or false']),
    ({'pixel_mm': [1.0, 1.0], 'slice_mm': 5.0, 'origin_mm': [0, 0, float('nan')]}, ['origin_mm', 'finite']),
])
def test_png_spacing_wrong_types(tmp_path, spacing, words):
    """A string "no" was read as true (slices flipped); a NaN origin went into the affine."""
    lab, tab = write_phantom('column', tmp_path, 'png')
    (lab / 'spacing.yaml').write_text(yaml.safe_dump(spacing))
    expect_error(tmp_path, 'build-model', lab, '--tissues', tab, '-o', tmp_path / 'm.npz', *SLICE,
                 words=['spacing.yaml', *words])


@pytest.mark.parametrize('argv', [['build-model', '--slices', '-3'], ['simulate', 'missing.npz'],
                                  ['simulate', '--duration', '-1'], ['info', 'missing.mcap']])
def test_an_argument_error_is_answered_before_the_numerics_load(tmp_path, argv):
    """The parser and the arguments' checks import no numba and no scipy (core/build_settings.py holds the builder's
    defaults apart from its geometry; simulate imports the solver once its inputs are read): a mistyped command
    answers at once. The error itself is the one of the tests above."""
    probe = ('import sys, runpy; sys.argv = ["tissue-sim", *sys.argv[1:]]\n'
             'try:\n    runpy.run_module("tissue_sim.cli", run_name="__main__")\n'
             'except SystemExit as e:\n'
             '    print(sorted(m for m in ("numba", "scipy") if m in sys.modules), e.code)')
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get('PYTHONPATH', '')]))
    r = subprocess.run([sys.executable, '-c', probe, *argv], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.stdout.strip() == '[] 2', (r.stdout, r.stderr)
    assert len(r.stderr.strip().splitlines()) == 1 and ': error: ' in r.stderr, r.stderr


@pytest.mark.parametrize('argv, words', [
    (['validate', '--settle', 'abc'], ['tissue-sim validate: error: argument --settle', "invalid float value: 'abc'"]),
    (['simulate', '--no-such-option'], ['unrecognized arguments: --no-such-option']),
    (['no-such-command'], ["invalid choice: 'no-such-command'"]),
    (['analyze'], ['the following arguments are required: run']),
])
def test_a_parser_error_is_one_line_too(tmp_path, argv, words):
    """argparse's own errors (a mistyped value, an unknown option or command, a missing argument) are one line with
    exit 2 like the commands' checks, without argparse's usage block (tissue_sim.errors.ArgumentParser)."""
    line = expect_error(tmp_path, *argv, words=words)
    assert line.endswith('(--help lists the options)') and not line.startswith('usage')


def test_bounded_argument_types():
    """tissue_sim.errors.bounded: the range checks of the benchmarks' options, each refusal one line of the parser."""
    import argparse

    from tissue_sim.errors import ArgumentParser, bounded
    assert bounded(above=0)('0.5') == 0.5 and bounded(int, low=1)('3') == 3 and bounded(int, low=0, high=20)('20') == 20
    for conv, text, msg in ((bounded(above=0), '0', '0 must be > 0'), (bounded(above=0), 'nan', 'finite'),
                            (bounded(low=0), '-inf', 'finite'), (bounded(int, low=1), '0', '0 must be >= 1'),
                            (bounded(int, high=20), '21', '21 must be <= 20'), (bounded(int), '1.5', 'not an integer'),
                            (bounded(), 'x', "'x' is not a number")):
        with pytest.raises(argparse.ArgumentTypeError, match=msg):
            conv(text)
    p = ArgumentParser(prog='bench')
    p.add_argument('--seconds', type=bounded(above=0))
    with pytest.raises(SystemExit) as e:
        p.parse_args(['--seconds', '-1'])
    assert e.value.code == 2
