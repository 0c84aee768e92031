"""Bone contact (core/solver/contact.py, docs/contact.md): the signed-distance grid against exact
distances of known meshes, the projection kernel on analytic cases (a vertex falling onto a sphere
or a box bone, a bone moving into a vertex, friction), the broad phase giving the same result as
testing every vertex every sub-step, the fast step against reference_step with contact on (a knee
phantom whose tissue hits its bones), constants in the model and buffers per State, and on the bundled
limb (slow): no free vertex more than 1 mm inside a bone over an active 0-120 deg flexion and a passive
sweep, where without contact there are."""
import dataclasses
import math

import numpy as np
import pytest
import trimesh

from tissue_sim.core import solver
from tissue_sim.core.builder.bones import winding_number
from tissue_sim.core.model import JOINT_HINGE, TISSUE_FAT, TISSUE_MUSCLE
from tissue_sim.core.solver import contact as C, phantom
from tissue_sim.core.solver.model import frozen     # read-only, as the model's arrays: no extra compile

H = 1.5e-3          # grid spacing of the tests [m]
MARGIN = 5e-4


def _exact_signed(V, T, P):
    """Signed distance (negative inside) of points P to mesh (V, T): brute-force closest point over
    every triangle (trimesh) and the generalised winding number (builder) for the sign."""
    tri = V[T]
    Q = np.repeat(P, len(T), axis=0)
    cp = trimesh.triangles.closest_point(np.tile(tri, (len(P), 1, 1)), Q)
    d = np.linalg.norm(cp - Q, axis=1).reshape(len(P), len(T)).min(1)
    return np.where(winding_number(V, T, P) > 0.5, -d, d)


def _sphere(r=0.02, centre=(0.0, 0.0, 0.0)):
    m = trimesh.creation.icosphere(subdivisions=3, radius=r)
    return np.asarray(m.vertices) + np.asarray(centre), np.asarray(m.faces)


def _box(ext=(0.04, 0.03, 0.05)):
    m = trimesh.creation.box(extents=ext)
    return np.asarray(m.vertices, float), np.asarray(m.faces)


def _grid_values(cg, b, P):
    d = np.empty(len(P))
    g = np.empty((len(P), 3))
    C.sample_grid(cg.g_origin, cg.g_inv_h, cg.g_dims, cg.g_off, cg.g_phi, b, np.ascontiguousarray(P), d, g)
    return d, g


@pytest.mark.parametrize('shape', ['sphere', 'box'])
def test_sdf_grid_matches_exact_distances(shape):
    """Trilinear samples of the grid at random points within 2 cells of the surface (every corner of
    their cell in the exact band) are within 0.3 cell of the exact signed distance (sphere: within
    0.1 cell), with the right sign beyond one cell; further out within 1.5 cells; the gradient is the
    exact surface normal direction to within 10 deg on the sphere."""
    V, T = _sphere() if shape == 'sphere' else _box()
    tup = C.build_grids([(V, T)], np.array([0]), MARGIN, 0.0, H, np.zeros((0, 3)), np.zeros(0, np.int32))
    rng = np.random.default_rng(1)
    lo, hi = V.min(0) - 4 * H, V.max(0) + 4 * H
    P = rng.uniform(lo, hi, size=(4000, 3))
    exact = _exact_signed(V, T, P)
    near = np.abs(exact) < 2 * H
    d, g = _grid_values(tup, 0, P)
    err = np.abs(d[near] - exact[near])
    assert near.sum() > 500
    assert err.max() < (0.1 if shape == 'sphere' else 0.3) * H, err.max() / H
    far = np.abs(exact) > H
    assert np.all(np.sign(d[far]) == np.sign(exact[far]))
    # beyond the band the grid keeps the sign and stays within about a cell
    band_out = (np.abs(exact) > 2 * H) & np.isfinite(d)
    assert np.all(np.abs(d[band_out] - exact[band_out]) < 1.5 * H)
    if shape == 'sphere':
        sel = near & (np.linalg.norm(P, axis=1) > 0.005)
        radial = P[sel] / np.linalg.norm(P[sel], axis=1)[:, None]
        assert np.degrees(np.arccos(np.clip(np.sum(g[sel] * radial, axis=1), -1, 1))).max() < 10


