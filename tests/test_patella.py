"""The moving patella (issue 19 item 4): the patella is its own segment on the coupled joint
patellofemoral_r, posed by a cubic spline of the knee angle through the table joints.yaml holds
(tools/anatomy/patella.py samples the source model's patellofemoral path).

* its pose equals the source model's, evaluated by the opensim engine, between the table's rows;
* it stays in the femoral groove over 0-120 deg, measured on the bone meshes;
* the coupled joint is energy-consistent: its tissue forces act on the knee by virtual work (the lock
  torque equals f . dx/dtheta by finite differences of the forward kinematics), and a knee swinging
  under gravity with a heavy coupled segment keeps its energy;
* on the bundled model the hamstrings still flex the knee and the quadriceps, inserting on the
  patella, extend it (their torque through the coupling has the extensor sign)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tissue_sim.core import model as M
from tissue_sim.core import solver
from tissue_sim.core.solver import phantom
from tissue_sim.core.solver import skeleton as SK
from tissue_sim.core.solver.measures import skeleton_energy
from tissue_sim.core.solver.model import frozen     # read-only, as the model's arrays: no extra compile


@pytest.fixture(scope='module')
def tm(default_tm):
    return default_tm


@pytest.fixture(scope='module')
def sim(tm):
    return solver.compile_model(tm, solver.Params.physical())


def _posed(sim, deg):
    st = solver.make_state(sim)
    q = np.zeros(sim.n_joints)
    q[sim.tissue.joint_names.index('knee_r')] = math.radians(deg)
    solver.set_joint_positions(sim, st, q)
    return st


def test_bundled_model_has_the_coupled_patella(tm):
    j = tm.joint_names.index('patellofemoral_r')
    s = tm.segment_names.index('patella')
    assert tm.joint_type[j] == M.JOINT_COUPLED and tm.joint_child[j] == s
    assert tm.segment_names[tm.segment_parent[s]] == 'thigh'
    assert tm.joint_names[tm.joint_driver[j]] == 'knee_r'
    assert tm.bone_segment[tm.bone_names.index('patella')] == s
    assert np.count_nonzero(tm.vertex_segment == s) > 10          # tissue bound to the patella
    # the quadriceps insert on the patella (tissues.yaml), the hamstrings on the shank
    anchors = tm.meta['anchors']
    for m in ('rectus_femoris', 'vastus_medialis', 'vastus_intermedius'):
        assert anchors[m]['insertion'][0] == 'patella' and anchors[m]['insertion'][1] > 0, m
    assert anchors['semimembranosus']['insertion'][0] == 'shank'


def test_patella_pose_matches_opensim_between_the_table_rows(tm, sim):
    """The solver's patella (spline through the 5-deg table) against the opensim engine on the source
    model, at angles between the rows: every patella mesh vertex within 0.01 mm (measured: 0.6 um at
    47.5 deg over every 2.5-deg midpoint)."""
    pytest.importorskip('Pose2Sim')
    from tissue_sim.core import validation as V
    try:
        osim_mod = V._import_opensim
    except AttributeError:                                  # pragma: no cover
        pytest.skip('no opensim import helper')
    try:
        path = V.source_model_path()
    except V.ValidationError as e:
        pytest.skip(str(e))
    pb = tm.bone_names.index('patella')
    ps = int(tm.bone_segment[pb])
    PV = tm.bone_mesh(pb)[0]
    A = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])      # OpenSim femur frame -> model frame
    angles = [2.5, 12.0, 27.5, 46.0, 63.0, 88.0, 101.5, 117.5, 120.0]
    ref = []
    with V._environment_kept():
        try:
            osim = osim_mod()
        except ImportError:
            pytest.skip('opensim not installed (requirements/validation.txt)')
        osim.Logger.setLevelString('warn')
        model = osim.Model(str(path))
        state = model.initSystem()
        coord = model.getCoordinateSet().get('knee_angle_r')
        fem, pat = model.getBodySet().get('femur_r'), model.getBodySet().get('patella_r')

        def pose(body):
            X = body.getTransformInGround(state)
            return (np.array([[X.R().get(i, k) for k in range(3)] for i in range(3)]),
                    np.array([X.p().get(i) for i in range(3)]))
        for deg in [0.0] + angles:
            coord.setValue(state, math.radians(deg))
            model.realizePosition(state)
            (Rf, pf), (Rp, pp) = pose(fem), pose(pat)
            ref.append((Rf.T @ Rp, Rf.T @ (pp - pf)))            # patella in the femur frame
    (R0, p0), worst = ref[0], 0.0
    for deg, (R, p) in zip(angles, ref[1:]):
        # a rest vertex X (OpenSim body coordinates b = R0^T (A^T X - p0)) at the OpenSim pose
        b = (PV @ A - p0) @ R0
        want = (b @ R.T + p) @ A.T
        st = _posed(sim, deg)
        got = PV @ st.seg_R[ps].T + st.seg_t[ps]
        err = np.linalg.norm(got - want, axis=1).max()
        worst = max(worst, err)
        assert err < 1e-5, f'{deg} deg: patella {err * 1e3:.4f} mm from OpenSim'
    assert worst > 0.0


def test_patella_stays_in_the_femoral_groove(tm, sim):
    """On the bone meshes over 0-120 deg: the patella's centre (mean of its mesh vertices) 8-20 mm from
    the femur's surface (its thickness is ~20 mm: it rides on the trochlea, then the condyles), the
    nearest femur point in the middle 30-70 % of the condyles' medio-lateral width (the groove and the
    intercondylar notch), the centre at most 5 mm behind the knee axis (the source model's path puts it 2.9 mm behind
    the hinge's fitted centre at 120 deg, 5.6 mm behind the walker knee's instantaneous centre there; in front of it
    to 110 deg) and at most 5 % of the patella's mesh
    vertices inside the femur, none deeper than 5 mm (measured: at most 3 of 72, 4.1 mm deep at 60 deg; the
    pose is the source model's to 0.01 mm, so its meshes overlap alike). (Rigid with the
    shank, as before, the centre was 31 mm below the femur at 120 deg, behind the knee axis.)"""
    import trimesh
    from tissue_sim.core.builder.bones import winding_number
    FV, FT = tm.bone_mesh(tm.bone_names.index('femur'))
    pb = tm.bone_names.index('patella')
    PV = tm.bone_mesh(pb)[0]
    ps = int(tm.bone_segment[pb])
    kj = tm.joint_names.index('knee_r')
    centre = tm.joint_centre[kj]
    distal = FV[FV[:, 2] < centre[2] + 0.06]
    ylo, yhi = distal[:, 1].min(), distal[:, 1].max()
    tri = FV[FT]

    def nearest(Q):
        Qr = np.repeat(Q, len(FT), axis=0)
        cp = trimesh.triangles.closest_point(np.tile(tri, (len(Q), 1, 1)), Qr)
        d = np.linalg.norm(cp - Qr, axis=1).reshape(len(Q), len(FT))
        k = d.argmin(1)
        return d[np.arange(len(Q)), k], cp.reshape(len(Q), len(FT), 3)[np.arange(len(Q)), k]
    for deg in range(0, 121, 10):
        st = _posed(sim, deg)
        P = PV @ st.seg_R[ps].T + st.seg_t[ps]
        c = P.mean(0)
        d, cp = nearest(c[None])
        assert 0.008 < d[0] < 0.020, f'{deg} deg: patella centre {d[0] * 1e3:.1f} mm from the femur'
        frac = (cp[0, 1] - ylo) / (yhi - ylo)
        assert 0.3 < frac < 0.7, f'{deg} deg: nearest femur point at {frac:.2f} of the condyles\' width'
        assert c[0] > centre[0] - 0.005, f'{deg} deg: patella centre {1e3 * (centre[0] - c[0]):.1f} mm behind the knee axis'
        inside = winding_number(FV, FT, P) > 0.5
        assert inside.sum() <= 0.05 * len(P), f'{deg} deg: {inside.sum()} patella vertices inside the femur'
        if inside.any():
            assert nearest(P[inside])[0].max() < 0.005


# ------------------------------------------------------------------------- the coupled joint on a phantom
def knee_with_patella(patella_mass=0.5):
    """The knee phantom with a coupled 'patella' (a leaf under the thigh, its path an analytic table in the
    knee angle, exaggerated mass) onto which the quadriceps column's bottom ring is bound."""
    tm = phantom.knee()
    th = np.radians(np.arange(0, 121, 10.0))
    rows = np.column_stack([th, 0.8 * th, 0.05 * (np.cos(th) - 1) - 0.01 * th, 0.002 * np.sin(th), -0.03 * np.sin(th)])
    vseg = np.array(tm.vertex_segment)
    qv = np.unique(np.concatenate([tm.cell(c) for c in np.flatnonzero(tm.cell_muscle == 1)]))
    vseg[qv[tm.rest_positions[qv, 2] < tm.rest_positions[qv, 2].min() + 1e-9]] = 2
    return dataclasses.replace(
        tm, vertex_segment=vseg,
        segment_names=tm.segment_names + ('patella',), segment_parent=np.append(tm.segment_parent, 0).astype(np.int32),
        segment_mass=np.append(tm.segment_mass, patella_mass),
        segment_com=np.vstack([tm.segment_com, [[0.05, 0, 0.01]]]),
        segment_inertia=np.concatenate([tm.segment_inertia, [np.diag([2e-3, 3e-3, 1e-3])]]),
        joint_names=tm.joint_names + ('patellofemoral_r',),
        joint_type=np.append(tm.joint_type, M.JOINT_COUPLED).astype(np.uint8),
        joint_parent=np.append(tm.joint_parent, 0).astype(np.int32), joint_child=np.append(tm.joint_child, 2).astype(np.int32),
        joint_axis=np.vstack([tm.joint_axis, [[0.0, 1.0, 0.0]]]), joint_centre=np.vstack([tm.joint_centre, [[0.05, 0, 0.0]]]),
        joint_range=np.vstack([tm.joint_range, [[0, rows[:, 1].max()]]]), joint_rest=np.append(tm.joint_rest, 0.0),
        joint_driver=np.array([-1, 0], np.int32), coupling_offsets=np.array([0, 0, len(rows)], np.int64),
        coupling_table=rows, joint_path_offsets=np.zeros(3, np.int64), joint_path_axes=np.zeros((2, 2, 3)),
        path_powers=np.column_stack([tm.path_powers, np.zeros(len(tm.path_powers), np.int32)])).validate()


