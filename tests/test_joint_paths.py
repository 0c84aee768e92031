"""The knee as a hinge with a path (core/model.py, solver/skeleton.py ``path_frame``; docs/solver.md "Skeleton"): the
bundled knee follows the source model's walker knee (its tibia also turns about two secondary axes and translates with
the angle), its dynamics are consistent with that motion (virtual work, energy), and ``Params.joint_paths`` off gives
the plain hinge about the fitted centre (the paper set)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tissue_sim.core import solver
from tissue_sim.core.builder import load_joints
from tissue_sim.core.solver import skeleton as SK
from tissue_sim.core.solver.measures import joint_torques, skeleton_energy
from tissue_sim.core.solver.model import frozen     # read-only, as the model's arrays: no extra compile

KNEE = 0


@pytest.fixture(scope='module')
def sims(default_tm):
    return {paths: solver.compile_model(default_tm, solver.Params.physical(joint_paths=paths)) for paths in (True, False)}


def _posed(sim, deg, ankle_deg=0.0):
    q = np.zeros(sim.n_joints)
    q[KNEE], q[1] = math.radians(deg), math.radians(ankle_deg)
    return solver.set_joint_positions(sim, solver.make_state(sim), q)


def _step(sim, sk, st, f, h, lock):
    J = sim.n_joints
    lt = np.zeros(J)
    ok = SK.skeleton_step(h, st.q, st.qd, f, st.x, sk, sim.att_idx, sim.att_seg, 0.0, 0.3, 1.0, st.seg_R, st.seg_t,
                          np.zeros((J, 8 + J)), lock, st.q.copy(), lt, np.zeros(J), np.zeros((sim.n_segments, 6)))
    assert ok
    return lt


def test_the_knee_follows_the_source_models_walker_knee(sims):
    """The shank's pose at 0-120 deg against the tibia's in the source model (the OpenSim API, independent of the
    tables the generator wrote): points of the tibia plateau, its shaft and the ankle centre within 0.05 mm. The plain
    hinge (joint_paths off, the paper set) is off by millimetres, most at the tibia's lateral edge (its axial rotation)."""
    import importlib.util
    if importlib.util.find_spec('opensim') is None:
        pytest.skip('opensim not installed (requirements/validation.txt; make test installs it)')
    from tissue_sim.core import validation as V
    osm = V._import_opensim()           # (never a plain import: it rewrites this process's environment)
    S = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])        # OpenSim femur frame -> model frame
    X = np.array([[0.0, 0.0, -0.827], [0.03, -0.035, -0.44], [-0.03, 0.03, -0.45], [0.0, 0.0, -0.6]])
    errs = {True: 0.0, False: 0.0}
    with V._environment_kept():
        osm.Logger.setLevelString('error')
        model = osm.Model(str(V.source_model_path()))
        state = model.initSystem()
        for c in model.getCoordinateSet():
            if not c.get_locked():
                c.setValue(state, 0.0, False)
        femur, tibia = model.getBodySet().get('femur_r'), model.getBodySet().get('tibia_r')
        knee = model.getCoordinateSet().get('knee_angle_r')
        pose = {}
        for deg in (0.0, 15.0, 45.0, 80.0, 105.0, 120.0):
            knee.setValue(state, math.radians(deg))
            model.realizePosition(state)
            T = tibia.findTransformBetween(state, femur)
            R = S @ np.array([[T.R().get(r, k) for k in range(3)] for r in range(3)]) @ S.T
            pose[deg] = (R, S @ np.array([T.p().get(k) for k in range(3)]))
    R0, t0 = pose[0.0]
    for deg, (R, t) in pose.items():
        ref = (X - t0) @ (R @ R0.T).T + t                          # rest -> deg in the source model
        for paths, sim in sims.items():
            st = _posed(sim, deg)
            errs[paths] = max(errs[paths], float(np.abs(X @ st.seg_R[1].T + st.seg_t[1] - ref).max()))
    assert errs[True] < 5e-5, errs
    assert errs[False] > 3e-3, errs                                 # the hinge without the path: millimetres off