def _single(meshes, bone_segment, x0, friction=0.0, n_segments=1):
    """(ContactGrids, ContactWork) for free vertices at x0 (their rest positions: outside every bone)."""
    x0 = np.atleast_2d(np.asarray(x0, float))
    cg = C.build_grids(meshes, np.asarray(bone_segment), MARGIN, friction, H, x0, -np.ones(len(x0), np.int32))
    return cg, C.work(cg, n_segments)


def _pose(S):
    return np.tile(np.eye(3), (S, 1, 1)), np.zeros((S, 3))


@pytest.mark.parametrize('friction', [0.0, 0.3])
def test_vertex_falling_onto_sphere_stays_outside(friction):
    """A vertex moving down at 1 m/s with a tangential 0.2 m/s onto a sphere bone of radius 2 cm (an
    icosphere mesh): after every sub-step it is outside the mesh, at the margin (within 0.05 mm, exact
    mesh distance) once in contact; at the contact its inward normal velocity is gone and the
    tangential velocity is kept (frictionless) or reduced by mu x |v_n| (Coulomb)."""
    V, T = _sphere()
    x = np.array([[0.0, 0.0, 0.03]])
    tup, cw = _single([(V, T)], [0], x, friction)
    seg_R, seg_t = _pose(1)
    v = np.array([[0.2, 0.0, -1.0]])
    h = 1e-4
    first = None
    for k in range(300):
        vin = v.copy()
        x += h * v
        hit = C.bone_contact(h, x, v, seg_R, seg_t, tup, cw, frozen(np.ones(len(x))), np.zeros((len(seg_R), 6)))
        d = _exact_signed(V, T, x)[0]
        assert d > MARGIN - 5e-5, (k, d)
        if hit and first is None:
            first = k
            assert abs(d - MARGIN) < 5e-5
            n = _grid_values(tup, 0, x)[1][0]     # the grid's normal where the projection put it (~ the one used)
            vn_in = vin[0] @ n
            vt_in = vin[0] - vn_in * n
            assert vn_in < -0.5 and abs(v[0] @ n) < 1e-3 * abs(vn_in)   # normal velocity removed
            vt = v[0] - (v[0] @ n) * n
            expect = np.linalg.norm(vt_in) * max(0.0, 1 - friction * abs(vn_in) / np.linalg.norm(vt_in))
            assert np.linalg.norm(vt) == pytest.approx(expect, rel=1e-3, abs=1e-4)
    assert first is not None
    assert np.linalg.norm(v) < 0.3                    # it slides off with its tangential speed at the contact (0.27 m/s)


def test_vertex_pushed_into_box_leaves_along_face_normal():
    """A vertex placed 3 mm inside the top face of a box bone (far from its edges) is projected to
    the margin above the face, straight up (x, y unchanged), its downward velocity removed."""
    V, T = _box()
    top = V[:, 2].max()
    tup, cw = _single([(V, T)], [0], [[0.003, -0.002, top + 0.01]])
    seg_R, seg_t = _pose(1)
    x = np.array([[0.003, -0.002, top - 0.003]])
    v = np.array([[0.1, 0.0, -0.5]])
    wr = np.zeros((1, 6))
    m, h = 0.004, 1e-3                       # [kg] the vertex's mass (1 / the integrator's inv_den), [s]
    assert C.bone_contact(h, x, v, seg_R, seg_t, tup, cw, frozen([1.0 / m]), wr) == 1
    assert x[0, 2] == pytest.approx(top + MARGIN, abs=2e-5)
    assert x[0, :2] == pytest.approx([0.003, -0.002], abs=1e-6)
    assert v[0] == pytest.approx([0.1, 0.0, 0.0], abs=1e-3)
    # the bone takes the reaction: the vertex gained m dv = m (0, 0, 0.5) in the sub-step, so the bone gets
    # -m dv / h = 2 N downwards at the vertex, with its moment about the origin
    F = np.array([0.0, 0.0, -0.5 * m / h])
    assert wr[0, :3] == pytest.approx(F, abs=1e-3 * 2.0)
    assert wr[0, 3:] == pytest.approx(np.cross(x[0], F), abs=1e-6)