@pytest.fixture(scope='module')
def psim():
    return solver.compile_model(knee_with_patella(), solver.Params.physical())


def test_coupling_virtual_work_equals_finite_differences(psim):
    """A force f on a patella vertex, the knee locked: the lock's torque is -f . dx/dtheta, dx/dtheta by
    central differences of the forward kinematics (the coupling Jacobian)."""
    i = int(np.flatnonzero(psim.vertex_segment == 2)[0])
    sk = psim.skeleton._replace(gravity=frozen(np.zeros(3)))
    fv = np.array([3.0, -1.0, 7.0])
    for deg in (5.0, 37.0, 80.0, 115.0):
        th, e = math.radians(deg), 1e-6
        xp = solver.set_joint_positions(psim, solver.make_state(psim), [th + e, 0.0]).x[i]
        xm = solver.set_joint_positions(psim, solver.make_state(psim), [th - e, 0.0]).x[i]
        st = solver.set_joint_positions(psim, solver.make_state(psim), [th, 0.0])
        np.testing.assert_allclose(st.q[1], 0.8 * th, rtol=1e-2)          # its coordinate: the spline's angle
        f = np.zeros_like(st.x)
        f[i] = fv
        lt = np.zeros(2)
        SK.skeleton_step(1e-4, st.q, st.qd, f, st.x, sk, psim.att_idx, psim.att_seg, 0.0, 0.3, 1.0, st.seg_R, st.seg_t,
                         np.zeros((2, 10)), np.array([True, False]), st.q.copy(), lt, np.zeros(2), np.zeros((psim.n_segments, 6)))
        np.testing.assert_allclose(-lt[0], fv @ (xp - xm) / (2 * e), rtol=1e-6, atol=1e-9)


