"""Recordings of real nodes a rosbag2 user trusts: the recorder writes the QoS the publishers offer
and the type hash on every channel (read back by rosbags), keeps a throttled topic at its rate, and a
replay of the recording offers the topology transient-local again, so a subscriber that joins late
still gets it."""
from __future__ import annotations

import time

import pytest

import rosutil  # noqa: F401  (activates the workspace before rclpy; skips if not built)
from rosutil import assert_own_participant, isolated_domain, ros_context, run_executable, spin_until, wait_for_publishers

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_recording_metadata_throttle_and_late_subscriber_of_a_replay(tmp_path):
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability
    from sensor_msgs.msg import JointState
    from tissue_msgs.msg import TissueTopology

    out = tmp_path / 'rec.mcap'
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        joints = []
        sub = node.create_subscription(JointState, '/joint_states', lambda m: joints.append(m), 10)
        with run_executable('simulator', '--ros-args', '-p', 'model:=phantom:knee', env=dom.env) as sim:
            sim.wait_for_output('publishing at', timeout=240)
            wait_for_publishers(node, sub, 1, timeout=60)
            with run_executable('recorder', '-o', out, '--topics', '/tissue/markers',
                                '--max-rate', '/tissue/markers=5', env=dom.env) as rec:
                rec.wait_for_output(r'recording /tissue/markers', timeout=60)
                rec.wait_for_output(r'recording /tissue/topology', timeout=60)
                t0 = time.monotonic()
                spin_until(lambda: time.monotonic() - t0 > 4.0, node, 10, '4 s of recording')
            assert rec.returncode == 0, rec.output
        assert sim.returncode == 0, sim.output
        node.destroy_node()

    with AnyReader([out]) as r:
        by_topic = {c.topic: c for c in r.connections}
        times = {}
        for c, t, _ in r.messages():
            times.setdefault(c.topic, []).append(t)
        computed = {c.topic: r.typestore.hash_rihs01(c.msgtype) for c in r.connections}
    from mcap.reader import make_reader
    with open(out, 'rb') as f:
        recorded = {c.topic: c.metadata.get('topic_type_hash') for c in make_reader(f).get_summary().channels.values()}
    topo_q = by_topic['/tissue/topology'].ext.offered_qos_profiles
    assert topo_q and all(q.durability == QosDurability.TRANSIENT_LOCAL for q in topo_q)
    assert all(q.durability == QosDurability.VOLATILE for q in by_topic['/joint_states'].ext.offered_qos_profiles)
    assert recorded == computed          # every channel's RIHS01 hash is the one rosbags computes for its type
    span = (times['/joint_states'][-1] - times['/joint_states'][0]) * 1e-9
    assert span > 2.0
    # over the markers' own span: the recorder may match the markers' writer (a participant of its own) a moment
    # before or after the frame's (DDS discovery; up to 2.6 s seen here)
    mk = times['/tissue/markers']
    marker_rate = (len(mk) - 1) / ((mk[-1] - mk[0]) * 1e-9)
    assert 3.0 < marker_rate <= 5.6, f'markers kept at {marker_rate:.2f} Hz (max-rate 5)'
    assert len(times['/joint_states']) / span > 20.0          # an unthrottled topic keeps its ~34 Hz

    # replay, then subscribe late with transient-local durability: the topology still arrives
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        with run_executable('replay', out, '--loop', env=dom.env) as rep:
            rep.wait_for_output(r'replay: \d+ messages', timeout=60)
            time.sleep(3.0)        # the topology was published long before this subscriber exists
            node = rclpy.create_node('late', context=ctx)
            got = []
            node.create_subscription(TissueTopology, '/tissue/topology', got.append,
                                     QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))
            spin_until(lambda: got, node, 30, 'the replayed topology for a late subscriber')
            assert got[0].muscle_names
            # the markers replayed from a DDS participant of their own, as the simulator sends them
            assert_own_participant(node, '/tissue/markers', 'replay_markers', '/tissue/topology', 'replay')
            node.destroy_node()