def test_moving_bone_pushes_vertex_with_its_velocity():
    """A box bone on segment 1 translating at +2 m/s along x into a vertex at rest in front of its
    +x face: the vertex is kept at the margin in front of it and takes the bone's velocity along the
    face normal (the relative velocity, not the world velocity, loses its inward part), nothing
    across it. The segment pose before the sub-step is (R0, t0)."""
    V, T = _box()
    x = np.array([[V[:, 0].max() + 0.0015, 0.002, -0.003]])
    tup, cw = _single([(V, T)], [1], x, n_segments=2)
    seg_R, seg_t = _pose(2)
    v = np.zeros((1, 3))
    h, u = 1e-4, 2.0
    for k in range(20):
        cw.R0[:] = seg_R
        cw.t0[:] = seg_t                       # the pose at the sub-step's start (advance: forward kinematics of q0)
        seg_t[1, 0] += h * u
        x += h * v
        C.bone_contact(h, x, v, seg_R, seg_t, tup, cw, frozen(np.ones(len(x))), np.zeros((len(seg_R), 6)))
        assert _exact_signed(V, T, x - seg_t[1])[0] > MARGIN - 5e-5
    assert abs(_exact_signed(V, T, x - seg_t[1])[0] - MARGIN) < 5e-5
    assert v[0, 0] == pytest.approx(u, rel=1e-3)
    assert abs(v[0, 1]) < 1e-3 and abs(v[0, 2]) < 1e-3


def test_broad_phase_gives_the_result_of_a_full_pass_every_substep():
    """Vertices in a random walk about two bones on two moving segments: the broad phase (tests only
    vertices that may have used up their slack) gives bit-identical positions and velocities to
    testing every vertex every sub-step (slack reset to 0), while testing far fewer vertices."""
    rng = np.random.default_rng(3)
    meshes = [_sphere(r=0.015), _box((0.02, 0.02, 0.03))]
    meshes[1] = (meshes[1][0] + [0.04, 0.0, 0.0], meshes[1][1])
    x0 = np.concatenate([rng.normal(0, 0.012, (150, 3)) * [2, 1, 1] + [0.02, 0, 0]])
    d = np.min([_exact_signed(V, T, x0) for V, T in meshes], axis=0)
    x0 = x0[d > 2e-3]
    runs = []
    for full in (False, True):
        tup, cw = _single(meshes, [0, 1], x0, n_segments=2)
        seg_R, seg_t = _pose(2)
        x, v = x0.copy(), np.zeros_like(x0)
        r = np.random.default_rng(5)
        for k in range(400):
            cw.R0[:] = seg_R
            cw.t0[:] = seg_t
            ang = 0.002 * k
            seg_R[1] = [[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1]]
            seg_t[1] = [0.0, 0.0, 0.0005 * math.sin(0.05 * k)]
            v += r.normal(0, 0.3, v.shape)
            v *= 0.9
            x += 1e-4 * v * 10
            if full:
                cw.slack[:] = 0.0              # every vertex tested against every grid
            C.bone_contact(1e-3, x, v, seg_R, seg_t, tup, cw, frozen(np.ones(len(x))), np.zeros((len(seg_R), 6)))
        runs.append((x, v, cw.stats.copy()))
    (xa, va, sa), (xb, vb, sb) = runs
    assert xa.tobytes() == xb.tobytes() and va.tobytes() == vb.tobytes()
    assert sa[1] < 0.5 * sb[1]


