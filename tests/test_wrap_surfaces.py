"""Wrap surfaces (the source model's wrap cylinders): the tissue table's wrap_surfaces, the builder's TissueModel.wrap_*,
the model file, and the bundled limb's."""
import dataclasses
import re

import numpy as np
import pytest

from phantoms import make_phantom
from tissue_sim.core import model as M
from tissue_sim.core.builder import build_model, load_tissue_table
from tissue_sim.errors import UserError

P = {'slice_mm': 25.0, 'muscle_rays': 10, 'min_area_mm2': 20.0, 'sections': 'rays'}   # tests/test_builder.py's
CYL = {'name': 'cyl', 'segment': 'upper', 'body': 'femur_r', 'centre_m': [0.0, 0.0, 0.0125], 'axis': [0.0, 3.0, 0.0],
       'radius_m': 0.02, 'length_m': 0.1, 'quadrant': [-2.0, 0.0, 0.0]}


def _table(**wraps):
    """The column phantom's table with wrap_surfaces on the labels given (label=list)."""
    lab, aff, tab = make_phantom('column')
    for k, v in wraps.items():
        tab['labels'][int(k[1:])]['wrap_surfaces'] = v
    return lab, aff, tab


@pytest.fixture(scope='module')
def wrapped():
    """The column built with 'cyl' on both muscles and 'low' (every side) on the extensor."""
    lab, aff, tab = _table(l11=[CYL], l12=[dict(CYL), dict(CYL, name='low', segment='lower', quadrant=None,
                                                             centre_m=[0.0, 0.0, -0.05], axis=[1, 1, 0])])
    return build_model((lab, aff), tab, **P)[0]


def test_the_table_parses_a_wrap_surface_and_normalises_its_directions():
    _, _, tab = _table(l11=[CYL, dict(CYL, name='b', quadrant=None)])
    ws = load_tissue_table(tab)['labels'][11]['wrap_surfaces']
    assert [w['name'] for w in ws] == ['cyl', 'b'] and ws[0]['segment'] == 'upper'
    assert np.allclose(ws[0]['centre'], [0, 0, 0.0125]) and np.allclose(ws[0]['axis'], [0, 1, 0])
    assert np.allclose(ws[0]['quadrant'], [-1, 0, 0]) and ws[1]['quadrant'] is None
    assert ws[0]['radius'] == 0.02 and ws[0]['length'] == 0.1
    assert load_tissue_table(make_phantom('column')[2])['labels'][11]['wrap_surfaces'] == []


@pytest.mark.parametrize('label,bad,msg', [
    (11, [{k: v for k, v in CYL.items() if k != 'radius_m'}], 'label 11 (flexor): wrap_surfaces[0] (cyl) needs "radius_m"'),
    (11, [dict(CYL, axis=[0, 0, 0])], 'label 11 (flexor): wrap_surfaces[0] (cyl) needs "axis": 3 finite numbers, not all zero'),
    (11, [dict(CYL, quadrant=[0, 0, 0])], 'wrap_surfaces[0] (cyl) needs "quadrant"'),
    (11, [dict(CYL, length_m=-0.1)], 'wrap_surfaces[0] (cyl) needs "length_m": a finite number > 0'),
    (11, [dict(CYL, centre_m=[0, 0])], 'wrap_surfaces[0] (cyl) needs "centre_m"'),
    (11, [dict(CYL, name='')], 'label 11 (flexor): wrap_surfaces[0] needs "name"'),
    (11, [dict(CYL, segment='pelvis')], "label 11 (flexor): wrap surface 'cyl' segment 'pelvis' is not in the joints file"),
    (11, CYL, 'label 11 (flexor): wrap_surfaces must be a list'),
    (40, [CYL], 'label 40 (fat): wrap_surfaces must be a list of {name, segment, centre_m, axis, radius_m, length_m, '
                'quadrant} on a muscle'),
    (1, [CYL], 'label 1 (upper_bone): wrap_surfaces must be a list')])
def test_a_bad_wrap_surface_is_a_clear_error(label, bad, msg):
    _, _, tab = make_phantom('column')
    tab['labels'][label]['wrap_surfaces'] = bad
    with pytest.raises(UserError, match=re.escape(msg)):
        load_tissue_table(tab)


def test_the_builder_makes_one_surface_per_name_with_the_muscles_that_list_it(wrapped):
    tm = wrapped
    f, e = tm.muscle_index('flexor'), tm.muscle_index('extensor')
    assert tm.wrap_names == ('cyl', 'low')
    assert list(tm.wrap_segment) == [tm.segment_names.index('upper'), tm.segment_names.index('lower')]
    assert list(tm.wrap_muscle_offsets) == [0, 2, 3] and list(tm.wrap_muscles) == [f, e, e]
    assert np.allclose(tm.wrap_geometry[0], [0, 0, 0.0125, 0, 1, 0, -1, 0, 0, 0.02, 0.1])
    s = 2 ** -0.5
    assert np.allclose(tm.wrap_geometry[1], [0, 0, -0.05, s, s, 0, 0, 0, 0, 0.02, 0.1])   # every side: zeros


