"""The wrap surfaces (stage 4b, contact.wrap_contact; docs/contact.md "Wrap surfaces"): the source model's wrap
cylinders keep the free vertices of the muscles that wrap over them outside."""
import dataclasses

import numpy as np
import pytest

from tissue_sim.core import solver
from tissue_sim.core.solver import contact as C
from tissue_sim.core.solver import phantom
from tissue_sim.core.solver.model import frozen     # read-only, as the model's arrays: no extra compile


def _cylinder_grids(x0, geo, floors=None):
    """ContactGrids without bones and one wrap cylinder (geo: centre, axis, quadrant, radius, length) over every
    vertex at x0 (its floor: the radius, or floors)."""
    x0 = np.atleast_2d(np.asarray(x0, float))
    n = len(x0)
    cg = C.build_grids([], np.zeros(0, np.int32), 5e-4, 0.0, 1.5e-3, x0, -np.ones(n, np.int32))
    g = np.asarray(geo, float)
    return cg._replace(w_seg=frozen([0], np.int32), w_geo=frozen([[*g[:9], g[9], 0.5 * g[10]]]),
                       w_off=frozen([0, n], np.int64), w_idx=frozen(np.arange(n), np.int32),
                       w_floor=frozen(np.full(n, g[9]) if floors is None else floors, float))


def test_vertex_inside_is_moved_radially_and_loses_its_inward_velocity():
    """A cylinder of radius 2 cm about +y through the origin, 10 cm long, wrapping on its +z side only. A vertex 4 mm
    inside on the +z side moves radially onto the surface (its y unchanged), its inward radial velocity is removed
    and the rest kept, and the segment takes -m dv / h at the vertex; one beyond the length, one on the -z side and
    one outside are left alone; one whose floor is 12 mm (inside at rest) goes to 12 mm, not to the radius."""
    x = np.array([[0.015, 0.01, 0.005],          # inside, +z side
                  [0.010, 0.06, 0.005],          # beyond the length (|y| > 5 cm)
                  [0.005, 0.00, -0.010],         # on the -z side: the quadrant leaves it
                  [0.000, 0.00, 0.025],          # outside
                  [0.005, -0.02, 0.010]])        # floor 12 mm, at 11.2 mm
    cg = _cylinder_grids(x, [0, 0, 0, 0, 1, 0, 0, 0, 1, 0.02, 0.1], floors=[0.02, 0.02, 0.02, 0.02, 0.012])
    cw = C.work(cg, 1)
    v = np.tile([-0.3, 0.2, 0.1], (5, 1))
    x1, v1, wr = x.copy(), v.copy(), np.zeros((1, 6))
    m, h = 0.004, 1e-3
    R, t = np.eye(3)[None], np.zeros((1, 3))
    assert C.wrap_contact(h, x1, v1, R, t, cg, cw, frozen(np.full(5, 1.0 / m)), wr) == 2
    n = np.array([0.015, 0.0, 0.005]) / np.hypot(0.015, 0.005)
    assert x1[0] == pytest.approx(0.02 * n + [0, 0.01, 0], abs=1e-12)
    vn = v[0] @ n
    assert vn < 0 and v1[0] == pytest.approx(v[0] - vn * n, abs=1e-12) and abs(v1[0] @ n) < 1e-12
    assert np.hypot(x1[4, 0], x1[4, 2]) == pytest.approx(0.012, abs=1e-12) and x1[4, 1] == -0.02
    assert np.array_equal(x1[1:4], x[1:4]) and np.array_equal(v1[1:4], v[1:4])
    F = -m * ((v1[0] - v[0]) + (v1[4] - v[4])) / h
    assert wr[0, :3] == pytest.approx(F, rel=1e-12)
    M = -m * (np.cross(x1[0], v1[0] - v[0]) + np.cross(x1[4], v1[4] - v[4])) / h
    assert wr[0, 3:] == pytest.approx(M, rel=1e-12)


def test_moving_cylinder_carries_the_vertex_with_its_velocity():
    """The cylinder's segment translates at +2 m/s along x into a vertex at rest just outside: the vertex stays on the
    surface and takes the cylinder's velocity along the radial direction (the velocity relative to the cylinder loses
    its inward part), nothing across it."""
    x = np.array([[0.0205, 0.0, 0.0]])
    cg = _cylinder_grids(x, [0, 0, 0, 0, 1, 0, 0, 0, 0, 0.02, 0.1])
    cw = C.work(cg, 1)
    R, t = np.eye(3)[None], np.zeros((1, 3))
    v = np.zeros((1, 3))
    h, u = 1e-4, 2.0
    for _ in range(20):
        cw.R0[:] = R
        cw.t0[:] = t
        t[0, 0] += h * u
        x += h * v
        C.wrap_contact(h, x, v, R, t, cg, cw, frozen(np.ones(1)), np.zeros((1, 6)))
        assert np.hypot(x[0, 0] - t[0, 0], x[0, 2]) >= 0.02 - 1e-12
    assert v[0, 0] == pytest.approx(u, rel=1e-9) and abs(v[0, 1]) < 1e-12 and abs(v[0, 2]) < 1e-12