def test_contact_off_in_the_paper_set_on_in_the_physical_set(default_tm):
    assert solver.Params.paper().bone_contact is False
    assert solver.Params.physical().bone_contact is True
    sim = solver.compile_model(default_tm, solver.Params.paper())
    assert sim.contact.g_seg.shape == (0,)
    sim = solver.compile_model(default_tm, solver.Params.physical())
    assert sorted(sim.contact.g_seg.tolist()) == sorted(set(default_tm.bone_segment.tolist()))   # one grid per segment with bones
    with pytest.raises(ValueError, match='contact_margin'):
        solver.Params.physical(contact_margin=-1.0)


# ----------------------------------------------------------------------------------- in the step
def _knee_with_bones():
    """The knee phantom (hamstring column 4 cm behind the hinge, quadriceps 4 cm in front, r 1.5 cm) with bones:
    a sphere of radius 2.2 cm at the knee centre on the thigh (segment 0, fixed) and a box 2 x 2 x 9 cm below the
    knee on the shank (segment 1, moving). At rest the columns clear them by 3 mm; as the hamstring pulls the
    shank into flexion its free middle cuts the corner into the sphere."""
    tm = phantom.knee(n_gaps=12, knee_range_deg=(0.0, 90.0))
    Vs, Ts = _sphere(r=0.022)
    Vb, Tb = _box((0.02, 0.02, 0.09))
    Vb = Vb + [0.0, 0.0, -0.075]
    return dataclasses.replace(
        tm, bone_names=('femur', 'tibia'), bone_segment=np.array([0, 1], np.int32),
        bone_vertex_offsets=np.array([0, len(Vs), len(Vs) + len(Vb)], np.int64),
        bone_vertices=np.concatenate([Vs, Vb]).astype(np.float64),
        bone_triangle_offsets=np.array([0, len(Ts), len(Ts) + len(Tb)], np.int64),
        bone_triangles=np.concatenate([Ts, Tb]).astype(np.int32))


@pytest.mark.parametrize('friction', [0.0, 0.3])
def test_fast_step_matches_the_reference_step_with_contact(friction):
    """With contact on, step() (the compiled stage with its broad phase) and reference_step (every free vertex
    tested every sub-step, in numpy) give the same trajectory on the knee phantom with bones while tissue is
    projected out of both bones (the fixed sphere and the moving box); without contact it enters both.
    Tolerances: the positions as tests/test_solver_reference.py's default-model test (1e-8 of the motion), the
    velocities 1e-6 of the largest: a projection's velocity change is discontinuous in the position, so rounding
    differences grow faster than without contact (measured over these 300 steps: positions 6e-10 m of 0.17 m of
    motion, velocities 1e-7 m/s of 1.7 m/s frictionless, 3e-10 m and 2.3e-7 m/s with friction; without contact
    1e-13 and 1e-11). Frictionless and with Coulomb friction 0.3."""
    tm = _knee_with_bones()
    closest = {}
    for on in (True, False):
        sim = solver.compile_model(tm, solver.Params.paper(rotation_iterations=50, bone_contact=True,
                                                           contact_friction=friction))
        if not on:
            sim_off = solver.compile_model(tm, solver.Params.paper(rotation_iterations=50))
        fast, ref = solver.make_state(sim if on else sim_off), solver.make_state(sim)
        ctrl = solver.make_control(sim)
        ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
        low = np.full(2, np.inf)
        for _ in range(300):
            solver.step(sim if on else sim_off, fast, ctrl)
            if on:
                solver.reference_step(sim, ref, ctrl.activation)
            low = np.minimum(low, C.signed_distances(sim, fast.x[sim.free_idx], fast.seg_R, fast.seg_t).min(0))
        closest[on] = low
        if on:
            assert fast.q[0] > 0.5                                    # the knee flexed (about 1 rad)
            motion = np.abs(fast.x - sim.rest).max()
            assert np.abs(fast.x - ref.x).max() <= 1e-8 * motion
            assert np.abs(fast.v - ref.v).max() <= 1e-6 * np.abs(ref.v).max()
            assert np.allclose(fast.q, ref.q, rtol=1e-8, atol=1e-10)
            stats = fast.workspace.contact.stats
            assert stats[0] == 300 and stats[1] < 0.1 * 300 * 2 * sim.free_idx.size    # the broad phase skipped most
    # touched both and stayed outside: at the margin to within 0.1 mm (measured closest: 0.499 mm from the sphere,
    # 0.468 mm from the box, at its edges where the interpolated gradient is not the exact normal)
    assert np.all(closest[True] > MARGIN - 1e-4) and np.all(closest[True] < MARGIN)
    assert np.all(closest[False] < -2e-3), closest[False]                              # without contact: inside both