def test_coupled_segment_energy_is_conserved(psim):
    """The knee swinging freely under gravity (no tissue force, no damping, no end stop) with a heavy
    coupled patella (0.5 kg, its path moving its centre of mass by centimetres): the skeleton's energy,
    the patella's kinetic and potential energy included, stays within 0.05 % of its swing (symplectic
    Euler's bounded oscillation, no drift). Without the patella's inertia and bias in the driver's
    equation the energy would not be conserved."""
    sk = psim.skeleton._replace(gravity=frozen([0.0, 0.0, -9.81]), j_range=frozen([[-10.0, 10.0], [-10.0, 10.0]]))
    s2 = dataclasses.replace(psim, skeleton=sk, gravity=sk.gravity, j_range=sk.j_range)
    st = solver.set_joint_positions(psim, solver.make_state(psim), [math.radians(60.0), 0.0])
    f = np.zeros_like(st.x)
    E0, E, qs = skeleton_energy(s2, st), [], []
    for n in range(20000):
        SK.skeleton_step(1e-4, st.q, st.qd, f, st.x, sk, psim.att_idx, psim.att_seg, 0.0, 0.3, 1.0, st.seg_R, st.seg_t,
                         np.zeros((2, 10)), np.zeros(2, bool), st.q.copy(), np.zeros(2), np.zeros(2), np.zeros((psim.n_segments, 6)))
        if n % 500 == 0:
            E.append(skeleton_energy(s2, st))
            qs.append(st.q[0])
    assert np.ptp(qs) > math.radians(60.0)                         # it swings
    assert np.max(np.abs(np.array(E) - E0)) < 5e-4 * abs(E0), (E0, np.max(np.abs(np.array(E) - E0)))


