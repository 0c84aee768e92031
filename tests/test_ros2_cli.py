"""The `ros2` command-line and launch tools (installed by `make ros2-tools` into the pip set-up)
against the real nodes: `ros2 run`, `ros2 topic hz`, `ros2 param set/get`, `ros2 interface show`,
`ros2 launch tissue_sim demo.launch.py`.

Under `make test` the tools are installed first and their absence is an error; run directly
without them, these tests are skipped with the command that installs them."""
from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import signal
import subprocess
import time

import pytest

import rosutil  # noqa: F401  (activates the workspace before rclpy; skips if not built)
from rosutil import Proc, isolated_domain, ros_context, spin_until, wait_for_publishers

pytestmark = [pytest.mark.ros, pytest.mark.slow]

ROS2 = shutil.which('ros2', path=os.environ.get('PATH'))
if ROS2 is None:
    if os.environ.get('TISSUE_SIM_REQUIRE_WS') == '1':
        raise RuntimeError('the ros2 command is missing: `make ros2-tools` should have installed it')
    pytest.skip('the ros2 command is not installed (make ros2-tools)', allow_module_level=True)


@contextlib.contextmanager
def started(argv, env):
    """Start argv in a session of its own; on exit SIGINT the whole process group (`ros2 run` does
    not forward signals to the node it starts), escalating to SIGKILL."""
    proc = Proc(argv, env)
    try:
        yield proc
    finally:
        for sig, wait in ((signal.SIGINT, 15.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.popen.pid, sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.popen.wait(wait)
                # the group may outlive its leader: check it is empty
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.popen.pid, 0)
                    continue
                break


def ros2(env, *args, timeout=60.0, spin_time=5.0):
    """Run a ros2 command. Without the daemon it discovers the graph itself for --spin-time
    (default 0.5 s): too short on a loaded machine ('Node not found'), so spin_time."""
    if '--no-daemon' in args:
        args = (*args, '--spin-time', f'{spin_time:g}')
    return subprocess.run([ROS2, *args], env=env, capture_output=True, text=True, timeout=timeout)


def ros2_graph(env, *args, found=lambda r: 'Node not found' not in r.stderr):
    """A `ros2` verb that must discover the simulator first (--no-daemon: each call is a new
    participant): 2 s of discovery (a local participant is found within it), then 5 s twice where
    the result is not found() yet (a loaded machine)."""
    for spin_time in (2.0, 5.0, 5.0):
        r = ros2(env, *args, '--no-daemon', spin_time=spin_time)
        if found(r):
            break
    return r


def test_ros2_run_topic_hz_param_and_interface():
    with isolated_domain() as dom:
        env = dict(dom.env)
        with started([ROS2, 'run', 'tissue_sim', 'simulator'], env) as sim:
            sim.wait_for_output(r'publishing at', timeout=240)
            # ros2 topic hz prints 'average rate: X' once a second: take the third
            with started([ROS2, 'topic', 'hz', '/joint_states', '--window', '60'], env) as hz:
                m = hz.wait_for_output(r'(?s)average rate: [0-9.]+.*average rate: [0-9.]+.*average rate: ([0-9.]+)',
                                       timeout=60)
            rate = float(m.group(1))
            assert 30.0 < rate < 40.0, f'ros2 topic hz saw {rate} Hz on /joint_states'

            assert '/simulator' in ros2_graph(env, 'node', 'list', found=lambda r: '/simulator' in r.stdout.split()
                                              ).stdout.split()
            r = ros2_graph(env, 'param', 'set', '/simulator', 'rate', '0.5')
            assert r.returncode == 0 and 'successful' in r.stdout, r.stdout + r.stderr
            r = ros2_graph(env, 'param', 'get', '/simulator', 'rate')
            assert re.search(r'0\.5\b', r.stdout), r.stdout + r.stderr
            r = ros2_graph(env, 'param', 'get', '/simulator', 'params')      # the default set moves the knee
            assert 'physical' in r.stdout, r.stdout + r.stderr
            r = ros2_graph(env, 'param', 'set', '/simulator', 'params', 'paper')   # read-only
            assert 'successful' not in r.stdout and 'read-only' in r.stdout + r.stderr, r.stdout + r.stderr
            r = ros2_graph(env, 'param', 'describe', '/simulator', 'publish_rate')
            assert 'Read only: true' in r.stdout, r.stdout
        r = ros2(env, 'interface', 'show', 'tissue_msgs/msg/MuscleActivation')
        assert r.returncode == 0 and 'activation' in r.stdout, r.stdout + r.stderr
        r = ros2(env, 'pkg', 'executables', 'tissue_sim')
        assert {'tissue_sim simulator', 'tissue_sim activation', 'tissue_sim recorder'} <= set(r.stdout.splitlines())


def test_ros2_launch_demo_moves_the_knee_and_one_sigint_stops_all(tmp_path):
    from sensor_msgs.msg import JointState
    import rclpy
    out = tmp_path / 'launch.mcap'
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        knee, tf, desc = [], [], []
        from std_msgs.msg import String
        from tf2_msgs.msg import TFMessage
        from tissue_sim.ros.common import qos_latched
        node.create_subscription(TFMessage, '/tf', tf.append, 100)
        node.create_subscription(String, '/robot_description', desc.append, qos_latched())
        sub = node.create_subscription(
            JointState, '/joint_states',
            lambda m: knee.append(m.position[list(m.name).index('knee_r')]) if 'knee_r' in m.name else None, 10)
        with started([ROS2, 'launch', 'tissue_sim', 'demo.launch.py', 'record:=true', f'output:={out}',
                      'rise:=2.0'], dict(dom.env)) as launch:
            wait_for_publishers(node, sub, 1, timeout=240)
            spin_until(lambda: knee and abs(knee[-1]) > math.radians(20), node, 60,
                       'the launched activation profile to flex the knee beyond 20 degrees')
            # the pip set-up has no robot_state_publisher: the simulator publishes TF and the description
            spin_until(lambda: tf and desc, node, 20, '/tf and /robot_description')
            assert {t.child_frame_id for t in tf[-1].transforms} == {'shank', 'foot', 'patella'}     # the knee, the ankle and the patella (coupled to the knee) move
            assert '<robot name="lower_limb_r">' in desc[0].data
            os.killpg(launch.popen.pid, signal.SIGINT)          # one Ctrl-C
            rc = launch.popen.wait(30)
        node.destroy_node()
    text = launch.output
    assert rc == 0, text
    for exe in ('simulator', 'activation', 'recorder'):
        assert re.search(rf'\[{exe}-\d+\]: process has finished cleanly', text), text
    from mcap.reader import make_reader
    with open(out, 'rb') as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {'/tissue/state', '/joint_states'} <= topics


def test_launch_file_starts_robot_state_publisher_only_when_present_with_the_simulator_tf_off():
    """The launch file's two set-ups, evaluated by launch itself: where robot_state_publisher is
    installed (forced here: the pip set-up has none) it runs with the URDF of the simulator's model
    and sim time, and the simulator's own TF and description are off; where it is absent (this
    set-up, robot_state_publisher:=auto) only the simulator runs, publishing them itself."""
    import importlib.util
    from launch import LaunchContext
    from launch_ros.utilities import evaluate_parameters
    from tissue_sim.core import urdf
    from tissue_sim.core.load import load_model
    path = rosutil.INSTALL / 'tissue_sim' / 'share' / 'tissue_sim' / 'launch' / 'demo.launch.py'
    spec = importlib.util.spec_from_file_location('demo_launch', path)
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    assert not demo.have_robot_state_publisher()          # the pip set-up

    def actions(**conf):
        ctx = LaunchContext()
        ctx.launch_configurations.update(dict({'params': 'physical', 'publish_markers': 'true'}, **conf))
        return {a.node_executable: evaluate_parameters(ctx, a._Node__parameters)[0]
                for a in demo.simulator_and_tf(ctx)}

    got = actions(model='', robot_state_publisher='auto')
    assert list(got) == ['simulator']
    assert got['simulator']['publish_tf'] is True and got['simulator']['publish_robot_description'] is True
    for model in ('', 'phantom:knee'):
        got = actions(model=model, robot_state_publisher='true')
        assert list(got) == ['simulator', 'robot_state_publisher']
        assert got['simulator']['publish_tf'] is False and got['simulator']['publish_robot_description'] is False
        rsp = got['robot_state_publisher']
        assert rsp['use_sim_time'] is True
        assert rsp['robot_description'] == urdf.robot_description(load_model(model))
    with pytest.raises(ValueError, match='robot_state_publisher:=maybe'):
        actions(model='', robot_state_publisher='maybe')
