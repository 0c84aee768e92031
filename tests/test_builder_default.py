"""The bundled lower limb with default ("paper") settings: a model of the paper's size (Table 1)."""
import json

import numpy as np
import pytest

from tissue_sim.core import builder
from tissue_sim.core import model as M

try:
    builder.default_inputs()
    HAVE_ANATOMY = True
except FileNotFoundError:
    HAVE_ANATOMY = False

pytestmark = pytest.mark.skipif(not HAVE_ANATOMY, reason='bundled anatomy (data/lower_limb) not present')


@pytest.fixture(scope='module')
def built():
    """(model, report) of the bundled limb at default settings (no cache)."""
    lab, tis = builder.default_inputs()
    return builder.build_model(lab, tis)


@pytest.fixture(scope='module')
def default(tmp_path_factory):
    import os
    d = tmp_path_factory.mktemp('cache')
    old = os.environ.get('TISSUE_SIM_CACHE')
    os.environ['TISSUE_SIM_CACHE'] = str(d)
    try:
        tm = builder.default_model()
        again = builder.default_model()
    finally:
        if old is None:
            os.environ.pop('TISSUE_SIM_CACHE')
        else:
            os.environ['TISSUE_SIM_CACHE'] = old
    return tm, again, d


def test_paper_size(default):
    tm, _, _ = default
    t = builder.table1(tm)
    assert t['bones'] == 6
    # the muscle cells include the tendon cells (muscle label) of the 14 tendons, which the paper's model
    # has not; a uniform tendon section is one longer cell (merge_tol). Measured 355 (+22 %) before the
    # gastrocnemii got their tendons (issue 19), 367 (+26 %) with them: a description of the limb, not a target
    hi = {'muscle_cells': 1.30}
    for k in ('muscles', 'muscle_cells', 'muscle_vertices', 'fat_cells', 'fat_vertices', 'shared_vertices'):
        p = builder.PAPER_TABLE1[k]
        assert 0.75 * p <= t[k] <= hi.get(k, 1.25) * p, (k, t[k], p)


def test_valid_cells_and_attachment(default):
    from tissue_sim.core.builder.quality import cell_volumes, surface_checks
    tm, _, _ = default
    tm.validate()
    assert np.all(cell_volumes(tm) > 0)
    assert all(v['watertight'] for v in surface_checks(tm).values())
    # both the thigh and the shank carry attached soft tissue; hamstrings exist
    segs = set(tm.vertex_segment[tm.vertex_segment >= 0].tolist())
    assert {tm.segment_names.index('thigh'), tm.segment_names.index('shank')} <= segs
    assert sum(g == 'hamstrings' for g in tm.muscle_groups) >= 3
    assert tm.n_joints >= 1 and M.JOINT_HINGE in tm.joint_type.tolist()


def test_cached_on_disk(default):
    tm, again, d = default
    assert again.content_hash() == tm.content_hash()
    assert len(list(d.glob('default_model_*.npz'))) == 1


def test_cli_without_labels(tmp_path, capsys):
    from tissue_sim.cli import main
    assert main(['build-model', '-o', str(tmp_path / 'm.npz'), '--json']) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d['fat_cells'] == 540 and d['bones'] == 6


def test_every_tissue_within_10_percent_of_its_label_volume(built):
    """Issue 20: contour sections keep every muscle and the fat within +-10 % of its label volume."""
    tm, rep = built
    r = rep['quality']['volume_ratio']
    assert len(r) == len(tm.muscle_names) + 1
    bad = {k: v for k, v in r.items() if abs(v - 1) > 0.10}
    assert not bad, bad
    assert not any('built volume' in w for w in rep['quality']['warnings'])


def test_no_inverted_cell_and_every_bone_holds_soft_tissue(built):
    tm, rep = built
    assert rep['cells']['inverted'] == 0 and not rep['cells']['dropped_degenerate']
    assert all(n > 0 for n in rep['quality']['bone_attached_vertices'].values()), rep['quality']['bone_attached_vertices']
    assert rep['quality']['shear']['muscle']['median'] < 0.5