def test_without_wrap_surfaces_a_model_has_none():
    lab, aff, tab = make_phantom('column')
    tm, _ = build_model((lab, aff), tab, **P)
    assert tm.wrap_names == () and tm.wrap_segment.shape == (0,) and tm.wrap_geometry.shape == (0, 11)
    assert list(tm.wrap_muscle_offsets) == [0] and tm.wrap_muscles.size == 0


def test_one_name_with_two_geometries_is_a_clear_error():
    lab, aff, tab = _table(l11=[CYL], l12=[dict(CYL, radius_m=0.021)])
    with pytest.raises(UserError, match=re.escape("label 12 (extensor): wrap surface 'cyl' differs from the one of that "
                                                  "name another muscle lists")):
        build_model((lab, aff), tab, **P)


def test_the_model_file_keeps_the_wrap_surfaces_and_an_older_file_loads_without(wrapped, tmp_path):
    tm = wrapped
    again = M.TissueModel.load(tm.save(tmp_path / 'm.npz'))
    assert again.wrap_names == tm.wrap_names and again.content_hash() == tm.content_hash()
    for f in ('wrap_segment', 'wrap_geometry', 'wrap_muscle_offsets', 'wrap_muscles'):
        assert np.array_equal(getattr(again, f), getattr(tm, f)) and getattr(again, f).dtype == getattr(tm, f).dtype, f
    # a model file written before the fields existed loads with none
    arrays = {k: v for k, v in np.load(tmp_path / 'm.npz').items() if not k.startswith('wrap_')}
    np.savez_compressed(tmp_path / 'old.npz', **arrays)
    old = M.TissueModel.load(tmp_path / 'old.npz')
    assert old.wrap_names == () and old.wrap_geometry.shape == (0, 11) and list(old.wrap_muscle_offsets) == [0]


@pytest.mark.parametrize('change,msg', [
    ({'wrap_segment': np.array([0, 2], np.int32)}, 'wrap_segment or wrap_muscles out of range'),
    ({'wrap_muscles': np.array([0, 1, 5], np.int32)}, 'wrap_segment or wrap_muscles out of range'),
    ({'wrap_names': ('cyl', 'cyl')}, 'wrap names must be unique'),
    ({'wrap_names': ('cyl',)}, 'wrap arrays inconsistent'),
    ({'wrap_muscle_offsets': np.array([0, 2, 4], np.int64)}, 'wrap arrays inconsistent'),
    ('axis', 'axes must be unit vectors'),
    ('radius', 'radius and length must be > 0'),
    ('nan', 'wrap_geometry has non-finite values')])
def test_validate_rejects_bad_wrap_arrays(wrapped, change, msg):
    if isinstance(change, str):
        g = wrapped.wrap_geometry.copy()
        g[0, {'axis': 4, 'radius': 9, 'nan': 0}[change]] = {'axis': 2.0, 'radius': 0.0, 'nan': np.nan}[change]
        change = {'wrap_geometry': g}
    with pytest.raises(M.ModelError, match=re.escape(msg)):
        dataclasses.replace(wrapped, **change).validate()


def test_the_bundled_limb_carries_the_source_models_wrap_cylinders():
    """The knee extensors' cylinder at the distal femur (thigh) and the short head's on the tibia (shank), posed at
    full extension as the source model has them (tools/anatomy/generate.py, PROVENANCE.md)."""
    from tissue_sim.core.builder import default_model
    tm = default_model()
    w = {n: i for i, n in enumerate(tm.wrap_names)}

    def muscles(name):
        i = w[name]
        return {tm.muscle_names[m] for m in tm.wrap_muscles[tm.wrap_muscle_offsets[i]:tm.wrap_muscle_offsets[i + 1]]}
    assert muscles('KnExt_at_fem_r') == {'rectus_femoris', 'vastus_lateralis', 'vastus_medialis', 'vastus_intermedius'}
    assert muscles('BF_at_gastroc_r') == {'biceps_femoris_short_head'}
    assert tm.segment_names[tm.wrap_segment[w['KnExt_at_fem_r']]] == 'thigh'
    assert tm.segment_names[tm.wrap_segment[w['BF_at_gastroc_r']]] == 'shank'
    g = tm.wrap_geometry[w['KnExt_at_fem_r']]
    assert np.allclose(g[:3], [0.0036, -0.0021, -0.4027], atol=1e-4) and np.allclose(g[3:6], [0.051, -0.997, 0.062], atol=1e-3)
    assert np.all(g[6:9] == 0) and np.allclose(g[9:], [0.025, 0.1])
    g = tm.wrap_geometry[w['BF_at_gastroc_r']]
    assert np.allclose(g[:3], [-0.058, 0.00127, -0.4574], atol=1e-4) and np.allclose(g[3:9], [0, -1, 0, 0, 0, 1])
    assert np.allclose(g[9:], [0.03, 0.15])
    assert {'Gastroc_at_condyles_r', 'GasMed_at_shank_r', 'GasLat_at_shank_r'} <= set(w)
