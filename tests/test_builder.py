"""Model builder on analytic phantoms (tests/phantoms.py): exact counts, volumes, sharing, attachment."""
import math

import re

import numpy as np
import pytest

from phantoms import KNEE_Z, R_BODY, R_BONE, R_MUS, X_MUS, Z0, Z1, make_phantom, make_phantom_model
from tissue_sim.core import model as M
from tissue_sim.core import geometry
from tissue_sim.core.builder import build_model
from tissue_sim.core.builder.quality import cell_volumes, surface_checks, table1
from tissue_sim.core.builder.rays import polygon_area

H = (Z1 - Z0) / 1000.0          # m
N_SLICES = 9                    # every 25 mm over 200 mm
P = {'slice_mm': 25.0, 'muscle_rays': 10, 'min_area_mm2': 20.0, 'sections': 'rays'}   # the paper's rays


def inscribed(n, r):
    return 0.5 * n * r * r * math.sin(2 * math.pi / n)


@pytest.fixture(scope='module')
def column():
    lab, aff, tab = make_phantom('column')
    return build_model((lab, aff), tab, **P)


def muscle_cells(tm, name):
    return np.nonzero(tm.cell_muscle == tm.muscle_index(name))[0]


def test_column_exact_counts(column):
    tm, rep = column
    t = rep['table1']
    assert len(tm.slice_z) == N_SLICES
    assert np.allclose(tm.slice_z, np.linspace(Z0, Z1, N_SLICES) / 1000.0)
    assert t['bones'] == 2 and t['muscles'] == 2
    assert t['muscle_cells'] == 2 * (N_SLICES - 1)
    assert t['muscle_vertices'] == 2 * N_SLICES * 10
    assert t['fat_cells'] == (N_SLICES - 1) * 12
    assert t['fat_vertices'] == 8 * t['fat_cells']             # paper's count: incidences
    assert t['fat_vertices_unique'] == N_SLICES * 24
    assert np.all(np.diff(tm.cell_offsets)[tm.cell_tissue == M.TISSUE_MUSCLE] == 20)
    assert np.all(np.diff(tm.cell_offsets)[tm.cell_tissue == M.TISSUE_FAT] == 8)
    assert t == table1(tm)


def test_column_cells_valid_and_surfaces_closed(column):
    tm, rep = column
    tm.validate()
    assert rep['cells']['inverted'] == 0 and not rep['cells']['dropped_degenerate']
    assert np.all(cell_volumes(tm) > 1e-6)
    s = surface_checks(tm)
    assert set(s) == {'muscle/flexor', 'muscle/extensor', 'fat'}
    assert all(v['watertight'] and v['outward'] for v in s.values())
    # each muscle's closed surface encloses exactly the sum of its cells
    vols = cell_volumes(tm)
    for name in ('flexor', 'extensor'):
        assert s[f'muscle/{name}']['volume_cm3'] == pytest.approx(vols[muscle_cells(tm, name)].sum() * 1e6, rel=1e-6)


def test_column_volumes_match_analytic(column):
    tm, _ = column
    vols = cell_volumes(tm)
    expect = inscribed(10, R_MUS / 1000.0) * H                 # prism of the inscribed 10-gon
    for name in ('flexor', 'extensor'):
        assert vols[muscle_cells(tm, name)].sum() == pytest.approx(expect, rel=0.03)
    # fat: outer 12-gon of the body minus the inner polygon (farthest exit from bone + muscles per ray)
    ang = 2 * np.pi * np.arange(12) / 12
    inner = []
    for a in ang:
        u = np.array([math.cos(a), math.sin(a)])
        r = R_BONE
        for cx in (X_MUS, -X_MUS):
            p = u @ np.array([cx, 0.0])
            disc = p * p - (cx * cx - R_MUS ** 2)
            if disc >= 0 and p + math.sqrt(disc) > 0:
                r = max(r, p + math.sqrt(disc))
        inner.append(r)
    inner = np.array(inner) / 1000.0
    a_in = 0.5 * np.sum(inner * np.roll(inner, -1)) * math.sin(2 * np.pi / 12)
    expect_fat = (inscribed(12, R_BODY / 1000.0) - a_in) * H
    assert vols[tm.cell_tissue == M.TISSUE_FAT].sum() == pytest.approx(expect_fat, rel=0.03)