def test_grids_are_model_constants_and_buffers_belong_to_each_state():
    """The grids are read-only arrays of the SimModel; the broad-phase records and pose buffers live in each
    State's workspace: two states stepping one model share no memory, and stepping one leaves the other's
    records untouched (its result is that of a state stepped alone)."""
    sim = solver.compile_model(_knee_with_bones(), solver.Params.paper(bone_contact=True))
    assert all(not a.flags.writeable for a in sim.contact) and sim.contact.g_seg.tolist() == [0, 1]
    ctrl = solver.make_control(sim)
    ctrl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    a, b, alone = solver.make_state(sim), solver.make_state(sim), solver.make_state(sim)
    for k in range(150):
        solver.step(sim, a, ctrl)
        if k % 2 == 0:                          # b and alone: half as often, interleaved with a
            solver.step(sim, b, ctrl)
    for _ in range(75):
        solver.step(sim, alone, ctrl)
    wa, wb = a.workspace.contact, b.workspace.contact
    assert all(not np.shares_memory(x, y) for x, y in zip(wa, wb))
    assert b.x.tobytes() == alone.x.tobytes() and b.v.tobytes() == alone.v.tobytes()
    assert wb.stats.tolist() == alone.workspace.contact.stats.tolist()
    assert a.copy().workspace is None


# ----------------------------------------------------------------------------------- bundled limb
def _knee(sim):
    tm = sim.tissue
    return [j for j, n in enumerate(tm.joint_names) if 'knee' in n and tm.joint_type[j] == JOINT_HINGE][0]


def _deep(sim, st):
    """Free vertices more than 1 mm inside a bone (measured on the bone meshes) and the deepest [m]."""
    pen = C.mesh_penetration(sim, st)
    return sum(v[1] for v in pen.values()), max(v[2] for v in pen.values())


@pytest.fixture(scope='module')
def limb_runs(default_tm):
    """Physical set, contact on and off: full hamstring activation for 1.5 s (the knee reaches its
    120-deg stop between 0.5 and 1 s), and a passive sweep 0-120 deg (the knee driven at 100 deg/s,
    then held 0.5 s); (deep count, deepest, inverted cells) every 0.25 s / 20 deg; and in the active run
    (time [s], inverted cells) every 25 ms ('active_fine')."""
    out = {}
    for on in (True, False):
        sim = solver.compile_model(default_tm, solver.Params.physical(bone_contact=on))
        j = _knee(sim)
        rows, fine = [], []
        st, ctl = solver.make_state(sim), solver.make_control(sim)
        ctl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
        for _ in range(6):
            for _ in range(10):
                solver.step(sim, st, ctl, n_steps=25)
                fine.append((st.step * sim.params.dt, C.inverted_cells(sim, st.x)[0]))
            rows.append((math.degrees(st.q[j]),) + _deep(sim, st) + (fine[-1][1],))
        active = rows
        rows = []
        st, ctl = solver.make_state(sim), solver.make_control(sim)
        q, qd = st.q.copy(), np.zeros_like(st.q)
        rate = math.radians(100.0)
        n = int(round(math.radians(120.0) / rate / sim.params.dt))
        for i in range(1, n + 1 + 500):
            q[j] = rate * sim.params.dt * min(i, n)
            qd[j] = rate if i <= n else 0.0
            solver.set_joint_positions(sim, st, q, qd)
            solver.step(sim, st, ctl)
            if i % 200 == 0 or i == n + 500:
                rows.append((math.degrees(st.q[j]),) + _deep(sim, st) + (C.inverted_cells(sim, st.x)[0],))
        out[on] = dict(active=active, passive=rows, active_fine=fine)
    return out


