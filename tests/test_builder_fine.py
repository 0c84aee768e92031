"""Finer builds of the bundled limb (issue 23): ``refine`` R scales the slice gaps and the ring vertex
counts consistently; every muscle stays present and one connected chain (small pieces the label
volume cuts off at fine slicing are left out and reported, never half a muscle); bad R is one error
line, exit 2, nothing written."""
import json

import numpy as np
import pytest

from tissue_sim.cli import main
from tissue_sim.core import builder
from tissue_sim.core.build_settings import settings_with_defaults
from tissue_sim.core.builder.assemble import cut_fragments, smooth_path
from tissue_sim.core.builder import quality
from tissue_sim.errors import UserError

try:
    builder.default_inputs()
    HAVE_ANATOMY = True
except FileNotFoundError:
    HAVE_ANATOMY = False
needs_anatomy = pytest.mark.skipif(not HAVE_ANATOMY, reason='bundled anatomy (data/lower_limb) not present')


def test_refine_scales_the_counts_from_the_defaults_and_the_given_settings():
    d = settings_with_defaults({})
    s = settings_with_defaults({'refine': 3})
    assert (s['slices'] - 1, s['muscle_rays'], s['fat_rays']) == (3 * (d['slices'] - 1), 3 * d['muscle_rays'], 3 * d['fat_rays'])
    assert s['min_cell_volume_mm3'] == pytest.approx(d['min_cell_volume_mm3'] / 27)
    for k in ('share_mm', 'attach_mm', 'min_area_mm2', 'min_fat_mm'):      # physical lengths stay
        assert s[k] == d[k]
    s = settings_with_defaults({'refine': 2, 'slice_mm': 25, 'muscle_rays': 8})
    assert (s['slice_mm'], s['muscle_rays'], s['slices']) == (12.5, 16, None)
    assert settings_with_defaults({'refine': 2, 'slice_step': 4})['slice_step'] == 2
    assert settings_with_defaults({'refine': 1.5})['fat_rays'] == 18


@pytest.mark.parametrize('bad', [0, 0.5, -3, float('nan'), float('inf'), True, '3', 51])
def test_bad_refine_is_a_user_error(bad):
    with pytest.raises(UserError, match='refine must be a number in'):
        settings_with_defaults({'refine': bad})


def test_refine_with_an_uneven_slice_step_is_a_user_error():
    with pytest.raises(UserError, match='whole number of slices'):
        settings_with_defaults({'refine': 2, 'slice_step': 3})


def test_cut_fragments_leaves_out_only_small_pieces():
    # one muscle: a belly on slices 0-5 (area 1) and a piece on slices 8-9 (area a), cut off by 6-7
    z = np.arange(10, dtype=float)
    area = lambda a: (lambda zi, i: 1.0 if zi <= 5 else a)      # noqa: E731
    chains = [[(q, 0) for q in range(6)], [(8, 0), (9, 0)]]
    keep, cut = cut_fragments(chains, area(0.02), z, 0.01)
    assert keep == chains[:1] and len(cut) == 1
    assert (cut[0]['from_slice'], cut[0]['to_slice']) == (8, 9) and cut[0]['share'] == pytest.approx(0.02 / 5.02, abs=1e-5)
    keep, cut = cut_fragments(chains, area(0.2), z, 0.01)        # 4 % of the muscle: kept (a break)
    assert keep == chains and cut == []
    keep, cut = cut_fragments(chains, area(0.02), z, 0.0)         # 0: off
    assert keep == chains and cut == []
    # a split muscle (two branches over the same gaps) is one piece: nothing cut
    split = [[(q, 0) for q in range(6)], [(3, 1), (4, 1), (5, 1)]]
    assert cut_fragments(split, area(1.0), z, 0.4) == (split, [])


