"""Contour cross-sections, connected muscles, joint-respecting bindings and the quality checks
(docs/builder.md), on the phantoms of tests/phantoms.py made by code."""
import numpy as np
import pytest

from phantoms import KNEE_Z, make_hard_phantom, make_phantom
from tissue_sim.core import model as M
from tissue_sim.core.builder import build_model
from tissue_sim.core.builder import contours as CT
from tissue_sim.core.builder.quality import cell_shear, cell_volumes, surface_checks
from tissue_sim.core.builder.rays import polygon_area
from tissue_sim.errors import UserError

P = {'slice_mm': 25.0}


@pytest.fixture(scope='module')
def hard():
    lab, aff, tab = make_hard_phantom()
    return build_model((lab, aff), tab, **P)


@pytest.fixture(scope='module')
def hard_rays():
    lab, aff, tab = make_hard_phantom()
    return build_model((lab, aff), tab, sections='rays', **P)


def test_every_tissue_keeps_its_label_volume(hard):
    """Wrapped, crescent, split, mid-stack-ending muscles and the fat (bumpy skin): +-10 %."""
    tm, rep = hard
    r = rep['quality']['volume_ratio']
    assert set(r) == {'wrap', 'crescent', 'split', 'short', 'fat'}
    for name, v in r.items():
        assert 0.9 <= v <= 1.1, (name, v)
    assert rep['quality']['warnings'] == []


def test_rays_lose_the_wrapped_and_crescent_muscles_and_the_report_says_so(hard_rays):
    """The paper's rays (still available): the wrapped muscle loses > 30 %, and the quality report warns."""
    tm, rep = hard_rays
    r = rep['quality']['volume_ratio']
    assert r['wrap'] < 0.7 and r['crescent'] < 0.9
    assert any(w.startswith('wrap: built volume') for w in rep['quality']['warnings'])
    assert any(w.startswith('wrap: built volume') for w in rep['warnings'])


def test_cells_valid_surfaces_closed_and_untwisted(hard):
    tm, rep = hard
    tm.validate()
    assert rep['cells']['inverted'] == 0 and not rep['cells']['dropped_degenerate']
    assert np.all(cell_volumes(tm) > 0)
    assert all(v['watertight'] and v['outward'] for v in surface_checks(tm).values())
    sh, _ = cell_shear(tm)
    assert sh[tm.cell_tissue == M.TISSUE_MUSCLE].max() < 1.0          # straight muscles: no twist between rings
    assert rep['quality']['shear']['muscle']['over_limit'] == 0
    for c in np.nonzero(tm.cell_tissue == M.TISSUE_MUSCLE)[0]:
        v = tm.rest_positions[tm.cell(c)]
        n = len(v) // 2
        assert polygon_area(v[:n, :2]) > 0 and polygon_area(v[n:, :2]) > 0


def test_split_muscle_is_two_chains_and_one_bone_becomes_two():
    lab, aff, tab = make_hard_phantom()
    tm, rep = build_model((lab, aff), tab, merge_gaps=1, **P)          # one cell per slice gap: countable
    m = tm.muscle_index('split')
    cs = tm.cell_slice[tm.cell_muscle == m]
    zc = tm.slice_z[cs]
    assert np.count_nonzero(zc >= 0) == 2 * np.count_nonzero(tm.slice_z[:-1] >= 0)    # two branches above z = 0
    assert rep['quality']['breaks'] == []
    att = rep['quality']['bone_attached_vertices']
    assert att['tibia'] > 0 and att['fibula'] > 0 and att['upper_bone'] > 0


def test_muscle_ending_mid_stack(hard):
    tm, rep = hard
    m = tm.muscle_index('short')
    top = tm.slice_z[tm.cell_slice[tm.cell_muscle == m] + 1].max()
    assert top == pytest.approx(0.025)           # last slice below its end at z = 37 mm
    assert 0.9 <= rep['quality']['volume_ratio']['short'] <= 1.1      # the end ring stands for its slab