def test_rings_aligned_ccw_and_on_the_contour(column):
    tm, _ = column
    for name, cx in (('flexor', -X_MUS), ('extensor', X_MUS)):
        for c in muscle_cells(tm, name):
            v = tm.rest_positions[tm.cell(c)]
            bot, top = v[:10], v[10:]
            assert polygon_area(bot[:, :2]) > 0 and polygon_area(top[:, :2]) > 0      # CCW from +z
            assert np.all(top[:, 2] > bot[:, 2])
            free = (tm.vertex_flags[tm.cell(c)[:10]] & M.VF_SHARED) == 0
            d = bot[:, :2] * 1000.0 - [cx, 0.0]
            ang = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360
            # vertex k points along 36 k degrees (no twist) and lies on the circle (within a pixel)
            assert np.allclose(ang[free], (36.0 * np.arange(10))[free], atol=2.0)
            assert np.allclose(np.hypot(d[free, 0], d[free, 1]), R_MUS, atol=0.8)
    # fat rings: inner a, inner b, outer b, outer a with a -> b counter-clockwise (so the ring is clockwise)
    for c in np.nonzero(tm.cell_tissue == M.TISSUE_FAT)[0]:
        v = tm.rest_positions[tm.cell(c)]
        assert polygon_area(v[:4, :2]) < 0
        assert np.linalg.norm(v[2, :2]) > np.linalg.norm(v[1, :2]) and np.linalg.norm(v[3, :2]) > np.linalg.norm(v[0, :2])


def test_fibres_along_the_column(column):
    tm, _ = column
    mus = tm.cell_tissue == M.TISSUE_MUSCLE
    assert np.allclose(tm.cell_fibre[mus], [0, 0, 1], atol=0.02)


def test_sharing_merges_touching_tissues(column):
    tm, rep = column
    p = tm.rest_positions
    fl = tm.vertex_flags
    # fat ray 0 ends on the far side of the extensor at (60, 0) mm, as does extensor ray 0: one vertex
    for z in tm.slice_z:
        for x in (60.0, -60.0):
            near = np.nonzero(np.linalg.norm(p - [x / 1000, 0, z], axis=1) < 1.5e-3)[0]
            assert len(near) == 1, (x, z, near)
            v = near[0]
            assert fl[v] & M.VF_SHARED and fl[v] & M.VF_MUSCLE and fl[v] & M.VF_FAT
            assert p[v, 2] == z                               # stays on the slice plane
    assert rep['table1']['shared_vertices'] == int(np.count_nonzero(fl & M.VF_SHARED))
    assert rep['sharing']['vertices_before'] - rep['sharing']['vertices_after'] >= rep['table1']['shared_vertices']


def test_no_sharing_when_threshold_zero():
    lab, aff, tab = make_phantom('column')
    tm, rep = build_model((lab, aff), tab, share_mm=0, **P)
    assert rep['table1']['shared_vertices'] == 0
    assert tm.n_vertices == 2 * N_SLICES * 10 + N_SLICES * 24
    tm2, rep2 = build_model((lab, aff), tab, share_mm=12, **P)
    assert rep2['table1']['shared_vertices'] > 0 and tm2.n_vertices < tm.n_vertices
    assert rep2['cells']['inverted'] == 0