def _knee_with_wrap():
    """The knee phantom (hinge at the origin about +y; hamstring column 4 cm behind, quadriceps 4 cm in front, r 1.5
    cm) with a wrap cylinder of radius 3 cm about the knee axis on the thigh for the quadriceps: at rest one quadriceps
    vertex lies inside (5 mm), and as the hamstring flexes the knee the quadriceps' free middle is pulled round it."""
    tm = phantom.knee(n_gaps=12, knee_range_deg=(0.0, 90.0))
    return dataclasses.replace(tm, wrap_names=('quadriceps_at_knee',), wrap_segment=np.array([0], np.int32),
                               wrap_geometry=np.array([[0, 0, 0, 0, 1, 0, 0, 0, 0, 0.03, 0.1]], float),
                               wrap_muscle_offsets=np.array([0, 1], np.int64), wrap_muscles=np.array([1], np.int32))


def _radial(sim, st):
    """Each wrap vertex's distance from the cylinder's axis (in the thigh's frame)."""
    cg = sim.contact
    p = (st.x[cg.w_idx] - st.seg_t[0]) @ st.seg_R[0]
    return np.hypot(p[:, 0], p[:, 2])


def test_fast_step_matches_the_reference_step_with_a_wrap_surface():
    """With the wrap surface on, step() (contact.wrap_contact, compiled) and reference_step (reference.wrap_stage,
    numpy) give the same trajectory on the knee phantom while the quadriceps is pulled round the cylinder; every wrap
    vertex stays at or beyond its floor. Without the surface the same motion takes them 8 mm or more inside it.
    Tolerance as the bone contact's reference test: 1e-8 of the motion."""
    tm = _knee_with_wrap()
    sim = solver.compile_model(tm, solver.Params.paper(rotation_iterations=50, wrap_surfaces='all'))
    off = solver.compile_model(tm, solver.Params.paper(rotation_iterations=50))
    assert sim.contact.w_seg.tolist() == [0] and off.contact.w_seg.size == 0
    cg = sim.contact
    assert np.sum(cg.w_floor < 0.03) == 1 and cg.w_floor.min() == pytest.approx(0.025)      # inside at rest
    fast, ref, free = solver.make_state(sim), solver.make_state(sim), solver.make_state(off)
    ctrl = solver.make_control(sim)
    ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    low, low_off, on_floor = np.inf, np.inf, 0
    for _ in range(300):
        solver.step(sim, fast, ctrl)
        solver.reference_step(sim, ref, ctrl.activation)
        solver.step(off, free, ctrl)
        gap = _radial(sim, fast) - cg.w_floor
        low = min(low, gap.min())
        on_floor = max(on_floor, int(np.sum(np.abs(gap) < 1e-9)))
        low_off = min(low_off, (_radial(sim, free) - cg.w_floor).min())
    assert fast.q[0] > 0.5                                           # the knee flexed
    motion = np.abs(fast.x - sim.rest).max()
    assert np.abs(fast.x - ref.x).max() <= 1e-8 * motion
    assert np.allclose(fast.q, ref.q, rtol=1e-8, atol=1e-10)
    assert low > -1e-9 and on_floor >= 3                           # held on the surface, not inside
    assert low_off < -8e-3                                          # without it: well inside


def test_wrap_surfaces_of_the_bundled_limb(default_tm):
    """The bundled limb carries its source model's wrap cylinders; the physical set uses KnExt_at_fem_r (on the
    thigh) for the free vertices of the four quadriceps' cells and ST_at_condyles_r (on the shank) for
    semitendinosus', the paper set none; 'all' every surface; a name the model does not have, none."""
    tm = default_tm
    names = list(tm.wrap_names)
    cg = solver.compile_model(tm, solver.Params.physical()).contact
    expect = {'KnExt_at_fem_r': ('thigh', ['rectus_femoris', 'vastus_intermedius', 'vastus_lateralis', 'vastus_medialis']),
              'ST_at_condyles_r': ('shank', ['semitendinosus'])}
    assert cg.w_seg.size == 2
    for k, (name, (seg, muscles)) in enumerate(expect.items()):
        w = names.index(name)
        mus = tm.wrap_muscles[tm.wrap_muscle_offsets[w]:tm.wrap_muscle_offsets[w + 1]]
        assert sorted(tm.muscle_names[m] for m in mus) == muscles
        assert cg.w_seg[k] == list(tm.segment_names).index(seg) == tm.wrap_segment[w]
        cells = np.flatnonzero(np.isin(tm.cell_muscle, mus))
        verts = np.unique(np.concatenate([tm.cell_vertices[tm.cell_offsets[c]:tm.cell_offsets[c + 1]] for c in cells]))
        verts = verts[(tm.vertex_segment[verts] < 0) & ~np.isin(verts, tm.via_point_vertices)]
        idx = cg.w_idx[cg.w_off[k]:cg.w_off[k + 1]]
        assert np.array_equal(np.sort(idx), verts)
        floor = cg.w_floor[cg.w_off[k]:cg.w_off[k + 1]]
        assert np.all(floor <= tm.wrap_geometry[w, 9]) and np.all(floor > 0)
    assert solver.compile_model(tm, solver.Params.paper()).contact.w_seg.size == 0
    assert solver.compile_model(tm, solver.Params.physical(wrap_surfaces='all')).contact.w_seg.size == len(names)
    assert solver.compile_model(tm, solver.Params.physical(wrap_surfaces='no_such_wrap')).contact.w_seg.size == 0