def test_rotated_flipped_anisotropic_grid_gives_the_same_volumes(hard):
    tm, rep = hard
    lab, aff, tab = make_hard_phantom(rotated=False)
    tm2, rep2 = build_model((lab, aff), tab, **P)
    assert np.allclose(tm.slice_z, tm2.slice_z)
    v1, v2 = cell_volumes(tm), cell_volumes(tm2)
    for name in ('wrap', 'crescent', 'split', 'short'):
        a, b = v1[tm.cell_muscle == tm.muscle_index(name)].sum(), v2[tm2.cell_muscle == tm2.muscle_index(name)].sum()
        assert a == pytest.approx(b, rel=0.03), name


def test_ring_start_minimises_twist():
    """The ring chosen on a rotated copy of an outline matches the reference vertex by vertex."""
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    xy = np.stack([0.03 * np.cos(t) * (1 + 0.3 * np.cos(2 * t)), 0.02 * np.sin(t)], 1)
    fine = CT.resample(xy, CT.FINE * 12)
    ref, s0 = CT.best_ring(fine, 12, None, None)
    assert s0 >= 0
    shifted = np.roll(fine, 37, axis=0) + [0.01, -0.005]
    ring, _ = CT.best_ring(shifted, 12, ref, None)
    assert np.abs(ring - [0.01, -0.005] - ref).max() < 1e-9


def _foot(n=36):
    """A long skin outline (the foot's lowest slices: 250 x 70 mm) and a small inner region near its heel end."""
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    skin = np.stack([0.125 * np.cos(t), 0.035 * np.sin(t) * (1 + 0.15 * np.cos(t))], 1)
    outer, _ = CT.best_ring(CT.resample(skin, CT.FINE * n), n, None, None)
    inner = CT.resample(np.stack([-0.085 + 0.012 * np.cos(t), 0.01 * np.sin(t)], 1), CT.FINE * n)
    return outer, inner


def test_fat_inner_ring_keeps_its_vertices_apart_where_a_long_skin_faces_a_small_region():
    """The pairing along the inner outline (contours.pair_inner): valid quads, neighbouring inner vertices at least
    INNER_FLOOR x the even spacing apart. Pairing by angle about the region's centre (fat_rings' first try) crowds
    them here; on the 6x limb's foot it made coincident inner vertices, on the 3x crossing cells (rays instead)."""
    n = 36
    outer, inner = _foot(n)
    even = CT.polygon_perimeter(inner) / n
    assert CT.gaps(CT.pair_by_angle(inner, outer)).min() < 0.2 * even
    paired = CT.pair_inner(inner, outer)
    assert paired is not None and CT.fat_quads_valid(paired, outer)
    assert CT.gaps(paired).min() >= 0.95 * CT.INNER_FLOOR * even
    # concentric circles: every inner vertex is the radial foot of its skin vertex
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([0.05 * np.cos(t), 0.05 * np.sin(t)], 1)
    circ = CT.resample(np.stack([0.03 * np.cos(t), 0.03 * np.sin(t)], 1), CT.FINE * n)
    p = CT.pair_inner(circ, ring)
    assert np.abs(p - 0.6 * ring).max() < 1e-9


def _pair_dp_numpy(I, dist, outer, g, G, even, quads=True):
    """contours._pair_dp written with numpy over the fine points (each step's candidates at once): the reference."""
    m1, n = dist.shape
    m = m1 - 1
    tri2 = CT._tri2
    cost = np.full(m1, np.inf)
    cost[0] = dist[0, 0]
    back = np.zeros((n, m1), dtype=np.int64)
    for k in range(n):
        ob, oa = outer[(k + 1) % n], outer[k]
        new, arg = np.full(m1, np.inf), np.zeros(m1, dtype=np.int64)
        t = np.flatnonzero(np.isfinite(cost))
        if t.size == 0:
            break
        for dlt in range(g, G + 1):
            u = t + dlt
            ok = (u == m) if k == n - 1 else (u <= m - g * (n - 1 - k))
            tt, uu = t[ok], u[ok]
            ia, ib = I[tt], I[uu]
            valid = ((tri2(ia, ib, ob) < 0) & (tri2(ia, ob, oa) < 0)) | ((tri2(ia, ib, oa) < 0) & (tri2(ib, ob, oa) < 0))
            valid |= not quads
            tt, uu = tt[valid], uu[valid]
            c = cost[tt] + (dist[uu, (k + 1) % n] if k < n - 1 else 0.0) + (dlt / even - 1.0) ** 2
            better = c < new[uu]
            new[uu[better]] = c[better]
            arg[uu[better]] = tt[better]
        cost, back[k] = new, arg
    idx = np.zeros(n, dtype=np.int64)
    if not np.isfinite(cost[m]):
        return np.inf, idx
    u = m
    for k in range(n - 1, 0, -1):
        u = back[k][u]
        idx[k] = u
    return cost[m], idx