def test_bone_attachment(column):
    tm, rep = column
    p = tm.rest_positions * 1000.0
    dist = np.hypot(p[:, 0], p[:, 1]) - R_BONE
    att = tm.vertex_segment >= 0
    attach_mm = tm.meta['attach_mm']
    assert att.any()
    assert np.all(dist[att] <= attach_mm + 1.0)
    assert np.all(dist[~att] > attach_mm - 1.0)
    # segment of the bone on that slice: upper above the knee, lower below
    up = tm.segment_names.index('upper')
    assert sum(rep['attachment'].values()) == int(att.sum()) and rep['attachment']['upper'] > 0 and rep['attachment']['lower'] > 0
    assert np.all((tm.vertex_segment[att] == up) == (p[att, 2] >= KNEE_Z))
    # the flexor's ray 0 and the extensor's ray 5 touch the bone on every slice
    for z in tm.slice_z:
        for x in (-10.0, 10.0):
            v = np.argmin(np.linalg.norm(tm.rest_positions - [x / 1000, 0, z], axis=1))
            assert tm.vertex_segment[v] >= 0
    # fat inner points at 90 and 270 degrees lie on the bone (no muscle there)
    for z in tm.slice_z:
        for y in (10.0, -10.0):
            v = np.argmin(np.linalg.norm(tm.rest_positions - [0, y / 1000, z], axis=1))
            assert tm.vertex_flags[v] & M.VF_FAT and tm.vertex_segment[v] >= 0


def test_table_fields_and_skeleton(column):
    tm, _ = column
    f, e = tm.muscle_index('flexor'), tm.muscle_index('extensor')
    assert tm.muscle_groups[f] == 'hamstrings' and tm.muscle_max_force[f] == 1000.0
    assert tm.muscle_fibre_length[f] == 0.1
    assert math.isnan(tm.muscle_max_force[e]) and math.isnan(tm.muscle_fibre_length[e])
    assert np.all(tm.cell_k_scale[tm.cell_muscle == e] == 2.0) and np.all(tm.cell_k_scale[tm.cell_muscle == f] == 1.0)
    assert tm.segment_names == ('upper', 'lower') and list(tm.segment_parent) == [-1, 0]
    assert tm.joint_names == ('knee',) and tm.joint_type[0] == M.JOINT_HINGE
    assert np.allclose(tm.joint_centre[0], [0, 0, KNEE_Z / 1000]) and np.allclose(tm.joint_range[0], np.radians([0, 120]))
    assert tm.bone_names == ('upper_bone', 'lower_bone') and list(tm.bone_segment) == [0, 1]
    # bones: closed surfaces whose volume matches the cylinder within 5 %
    import trimesh
    for b, (z0, z1) in enumerate(((KNEE_Z - 2.5, Z1), (Z0, KNEE_Z - 2.5))):
        v, t = tm.bone_mesh(b)
        m = trimesh.Trimesh(v, t, process=False)
        assert m.is_watertight and m.volume > 0
        assert m.volume == pytest.approx(math.pi * (R_BONE / 1000) ** 2 * (z1 - z0) / 1000, rel=0.08)
    # skin quads: outer points, outward normal
    q = tm.rest_positions[tm.skin_quads]
    assert np.allclose(np.hypot(q[..., 0], q[..., 1]) * 1000, R_BODY, atol=0.8)
    n = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 1])
    assert np.all(np.einsum('ij,ij->i', n[:, :2], q.mean(1)[:, :2]) > 0)
    assert np.all(tm.cell_tissue[tm.skin_quad_cell] == M.TISSUE_FAT)
    assert np.all(tm.vertex_flags[tm.skin_quads.ravel()] & M.VF_SKIN)


def test_save_load_roundtrip(column, tmp_path):
    tm, _ = column
    p = tm.save(tmp_path / 'm.npz')
    tm2 = M.TissueModel.load(p)
    assert tm2.content_hash() == tm.content_hash()
    assert tm2.meta['settings']['muscle_rays'] == 10