def test_the_path_in_the_joints_file():
    """joints.yaml: the knee's path turns the tibia by up to ~15 deg about its long axis (the walker knee's
    rotation3) and ~2 deg about the antero-posterior axis, with millimetre offsets from the hinge centre."""
    from tissue_sim.core.builder import default_inputs
    skel = load_joints(default_inputs()[1].parent / 'joints.yaml')
    o = skel['joint_path_offsets']
    rows = skel['joint_path_table'][o[KNEE]:o[KNEE + 1]]
    assert len(rows) >= 20 and rows[0, 0] == 0.0 and math.degrees(rows[-1, 0]) >= 120.0
    np.testing.assert_allclose(rows[0, 1:], 0.0, atol=1e-9)         # the rest pose is the model's
    assert 10.0 < math.degrees(np.abs(rows[:, 2]).max()) < 20.0
    assert 0.5 < math.degrees(np.abs(rows[:, 1]).max()) < 5.0
    assert np.abs(rows[:, 3:]).max() < 0.01
    ax = skel['joint_path_axes'][KNEE]
    assert abs(ax[1] @ [0.0, 0.0, 1.0]) > 0.95                       # rotation3: about the tibia's long axis
    np.testing.assert_allclose(ax @ ax.T, np.eye(2), atol=1e-5)      # unit, perpendicular


@pytest.mark.parametrize('deg', [5.0, 37.0, 80.0, 115.0])
def test_path_jacobian_is_the_derivative_of_the_pose(sims, deg):
    """A force on a shank vertex, the hinges locked: the knee lock's torque is -f . dx/dq, dx/dq by central differences
    of the forward kinematics; measures.joint_torques equals the kernel's for forces on every bone-attached vertex
    (shank, foot and the coupled patella); skeleton.joint_jacobians' velocity W x (x - P) + D of shank points equals
    dx/dq."""
    sim = sims[True]
    sk = sim.skeleton._replace(gravity=frozen(np.zeros(3)))
    lock = np.array([t == 1 for t in sim.j_type])
    i = int(np.flatnonzero(sim.vertex_segment == 1)[5])
    e = 1e-6
    xp, xm = _posed(sim, deg + math.degrees(e)).x, _posed(sim, deg - math.degrees(e)).x
    st = _posed(sim, deg)
    fv = np.array([3.0, -1.0, 7.0])
    f = np.zeros_like(st.x)
    f[i] = fv
    lt = _step(sim, sk, _posed(sim, deg), f, 1e-4, lock)
    np.testing.assert_allclose(-lt[KNEE], fv @ (xp[i] - xm[i]) / (2 * e), rtol=1e-6, atol=1e-9)
    W, P, D = SK.joint_jacobians(st.q, sim.skeleton, st.seg_R, st.seg_t)
    shank = np.flatnonzero(sim.vertex_segment == 1)[:50]
    v = np.cross(W[KNEE], st.x[shank] - P[KNEE]) + D[KNEE]
    np.testing.assert_allclose(v, (xp[shank] - xm[shank]) / (2 * e), atol=1e-7)
    if deg < 60:            # the tibia's axial rotation grows fastest there: W is not the plain hinge's axis
        assert np.linalg.norm(np.cross(W[KNEE], sim.j_axis[KNEE])) > 0.05
    ft = np.random.default_rng(1).standard_normal(st.x.shape)
    ft[sim.inv_mass > 0] = 0.0          # (on free vertices a force reaches a bone only through a point via ring: the step's)
    lt = _step(sim, sk, _posed(sim, deg), ft, 1e-4, lock)
    np.testing.assert_allclose(joint_torques(sim, st, ft)[KNEE], -lt[KNEE], rtol=1e-9)