def _grown_toes(n=36):
    """The foot's skin outline (_foot) and the next slice's, its front half stretched by up to 40 mm (the toes), its
    heel half where it was: (the even ring of the first (anterior start), the first's and the second's fine outlines)."""
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    a = np.stack([0.125 * np.cos(t), 0.035 * np.sin(t) * (1 + 0.15 * np.cos(t))], 1)
    b = a.copy()
    b[:, 0] = np.where(a[:, 0] > 0.0, a[:, 0] + 0.04 * (a[:, 0] / 0.125) ** 2, a[:, 0])
    fine_a = CT.resample(a, CT.FINE * n)
    ring_a, _ = CT.best_ring(fine_a, n, None, None)
    return ring_a, fine_a, CT.resample(b, CT.FINE * n)


def test_follow_ring_moves_each_vertex_as_little_as_its_outline_moves():
    """contours.follow_ring (builder setting fat_follow): where an outline grows at one end between slices (the toes),
    the even ring from the least-twist start (best_ring) slides every vertex along it, the heel's by ~1 spacing
    although the heel's outline did not move; the ring that follows its predecessor keeps them in place (< 0.1
    spacing), moves none further than the outline moved, and keeps its neighbours apart (INNER_FLOOR)."""
    n = 36
    ring_a, fine_a, fine_b = _grown_toes(n)
    spacing = CT.polygon_perimeter(fine_b) / n
    heel = ring_a[:, 0] < 0.0
    even, _ = CT.best_ring(fine_b, n, ring_a, None)
    follow = CT.follow_ring(fine_b, ring_a)
    d_even, d_follow = np.linalg.norm(even - ring_a, axis=1), np.linalg.norm(follow - ring_a, axis=1)
    assert d_even[heel].max() > 0.8 * spacing
    assert d_follow[heel].max() < 0.1 * spacing
    assert d_follow.max() <= 0.04 * 1.01                # the toes' tip moved 40 mm (the fine outline: within 1 %)
    assert CT.is_simple(follow) and polygon_area(follow) > 0
    assert CT.gaps(follow).min() >= 0.95 * CT.INNER_FLOOR * CT.polygon_perimeter(fine_b) / n
    # on the ring's own outline it is the ring itself
    assert np.abs(CT.follow_ring(fine_a, ring_a) - ring_a).max() < 1e-12