def test_tapered_muscle_ends_between_slices():
    lab, aff, tab = make_phantom('tapered')
    tm, rep = build_model((lab, aff), tab, merge_gaps=1, **P)          # one cell per slice gap: countable
    f = muscle_cells(tm, 'flexor')
    # present (area >= 20 mm^2) on z = -100 .. 25 mm: 6 rings, 5 cells; the z = 50 sliver is dropped and reported
    assert len(f) == 5
    assert tm.slice_z[tm.cell_slice[f]].max() == pytest.approx(0.0)
    assert any(d['name'] == 'flexor' and d['slice'] == 6 for d in rep['dropped_components'])
    assert surface_checks(tm)['muscle/flexor']['watertight']
    zs = np.linspace(Z0, 25.0, 6)
    r = R_MUS * (60.0 - zs) / 160.0 / 1000.0
    a = inscribed(10, 1.0) * r ** 2
    expect = sum(0.025 / 3 * (a[i] + a[i + 1] + math.sqrt(a[i] * a[i + 1])) for i in range(5))
    assert cell_volumes(tm)[f].sum() == pytest.approx(expect, rel=0.05)
    assert np.all(cell_volumes(tm) > 0)


def test_two_bones_in_one_slice():
    lab, aff, tab = make_phantom('two_bones')
    tm, rep = build_model((lab, aff), tab, **P)
    assert rep['cells']['inverted'] == 0 and rep['closed_surfaces']
    # fat rays start at the centroid of both bones' pixels
    a1, a2 = math.pi * 12 ** 2, math.pi * 6 ** 2
    c = (np.array([10.0, -15.0]) * a1 + np.array([-5.0, 25.0]) * a2) / (a1 + a2) / 1000.0
    fat = np.nonzero(tm.cell_tissue == M.TISSUE_FAT)[0]
    for cid in fat[:12]:
        v = tm.rest_positions[tm.cell(cid)]
        ids = tm.cell(cid)
        for i_in, i_out in ((0, 3), (1, 2)):
            if (tm.vertex_flags[ids[[i_in, i_out]]] & M.VF_SHARED).any():
                continue
            d1, d2 = v[i_in, :2] - c, v[i_out, :2] - c
            # the inner point lies on the ray from c through the outer point (within 0.5 mm)
            assert abs(d1[0] * d2[1] - d1[1] * d2[0]) / np.linalg.norm(d2) < 0.5e-3
            assert d1 @ d2 > 0
    # attachment to the nearest bone's segment
    p = tm.rest_positions * 1000
    att = tm.vertex_segment >= 0
    d_tib = np.hypot(p[:, 0] - 10, p[:, 1] + 15) - 12
    d_fib = np.hypot(p[:, 0] + 5, p[:, 1] - 25) - 6
    assert np.any(tm.vertex_segment == 0) and np.any(tm.vertex_segment == 1)
    assert np.all(tm.vertex_segment[att] == np.where(d_tib[att] < d_fib[att], 0, 1))


def test_split_region_gives_two_chains():
    lab, aff, tab = make_phantom('split')
    tm, rep = build_model((lab, aff), tab, merge_gaps=1, **P)          # one cell per slice gap: countable
    f = muscle_cells(tm, 'flexor')
    # one disc on z < 0 (4 slices), two discs on z >= 0 (5 slices): chain of 9 rings + chain of 5 rings
    assert len(f) == 8 + 4
    assert surface_checks(tm)['muscle/flexor']['watertight']
    assert rep['cells']['inverted'] == 0


def test_non_convex_region_uses_interior_origin():
    lab, aff, tab = make_phantom('cshape')
    tm, rep = build_model((lab, aff), tab, **P)
    f = muscle_cells(tm, 'flexor')
    assert len(f) == N_SLICES - 1 and rep['cells']['inverted'] == 0
    v = tm.rest_positions[np.unique(np.concatenate([tm.cell(c) for c in f]))] * 1000
    free = (tm.vertex_flags[np.unique(np.concatenate([tm.cell(c) for c in f]))] & M.VF_SHARED) == 0
    r = np.hypot(v[:, 0], v[:, 1])
    ang = np.abs(np.degrees(np.arctan2(v[:, 1], v[:, 0])))
    # 'first' crossing keeps the polygon inside the C (never across the bone or the opening)
    assert np.all(r[free] >= R_BONE - 1.0) and np.all(r[free] <= 41.0) and np.all(ang[free] >= 98.0)
    assert rep['areas']['per_muscle']['flexor']['median_area_ratio'] > 0.5


