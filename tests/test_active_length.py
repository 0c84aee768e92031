"""The active tension's rest length along the muscle's centre line (`Params.active_length: path`; docs/solver.md
"The tension's rest length along the muscle", docs/convergence.md "Where it stands").

A muscle cell's active tension T = a k_a n/4 max(l - lam L, 0) pulls its two ring centroids together. With `chord`
(the paper set's, which has no tension) L is the rest distance between them; the rings' centroids wander sideways from
slice to slice, a chain under tension pulls those offsets straight and its cells end up shorter than L, delivering
less than the calibrated force, the more the finer the slices. `path` (the physical set's) measures L along the
muscle's smoothed centre line; the cells of its first and last gap keep their chord.

The same centre line (`measures.centre_lines`) is what a muscle's reported length is measured along with
`Params.length_measure: centre_line` (the physical set's; docs/solver.md "Muscle length"): end ring to end ring
through the smoothed gap centres, so that neither the rings' sideways wander nor a slack chain's kinks count as
musculotendon length."""
import types

import numpy as np
import pytest

from tissue_sim.core import solver
from tissue_sim.core.solver import measures, model as M

HAMSTRINGS = ('biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus', 'semitendinosus')


def _zigzag_chain(n_cells=30, gap=0.01, offset=0.003, ring=6, radius=0.01):
    """A straight muscle along z built of n_cells prisms whose rings sit alternately +-offset off the axis in x
    (the centroid wander of a segmented muscle), plus one fat cell; the fields path_lengths reads."""
    ang = np.linspace(0, 2 * np.pi, ring, endpoint=False)
    rings = [np.stack([radius * np.cos(ang) + offset * (-1) ** s, radius * np.sin(ang), np.full(ring, s * gap)], 1)
             for s in range(n_cells + 1)]
    x = np.concatenate(rings + [rings[0] + (0.05, 0, 0), rings[1] + (0.05, 0, 0)])
    cv, off = [], [0]
    for c in range(n_cells):
        cv += list(range(c * ring, (c + 1) * ring)) + list(range((c + 1) * ring, (c + 2) * ring))
        off.append(len(cv))
    base = (n_cells + 1) * ring
    cv += list(range(base, base + 2 * ring))
    off.append(len(cv))
    tm = types.SimpleNamespace(n_muscles=1, cell_muscle=np.array([0] * n_cells + [-1]),
                               cell_slice=np.array(list(range(n_cells)) + [0]), vertex_segment=np.full(len(x), -1))
    return tm, x, np.array(off), np.array(cv)


def _kinked(x, ring=6, at=10, half_angle=np.radians(35)):
    """The straight chain's positions bent at ring ``at`` into two straight legs, each half_angle off the z axis."""
    bent = x.copy()
    z0 = at * 0.01
    dz = x[:, 2] - z0
    s = np.where(dz < 0, -1.0, 1.0)
    bent[:, 0] = x[:, 0] + np.abs(dz) * np.sin(half_angle)
    bent[:, 2] = z0 + s * np.abs(dz) * np.cos(half_angle)
    return bent


def test_centre_line_passes_through_a_ring_bound_whole_to_a_bone():
    """A via ring (bound whole to one segment, the builder's via points) is a point of the centre line, as the
    source model's path passes through its via point: a muscle bent there measures both legs in full, the Gaussian
    smooths each piece on its own (and cuts the corner of a ring that is free); the cells next to it keep their chord."""
    tm, x, off, cv = _zigzag_chain(n_cells=20, offset=0.0)
    bent = _kinked(x)
    legs = 0.20 * 1.0             # two straight legs of 10 gaps of 10 mm, bent at ring 10
    free = measures.centre_lines(tm, off, cv, bent, 0.015)
    assert free.lengths(bent, 1)[0] < legs - 0.002                      # the smoothing cuts a free ring's corner
    tm.vertex_segment[10 * 6:11 * 6] = 0                                 # ring 10 bound whole to segment 0
    lines = measures.centre_lines(tm, off, cv, bent, 0.015)
    assert lines.lengths(bent, 1)[0] == pytest.approx(legs, rel=1e-9)
    pts = lines.points(bent)
    kink = bent[10 * 6:11 * 6].mean(0)
    assert np.any(np.all(np.isclose(pts, kink, rtol=0, atol=1e-12), axis=1))   # the ring's centroid is on the line
    assert [p.size for p in lines.pieces(0)] == [10, 10] and free.pieces(0)[0].size == 20
    chord = np.zeros(len(off) - 1)
    measures.cell_axial_lengths(bent, off, cv, chord)
    L = M.path_lengths(tm, bent, off, cv, chord, sigma=0.015, lines=lines)
    assert np.allclose(L[:-1], chord[:-1], rtol=1e-9)                  # straight legs: every cell's chord
    Lf = M.path_lengths(tm, bent, off, cv, chord, sigma=0.015, lines=free)
    assert Lf[9] < 0.99 * chord[9] and Lf[10] < 0.99 * chord[10]        # free: the kink's cells are cut
    # a ring bound only in part is no via ring
    tm.vertex_segment[10 * 6] = -1
    assert measures.centre_lines(tm, off, cv, bent, 0.015).lengths(bent, 1)[0] < legs - 0.002