@pytest.mark.parametrize('case', ['foot', 'circles', 'star', 'follow'])
def test_pairing_kernel_matches_the_numpy_reference(case):
    """contours._pair_dp (numba) gives the numpy reference's cost and pairing bit for bit, from every start that
    pair_inner tries, on the foot-like outline, concentric circles and a skin outline no pairing can face, and
    without the quads' test from every start follow_ring tries (a ring of the slice below)."""
    n = 36 if case != 'star' else 40
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    quads = case != 'follow'
    if case == 'foot':
        outer, inner = _foot(n)
    elif case == 'follow':
        outer, _, inner = _grown_toes(n)
    elif case == 'circles':
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        outer = np.stack([0.05 * np.cos(a), 0.05 * np.sin(a)], 1)
        inner = CT.resample(np.stack([0.03 * np.cos(t), 0.03 * np.sin(t)], 1), CT.FINE * n)
    else:
        r = 0.05 * (1 + 0.6 * np.cos(5 * t))
        outer, _ = CT.best_ring(CT.resample(np.stack([r * np.cos(t), r * np.sin(t)], 1), CT.FINE * n), n, None, None)
        inner = CT.resample(np.stack([0.065 + 0.004 * np.cos(t), 0.004 * np.sin(t)], 1), CT.FINE * n)
    m = len(inner)
    even = m / n
    g = max(1, int(np.ceil(CT.INNER_FLOOR * even)))
    G = max(g, min(m // 2, int(np.ceil(6 * even))))
    if quads:
        d2 = np.sum((inner[:, None, :] - outer[None]) ** 2, axis=2)
        d2 *= CT.INNER_NEAR / (float(np.mean(np.min(d2, axis=0))) + 1e-24)
    else:
        d2 = CT._follow_cost(inner, outer)
    found = 0
    for s0 in np.argsort(d2[:, 0], kind='stable')[:16]:
        off = (s0 + np.arange(m + 1)) % m
        c, idx = CT._pair_dp(inner[off], d2[off], outer, g, G, even, quads)
        c_ref, idx_ref = _pair_dp_numpy(inner[off], d2[off], outer, g, G, even, quads)
        assert c == c_ref and np.array_equal(idx, idx_ref)
        found += np.isfinite(c)
    assert (found == 0) == (case == 'star')


def test_fat_inner_ring_none_where_no_layer_of_cells_can_face_the_skin():
    """A skin outline that is not star-shaped from the inner region (a notch facing away from it): no monotone pairing
    gives valid quads, and the builder falls back to rays on that slice (reported)."""
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    r = 0.05 * (1 + 0.6 * np.cos(5 * t))                 # a five-pointed star with deep notches
    star, _ = CT.best_ring(CT.resample(np.stack([r * np.cos(t), r * np.sin(t)], 1), CT.FINE * 40), 40, None, None)
    inner = CT.resample(np.stack([0.065 + 0.004 * np.cos(t), 0.004 * np.sin(t)], 1), CT.FINE * 40)
    assert CT.pair_inner(inner, star) is None


def test_area_matching_keeps_a_crescent_area():
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    outer = np.stack([np.cos(t), np.sin(t)], 1)
    m = np.zeros((200, 200), bool)
    ii, jj = np.mgrid[:200, :200]
    m[(np.hypot(ii - 100, jj - 100) <= 60) & (np.hypot(ii - 100, jj - 130) > 45)] = True
    fine = CT.region_fine(m, (0, 0), np.eye(2) * 1e-3, np.zeros(2), 12)
    ring, _ = CT.best_ring(fine, 12, None, m.sum() * 1e-6)
    assert CT.is_simple(ring)
    assert polygon_area(ring) == pytest.approx(m.sum() * 1e-6, rel=0.01)
    del outer


def test_thin_tendon_beside_its_belly_stays_one_chain():
    """No overlap between tendon and belly on neighbouring slices: the chain is still linked."""
    lab, aff, tab = make_phantom('tendon')
    tm, rep = build_model((lab, aff), tab, merge_gaps=1, **P)           # one cell per slice gap
    m = tm.muscle_index('flexor')
    cs = np.sort(tm.cell_slice[tm.cell_muscle == m])
    assert np.array_equal(cs, np.arange(len(tm.slice_z) - 1))
    assert rep['quality']['breaks'] == []


def test_uniform_tendon_is_one_longer_cell():
    """The flexor's straight uniform tendon (r 4 mm, slices 4-8 at z = 0..100 mm) needs no cell per slice
    gap: its rings at z = 25, 50 lie on the straight prism from z = 0 to z = 75, so that is one cell over
    merge_gaps = 3 gaps, then one to z = 100; the belly and the belly-tendon transition keep one cell per
    gap, the chain stays whole, the volume is that of the per-gap cells, the uniform extensor is untouched."""
    lab, aff, tab = make_phantom('tendon')
    tm1, _ = build_model((lab, aff), tab, merge_gaps=1, **P)
    tm, rep = build_model((lab, aff), tab, **P)
    m = tm.muscle_index('flexor')
    c = np.flatnonzero(tm.cell_muscle == m)
    assert np.array_equal(np.sort(tm.cell_slice[c]), [0, 1, 2, 3, 4, 7])
    h = np.ptp(tm.rest_positions[tm.cell(c[tm.cell_slice[c] == 4][0]), 2])
    assert h == pytest.approx(3 * 0.025)
    assert rep['quality']['breaks'] == [] and rep['cells']['inverted'] == 0
    v1 = cell_volumes(tm1)[tm1.cell_muscle == m].sum()
    assert cell_volumes(tm)[c].sum() == pytest.approx(v1, rel=0.01)
    e = tm.muscle_index('extensor')
    assert np.count_nonzero(tm.cell_muscle == e) == np.count_nonzero(tm1.cell_muscle == e) == len(tm.slice_z) - 1
    assert all(v['watertight'] for v in surface_checks(tm).values())
    assert tm.n_cells == tm1.n_cells - 2


def test_a_real_break_is_an_error_naming_the_muscle_and_slices():
    lab, aff, tab = make_phantom('gap')
    with pytest.raises(UserError, match=r'muscle flexor \(label 11\) breaks between slices 3 and 5'):
        build_model((lab, aff), tab, **P)
    tm, rep = build_model((lab, aff), tab, allow_broken=True, **P)
    assert rep['quality']['breaks'][0]['from_slice'] == 3
    assert any('flexor breaks between slices 3 and 5' in w for w in rep['quality']['warnings'])


def test_a_small_piece_cut_off_is_left_out_with_a_warning_and_max_fragment_0_makes_it_a_break():
    """A piece of a muscle cut off from its belly by slices without its label and holding at most max_fragment (1 %)
    of its volume is left out, named in a warning and in quality.fragments_left_out; the rest is one chain. With
    max_fragment 0 the same labels are a break: the error names the muscle and the slices."""
    lab, aff, tab = make_phantom('fragment')
    tm, rep = build_model((lab, aff), tab, **P)
    (f,) = rep['quality']['fragments_left_out']
    assert (f['muscle'], f['label'], f['from_slice'], f['to_slice']) == ('flexor', 11, 0, 1) and 0 < f['share'] <= 0.01
    assert any('flexor' in w and 'left out' in w for w in rep['warnings'])
    assert rep['quality']['breaks'] == []
    m = tm.muscle_index('flexor')
    assert sorted(set(tm.cell_slice[tm.cell_muscle == m].tolist())) == list(range(3, len(tm.slice_z) - 1))
    with pytest.raises(UserError, match=r'muscle flexor \(label 11\) breaks between slices 1 and 3'):
        build_model((lab, aff), tab, max_fragment=0, **P)


def test_a_muscle_not_crossing_the_knee_is_not_bound_across_it():
    """extensor: origin and insertion on 'upper'; it touches the bone below the knee too, but none of
    its vertices is bound to 'lower' (nothing of a muscle is bound across a joint it does not cross)."""
    lab, aff, tab = make_phantom('column')
    tab['labels'][12] = dict(tab['labels'][12], origin='upper', insertion='upper')
    tm, rep = build_model((lab, aff), tab, **P)
    m = tm.muscle_index('extensor')
    vs = np.unique(np.concatenate([tm.cell(c) for c in np.nonzero(tm.cell_muscle == m)[0]]))
    lower = tm.segment_names.index('lower')
    assert not np.any(tm.vertex_segment[vs] == lower)
    assert np.any(tm.vertex_segment[vs] == tm.segment_names.index('upper'))
    assert rep['quality']['attachment_refused_across_joint'] > 0
    # without origin/insertion the same vertices below the knee touch the lower bone and are bound to it
    lab, aff, tab = make_phantom('column')
    tm0, _ = build_model((lab, aff), tab, **P)
    vs0 = np.unique(np.concatenate([tm0.cell(c) for c in np.nonzero(tm0.cell_muscle == tm0.muscle_index('extensor'))[0]]))
    assert np.any((tm0.vertex_segment[vs0] == lower) & (tm0.rest_positions[vs0, 2] < KNEE_Z / 1000))


def test_end_ring_vertex_shared_with_a_muscle_not_crossing_the_joint_stays_unbound():
    """The flexor (origin 'upper', insertion 'lower') ends beside the extensor (origin and insertion on
    'upper'), which shares two of the flexor's insertion-ring vertices: the rest of the ring is fixed to
    'lower', those two are not (they would bind the extensor across the knee), and the report says so."""
    from phantoms import _grid
    lab, aff, tab = make_phantom('column')
    _, _, x, y, z = _grid()
    lab[lab == 12] = 40
    lab[(np.hypot(x + 20, y - 34) <= 18) & (lab == 40)] = 12           # the extensor against the flexor
    tab['labels'][11] = dict(tab['labels'][11], origin='upper', insertion='lower')
    tab['labels'][12] = dict(tab['labels'][12], origin='upper', insertion='upper')
    tm, rep = build_model((lab, aff), tab, **P)
    f, e = tm.muscle_index('flexor'), tm.muscle_index('extensor')
    vf = np.unique(np.concatenate([tm.cell(c) for c in np.nonzero(tm.cell_muscle == f)[0]]))
    ve = np.unique(np.concatenate([tm.cell(c) for c in np.nonzero(tm.cell_muscle == e)[0]]))
    zz = tm.rest_positions[vf, 2]
    bot = vf[np.isclose(zz, zz.min())]
    shared = np.intersect1d(bot, ve)
    lower = tm.segment_names.index('lower')
    assert len(shared) > 0
    assert not np.any(tm.vertex_segment[ve] == lower)
    assert np.all(tm.vertex_segment[np.setdiff1d(bot, shared)] == lower)
    assert tm.meta['anchors']['flexor']['insertion'] == ['lower', len(bot) - len(shared)]
    assert any(w.startswith('muscle flexor:') and 'insertion ring' in w and 'does not span lower' in w
               for w in rep['warnings'])


def test_bad_sections_setting():
    lab, aff, tab = make_phantom('column')
    with pytest.raises(UserError, match='sections'):
        build_model((lab, aff), tab, sections='spline', **P)


def test_cli_strict_fails_and_writes_nothing(tmp_path, capsys):
    from phantoms import write_phantom
    from tissue_sim.cli import main
    labels, tissues = write_phantom('cshape', tmp_path / 'in', 'npz')
    out = tmp_path / 'm.npz'
    rc = main(['build-model', str(labels), '--tissues', str(tissues), '--slice-mm', '25', '--sections', 'rays',
               '--muscle-rays', '6', '-o', str(out), '--strict'])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists()
    assert 'flexor: built volume' in err and '--strict' in err
    assert main(['build-model', str(labels), '--tissues', str(tissues), '--slice-mm', '25', '-o', str(out), '--strict']) == 0
    assert out.exists()
    capsys.readouterr()
    assert main(['build-model', str(labels), '--tissues', str(tissues), '--slice-mm', '25', '--sections', 'rays',
                 '--muscle-rays', '6', '-o', str(tmp_path / 'r.npz'), '--json']) == 0
    import json
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert any(w.startswith('flexor: built volume') for w in d['quality_warnings'])


def test_end_ring_round_another_bone_binds_what_sees_its_own_bone():
    """A quadriceps-like muscle whose insertion ring wraps round the 'upper' bone, beside a patella on 'lower': a ring
    vertex is fixed to 'lower' when the straight line to the patella crosses no other bone (the far side would swing
    through the upper bone in flexion), also where it lies nearer to the upper bone (the vastus lateralis' ring on the
    femur above the patella: docs/builder.md "Muscle origins and insertions")."""
    from phantoms import R_BONE, _grid
    lab, aff, tab = make_phantom('column')
    _, _, x, y, z = _grid()
    r = np.hypot(x, y)
    lab[(lab == 12) & (z < 25)] = 40
    lab[(r > R_BONE) & (r <= 22) & (z >= 20) & (z <= 30)] = 12         # at its end the muscle wraps the upper bone
    lab[(np.hypot(x - 64, y) <= 5) & (z >= 20) & (z <= 30)] = 3
    tab['labels'][3] = {'name': 'patella', 'tissue': 'bone', 'segment': 'lower'}
    tab['labels'][12] = dict(tab['labels'][12], origin='upper', insertion='lower')
    tm, rep = build_model((lab, aff), tab, **P)
    m = tm.muscle_index('extensor')
    vs = np.unique(np.concatenate([tm.cell(c) for c in np.nonzero(tm.cell_muscle == m)[0]]))
    zz = tm.rest_positions[vs, 2]
    ring = vs[np.isclose(zz, zz.min())]
    assert zz.min() == pytest.approx(0.025)
    lower = tm.segment_names.index('lower')
    bound = tm.vertex_segment[ring] == lower
    assert 0 < bound.sum() == tm.meta['anchors']['extensor']['insertion'][1]
    # the rule, geometrically: the segment from the vertex to the nearest patella point misses the upper bone's disc
    p = tm.rest_positions[ring, :2] * 1000
    c = np.array([64.0, 0.0])
    q = c + 5.0 * (p - c) / np.linalg.norm(p - c, axis=1, keepdims=True)
    t = np.clip(np.einsum('ij,ij->i', -p, q - p) / np.einsum('ij,ij->i', q - p, q - p), 0, 1)
    miss = np.linalg.norm(p + t[:, None] * (q - p), axis=1)            # closest approach to the upper bone's axis
    blocked, clear = miss < R_BONE - 1.5, miss > R_BONE + 1.5
    behind = p[:, 0] < -R_BONE                                          # the ring's far side (measured: 2 of 11)
    assert blocked.any() and behind.sum() >= 2
    assert not np.any(bound[blocked]) and not np.any(bound[behind])
    near_upper = clear & (np.linalg.norm(p, axis=1) - R_BONE < np.linalg.norm(p - c, axis=1) - 5.0)
    assert near_upper.sum() >= 4 and np.all(bound[near_upper])        # nearer the upper bone, in sight of the patella


def test_a_region_enclosing_a_hole_is_reported_and_keeps_its_area():
    """A muscle all round the bone: its ring follows the outer boundary with the label's area, and
    the report names every slice where the hole is not represented."""
    from phantoms import _grid
    lab, aff, tab = make_phantom('column')
    _, _, x, y, z = _grid()
    r = np.hypot(x, y)
    lab[(lab == 11) | (lab == 12)] = 40
    lab[np.hypot(x - 50, y) <= 12] = 12
    lab[(r > 14) & (r <= 30) & (lab == 40)] = 11
    tm, rep = build_model((lab, aff), tab, **P)
    q = rep['quality']
    assert 0.9 <= q['volume_ratio']['flexor'] <= 1.1
    holes = [d for d in q['sections_not_followed'] if d['muscle'] == 'flexor']
    assert len(holes) == len(tm.slice_z) and all('hole' in d['how'] for d in holes)


def test_fat_follow_from_the_command_line(tmp_path):
    """`tissue-sim build-model --fat-follow` builds with the setting (the model's settings say so) and valid fat
    cells; the default is off (the even rings)."""
    from phantoms import write_phantom
    from tissue_sim.cli import main
    lab, tab = write_phantom('column', tmp_path, 'nii')
    for flag, want in (('--fat-follow', True), (None, False)):
        out = tmp_path / f'm_{want}.npz'
        assert main(['build-model', str(lab), '--tissues', str(tab), '-o', str(out), '--slice-mm', '25']
                    + ([flag] if flag else [])) == 0
        tm = M.TissueModel.load(out)
        assert tm.meta['settings']['fat_follow'] is want
        assert np.all(cell_volumes(tm) > 0)