def test_settings_change_counts_exactly():
    lab, aff, tab = make_phantom('column')
    tm, rep = build_model((lab, aff), tab, muscle_rays=6, fat_rays=8, slice_mm=10.0, share_mm=0)
    t = rep['table1']
    assert len(tm.slice_z) == 21
    assert t['muscle_cells'] == 2 * 20 and t['muscle_vertices'] == 2 * 21 * 6
    assert t['fat_cells'] == 20 * 8 and t['fat_vertices_unique'] == 21 * 16
    tm3, rep3 = build_model((lab, aff), tab, slice_step=8)        # every 8th 5-mm slice = 40 mm
    assert len(tm3.slice_z) == 6
    tm4, rep4 = build_model((lab, aff), tab, slices=5)             # evenly over the extent: k = 0, 10, .., 40
    assert np.allclose(tm4.slice_z, np.linspace(Z0, Z1, 5) / 1000.0)
    from tissue_sim.core.builder import DEFAULTS
    assert rep4['table1']['fat_cells'] == 4 * 12 and rep4['table1']['muscle_vertices'] == 2 * 5 * DEFAULTS['muscle_rays']
    from tissue_sim.errors import UserError
    with pytest.raises(UserError, match='only one of'):
        build_model((lab, aff), tab, slices=5, slice_mm=10.0)
    with pytest.raises(UserError, match='46 slices'):
        build_model((lab, aff), tab)                               # the paper's 46 slices do not fit 41


def test_phantom_model_helper():
    tm = make_phantom_model('column')
    assert isinstance(tm, M.TissueModel) and tm.n_cells == 16 + 96


def test_prism_volume_of_unit_cube():
    ring = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    pos = np.concatenate([ring, ring + [0, 0, 1]])
    v = geometry.prism_volumes(pos, np.array([0, 8]), np.arange(8))
    assert v[0] == pytest.approx(1.0)
    assert geometry.prism_volumes(pos, np.array([0, 8]), np.arange(8), np.array([True]))[0] == pytest.approx(-1.0)


@pytest.mark.parametrize('axis', [0, 1, 2])
def test_voxel_axis_flips_give_the_same_model(column, axis):
    """The model lives in the model frame: reversing a voxel axis (and its affine column) changes nothing."""
    tm, _ = column
    lab, aff, tab = make_phantom('column')
    aff2 = aff.copy()
    aff2[:3, 3] = aff[:3, :3] @ np.eye(3)[axis] * (lab.shape[axis] - 1) + aff[:3, 3]
    aff2[:3, axis] = -aff[:3, axis]
    tm2, _ = build_model((np.flip(lab, axis), aff2), tab, **P)
    assert np.allclose(tm2.slice_z, tm.slice_z)
    assert tm2.n_vertices == tm.n_vertices and tm2.n_cells == tm.n_cells
    # same vertex positions (as a set) and same cell geometry
    order = np.lexsort(tm.rest_positions.T.round(7))
    order2 = np.lexsort(tm2.rest_positions.T.round(7))
    assert np.allclose(tm.rest_positions[order], tm2.rest_positions[order2], atol=1e-6)
    assert np.allclose(np.sort(cell_volumes(tm)), np.sort(cell_volumes(tm2)), rtol=1e-6)