def test_path_length_of_a_zigzag_chain_is_its_length_along_the_axis():
    tm, x, off, cv = _zigzag_chain()
    chord = np.zeros(len(off) - 1)
    measures.cell_axial_lengths(x, off, cv, chord)
    assert np.allclose(chord[:-1], np.hypot(0.01, 0.006))          # each chord crosses the axis: 11.7 mm
    L = M.path_lengths(tm, x, off, cv, chord, sigma=0.015)
    assert np.allclose(L[1:-2], 0.01, rtol=2e-3), L[1:-2]           # along the centre line: the 10-mm gap
    assert L[0] == chord[0] and L[-2] == chord[-2]                  # the end gaps keep their chord
    assert L[-1] == chord[-1]                                       # a fat cell keeps its chord
    # a muscle that truly bends keeps its length: the same chain on a 60-mm-radius arc, no zigzag
    tm, x, off, cv = _zigzag_chain(offset=0.0)
    z = x[:, 2].copy()
    bent = x.copy()
    bent[:, 0] = x[:, 0] + 0.06 * (1 - np.cos(z / 0.06))
    bent[:, 2] = 0.06 * np.sin(z / 0.06)
    chord = np.zeros(len(off) - 1)
    measures.cell_axial_lengths(bent, off, cv, chord)
    L = M.path_lengths(tm, bent, off, cv, chord, sigma=0.015)
    assert np.allclose(L[3:-4], chord[3:-4], rtol=2e-3) and np.all(L[:-1] > 0.97 * chord[:-1])   # (the ends of a
    # 286-deg arc lose < 3 %: the smoothing holds the centre line's ends)


def test_path_is_the_physical_sets_and_only_shortens(default_tm):
    assert solver.Params.physical().active_length == 'path' and solver.Params.paper().active_length == 'chord'
    a = solver.compile_model(default_tm, solver.Params.physical(active_length='chord'))
    b = solver.compile_model(default_tm, solver.Params.physical())
    chord = np.zeros(default_tm.n_cells)
    measures.cell_axial_lengths(np.asarray(default_tm.rest_positions, float), a.off, a.cv, chord)
    assert np.array_equal(a.rest_length, chord)
    mus = np.asarray(default_tm.cell_muscle) >= 0
    assert np.all(b.rest_length <= chord * (1 + 1e-12)) and np.all(b.rest_length >= 0.5 * chord * (1 - 1e-12))
    assert np.array_equal(b.rest_length[~mus], chord[~mus])
    assert 0.9 < np.median(b.rest_length[mus] / chord[mus]) < 1.0
    with pytest.raises(ValueError, match='active_length'):
        solver.Params.physical(active_length='fibre')
    with pytest.raises(ValueError, match='active_path_sigma'):
        solver.Params.physical(active_path_sigma=0.0)