def test_free_swing_conserves_the_skeletons_energy(sims):
    """Knee and ankle swinging freely under gravity (no tissue force, no damping, no end stops), 2 s: the skeleton's
    energy (its path's motion included) stays within 0.3 % of its start, the bounded oscillation of symplectic Euler
    (halving h halves it), as the plain hinge's does; with a wrong Jacobian or bias it drifts."""
    devs = {}
    for paths, h in ((True, 1e-4), (True, 5e-5), (False, 1e-4)):
        sim = sims[paths]
        J = sim.n_joints
        sk = sim.skeleton._replace(gravity=frozen([0.0, 0.0, -9.81]), j_range=frozen([[-10.0, 10.0]] * J))
        s2 = dataclasses.replace(sim, skeleton=sk, gravity=sk.gravity, j_range=sk.j_range)
        st = _posed(sim, 60.0, 10.0)
        f = np.zeros_like(st.x)
        E0, E, qs = skeleton_energy(s2, st), [], []
        for n in range(int(round(2.0 / h))):
            _step(sim, sk, st, f, h, np.zeros(J, bool))
            if n % int(round(0.05 / h)) == 0:
                E.append(skeleton_energy(s2, st))
                qs.append(st.q[KNEE])
        assert np.ptp(qs) > math.radians(90.0)                      # it swings
        devs[(paths, h)] = float(np.max(np.abs(np.array(E) - E0)) / abs(E0))
    assert devs[(True, 1e-4)] < 3e-3, devs
    assert devs[(True, 5e-5)] < 0.6 * devs[(True, 1e-4)], devs      # first order in h: no drift of its own
    assert devs[(True, 1e-4)] < 1.5 * devs[(False, 1e-4)], devs


def test_paper_set_keeps_the_plain_hinge(default_tm):
    """Params.paper() (joint_paths off): the knee is the plain hinge about its axis through its centre, its secondary
    path unused (the knee's and ankle's rows empty in the skeleton's tables, the patella's kept)."""
    sim = solver.compile_model(default_tm, solver.Params.paper())
    assert sim.cp_off[KNEE + 1] == sim.cp_off[KNEE] and sim.cp_off[-1] > sim.cp_off[-2]
    st = _posed(sim, 70.0)
    R = Rotation.from_rotvec(math.radians(70.0) * np.asarray(sim.j_axis[KNEE])).as_matrix()
    np.testing.assert_allclose(st.seg_R[1], R, atol=1e-12)
    c = np.asarray(sim.j_centre[KNEE])
    np.testing.assert_allclose(st.seg_R[1] @ c + st.seg_t[1], c, atol=1e-12)


@pytest.mark.parametrize('path, message', [
    ({'axes': [[1, 0, 0]], 'table': [[0, 0, 0, 0, 0, 0]] * 4}, 'path axes must be a list of 2 axes'),
    ({'axes': [[1, 0, 0], [0, 0, 0]], 'table': [[0, 0, 0, 0, 0, 0]] * 4}, 'path axes must be non-zero'),
    ({'axes': [[1, 0, 0], [0, 0, 1]], 'table': [[0, 0, 0, 0, 0, 0]] * 3}, 'needs a "table" of at least 4 rows'),
    ({'axes': [[1, 0, 0], [0, 0, 1]], 'table': [[5.0 * i, 0, 0, 0, 0] for i in range(4)]}, 'path table row 0'),
    ({'axes': [[1, 0, 0], [0, 0, 1]], 'table': [[0, 0, 0, 0, 0, 0]] * 4}, 'strictly increasing angle_deg'),
    ({'axes': [[1, 0, 0], [0, 0, 1]], 'table_columns': ['q'], 'table': [[0] * 6]}, 'table_columns must be'),
    ('walker', '"path" must be a mapping'),
])
def test_a_bad_path_is_one_clear_error(path, message):
    """A malformed hinge path in the joints file: the builder's UserError names the joint and the problem (the
    command line turns it into one line and exit code 2, tests/test_bad_inputs.py)."""
    from tissue_sim.errors import UserError
    d = {'segments': [{'name': 'a', 'parent': None, 'mass': 1.0, 'com': [0, 0, 0], 'inertia': np.eye(3).tolist()},
                      {'name': 'b', 'parent': 'a', 'mass': 1.0, 'com': [0, 0, -0.5], 'inertia': np.eye(3).tolist()}],
         'joints': [{'name': 'knee', 'type': 'hinge', 'parent': 'a', 'child': 'b', 'axis': [0, 1, 0],
                     'centre': [0, 0, -0.4], 'path': path}]}
    with pytest.raises(UserError, match=message) as e:
        load_joints(d)
    assert "joint 'knee'" in str(e.value) and '\n' not in str(e.value)