def test_best_origin_covers_at_least_the_centroid_polygon():
    lab, aff, tab = make_phantom('cshape')
    _, rb = build_model((lab, aff), tab, ray_origin='best', **P)
    _, rc = build_model((lab, aff), tab, ray_origin='centroid', **P)
    best = rb['areas']['per_muscle']['flexor']['median_area_ratio']
    cen = rc['areas']['per_muscle']['flexor']['median_area_ratio']
    assert best >= cen and rb['cells']['inverted'] == 0
    # convex discs: identical polygons either way
    assert rb['areas']['per_muscle']['extensor'] == rc['areas']['per_muscle']['extensor']
    from tissue_sim.errors import UserError
    with pytest.raises(UserError, match='ray_origin'):
        build_model((lab, aff), tab, ray_origin='middle', **P)


def test_sharing_is_undone_where_it_would_spoil_a_cell():
    """Merges that would shrink a cell below min_cell_volume are undone (the guard of section 2.4)."""
    lab, aff, tab = make_phantom('split')
    _, r0 = build_model((lab, aff), tab, slice_mm=25.0, share_mm=0, sections='rays')
    tm, r = build_model((lab, aff), tab, slice_mm=25.0, share_mm=30, min_cell_volume_mm3=8000, sections='rays')
    assert r0['cells']['min_volume_mm3'] > 8000
    assert r['sharing']['unshared_to_avoid_inversion'] > 0
    assert r['cells']['min_volume_mm3'] >= 8000 and not r['cells']['dropped_degenerate']
    assert r['table1']['shared_vertices'] > 0


def test_share_groups_never_take_two_vertices_of_one_ring():
    from tissue_sim.core.builder.sharing import share_groups
    # ring 0 (muscle 0): two vertices 2 mm apart; a fat vertex (ring 1) between them
    pos = np.array([[0, 0, 0], [0.002, 0, 0], [0.001, 0, 0]], float)
    rep = share_groups(pos, tissue=np.array([0, 0, -1]), ring=np.array([0, 0, 1]), slice_id=np.zeros(3, int), radius=0.005)
    assert rep[0] != rep[1] and rep[2] in (rep[0], rep[1])
    # different slices never merge
    pos[2, 2] = 0.001
    rep = share_groups(pos, tissue=np.array([0, 0, -1]), ring=np.array([0, 0, 1]), slice_id=np.array([0, 0, 1]), radius=0.005)
    assert len(set(rep.tolist())) == 3


def _anchored_table(origin='upper', insertion='lower'):
    lab, aff, tab = make_phantom('column')
    tab['labels'][11] = dict(tab['labels'][11], origin={'segment': origin, 'body': 'atlas'}, insertion=insertion)
    return lab, aff, tab


def test_muscle_origin_and_insertion_fix_the_end_rings():
    """The table's origin/insertion fix the flexor's top ring to 'upper' and its bottom ring to
    'lower'; with anchor_muscles=False only bone-touching vertices are fixed (the paper's rule)."""
    lab, aff, tab = _anchored_table()
    tm, rep = build_model((lab, aff), tab, **P)
    plain, _ = build_model((lab, aff), tab, **P, anchor_muscles=False)
    assert plain.meta['anchors'] == {}
    m = tm.muscle_index('flexor')
    cells = np.flatnonzero(tm.cell_muscle == m)
    vs = np.unique(np.concatenate([tm.cell_vertices[tm.cell_offsets[c]:tm.cell_offsets[c + 1]] for c in cells]))
    z = tm.rest_positions[vs, 2]
    top, bot = vs[np.isclose(z, z.max())], vs[np.isclose(z, z.min())]
    assert len(top) == len(bot) == 10
    # the whole ring is fixed, its vertices shared with the fat included (a shared vertex left free is
    # pulled along the muscle by its active tension: the muscle then shortens inside, docs/builder.md)
    assert np.any(tm.vertex_flags[top] & M.VF_SHARED) and np.any(tm.vertex_flags[bot] & M.VF_SHARED)
    assert tm.meta['anchors'] == {'flexor': {'origin': ['upper', 10], 'insertion': ['lower', 10]}}
    assert np.all(tm.vertex_segment[top] == tm.segment_names.index('upper'))
    assert np.all(tm.vertex_segment[bot] == tm.segment_names.index('lower'))
    # the same vertices, only the end rings' attachment differs from the plain build
    assert np.array_equal(tm.rest_positions, plain.rest_positions)
    changed = np.flatnonzero(tm.vertex_segment != plain.vertex_segment)
    assert set(changed) <= set(top) | set(bot) and len(changed) > 0