# ------------------------------------------------------------------------- the bundled knee with its patella
def _held_torque(sim, deg, active, settle=0.3):
    """Knee moved to deg at 200 deg/s, then held (the solver's joint lock, the ankle locked at rest) with the muscles of the given
    groups fully active: the tissue's knee torque [N m] (+ flexes), minus the lock's, mean over the last
    10 % of the hold (as tissue-sim validate measures it)."""
    st = solver.make_state(sim)
    ctrl = solver.make_control(sim)
    kj = sim.tissue.joint_names.index('knee_r')
    ctrl.joint_lock[:] = True
    ctrl.joint_target[:] = st.q
    for m, g in enumerate(sim.tissue.muscle_groups):
        ctrl.activation[m] = 1.0 if g in active else 0.0
    n_ramp = int(math.ceil(deg / 200.0 / sim.params.dt))      # to the angle at 200 deg/s (validate's ramp)
    for i in range(n_ramp):
        ctrl.joint_target[kj] = math.radians(deg * (i + 1) / n_ramp)
        solver.step(sim, st, ctrl)
    n = int(round(settle / sim.params.dt))
    solver.step(sim, st, ctrl, n_steps=n - n // 10)
    tau = 0.0
    for _ in range(n // 10):
        solver.step(sim, st, ctrl)
        tau -= st.joint_lock_torque[kj] / (n // 10)
    return tau


@pytest.mark.slow
@pytest.mark.parametrize('deg', [30.0, 90.0])
def test_quadriceps_extend_the_knee_through_the_patella(sim, deg):
    """Active quadriceps (inserting on the patella only) against the passive knee at the same angle: their
    knee torque, which reaches the shank only through the patella's coupling, is extensor (negative)."""
    passive = _held_torque(sim, deg, ())
    quads = _held_torque(sim, deg, ('quadriceps',))
    assert quads - passive < -5.0, (deg, quads, passive)


@pytest.mark.slow
def test_hamstrings_still_flex_the_knee(sim):
    """The free knee (ankle locked) from rest with the hamstrings fully active flexes past 10 deg in 0.5 s."""
    st = solver.make_state(sim)
    ctrl = solver.make_control(sim)
    kj = sim.tissue.joint_names.index('knee_r')
    ctrl.joint_lock[:] = True
    ctrl.joint_lock[kj] = False
    ctrl.joint_target[:] = st.q
    for m, g in enumerate(sim.tissue.muscle_groups):
        ctrl.activation[m] = 1.0 if g == 'hamstrings' else 0.0
    solver.step(sim, st, ctrl, n_steps=int(round(0.5 / sim.params.dt)))
    assert math.degrees(st.q[kj]) > 10.0
    pj = sim.tissue.joint_names.index('patellofemoral_r')
    assert st.q[pj] > 0.0                               # the patella followed the knee (its angle > 0)


def test_joint_torques_equal_the_kernels(psim):
    """measures.joint_torques (the analysis' generalized force of vertex forces) equals the torque the
    skeleton kernel applies (the knee lock's reaction) for forces on every bone-attached vertex: shank
    (hinge) and patella (coupling) alike."""
    from tissue_sim.core.solver.measures import joint_torques
    st = solver.set_joint_positions(psim, solver.make_state(psim), [math.radians(70.0), 0.0])
    f = np.random.default_rng(1).standard_normal(st.x.shape)
    tau = joint_torques(psim, st, f)
    lt = np.zeros(2)
    sk = psim.skeleton._replace(gravity=frozen(np.zeros(3)))
    SK.skeleton_step(1e-4, st.q, st.qd, f, st.x, sk, psim.att_idx, psim.att_seg, 0.0, 0.3, 1.0, st.seg_R, st.seg_t,
                     np.zeros((2, 10)), np.array([True, False]), st.q.copy(), lt, np.zeros(2), np.zeros((psim.n_segments, 6)))
    np.testing.assert_allclose(tau[0], -lt[0], rtol=1e-9)
    on_patella = psim.att_idx[psim.att_seg == 2]
    assert abs(joint_torques(psim, st, f, on_patella)[0]) > 0           # the patella's share is not zero