def test_centre_line_length_is_the_musculotendon_length_not_the_chord_sum():
    # a straight chain: end ring to end ring, whatever the smoothing
    tm, x, off, cv = _zigzag_chain(offset=0.0)
    lines = measures.centre_lines(tm, off, cv, x, 0.015)
    assert lines.lengths(x, 1)[0] == pytest.approx(0.30, rel=1e-12)
    # the zigzag: the chord sum counts the sideways wander (30 x 11.7 mm), the centre line does not
    tm, x, off, cv = _zigzag_chain()
    chord = np.zeros(len(off) - 1)
    measures.cell_axial_lengths(x, off, cv, chord)
    lines = measures.centre_lines(tm, off, cv, x, 0.015)
    assert chord[:-1].sum() == pytest.approx(0.35, rel=2e-3)
    assert lines.lengths(x, 1)[0] == pytest.approx(0.30, rel=0.01)
    # a true bend of radius R (60 mm) keeps its length up to the smoothing's exp(-sigma^2 / 2 R^2) (3 %)
    tm, x, off, cv = _zigzag_chain(offset=0.0)
    z = x[:, 2].copy()
    bent = x.copy()
    bent[:, 0] = x[:, 0] + 0.06 * (1 - np.cos(z / 0.06))
    bent[:, 2] = 0.06 * np.sin(z / 0.06)
    arc = measures.centre_lines(tm, off, cv, bent, 0.015).lengths(bent, 1)[0]
    assert 0.96 * 0.30 < arc < 0.30
    # the map is built once at rest and applied to any positions: the bent chain measured with the straight one's map
    # (its Gaussian's gap steps fixed by the straight spacing) agrees
    assert measures.centre_lines(tm, off, cv, x, 0.015).lengths(bent, 1)[0] == pytest.approx(arc, rel=1e-3)


def test_physical_set_reports_the_centre_line_length(default_tm):
    assert solver.Params.physical().length_measure == 'centre_line' and solver.Params.paper().length_measure == 'chord'
    sim = solver.compile_model(default_tm, solver.Params.physical())
    chordwise = solver.compile_model(default_tm, solver.Params.physical(length_measure='chord', active_length='chord'))
    state = solver.make_state(sim)
    ml = solver.observe(sim, state)['muscle_lengths']
    assert np.allclose(ml, sim.centre_lines.lengths(np.asarray(state.x), sim.n_muscles), rtol=0, atol=0)
    mc = solver.observe(chordwise, solver.make_state(chordwise))['muscle_lengths']
    assert np.allclose(mc, chordwise.muscle_rest_length)       # the chord sum, as the paper set reports it
    names = list(default_tm.muscle_names)
    lh = names.index('biceps_femoris_long_head')
    assert 0.95 < ml[lh] / mc[lh] < 0.99                      # the long head: 388 of the chords' 400 mm
    assert np.all(ml[mc > 0] < mc[mc > 0] * 1.001) and np.all(ml[mc > 0] > 0.5 * mc[mc > 0])
    with pytest.raises(ValueError, match='length_measure'):
        solver.Params.physical(length_measure='fibre')


def _isometric_forces(tm, active_length):
    """Each hamstring's active force [N] with the knee locked at 0 deg, all four fully active, after 0.3 s."""
    p = solver.Params.physical(integrator='implicit', substeps=1, active_length=active_length)
    sim = solver.compile_model(tm, p)
    st, ctl = solver.make_state(sim), solver.make_control(sim)
    ctl.joint_lock[list(tm.joint_names).index('knee_r')] = True
    idx = [list(tm.muscle_names).index(n) for n in HAMSTRINGS]
    ctl.activation[idx] = 1.0
    for _ in range(300):
        solver.step(sim, st, ctl)
    return solver.observe(sim, st)['muscle_active_forces'][idx]


@pytest.mark.slow
def test_path_length_keeps_the_isometric_hamstring_forces_on_a_finer_model(default_tm):
    """Held at 0 deg, 1x against 2x (`default_model(refine=2)`): along the centre line every hamstring within 6.5 %
    of the 1x limb (measured: long head 1.9 %, short head 3.9 %, semimembranosus 1.9 %, semitendinosus 5.3 %), with
    `chord` further off (2.4 / 5.5 / 3.9 / 10.5 %: its chains straighten further on the finer model; 9-24 % before
    the builder smoothed the finer models' muscle paths, docs/builder.md "Muscle paths")."""
    from tissue_sim.core.builder import default_model
    fine = default_model(refine=2)
    rel = {}
    for mode in ('chord', 'path'):
        coarse_f, fine_f = _isometric_forces(default_tm, mode), _isometric_forces(fine, mode)
        rel[mode] = np.abs(fine_f / coarse_f - 1.0)
        print(f'\n{mode}: 1x {np.round(coarse_f)} N, 2x {np.round(fine_f)} N, |2x/1x - 1| {np.round(rel[mode], 3)}')
    assert rel['path'].max() < 0.065, rel
    assert rel['chord'].max() > 1.5 * rel['path'].max(), rel