def test_via_points_fix_the_ring_nearest_each():
    """builder via_points: the flexor's ring on the slice nearest each via point is fixed to the via point's segment
    (two on the upper segment here); a via point beyond the muscle's slices, off its section, or whose ring fixed to
    the lower segment would turn the cell joining it to the free ring above inside out within the knee's range is
    listed, not bound; off (the paper's rule: only the end rings) the table's via points change nothing."""
    lab, aff, tab = _anchored_table()
    tab['labels'][11]['via_points'] = [{'segment': 'upper', 'at_m': [-0.035, 0.0, 0.061]},
                                       {'segment': 'lower', 'at_m': [-0.035, 0.0, -0.052]},
                                       {'segment': 'lower', 'at_m': [-0.035, 0.0, -5.0]},
                                       {'segment': 'lower', 'at_m': [0.035, 0.0, -0.052]},
                                       {'segment': 'upper', 'at_m': [-0.035, 0.0, 0.03]}]
    off, _ = build_model((lab, aff), tab, **P, via_points=False)
    tm, rep = build_model((lab, aff), tab, **P)
    assert off.meta['anchors'] == {'flexor': {'origin': ['upper', 10], 'insertion': ['lower', 10]}}
    a = tm.meta['anchors']['flexor']
    assert a['via 0'] == ['upper', 10] and a['via 4'] == ['upper', 10] and 'via 1' not in a
    assert a['vias_inside_out'] == [1]           # the lower ring turned 120 deg against the free ring above it
    assert a['vias_beyond_slices'] == [2]
    assert a['vias_off_section'] == [3]          # across the bone from the flexor: its section does not hold it
    m = tm.muscle_index('flexor')
    cells = np.flatnonzero(tm.cell_muscle == m)
    vs = np.unique(np.concatenate([tm.cell_vertices[tm.cell_offsets[c]:tm.cell_offsets[c + 1]] for c in cells]))
    z = tm.rest_positions[vs, 2]
    for at in (0.061, 0.03):
        ring = vs[np.isclose(z, z[np.argmin(abs(z - at))])]
        assert len(ring) == 10 and np.all(tm.vertex_segment[ring] == tm.segment_names.index('upper')), at
    changed = np.flatnonzero(tm.vertex_segment != off.vertex_segment)
    assert 0 < len(changed) <= 20 and np.array_equal(tm.rest_positions, off.rest_positions)


def test_a_via_ring_that_would_turn_a_cell_inside_out_is_held_at_its_centroid_for_the_named_muscles():
    """builder point_vias: the flexor's ring at the lower via point (refused whole: the cell above it would turn inside
    out) is listed as a point via for a muscle named (or every muscle: True): its 10 vertices stay free (but one the
    bone touches, bound by the paper's rule) and the model
    records them, their segment and muscle (TissueModel.via_point_*); not named, it is listed under vias_inside_out as
    before and the model has no point via."""
    lab, aff, tab = _anchored_table()
    tab['labels'][11]['via_points'] = [{'segment': 'lower', 'at_m': [-0.035, 0.0, -0.052]}]
    plain, _ = build_model((lab, aff), tab, **P)                         # default list: not the flexor
    assert plain.meta['anchors']['flexor']['vias_inside_out'] == [0] and plain.via_point_segment.size == 0
    for setting in (['flexor'], True):
        tm, _ = build_model((lab, aff), tab, **P, point_vias=setting)
        a = tm.meta['anchors']['flexor']
        assert a['vias_point'] == [0] and 'vias_inside_out' not in a and 'via 0' not in a
        assert list(tm.via_point_offsets) == [0, 10] and list(tm.via_point_segment) == [tm.segment_names.index('lower')]
        assert list(tm.via_point_muscle) == [tm.muscle_index('flexor')]
        ring = tm.via_point_vertices
        assert np.sum(tm.vertex_segment[ring] == -1) == 9 and np.ptp(tm.rest_positions[ring, 2]) < 1e-9
        assert abs(tm.rest_positions[ring, 2].mean() + 0.052) < 0.02          # the slice nearest the via point
        assert np.array_equal(tm.vertex_segment, plain.vertex_segment)       # nothing else bound differently


