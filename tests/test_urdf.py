"""The skeleton as URDF and TF (tissue_sim.core.urdf): the installed description is the one generated
from the bundled model; its forward kinematics, computed here from the URDF text alone by the URDF
specification, equal the solver's segment poses; the TF tree composes to the same poses; the pip
set-up's tf2_msgs/msg/TFMessage has ROS 2 Jazzy's type hash."""
from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tissue_sim.core import builder, solver, urdf

ROOT = Path(__file__).resolve().parents[1]
DESCRIPTION = ROOT / 'src' / 'tissue_sim' / 'description'


@pytest.fixture(scope='module')
def tm():
    return builder.default_model()


def test_committed_description_is_the_generated_one(tm, tmp_path):
    path = urdf.write_description(tm, tmp_path)
    assert path.read_text() == (DESCRIPTION / path.name).read_text()
    for stl in sorted((tmp_path / 'meshes').glob('*.stl')):
        assert stl.read_bytes() == (DESCRIPTION / 'meshes' / stl.name).read_bytes(), stl.name
    assert sorted(p.name for p in (DESCRIPTION / 'meshes').glob('*.stl')) == sorted(f'{b}.stl' for b in tm.bone_names)


def _urdf_fk(text: str, q: dict) -> dict:
    """World pose (R, p) of every link, from the URDF text by the URDF specification: a joint's
    origin (xyz, rpy = fixed-axis roll-pitch-yaw) places the child frame in the parent's, then a
    revolute joint rotates the child about `axis` (child frame) by its position, a prismatic joint
    translates it along `axis` by its position."""
    root = ET.fromstring(text)
    joints = {j.find('child').get('link'): j for j in root.findall('joint')}
    pose = {'world': (np.eye(3), np.zeros(3))}

    def get(link):
        if link in pose:
            return pose[link]
        j = joints[link]
        Rp, pp = get(j.find('parent').get('link'))
        o = j.find('origin')
        xyz = np.array([float(v) for v in o.get('xyz').split()])
        r, p_, y = (float(v) for v in o.get('rpy').split())
        Ro = Rotation.from_euler('z', y).as_matrix() @ Rotation.from_euler('y', p_).as_matrix() @ \
            Rotation.from_euler('x', r).as_matrix()
        Rj, tj = np.eye(3), np.zeros(3)
        if j.get('type') in ('revolute', 'prismatic'):
            axis = np.array([float(v) for v in j.find('axis').get('xyz').split()])
            axis = axis / np.linalg.norm(axis)
            if j.get('type') == 'revolute':
                Rj = Rotation.from_rotvec(q[j.get('name')] * axis).as_matrix()
            else:
                tj = q[j.get('name')] * axis
        pose[link] = (Rp @ Ro @ Rj, pp + Rp @ (xyz + Ro @ tj))
        return pose[link]
    for link in root.findall('link'):
        get(link.get('name'))
    return pose


