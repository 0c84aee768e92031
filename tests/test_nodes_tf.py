"""The simulator's TF tree and robot description over real DDS (isolated domain): /tf carries the
moving segments each frame, stamped with the frame's sim time, and composed with /tf_static it gives
the segment poses the same frame's /tissue/state carries; /tf_static and /robot_description reach a
LATE subscriber (transient local); the description is the URDF of the model the node runs, and the
/joint_states names are its joints (what robot_state_publisher needs)."""
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import rosutil  # noqa: F401  (activates the workspace before rclpy; skips if not built)
from rosutil import isolated_domain, ros_context, run_executable, spin_until, wait_for_subscribers
from test_nodes import knee_model   # noqa: F401  (fixture: the knee phantom as a file)
from test_urdf import _urdf_fk      # the URDF's forward kinematics by the URDF specification

pytestmark = pytest.mark.ros


def _pose(ts):
    tr, q = ts.transform.translation, ts.transform.rotation
    return Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), np.array([tr.x, tr.y, tr.z])


def _stamp(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def test_tf_static_and_robot_description_of_the_running_model(knee_model):
    import rclpy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage
    from tissue_msgs.msg import MuscleActivation, TissueState
    from tissue_sim.core import tissue_cdr, urdf
    from tissue_sim.core.model import TissueModel
    from tissue_sim.ros.common import qos_latched
    tm = TissueModel.load(knee_model)
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', '--ros-args', '-p', f'model:={knee_model}', '-p', 'publish_markers:=false',
                           env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        tf, states, js = [], [], []
        node.create_subscription(TFMessage, '/tf', tf.append, 100)
        node.create_subscription(TissueState, '/tissue/state', states.append, 100, raw=True)
        node.create_subscription(JointState, '/joint_states', js.append, 100)
        pub = node.create_publisher(MuscleActivation, '/tissue/activation', 10)
        sim.wait_for_output('simulator ready', timeout=120)
        wait_for_subscribers(node, pub, 1, timeout=30)
        m = MuscleActivation()
        m.muscle_names, m.activations = ['hamstring'], [1.0]
        pub.publish(m)
        # frames flow and the knee moves: the transforms below are not the rest pose
        spin_until(lambda: js and js[-1].position[0] > 0.3, node, 60, 'knee flexion > 0.3 rad')
        # LATE subscribers: created after the node published its static frames and description
        static, desc = [], []
        node.create_subscription(TFMessage, '/tf_static', static.append, qos_latched())
        node.create_subscription(String, '/robot_description', desc.append, qos_latched())
        spin_until(lambda: static and desc, node, 20, '/tf_static and /robot_description (transient local)')
        t0 = time.monotonic()
        spin_until(lambda: time.monotonic() - t0 > 0.5, node, 5, 'a few more frames')
        node.destroy_node()
    assert sim.returncode == 0, sim.output
    assert 'params physical' in sim.output          # the default parameter set

    # /robot_description: the URDF of the model this node runs (the knee phantom, not the bundled limb)
    assert len(desc) == 1 and desc[0].data == urdf.robot_description(tm)
    robot = ET.fromstring(desc[0].data)
    assert robot.get('name') == tm.name
    joints = {j.get('name'): j.get('type') for j in robot.findall('joint')}
    # /joint_states names the URDF's movable joints (robot_state_publisher's input)
    assert set(js[-1].name) <= set(joints) and joints['knee_r'] == 'revolute'
    # /tf_static: the fixed root under world, once
    assert len(static) == 1
    fixed = {ts.child_frame_id: ts for ts in static[0].transforms}
    assert [(ts.header.frame_id, c) for c, ts in fixed.items()] == [('world', 'thigh')]
    # /tf: the moving segment, every frame, stamped with the sim time of that frame's state
    assert len(tf) > 20
    assert all([(ts.header.frame_id, ts.child_frame_id) for ts in msg.transforms] == [('thigh', 'shank')]
               for msg in tf)
    by_stamp = {_stamp(msg.transforms[0].header): msg for msg in tf}
    js_by_stamp = {_stamp(m.header): m for m in js}
    matched = fk_matched = 0
    for raw in states:
        s = tissue_cdr.decode_state(raw)
        if s.stamp_ns not in by_stamp or s.joint_positions[0] < 0.1:
            continue
        matched += 1
        world = {'world': (np.eye(3), np.zeros(3))}
        for ts in list(static[0].transforms) + list(by_stamp[s.stamp_ns].transforms):
            Rp, pp = world[ts.header.frame_id]
            R, p = _pose(ts)
            world[ts.child_frame_id] = (Rp @ R, pp + Rp @ p)
        seg_R = Rotation.from_quat(s.segment_poses[:, 3:]).as_matrix()
        R_link, p_link = urdf.link_poses(tm, seg_R, s.segment_poses[:, :3])
        # what robot_state_publisher makes from /joint_states alone: the URDF's forward kinematics
        j = js_by_stamp.get(s.stamp_ns)
        fk = _urdf_fk(desc[0].data, dict(zip(j.name, j.position))) if j is not None else None
        fk_matched += j is not None
        for i, seg in enumerate(tm.segment_names):
            np.testing.assert_allclose(world[seg][0], R_link[i], atol=1e-6, err_msg=seg)
            np.testing.assert_allclose(world[seg][1], p_link[i], atol=1e-6, err_msg=seg)
            if fk is not None:
                np.testing.assert_allclose(fk[seg][0], R_link[i], atol=1e-6, err_msg=seg)
                np.testing.assert_allclose(fk[seg][1], p_link[i], atol=1e-6, err_msg=seg)
    assert fk_matched > 5, f'only {fk_matched} states matched a /joint_states message by stamp'
    assert matched > 5, f'only {matched} states with a flexed knee matched a /tf message by stamp'


def test_publish_tf_false_leaves_the_tree_to_robot_state_publisher(knee_model):
    """With publish_tf:=false (the launch file's setting when robot_state_publisher runs) the node
    publishes neither /tf nor /tf_static, but still the description and the joint states."""
    import rclpy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from tissue_sim.ros.common import qos_latched
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', '--ros-args', '-p', f'model:={knee_model}', '-p', 'publish_markers:=false',
                           '-p', 'publish_tf:=false', env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        js, desc = [], []
        node.create_subscription(JointState, '/joint_states', js.append, 10)
        node.create_subscription(String, '/robot_description', desc.append, qos_latched())
        sim.wait_for_output('simulator ready', timeout=120)
        spin_until(lambda: len(js) > 20 and desc, node, 60, 'joint states and the description')
        assert node.count_publishers('/tf') == 0 and node.count_publishers('/tf_static') == 0
        assert node.count_publishers('/joint_states') == 1
        node.destroy_node()
    assert sim.returncode == 0, sim.output