def test_the_bundled_semitendinosus_passes_its_tibial_via_point():
    """The bundled limb: semitendinosus' ring at the source model's P2 on the tibia is its one point via (refused
    whole by the inside-out test); gracilis' and sartorius' tibial via rings are not (point_vias: semitendinosus)."""
    from tissue_sim.core.builder import default_model
    tm = default_model()
    assert [tm.muscle_names[m] for m in tm.via_point_muscle] == ['semitendinosus']
    assert tm.meta['anchors']['semitendinosus']['vias_point'] == [0]
    assert tm.meta['anchors']['gracilis']['vias_inside_out'] == [0]
    ring = tm.via_point_vertices
    assert tm.segment_names[tm.via_point_segment[0]] == 'shank' and ring.size == 11
    p2 = np.array([-0.0312, 0.02417, -0.44823])                               # tissues.yaml via_points[0]
    assert np.linalg.norm(tm.rest_positions[ring].mean(axis=0) - p2) < 0.01


@pytest.mark.parametrize('bad,msg', [([{'segment': 'pelvis', 'at_m': [0, 0, 0]}], "via point segment 'pelvis' is not in"),
                                     ([{'segment': 'lower', 'at_m': [0, 0]}], 'via_points[0] needs "segment" and "at_m"'),
                                     ({'segment': 'lower'}, 'via_points must be a list')])
def test_bad_via_points_are_a_clear_error(bad, msg):
    from tissue_sim.errors import UserError
    lab, aff, tab = _anchored_table()
    tab['labels'][11]['via_points'] = bad
    with pytest.raises(UserError, match=re.escape(msg)):
        build_model((lab, aff), tab, **P)


@pytest.mark.parametrize('setting,msg', [({'via_mm': -1.0}, 'via_mm must be a number >= 0'),
                                         ({'via_points': 'yes'}, 'via_points must be true or false'),
                                         ({'fat_follow': 'yes'}, 'fat_follow must be true or false'),
                                         ({'point_vias': 'flexor'}, 'point_vias must be true, false or a list'),
                                         ({'point_vias': ['flexor', 3]}, 'point_vias must be true, false or a list')])
def test_bad_via_settings_are_a_clear_error(setting, msg):
    from tissue_sim.errors import UserError
    lab, aff, tab = _anchored_table()
    with pytest.raises(UserError, match=msg):
        build_model((lab, aff), tab, **P, **setting)


def test_anchor_is_refused_across_a_joint():
    """A ring whose slice has no bone of the named segment is left free, with a warning (no rigid
    lever through the joint): here the flexor's top ring names the lower segment."""
    lab, aff, tab = _anchored_table(origin='lower')
    tm, rep = build_model((lab, aff), tab, **P)
    assert 'origin' not in tm.meta['anchors'].get('flexor', {})
    assert any('flexor' in w and 'origin' in w and 'left unanchored' in w for w in rep['warnings'])


@pytest.mark.parametrize('bad,msg', [({'segment': 'pelvis'}, "origin segment 'pelvis' is not in the joints file"),
                                     ({'body': 'x'}, 'origin must be a segment name')])
def test_bad_origin_is_a_clear_error(bad, msg):
    from tissue_sim.errors import UserError
    lab, aff, tab = make_phantom('column')
    tab['labels'][11] = dict(tab['labels'][11], origin=bad)
    with pytest.raises(UserError, match=msg):
        build_model((lab, aff), tab, **P)