@pytest.mark.slow
@pytest.mark.parametrize('run', ['active', 'passive'])
def test_no_free_vertex_deeper_than_1mm_in_a_bone(limb_runs, run):
    """The issue's criterion over an active 0-120 deg flexion and a passive sweep; without contact
    (the old behaviour) dozens of free vertices lie more than 1 mm inside the femur and tibia."""
    rows = limb_runs[True][run]
    assert max(r[0] for r in rows) > 119.0                    # the knee went through 0-120 deg
    assert all(r[1] == 0 for r in rows), rows
    assert max(r[2] for r in rows) < 1e-3
    off = limb_runs[False][run]
    assert max(r[1] for r in off) > 20 and max(r[2] for r in off) > 5e-3


@pytest.mark.slow
def test_inverted_cells_with_contact_are_the_measured_known_ones(limb_runs, default_tm):
    """Measured (docs/contact.md "Ankle fat"): with contact, the physical set's fat volume term (volume_stiffness_fat
    20) and its fat damping (damping_ratio_fat 2.0), no fat cell is inverted at any recorded instant of either run
    (the active run every 25 ms through the knee's 120-deg stop), and no cell at all at the end of either. What may
    remain: muscle cells bound to two segments at once (a volume term cannot move bound vertices; before the
    builder's fix of the knee binding, vastus medialis cell 60 was one). With the fat damped like muscle
    (damping_ratio_fat -1, i.e. 0.3) fat cell 380 in front of the ankle is inverted from 0.6 to 0.9 s (V/V0 down to
    -0.36, `bench/contact.py --ankle --set damping_ratio_fat=-1`): this test then fails."""
    tm = default_tm
    vs = np.asarray(tm.vertex_segment)
    runs = limb_runs[True]
    for run, rows in (('active', runs['active_fine']), ('passive', [(r[0], r[3]) for r in runs['passive']])):
        for k, r in enumerate(rows):
            for c in r[1]:
                ids = tm.cell_vertices[tm.cell_offsets[c]:tm.cell_offsets[c + 1]]
                segs = set(vs[ids].tolist()) - {-1}
                bound_across = tm.cell_tissue[c] == TISSUE_MUSCLE and len(segs) >= 2
                assert bound_across, (run, k, c, segs)
        assert len(rows[-1][1]) == 0, (run, rows[-1][1])
    assert len(runs['active_fine']) == 60 and abs(runs['active_fine'][-1][0] - 1.5) < 1e-9


@pytest.mark.parametrize('tissue', [TISSUE_FAT, TISSUE_MUSCLE])
def test_damping_ratio_fat_sets_the_fat_cells_deformation_damping(tissue):
    """damping_ratio_fat (docs/solver.md "Damping"; physical 2.0, docs/contact.md "Ankle fat") is a fat cell's zeta;
    < 0 (the paper set) leaves it at damping_ratio; a muscle cell keeps damping_ratio whatever it is."""
    tm = phantom.one_cell(6, tissue=tissue)
    b = {z: solver.compile_model(tm, solver.Params.paper(damping_ratio=0.3, damping_ratio_fat=z)).damp_b
         for z in (-1.0, 2.0)}
    plain = {z: solver.compile_model(tm, solver.Params.paper(damping_ratio=z)).damp_b for z in (0.3, 2.0)}
    assert np.array_equal(b[-1.0], plain[0.3]) and plain[2.0][0] > 6.0 * plain[0.3][0] > 0
    assert np.array_equal(b[2.0], plain[2.0] if tissue == TISSUE_FAT else plain[0.3])
    assert solver.Params.paper().damping_ratio_fat < 0 and solver.Params.physical().damping_ratio_fat == 2.0
    with pytest.raises(ValueError, match='damping_ratio_fat'):
        solver.Params.paper(damping_ratio_fat=float('nan'))