def _cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize('bad', ['0', '-1', 'nan', 'inf', '0.9'])
def test_build_model_bad_refine_one_error_line_exit_2_nothing_written(bad, tmp_path, capsys):
    out = tmp_path / 'm.npz'
    code, o, e = _cli(capsys, 'build-model', '--refine', bad, '-o', out)
    assert code == 2
    lines = [ln for ln in e.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and 'error' in lines[0] and ('refine' in lines[0]), e
    assert not out.exists() and list(tmp_path.iterdir()) == []


@needs_anatomy
def test_build_model_refine_too_fine_for_the_volume(tmp_path, capsys):
    out = tmp_path / 'm.npz'
    code, o, e = _cli(capsys, 'build-model', '--refine', '8', '-o', out, '--report', tmp_path / 'r.json')
    assert code == 2
    lines = [ln for ln in e.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and 'error:' in lines[0] and '361 slices asked for (refine 8)' in lines[0], e
    assert list(tmp_path.iterdir()) == []


def _check_fine(tm, rep, base, R):
    t1, b1 = rep['table1'], base[1]['table1']
    assert len(tm.slice_z) - 1 == R * (len(base[0].slice_z) - 1)
    s = tm.meta['settings']
    assert (s['muscle_rays'], s['fat_rays']) == (R * 11, R * 12)
    # every muscle prism has rings of R x 11 vertices; fat cells are hexahedra (R x 12 per slice gap, below)
    n = np.diff(tm.cell_offsets)
    assert set(n[tm.cell_tissue == 1]) == {2 * R * 11} and set(n[tm.cell_tissue == 2]) == {8}
    # fat cells: one per slice gap and ray, less the degenerate ones dropped (reported)
    assert t1['fat_cells'] + len(rep['cells']['dropped_degenerate']) == (len(tm.slice_z) - 1) * R * 12
    assert rep['cells']['inverted'] == 0
    # vertices scale as R^2 (rings R x denser, R x more slices), within 25 %
    assert 0.75 * R ** 2 < t1['vertices'] / b1['vertices'] < 1.25 * R ** 2
    # every muscle present, one connected chain from its first to its last slice
    assert tm.muscle_names == base[0].muscle_names and t1['muscles'] == 28
    q = rep['quality']
    assert q['breaks'] == []
    for m in range(tm.n_muscles):
        cells = np.flatnonzero(tm.cell_muscle == m)
        covered = set()
        for c in cells:
            v = tm.cell(c)
            zb, zt = tm.rest_positions[v[:len(v) // 2], 2].mean(), tm.rest_positions[v[len(v) // 2:], 2].mean()
            i0, i1 = (int(np.argmin(np.abs(tm.slice_z - z))) for z in (zb, zt))
            covered.update(range(min(i0, i1), max(i0, i1)))
        assert covered == set(range(min(covered), max(covered) + 1)), tm.muscle_names[m]
    # what was left out is reported, small, and named in a warning; muscle volumes still match their labels
    for f in q['fragments_left_out']:
        assert f['share'] <= 0.01
        assert any(f['muscle'] in w and 'left out' in w for w in rep['warnings'])
    for name, r in q['volume_ratio'].items():
        assert abs(r - 1) < 0.1, (name, r)
    # no fat ring's inner vertices crowd together (wedge cells; contours.pair_inner, assemble.FALLBACK_CORE): on each
    # slice the shortest inner edge is at least 5 % of the mean (before: 1.7 % at 3x, 0 at 6x, on the foot)
    r, zi = quality.fat_inner_spacing(tm)
    assert r >= 0.05, (r, zi)
    assert q['fat_inner_spacing'] == {'min_ratio': round(r, 4), 'slice': zi}
    # the muscle chains follow their paths (assemble.smooth_path): the hamstrings' ring-centroid distances summed
    # within 15 % of the unrefined limb's (6x: biceps femoris long head 1.13, 1.23 before; 3x 1.03, 1.07 before)
    sm = rep['path_smoothing']
    assert base[1]['path_smoothing']['rings_moved'] == 0 and sm['rings_moved'] > 0 and sm['median_mm'] < 2
    for name in ('biceps_femoris_long_head', 'semimembranosus', 'semitendinosus'):
        ratio = _chord_sum(tm, name) / _chord_sum(base[0], name)
        assert 0.95 < ratio < 1.15, (name, ratio)
    return t1


def _chord_sum(tm, name):
    """[m] The distances between a muscle's successive ring centroids at rest, summed over its cells."""
    m = list(tm.muscle_names).index(name)
    total = 0.0
    for c in np.flatnonzero(tm.cell_muscle == m):
        v = tm.cell(c)
        x = tm.rest_positions[v]
        total += float(np.linalg.norm(x[len(v) // 2:].mean(axis=0) - x[:len(v) // 2].mean(axis=0)))
    return total


def test_smooth_path_puts_the_inner_rings_on_the_fitted_line_and_keeps_the_ends():
    """assemble.smooth_path: rings 2.5 mm apart whose centroids zigzag 1 mm about a straight slanted path end on
    it (the line fitted over +-17.5 mm); the chain's end rings and the rings' shapes stay; rings 17.5 mm apart (the
    unrefined limb's slicing) do not move."""
    ang = np.linspace(0, 2 * np.pi, 11, endpoint=False)
    base_ring = np.stack([0.01 * np.cos(ang), 0.008 * np.sin(ang), np.zeros(11)], axis=1)

    def chain(gap, n):
        out = []
        for i in range(n):
            z = -i * gap
            zig = 0.001 * (1 if i % 2 else -1)
            out.append(base_ring + [0.2 * z + zig, 0.1 * z, z])
        return out

    rings = chain(0.0025, 40)
    moves = []
    out = smooth_path(rings, 0.0175, moves)
    assert len(moves) == 38 and max(moves) < 0.0015
    for a, b in ((rings[0], out[0]), (rings[-1], out[-1])):
        assert np.array_equal(a, b)
    for i in range(8, 32):                  # away from the ends the fitted line is the path itself
        c = out[i].mean(axis=0)
        assert np.allclose(c[:2], [0.2 * c[2], 0.1 * c[2]], atol=5e-5), i     # (the 1-mm zigzag to < 5 %)
        assert np.allclose(out[i] - out[i].mean(axis=0), rings[i] - rings[i].mean(axis=0))   # the shape is kept
        assert out[i][0, 2] == rings[i][0, 2]
    coarse = chain(0.0175, 10)
    assert all(np.array_equal(a, b) for a, b in zip(coarse, smooth_path(coarse, 0.0175)))


@pytest.fixture(scope='module')
def base():
    lab, tis = builder.default_inputs()
    return builder.build_model(lab, tis)


@needs_anatomy
def test_three_times_finer_limb(base):
    lab, tis = builder.default_inputs()
    tm, rep = builder.build_model(lab, tis, refine=3)
    t1 = _check_fine(tm, rep, base, 3)
    # nothing of the labels is left out at 136 slices (the quadriceps tendons end on the patella's upper half:
    # docs/builder.md "Pieces cut off"; tests/test_builder_contour.py has a piece that is)
    assert rep['quality']['fragments_left_out'] == []
    assert t1['vertices'] > 25000


@needs_anatomy
@pytest.mark.slow
@pytest.mark.timeout(900)          # a 125,000-vertex build: ~30 s of CPU, minutes of wall on a loaded machine
def test_six_times_finer_limb(base):
    lab, tis = builder.default_inputs()
    tm, rep = builder.build_model(lab, tis, refine=6)
    _check_fine(tm, rep, base, 6)