def test_every_muscle_is_one_chain(built):
    """Issue 19.1: no muscle breaks between slices (semitendinosus 31-33, the short head 36-38,
    vastus medialis, gracilis, peroneus brevis and flexor hallucis longus broke before)."""
    tm, rep = built
    assert rep['quality']['breaks'] == []
    for m, name in enumerate(tm.muscle_names):
        # every slice gap from the muscle's first to its last is spanned by a cell (a uniform tendon's
        # cell spans several: bottom ring on cell_slice, top ring on a later slice)
        cells = np.flatnonzero(tm.cell_muscle == m)
        top = [int(np.argmin(np.abs(tm.slice_z - tm.rest_positions[tm.cell(c)[len(tm.cell(c)) // 2:], 2].mean())))
               for c in cells]
        covered = set()
        for c, t in zip(cells, top):
            covered.update(range(tm.cell_slice[c], t))
        lo, hi = tm.cell_slice[cells].min(), max(top)
        assert covered == set(range(lo, hi)), name


def test_no_vertex_bound_across_a_joint_its_muscles_do_not_cross(built):
    """Muscles whose origin and insertion lie on the thigh hold no vertex bound to the shank; the
    vasti's insertion rings bind only their vertices beside the patella, not the ones behind the femur."""
    from tissue_sim.core.builder.table import load_tissue_table
    tm, _ = built
    tab = load_tissue_table(builder.default_inputs()[1])['labels']
    seg = {v['name']: (v.get('origin'), v.get('insertion')) for v in tab.values() if v['tissue'] == 'muscle'}
    shank = tm.segment_names.index('shank')
    for m, name in enumerate(tm.muscle_names):
        if seg[name] != ('thigh', 'thigh'):
            continue
        vs = np.unique(np.concatenate([tm.cell(c) for c in np.nonzero(tm.cell_muscle == m)[0]]))
        assert not np.any(tm.vertex_segment[vs] == shank), name
    knee = tm.joint_centre[[i for i, n in enumerate(tm.joint_names) if 'knee' in n][0]]
    m = tm.muscle_index('vastus_medialis')
    vs = np.unique(np.concatenate([tm.cell(c) for c in np.nonzero(tm.cell_muscle == m)[0]]))
    on_shank = vs[tm.vertex_segment[vs] == shank]
    assert np.all(tm.rest_positions[on_shank, 0] > knee[0] + 0.02)        # anterior: beside the patella


def test_gastrocnemii_glide_over_the_tibia(built):
    """Default (bind_passed_over False, unshare_passed_over True): no vertex of the gastrocnemii (femur ->
    calcaneus) is bound to the tibia they pass over but the few it hides from them (wrapped round its top).
    bind_passed_over=True binds 14 of them (measured; 30 on the limb before the gastrocnemii's heads behind the condyles);
    bind_passed_over=False alone keeps 8 bound, every one shared with the origin ring of a muscle arising
    from the shank (soleus, peroneus longus, tibialis posterior, the long flexors and extensor hallucis), and
    leaves the hamstrings' insertion-ring vertices shared with them free. The default anchors every end
    ring and gives the gastrocnemius cells their own free copy of each shared vertex bound to the shank
    (measured 13). No other muscle's cells change."""
    from tissue_sim.core.builder.table import load_tissue_table
    tm, rep = built
    lab, tis = builder.default_inputs()
    old, _ = builder.build_model(lab, tis, bind_passed_over=True)
    shared, _ = builder.build_model(lab, tis, unshare_passed_over=False)
    tab = load_tissue_table(tis)['labels']
    origin = {v['name']: v.get('origin') for v in tab.values() if v['tissue'] == 'muscle'}
    shank = tm.segment_names.index('shank')
    gastro = [tm.muscle_index(n) for n in ('gastrocnemius_medialis', 'gastrocnemius_lateralis')]
    from_shank = [m for m, n in enumerate(tm.muscle_names) if origin[n] == 'shank']

    def vertices(t, ms):
        return np.unique(np.concatenate([t.cell(c) for c in np.nonzero(np.isin(t.cell_muscle, ms))[0]]))

    assert np.count_nonzero(old.vertex_segment[vertices(old, gastro)] == shank) > 10
    g = vertices(shared, gastro)
    # the vertices the tibia hides from the gastrocnemii (in front of its top, docs/builder.md "Gliding muscles
    # wrapped round a bone") are bound in every build with bind_passed_over False: measured 2
    wrapped = vertices(tm, gastro)
    wrapped = wrapped[tm.vertex_segment[wrapped] == shank]
    assert 0 < len(wrapped) <= 3, wrapped
    assert "'gliding_vertices_bound_where_wrapped': %d" % len(wrapped) in str(rep)
    assert np.all(tm.rest_positions[wrapped, 0] > 0.0)       # in front of the knee (x anterior)
    still = np.setdiff1d(g[shared.vertex_segment[g] == shank], wrapped)
    assert 0 < len(still) < 10 and np.all(np.isin(still, vertices(shared, from_shank))), still
    assert shared.n_vertices == old.n_vertices and np.array_equal(shared.cell_vertices, old.cell_vertices)
    changed = np.flatnonzero(shared.vertex_segment != old.vertex_segment)
    assert len(changed) and np.all(np.isin(changed, vertices(old, gastro)))
    # the default: none bound to the shank; each split copy is a free vertex of the gastrocnemii only, at
    # the place of a shank-bound end-ring vertex of a muscle on the shank
    assert np.array_equal(np.flatnonzero(tm.vertex_segment == shank)[np.isin(np.flatnonzero(tm.vertex_segment == shank),
                                                                             vertices(tm, gastro))], wrapped)
    n = shared.n_vertices
    new = np.arange(n, tm.n_vertices)
    assert 0 < len(new) < 20 and np.all(tm.vertex_segment[new] == -1)
    assert not np.any(np.isin(new, vertices(tm, [m for m in range(len(tm.muscle_names)) if m not in gastro])))
    # the same places, but where a vertex is free in one build and bound in the other: the free one may have been
    # moved out of the bone it lay in (bone_clearance_mm; measured: one gastrocnemius lateralis copy, 0.65 mm)
    same = tm.vertex_segment[:n] == shared.vertex_segment
    assert np.allclose(tm.rest_positions[:n][same], shared.rest_positions[same])
    assert np.all(np.linalg.norm(tm.rest_positions[:n][~same] - shared.rest_positions[~same], axis=1) < 1e-3)
    bound = np.flatnonzero(tm.vertex_segment[:n] == shank)
    d = np.linalg.norm(tm.rest_positions[new][:, None] - tm.rest_positions[bound][None], axis=2).min(1)
    assert np.count_nonzero(d > 1e-12) <= 2 and np.all(d < 1e-3), d
    for c in np.flatnonzero(~np.isin(tm.cell_muscle, gastro)):
        assert np.array_equal(tm.cell(c), shared.cell(c))


def test_hamstring_end_rings_fully_bound_to_origin_and_insertion(built):
    """Every vertex of each hamstring's proximal end ring is bound to its origin segment and every vertex
    of its distal end ring to its insertion segment, the ones it shares with neighbouring muscles or the
    fat included (a shared end-ring vertex left free is pulled along the muscle by its active tension:
    the long head and semimembranosus then delivered 30 % and 5 % of Fmax at a held knee)."""
    from tissue_sim.core.builder.table import load_tissue_table
    tm, _ = built
    tab = load_tissue_table(builder.default_inputs()[1])['labels']
    ends = {v['name']: (v.get('origin'), v.get('insertion')) for v in tab.values() if v['tissue'] == 'muscle'}
    for name in ('biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus', 'semitendinosus'):
        m = tm.muscle_index(name)
        cells = np.flatnonzero(tm.cell_muscle == m)
        vs = np.unique(np.concatenate([tm.cell(c) for c in cells]))
        z = tm.rest_positions[vs, 2]
        top, bot = vs[np.isclose(z, z.max())], vs[np.isclose(z, z.min())]
        assert len(top) == len(bot) == len(tm.cell(cells[0])) // 2, name
        assert np.any(tm.vertex_flags[bot] & M.VF_SHARED), name            # the case the rule is about
        origin, insertion = ends[name]
        assert np.all(tm.vertex_segment[top] == tm.segment_names.index(origin)), name
        assert np.all(tm.vertex_segment[bot] == tm.segment_names.index(insertion)), name
        fixed = {k: v for k, v in tm.meta['anchors'][name].items() if k in ('origin', 'insertion')}
        assert fixed == {'origin': [origin, len(top)], 'insertion': [insertion, len(bot)]}


def test_nothing_bound_across_the_knee_behind_it(built):
    """Issue 19.1 on the bundled limb, geometrically: a vertex bound to the shank above the knee centre can
    only be one of the quadriceps' insertion rings beside the patella (in front of the femur, ≥ 30 mm anterior
    of the knee centre), never the back-of-knee vertices that the hamstrings, the short head and sartorius
    share with vastus medialis (they swung through the femur in flexion and dragged the passive hamstrings);
    and nothing bound to the thigh lies lower than the femoral condyles (25 mm below the knee centre)."""
    tm, _ = built
    j = list(tm.joint_names).index('knee_r')
    d = tm.rest_positions - tm.joint_centre[j]
    shank, thigh = tm.segment_names.index('shank'), tm.segment_names.index('thigh')
    up = np.flatnonzero((tm.vertex_segment == shank) & (d[:, 2] > 0))
    assert np.all(d[up, 0] > 0.03), np.round(d[up][d[up, 0] <= 0.03] * 1e3)
    low = np.flatnonzero(tm.vertex_segment == thigh)
    assert d[low, 2].min() > -0.025, d[low, 2].min()


def test_no_free_vertex_inside_a_bone_at_rest(built):
    """bone_clearance_mm (default 0.5, docs/builder.md "Free vertices inside a bone"): no free vertex of the bundled
    limb lies inside a bone mesh at rest; the moved ones lie 0.5 mm outside. Without it (None) 4 gastrocnemius
    vertices lie 0.15-1.9 mm inside the tibia (measured), and 7 vasti vertices next to their end rings (free by the
    end-ring rule, docs/builder.md; the vastus medialis' 5 free insertion-ring vertices up to 2.4 mm and one more of
    it, one of the lateralis) in the femur, 4 of the 11 deeper than the contact tests' 1-mm criterion, and 2 of tensor
    fasciae latae's iliotibial tract in the lateral femoral condyle (1.2 mm): 14 moved (12 on the limb before the tract;
    19 before the gastrocnemii's heads behind the condyles)."""
    import trimesh
    from tissue_sim.core.builder.bones import winding_number
    tm, rep = built
    lab, tis = builder.default_inputs()
    raw, _ = builder.build_model(lab, tis, bone_clearance_mm=None)

    def inside(t):
        free = np.flatnonzero(np.asarray(t.vertex_segment) < 0)
        out = {}
        for b in range(len(t.bone_names)):
            V, T = t.bone_mesh(b)
            ins = free[winding_number(V, T, t.rest_positions[free]) > 0.5]
            for v in ins:
                cp = trimesh.triangles.closest_point(V[T], np.repeat(t.rest_positions[v:v + 1], len(T), axis=0))
                out[int(v)] = float(np.linalg.norm(cp - t.rest_positions[v], axis=1).min())
        return out

    before = inside(raw)
    assert len(before) >= 10 and max(before.values()) > 1e-3, before
    assert inside(tm) == {}
    moved = np.flatnonzero(np.any(tm.rest_positions != raw.rest_positions, axis=1))
    assert set(before) <= set(moved.tolist())      # (without the move one more is hidden by the tibia: bound there)
    assert np.all(np.linalg.norm(tm.rest_positions[moved] - raw.rest_positions[moved], axis=1) < 3.0e-3)
    assert "'free_vertices_moved_out_of_bones': %d" % len(moved) in str(rep) and len(moved) == 14


@pytest.mark.slow
def test_fat_rings_that_follow_the_slice_below(built):
    """Builder setting fat_follow (docs/builder.md "Fat tube"): on the bundled limb the fat rings that follow their
    predecessors slant less between slices (their cells' centroid offset over height: p95 and max lower than the even
    rings'), no two neighbouring inner vertices crowd together (the even rings' foot ring: 2.4 % of the even spacing),
    and the tube is the same: as many fat cells, none inverted, its volume within 3 % of the fat label's."""
    from tissue_sim.core.builder import contours
    lab, tis = builder.default_inputs()
    tm, rep = builder.build_model(lab, tis, fat_follow=True)
    even, follow = built[1]['quality'], rep['quality']
    assert follow['shear']['fat']['slant_p95'] < even['shear']['fat']['slant_p95']
    assert follow['shear']['fat']['slant_max'] < even['shear']['fat']['slant_max']
    assert even['fat_inner_spacing']['min_ratio'] < 0.1
    assert follow['fat_inner_spacing']['min_ratio'] >= 0.9 * contours.INNER_FLOOR
    assert follow['shear']['fat']['cells'] == even['shear']['fat']['cells']
    assert abs(follow['volume_ratio']['fat'] - 1.0) < 0.03
    fat = tm.cell_tissue == M.TISSUE_FAT
    from tissue_sim.core import geometry
    assert np.all(geometry.prism_volumes(tm.rest_positions, tm.cell_offsets, tm.cell_vertices, fat) > 0)