@pytest.mark.parametrize('knee_deg', [0.0, 35.0, 90.0, 120.0])
def test_urdf_kinematics_equal_the_solver_segment_poses(tm, knee_deg):
    sim = solver.compile_model(tm, solver.Params.physical())
    state = solver.make_state(sim)
    q = np.zeros(tm.n_joints)
    q[tm.joint_names.index('knee_r')] = math.radians(knee_deg)
    solver.set_joint_positions(sim, state, q)
    R_sim, p_sim = urdf.link_poses(tm, state.seg_R, state.seg_t)
    names, pos, _ = urdf.joint_states(sim, state.q, state.qd)      # what /joint_states carries
    fk = _urdf_fk(urdf.robot_description(tm), dict(zip(names, pos)))
    for s, seg in enumerate(tm.segment_names):
        R, p = fk[seg]
        np.testing.assert_allclose(R, R_sim[s], atol=1e-7, err_msg=seg)
        np.testing.assert_allclose(p, p_sim[s], atol=1e-7, err_msg=seg)
    # a bone vertex: the solver moves it with its segment; the URDF places the link-frame STL vertex
    v_link = urdf.bone_meshes_in_link_frames(tm)['tibia'][0][0]
    v_rest = tm.bone_mesh(tm.bone_names.index('tibia'))[0][0]
    s = int(tm.bone_segment[tm.bone_names.index('tibia')])
    R, p = fk[tm.segment_names[s]]
    np.testing.assert_allclose(R @ v_link + p, state.seg_R[s] @ v_rest + state.seg_t[s], atol=1e-7)
    if knee_deg > 0:   # flexion moves the shank behind and up relative to extension, and the patella
        assert not np.allclose(fk['shank'][0], np.eye(3))
        assert not np.allclose(fk['patella'][0], np.eye(3))
    # the knee's path (three translations, the hinge, two secondary rotations) and the coupled patella (three
    # translations and a rotation), all named in /joint_states
    # (the hinges' own coordinates first, as the solver orders them: position[0] is the knee angle)
    assert names == ['knee_r', 'ankle_r', 'knee_r_tx', 'knee_r_ty', 'knee_r_tz', 'knee_r_r2', 'knee_r_r3',
                     'patellofemoral_r_tx', 'patellofemoral_r_ty', 'patellofemoral_r_tz', 'patellofemoral_r']
    if knee_deg > 30:       # the walker knee's axial rotation of the tibia is in the URDF's chain
        assert abs(pos[names.index('knee_r_r3')]) > math.radians(5.0)


def test_tf_tree_composes_to_the_link_poses(tm):
    sim = solver.compile_model(tm, solver.Params.physical())
    state = solver.make_state(sim)
    q = np.zeros(tm.n_joints)
    q[tm.joint_names.index('knee_r')] = math.radians(60.0)
    solver.set_joint_positions(sim, state, q)
    R_sim, p_sim = urdf.link_poses(tm, state.seg_R, state.seg_t)
    world = {'world': (np.eye(3), np.zeros(3))}
    tfs = urdf.tf_transforms(tm, state.seg_R, state.seg_t)
    assert [(a, b) for a, b, _, _ in tfs] == [('world', 'thigh'), ('thigh', 'shank'), ('shank', 'foot'),
                                              ('thigh', 'patella')]
    for parent, child, t, quat in tfs:
        Rp, pp = world[parent]
        world[child] = (Rp @ Rotation.from_quat(quat).as_matrix(), pp + Rp @ t)
    for s, seg in enumerate(tm.segment_names):
        np.testing.assert_allclose(world[seg][0], R_sim[s], atol=1e-9)
        np.testing.assert_allclose(world[seg][1], p_sim[s], atol=1e-9)
    assert [urdf.is_static(tm, s) for s in range(4)] == [True, False, False, False]   # thigh root, knee, ankle, patella
    assert urdf.is_static(tm, 0, fixed_root=False) is False


def test_installed_description_and_tf2_msgs_type_hash():
    import rosutil  # noqa: F401  (the built workspace; skips locally if it is not built)
    share = rosutil.INSTALL / 'tissue_sim' / 'share' / 'tissue_sim'
    assert (share / 'urdf' / 'lower_limb_r.urdf').read_text() == (DESCRIPTION / 'lower_limb_r.urdf').read_text()
    assert (share / 'meshes' / 'femur.stl').is_file()
    from rosbags.typesys import Stores, get_typestore
    jazzy = get_typestore(Stores.ROS2_JAZZY).hash_rihs01('tf2_msgs/msg/TFMessage')
    desc = rosutil.INSTALL / 'tf2_msgs' / 'share' / 'tf2_msgs' / 'msg' / 'TFMessage.json'
    if not desc.is_file():                # a system ROS 2: its own tf2_msgs
        from ament_index_python.packages import get_package_share_directory
        desc = Path(get_package_share_directory('tf2_msgs')) / 'msg' / 'TFMessage.json'
    hashes = {h['type_name']: h['hash_string'] for h in json.loads(desc.read_text())['type_hashes']}
    assert hashes['tf2_msgs/msg/TFMessage'] == jazzy
    from tf2_msgs.msg import TFMessage  # noqa: F401  (importable from the workspace)
