"""Real nodes over DDS (isolated domains): simulator rate, activation effect, bad-message rejection,
the activation node's defaults and combination rule, recorder (SIGINT -> rosbags reads it; SIGKILL
-> our reader reads it), replay; the simulator's parameters declared once."""
import math
import os
import signal
import time

import numpy as np
import pytest

import rosutil  # noqa: F401  (activates the workspace before rclpy; skips if not built)
from rosutil import (assert_own_participant, isolated_domain, ros_context, run_executable, spin_until,
                     wait_for_publishers, wait_for_subscribers)

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def knee_model(tmp_path_factory):
    """The solver's two-muscle knee phantom (hamstring behind, quadriceps in front), as a file."""
    from tissue_sim.core.solver import phantom
    p = tmp_path_factory.mktemp('model') / 'knee.npz'
    phantom.knee().save(p)
    return p


@pytest.fixture(scope='module')
def builder_model(tmp_path_factory):
    """A model made by the real builder from a labelled phantom volume (bones, muscle, fat, skin)."""
    from phantoms import make_phantom_model
    p = tmp_path_factory.mktemp('model') / 'two_bones.npz'
    make_phantom_model('two_bones').save(p)
    return p


@pytest.fixture(scope='module')
def bundled_names_knee(tmp_path_factory):
    """The knee phantom with its hamstring named as in the bundled limb (long head of biceps femoris,
    group hamstrings), which the paper's names (biceps_femoris, ...) do not name exactly."""
    import dataclasses
    from tissue_sim.core.solver import phantom
    tm = phantom.knee()
    tm = dataclasses.replace(tm, muscle_names=('biceps_femoris_long_head', 'rectus_femoris'))
    assert tm.muscle_groups == ('hamstrings', 'quadriceps')
    p = tmp_path_factory.mktemp('model') / 'knee_bundled_names.npz'
    tm.save(p)
    return p


def sim_args(model, *extra):
    return ('--ros-args', '-p', f'model:={model}', *extra)


class Collector:
    """Arrival times (monotonic) and messages of one topic."""

    def __init__(self, node, cls, topic, keep=True, raw=False, qos=10):
        self.t, self.msgs = [], []
        self.keep = keep
        self.sub = node.create_subscription(cls, topic, self.cb, qos, raw=raw)

    def cb(self, m):
        self.t.append(time.monotonic())
        if self.keep:
            self.msgs.append(m)

    def rate_over(self, t0, t1):
        ts = [t for t in self.t if t0 <= t <= t1]
        return (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 2 else 0.0, len(ts)


def diag_values(msg):
    return {kv.key: kv.value for kv in msg.status[0].values}


def test_simulator_publishes_at_34hz_with_markers(builder_model):
    import rclpy
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage
    from tissue_msgs.msg import MuscleSet, TissueState, TissueTopology
    from visualization_msgs.msg import MarkerArray
    from tissue_sim.core import tissue_cdr
    from tissue_sim.ros.common import qos_latched
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', *sim_args(builder_model), env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        js = Collector(node, JointState, '/joint_states', keep=False)
        # raw: turning each MarkerArray into Python objects here would make this probe the bottleneck
        mk = Collector(node, MarkerArray, '/tissue/markers', raw=True)
        st = Collector(node, TissueState, '/tissue/state', raw=True)
        # /tf beside the markers, with tf2's listener depth: a depth-100 /tf publisher came in bursts here (7-19 Hz)
        tf = Collector(node, TFMessage, '/tf', keep=False, raw=True, qos=100)
        topo = Collector(node, TissueTopology, '/tissue/topology', raw=True, qos=qos_latched())
        bones = Collector(node, MarkerArray, '/tissue/bone_markers', qos=qos_latched())
        muscles = Collector(node, MuscleSet, '/tissue/muscles', qos=qos_latched())
        sim.wait_for_output('simulator ready', timeout=60)
        spin_until(lambda: len(js.t) > 10 and len(mk.t) > 10, node, 30, 'frames to flow')
        t0 = time.monotonic()
        spin_until(lambda: time.monotonic() - t0 > 5.0, node, 10, '5 s of frames')
        r_js, n_js = js.rate_over(t0, t0 + 5.0)
        r_mk, n_mk = mk.rate_over(t0, t0 + 5.0)
        r_tf, n_tf = tf.rate_over(t0, t0 + 5.0)
        print(f'joint_states {r_js:.2f} Hz ({n_js}), markers {r_mk:.2f} Hz ({n_mk}), tf {r_tf:.2f} Hz ({n_tf})')
        assert r_js >= 34.0 and r_mk >= 34.0 and r_tf >= 34.0
        # the markers from a DDS participant of their own (markers_own_participant), the frame's small topics from the
        # node's (bench/ros_rate.py --participants both: what the shared one did to /joint_states and /tf)
        assert_own_participant(node, '/tissue/markers', 'simulator_markers', '/joint_states', 'simulator')
        # a small model's TissueState (under state_own_participant_bytes) from the node's participant
        spin_until(lambda: [p.node_name for p in node.get_publishers_info_by_topic('/tissue/state')] == ['simulator'],
                   node, 20, 'simulator as the publisher of /tissue/state')
        # markers: the soft tissue in 'world' each frame (muscle opaque, skin/fat translucent); the bones
        # once, opaque, in their segments' TF frames, frame-locked (viewers move them with /tf)
        from rclpy.serialization import deserialize_message
        m = deserialize_message(mk.msgs[-1], MarkerArray)
        ns = {x.ns: x for x in m.markers}
        assert {'tissue/muscle/flexor', 'tissue/skin'} <= set(ns) and not any('/bone/' in k for k in ns)
        assert all(x.header.frame_id == 'world' and len(x.points) > 0 for x in m.markers)
        assert ns['tissue/muscle/flexor'].color.a == 1.0 and ns['tissue/skin'].color.a < 0.5
        # sent once (not per frame: 5 s would bring ~170): one message, or that message twice when the probe's
        # transient-local reader matches while the simulator writes it (DDS may then deliver the live sample and the
        # history copy; seen once in CI: 2 identical messages)
        assert 1 <= len(bones.msgs) <= 2 and all(x == bones.msgs[0] for x in bones.msgs), len(bones.msgs)
        b = {x.ns: x for x in bones.msgs[0].markers}
        assert b['tissue/bone/lower'].color.a == 1.0 and b['tissue/bone/lower'].header.frame_id == 'lower'
        assert b['tissue/bone/lower'].frame_locked and len(b['tissue/bone/lower'].points) > 0
        # the compact state decodes, is finite, and matches the topology sent once (transient-local)
        assert len(topo.msgs) == 1
        tp = tissue_cdr.decode_topology(topo.msgs[0])
        s = tissue_cdr.decode_state(st.msgs[-1])
        assert s.vertex_positions.shape == (tp.n_vertices, 3) and np.isfinite(s.vertex_positions).all()
        assert s.joint_names == ['knee'] and s.sim_time > 1.0
        # the muscles alone (what the activation node reads), the topology's, with its model hash
        assert 1 <= len(muscles.msgs) <= 2
        ms = muscles.msgs[0]
        assert list(ms.muscle_names) == list(tp.muscle_names) and list(ms.muscle_groups) == list(tp.muscle_groups)
        assert ms.model_hash == tp.meta['model_hash'] and ms.model_name == tp.name and len(tp.muscle_names) > 0
        # activations (the state), excitations (the commands: none) and each muscle's force [N], one per muscle
        assert s.excitations.shape == s.activations.shape == s.muscle_forces.shape == (len(s.muscle_names),)
        assert np.all(s.excitations == 0) and np.all(np.isfinite(s.muscle_forces))
        node.destroy_node()
    assert sim.returncode == 0, sim.output


@pytest.mark.parametrize('solver_thread', ['true', 'false'])
def test_activation_flexes_the_knee_and_bad_messages_are_rejected(knee_model, solver_thread):
    """Paper experiment (hamstrings only) flexes the knee (+ about +y); every kind of bad message
    is rejected and counted while the node keeps publishing finite frames. Both stepping loops: the
    solver in a thread of its own (the default) and in the frame timer."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from tissue_msgs.msg import MuscleActivation
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', *sim_args(knee_model, '-p', f'solver_thread:={solver_thread}'),
                           env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        js = Collector(node, JointState, '/joint_states')
        diag = Collector(node, DiagnosticArray, '/diagnostics')
        pub = node.create_publisher(MuscleActivation, '/tissue/activation', 10)
        sim.wait_for_output('simulator ready', timeout=60)
        wait_for_subscribers(node, pub, 1, timeout=30)
        spin_until(lambda: diag.msgs, node, 10, 'diagnostics')
        assert diag_values(diag.msgs[-1])['solver_thread'] == str(solver_thread == 'true')
        spin_until(lambda: len(js.msgs) > 5, node, 30, 'joint states')
        # -- bad messages first: none may change the (passive, resting) knee
        bad = [(['hamstring'], [math.nan]), (['hamstring'], [math.inf]), (['hamstring'], [-0.5]),
               (['hamstring'], [1.5]), (['no_such_muscle'], [0.5]), (['hamstring', 'quadriceps'], [0.5])]
        for names, values in bad:
            m = MuscleActivation()
            m.muscle_names = names
            m.activations = values
            pub.publish(m)
        want = {'rejected_nan': '1', 'rejected_inf': '1', 'rejected_out_of_range': '2',
                'rejected_unknown_muscle': '1', 'rejected_length_mismatch': '1'}
        spin_until(lambda: diag.msgs and all(diag_values(diag.msgs[-1]).get(k) == v for k, v in want.items()),
                   node, 15, f'diagnostics counting {want}')
        n_before = len(js.msgs)
        spin_until(lambda: len(js.msgs) > n_before + 20, node, 10, 'frames after the bad messages')
        assert abs(js.msgs[-1].position[0]) < 1e-3, 'a rejected message moved the knee'
        assert diag_values(diag.msgs[-1])['accepted_activations'] == '0'
        assert 'rejected activation message' in sim.output
        # -- the paper experiment from the activation node: hamstrings contract -> knee flexes
        with run_executable('activation', '--profile', 'paper', env=dom.env) as act:
            spin_until(lambda: js.msgs[-1].position[0] > 0.3, node, 30, 'knee flexion > 0.3 rad')
            assert act.returncode is None, act.output
        assert 'profile paper on 2 muscles' in act.output      # hamstring active, quadriceps passive (0)
        q = np.array([m.position[0] for m in js.msgs])
        assert np.isfinite(q).all() and np.all(np.diff(q[-20:]) > -1e-2)
        spin_until(lambda: int(diag_values(diag.msgs[-1])['accepted_activations']) > 0, node, 5,
                   'diagnostics counting accepted activations')
        assert diag_values(diag.msgs[-1])['rejected_nan'] == '1'
        node.destroy_node()
    assert sim.returncode == 0, sim.output


def _publish_activations(node, pub, n, period=0.01):
    from tissue_msgs.msg import MuscleActivation
    for i in range(n):
        m = MuscleActivation()
        m.header.stamp.sec, m.header.stamp.nanosec = 100, i
        m.muscle_names = ['hamstring', 'quadriceps']
        m.activations = [i / n, 1.0 - i / n]
        pub.publish(m)
        t0 = time.monotonic()
        spin_until(lambda: time.monotonic() - t0 >= period, node, 1, 'period')


def test_recorder_sigint_file_read_by_rosbags_then_replayed(tmp_path):
    import rclpy
    from rosbags.highlevel import AnyReader
    from tissue_msgs.msg import MuscleActivation
    from tissue_sim.core import mcapio
    out = tmp_path / 'rec.mcap'
    n = 60
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        pub = node.create_publisher(MuscleActivation, '/tissue/activation', 10)
        with run_executable('recorder', '-o', out, '--only', '--topics', '/tissue/activation', env=dom.env) as rec:
            rec.wait_for_output('recorder: writing', timeout=30)
            wait_for_subscribers(node, pub, 1, timeout=30)
            _publish_activations(node, pub, n)
            t0 = time.monotonic()
            spin_until(lambda: time.monotonic() - t0 > 1.0, node, 5, 'delivery')
        assert rec.returncode == 0, rec.output
        assert f'recorder: {n} messages' in rec.output, rec.output
        # independent reader
        with AnyReader([out]) as r:
            got = [r.deserialize(d, c.msgtype) for c, _, d in r.messages()]
            assert r.connections[0].msgtype == 'tissue_msgs/msg/MuscleActivation'
        assert [m.header.stamp.nanosec for m in got] == list(range(n))
        assert np.allclose([m.activations[0] for m in got], np.arange(n) / n)
        summary = mcapio.scan(out)
        assert not summary.truncated and 'versions' in summary.metadata['tissue_sim']
        # replay on the same topic: same bytes, same order, original spacing
        recorded = [m.data for m in mcapio.iter_messages(out)]
        log_t = np.array([m.log_time for m in mcapio.iter_messages(out)]) * 1e-9
        sub = Collector(node, MuscleActivation, '/tissue/activation', raw=True, qos=100)
        with run_executable('replay', out, '--wait-subscribers', '20', env=dom.env) as rp:
            spin_until(lambda: len(sub.msgs) >= n, node, 30, f'{n} replayed messages')
            rp.wait_for_output('replay: published', timeout=10)
        assert [bytes(b) for b in sub.msgs] == recorded
        gaps_rec, gaps_play = np.diff(log_t), np.diff(sub.t)
        assert abs(gaps_play.sum() - gaps_rec.sum()) < 0.25 * gaps_rec.sum() + 0.05
        node.destroy_node()


def test_recorder_killed_with_sigkill_leaves_a_readable_file(tmp_path):
    import rclpy
    from tissue_msgs.msg import MuscleActivation
    from tissue_sim.core import mcapio
    from tissue_sim.core.cdr import CdrReader
    out = tmp_path / 'killed.mcap'
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        pub = node.create_publisher(MuscleActivation, '/tissue/activation', 10)
        with run_executable('recorder', '-o', out, '--flush', '0.2', env=dom.env) as rec:
            rec.wait_for_output('recorder: writing', timeout=30)
            wait_for_subscribers(node, pub, 1, timeout=30)
            _publish_activations(node, pub, 80)
            t0 = time.monotonic()
            spin_until(lambda: time.monotonic() - t0 > 1.0, node, 5, 'two flush periods')
            rec.popen.send_signal(signal.SIGKILL)
            rec.popen.wait(10)
        node.destroy_node()
    s = mcapio.scan(out)
    assert s.truncated
    nsec = [CdrReader(m.data).header()[0] - 100_000_000_000 for m in mcapio.iter_messages(out)]
    assert nsec == list(range(80))        # everything flushed before the kill, in order


def test_executables_print_usage():
    import subprocess
    for exe in ('simulator', 'activation', 'recorder', 'replay'):
        r = subprocess.run([str(rosutil.exe_path(exe)), '--help'], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and r.stdout.startswith(f'usage: {exe}'), (exe, r.stdout, r.stderr)
    r = subprocess.run([str(rosutil.exe_path('activation')), '--level', '2'], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and r.stderr.strip() == 'error: --level 2.0: must be in [0, 1]'
    r = subprocess.run([str(rosutil.exe_path('activation')), '--level', 'abc'], capture_output=True, text=True,
                       timeout=60)          # argparse's own error: one line too (tissue_sim.errors.ArgumentParser)
    assert r.returncode == 2 and r.stderr.strip() == ("activation: error: argument --level: invalid float value: 'abc' "
                                                      '(--help lists the options)'), r.stderr
    r = subprocess.run([str(rosutil.exe_path('simulator')), '--model', '/nope.npz'], capture_output=True, text=True,
                       timeout=60, env=rosutil.ros_env(0))
    assert r.returncode == 2 and 'error: /nope.npz: no such model file' in r.stderr and 'Traceback' not in r.stderr
    r = subprocess.run([str(rosutil.exe_path('simulator')), '--ros-args', '-p', 'publish_rate:=1000.0'],
                       capture_output=True, text=True, timeout=60, env=rosutil.ros_env(0))
    assert r.returncode == 2 and 'publish_rate out of range' in r.stderr and 'Traceback' not in r.stderr


def test_a_model_that_diverges_from_rest_is_a_set_up_error(tmp_path):
    """The knee phantom, true masses, one 10-ms explicit sub-step under gravity: the node's warm-up diverges at step
    3; the node says so in one line with what to do and exits 2 (was a traceback)."""
    import subprocess
    params = tmp_path / 'unstable.yaml'
    params.write_text('preset: physical\nintegrator: explicit\nsubsteps: 1\ngravity: [0.0, 0.0, -9.81]\n'
                      'bone_contact: false\nfold_contact: ""\nsheath_group: ""\nsheath_below: ""\n')
    r = subprocess.run([str(rosutil.exe_path('simulator')), '--ros-args', '-p', 'model:=phantom:knee',
                        '-p', f'params:={params}', '-p', 'dt:=0.01'], capture_output=True, text=True, timeout=120,
                       env=rosutil.ros_env(0))
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith('error:')]
    assert r.returncode == 2 and 'Traceback' not in r.stderr, r.stderr
    assert len(lines) == 1 and 'does not run with these parameters' in lines[0] and 'diverged at step' in lines[0]
    assert 'integrator: implicit and substeps: 1 in a parameter file' in lines[0]


def test_replay_of_a_simulator_run_restores_state_clock_and_topology(knee_model, tmp_path):
    """Record a real simulator run, then replay it at 2x from 0.5 s in: the same TissueState bytes in
    order, /clock equal to their stamps, the topology delivered to a late (transient-local) joiner."""
    import rclpy
    from rosgraph_msgs.msg import Clock
    from tissue_msgs.msg import TissueState, TissueTopology
    from tissue_sim.core import mcapio
    from tissue_sim.core.cdr import CdrReader
    from tissue_sim.ros.common import qos_latched
    out = tmp_path / 'sim.mcap'
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        seen = Collector(node, TissueState, '/tissue/state', keep=False, raw=True)
        with run_executable('recorder', '-o', out, env=dom.env) as rec, \
                run_executable('simulator', *sim_args(knee_model, '-p', 'publish_markers:=false'), env=dom.env) as sim:
            sim.wait_for_output('simulator ready', timeout=60)
            rec.wait_for_output('recording /tissue/topology', timeout=30)
            rec.wait_for_output('recording /tissue/state', timeout=30)
            n0 = len(seen.t)                 # counted from the recorder's first state on
            spin_until(lambda: len(seen.t) >= n0 + 70, node, 30, '2 s of states')
        states = [m for m in mcapio.iter_messages(out, ['/tissue/state'])]
        topo = [m.data for m in mcapio.iter_messages(out, ['/tissue/topology'])]
        assert len(states) >= 60 and len(topo) == 1
        # --start skips the first 0.5 s of the recording, which starts with its first message of any
        # topic (the topology, published at set-up, can precede the first state by a frame or more)
        t0 = min(m.log_time for m in mcapio.iter_messages(out)) + 500_000_000
        expect = [m.data for m in states if m.log_time >= t0]
        stamps = [CdrReader(d).header()[0] for d in expect]
        st = Collector(node, TissueState, '/tissue/state', raw=True, qos=100)
        clk = Collector(node, Clock, '/clock', qos=100)
        with run_executable('replay', out, '--rate', '2', '--start', '0.5', '--topics', '/tissue/state',
                            '/tissue/topology', '--wait-subscribers', '8', env=dom.env) as rp:
            # a late joiner: created only after the replay has started publishing (so the replay waits its whole
            # 8 s for a subscriber on the topology: the states' and the clock's are matched long before)
            spin_until(lambda: len(st.msgs) >= 3, node, 30, 'replayed states')
            tp = Collector(node, TissueTopology, '/tissue/topology', raw=True, qos=qos_latched())
            def ns(c):
                return c.clock.sec * 1_000_000_000 + c.clock.nanosec
            # /clock is its own topic: wait for its last message too, not only for the states'
            spin_until(lambda: len(st.msgs) >= len(expect) and tp.msgs and clk.msgs and ns(clk.msgs[-1]) >= stamps[-1],
                       node, 30, 'the whole replay')
            rp.wait_for_output('replay: published', timeout=20)
        assert [bytes(b) for b in st.msgs] == expect
        assert bytes(tp.msgs[0]) == topo[0]
        clock_ns = [ns(c) for c in clk.msgs]
        assert clock_ns[-len(stamps):] == stamps
        span_rec = (states[-1].log_time - t0) * 1e-9
        span_play = st.t[-1] - st.t[0]
        assert abs(span_play - span_rec / 2) < 0.2 * span_rec / 2 + 0.1
        node.destroy_node()


def _call(node, client, req, timeout=20):
    assert client.wait_for_service(timeout_sec=timeout), f'service {client.srv_name} not available'
    fut = client.call_async(req)
    spin_until(fut.done, node, timeout, f'{client.srv_name} reply')
    return fut.result()


def test_marker_resolution_and_a_large_state_from_a_participant_of_its_own(builder_model):
    """-p marker_resolution:=R: the soft-tissue markers the node publishes are the model's display surface on that
    grid (core.markers.display_surface): the points of the encoder made with it, fewer than the full surface's.
    -p state_own_participant_bytes:=0: /tissue/state, larger than that, goes out from a DDS participant of its own
    (simulator_state), as a finer model's (1.6 MB on the 6x limb) does by default."""
    import rclpy
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from tissue_sim.core import markers
    from tissue_sim.core.model import TissueModel
    tm = TissueModel.load(builder_model)
    full, coarse = (markers.MarkerArrayEncoder(tm, bones=False, soft_resolution=r) for r in (0.0, 0.02))
    assert coarse.n_points < full.n_points
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', *sim_args(builder_model, '-p', 'marker_resolution:=0.02',
                                                  '-p', 'state_own_participant_bytes:=0'), env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        mk = Collector(node, MarkerArray, '/tissue/markers', raw=True)
        sim.wait_for_output('simulator ready', timeout=60)
        spin_until(lambda: len(mk.msgs) > 2, node, 30, 'markers')
        m = deserialize_message(mk.msgs[-1], MarkerArray)
        assert sum(len(x.points) for x in m.markers) == coarse.n_points < full.n_points
        assert_own_participant(node, '/tissue/state', 'simulator_state', '/joint_states', 'simulator')
        node.destroy_node()
    assert sim.returncode == 0, sim.output


def test_the_solver_steps_in_its_own_thread_by_default_and_in_the_timer_on_one_cpu(knee_model):
    """solver_thread defaults to true: on this machine's CPUs the node steps in a thread of its own; the same node
    allowed one CPU only (taskset) steps in its frame timer, says so in its log, and its diagnostics say
    solver_thread False."""
    import shutil
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from tissue_sim.core.realtime import usable_cpus
    if shutil.which('taskset') is None:
        pytest.skip('taskset (util-linux) not installed')
    runs = [([], 'True')] if usable_cpus() >= 2 else []
    runs.append((['taskset', '-c', str(min(os.sched_getaffinity(0)))], 'False'))
    for prefix, want in runs:
        with isolated_domain() as dom, ros_context(dom.id) as ctx, \
                rosutil.start_process([*prefix, str(rosutil.exe_path('simulator')), *sim_args(knee_model)],
                                      env=dom.env) as sim:
            node = rclpy.create_node('probe', context=ctx)
            diag = Collector(node, DiagnosticArray, '/diagnostics')
            sim.wait_for_output('simulator ready', timeout=60)
            spin_until(lambda: diag.msgs, node, 10, 'diagnostics')
            assert diag_values(diag.msgs[-1])['solver_thread'] == want, (prefix, sim.output)
            assert ('one CPU only' in sim.output) == (want == 'False'), sim.output
            node.destroy_node()
        assert sim.returncode == 0, sim.output


@pytest.mark.parametrize('solver_thread', ['true', 'false'])
def test_pause_reset_services_and_divergence_is_reported_not_published(knee_model, tmp_path, solver_thread):
    """~/pause stops sim time, ~/reset returns to rest; a solver divergence (forced with a tiny
    max_speed) pauses the node with an ERROR diagnostic while frames keep flowing, never NaN. Both
    stepping loops (the solver thread: the divergence is raised in it)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from sensor_msgs.msg import JointState
    from std_srvs.srv import SetBool, Trigger
    from tissue_msgs.msg import MuscleActivation
    params = tmp_path / 'fragile.yaml'
    params.write_text('max_speed: 0.05\n')        # [m/s]: a contracting hamstring exceeds it at once
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', *sim_args(knee_model, '-p', f'params:={params}', '-p', 'realtime:=false',
                                                  '-p', f'solver_thread:={solver_thread}'), env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        js = Collector(node, JointState, '/joint_states')
        diag = Collector(node, DiagnosticArray, '/diagnostics')
        pause = node.create_client(SetBool, '/simulator/pause')
        reset = node.create_client(Trigger, '/simulator/reset')
        pub = node.create_publisher(MuscleActivation, '/tissue/activation', 10)
        sim.wait_for_output('simulator ready', timeout=60)
        spin_until(lambda: len(js.msgs) > 3, node, 30, 'frames')
        stamp = lambda m: m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec   # noqa: E731
        # as fast as possible: sim time runs faster than wall time
        t_sim0, t_wall0 = stamp(js.msgs[-1]), time.monotonic()
        spin_until(lambda: time.monotonic() - t_wall0 > 1.0, node, 5, '1 s')
        assert stamp(js.msgs[-1]) - t_sim0 > 1.5
        assert _call(node, pause, SetBool.Request(data=True)).success
        spin_until(lambda: time.monotonic() - t_wall0 > 1.3, node, 5, 'settle')
        n, t_paused = len(js.msgs), stamp(js.msgs[-1])
        spin_until(lambda: len(js.msgs) > n + 10, node, 10, 'frames while paused')
        assert stamp(js.msgs[-1]) == t_paused                   # frames flow, time stands still
        assert _call(node, reset, Trigger.Request()).success
        spin_until(lambda: stamp(js.msgs[-1]) < 0.5, node, 10, 'sim time back to 0')
        assert _call(node, pause, SetBool.Request(data=False)).success
        # divergence
        wait_for_subscribers(node, pub, 1, timeout=20)
        m = MuscleActivation()
        m.muscle_names, m.activations = ['hamstring'], [1.0]
        pub.publish(m)
        spin_until(lambda: diag.msgs and diag.msgs[-1].status[0].level == DiagnosticStatus.ERROR, node, 20,
                   'an ERROR diagnostic')
        assert 'diverged' in diag.msgs[-1].status[0].message
        n = len(js.msgs)
        spin_until(lambda: len(js.msgs) > n + 10, node, 10, 'frames after the divergence')
        assert all(np.isfinite(list(j.position)).all() for j in js.msgs)
        assert 'solver diverged' in sim.output
        assert 'integrator: implicit and substeps: 1' in sim.output      # (the paper set: mass_scaled)
        resp = _call(node, pause, SetBool.Request(data=False))
        assert not resp.success and 'reset' in resp.message
        node.destroy_node()
    assert sim.returncode == 0, sim.output


def test_a_stop_during_start_up_is_a_stop_not_a_traceback(capsys):
    """SIGINT/SIGTERM while a node is still setting up: before rclpy.init it is a KeyboardInterrupt; after
    it, rclpy's handler has shut the context down and the next rclpy call raises (RCLError or
    NotInitializedException, depending on where the call meets the shut-down context). Both end the
    node as a stop does later ('stopped', exit code 0); any other error still propagates."""
    import rclpy
    from tissue_sim.ros.common import main_wrapper

    @main_wrapper
    def interrupted_before_init(argv=None):
        raise KeyboardInterrupt

    @main_wrapper
    def shut_down_before_the_node(argv=None):
        rclpy.init()
        rclpy.shutdown()                      # what rclpy's signal handler does
        rclpy.create_node('never_made')       # raises: rclpy is not initialised

    @main_wrapper
    def a_real_failure(argv=None):
        raise RuntimeError('boom')

    try:
        rc = interrupted_before_init()
    except KeyboardInterrupt:               # (would end the whole pytest session, not fail this test)
        pytest.fail('KeyboardInterrupt escaped main_wrapper')
    assert rc == 0
    assert shut_down_before_the_node() == 0
    assert capsys.readouterr().err.splitlines() == ['stopped', 'stopped']
    with pytest.raises(RuntimeError, match='boom'):
        a_real_failure()


def test_a_sigint_inside_take_message_is_a_stop_any_other_failure_is_not():
    """A SIGINT whose KeyboardInterrupt lands inside a subscription's take_message reaches common.spin as pybind11's
    RuntimeError ('Unable to convert call argument'), possibly before rclpy's own thread has shut the context down:
    spin counts it as the stop once the context goes down (here 0.1 s later, as rclpy's handler does); with the
    context still up after the wait, or any other RuntimeError, it is a failure and propagates."""
    import threading
    import rclpy
    from tissue_sim.ros.common import _shutdown_race
    race = RuntimeError("Unable to convert call argument '0' to Python object (#define PYBIND11_DETAILED_ERROR_MESSAGES "
                        "or compile in debug mode for details)")
    rclpy.init()
    try:
        assert not _shutdown_race(race)                 # the context stays up: a real fault
        assert not _shutdown_race(RuntimeError('boom'))
        timer = threading.Timer(0.1, rclpy.shutdown)
        timer.start()
        assert _shutdown_race(race)
        timer.join()
        assert not _shutdown_race(RuntimeError('boom'))  # other errors are faults even then
    finally:
        if rclpy.ok():
            rclpy.shutdown()


def test_a_burst_of_sigints_is_one_clean_stop(tmp_path, bundled_names_knee):
    """`ros2 launch` forwards a Ctrl-C to its nodes while the terminal's (or a killpg's) reaches them too,
    and users press it twice: six SIGINTs 10 ms apart end a running simulator and a running recorder
    cleanly (exit code 0, no traceback), and the recorder's MCAP file is finished (an independent reader
    finds its summary). Before ros.common.ignore_further_interrupts a later SIGINT, raised as a
    KeyboardInterrupt after main returned, made Python kill itself with SIGINT: the simulator exited with
    -2 (seen once in the launch test under load, every time with this burst)."""
    from mcap.reader import make_reader
    out = tmp_path / 'burst.mcap'
    for exe, args, ready in (('simulator', sim_args(bundled_names_knee, '-p', 'publish_markers:=false'),
                              'simulator ready'),
                             ('recorder', ('-o', out), 'recorder: writing')):
        with isolated_domain() as dom, run_executable(exe, *args, env=dom.env) as node:
            node.wait_for_output(ready, timeout=120)
            time.sleep(0.5)
            for _ in range(6):
                node.popen.send_signal(signal.SIGINT)
                time.sleep(0.01)
            rc = node.popen.wait(30)
        assert rc == 0, f'{exe}: exit {rc}\n{node.output}'
        assert 'Traceback' not in node.output, node.output
    with open(out, 'rb') as f:
        assert make_reader(f).get_summary() is not None


def test_activation_defaults_drive_the_hamstrings_of_the_model_the_simulator_runs(bundled_names_knee):
    """`activation --profile ramp` (no muscles given) and `activation` (no arguments) contract the
    hamstrings of the running model, whatever their names: the knee flexes, no message is rejected."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    with isolated_domain() as dom, ros_context(dom.id) as ctx, \
            run_executable('simulator', *sim_args(bundled_names_knee, '-p', 'publish_markers:=false'),
                           env=dom.env) as sim:
        node = rclpy.create_node('probe', context=ctx)
        js = Collector(node, JointState, '/joint_states')
        diag = Collector(node, DiagnosticArray, '/diagnostics')
        reset = node.create_client(Trigger, '/simulator/reset')
        sim.wait_for_output('simulator ready', timeout=60)
        spin_until(lambda: len(js.msgs) > 5, node, 30, 'joint states')
        with run_executable('activation', '--profile', 'ramp', '--rise', '0.5', env=dom.env) as act:
            spin_until(lambda: js.msgs[-1].position[0] > 0.3, node, 30, 'knee flexion > 0.3 rad (ramp)')
            assert act.returncode is None, act.output
        assert 'profile ramp on 1 muscles: biceps_femoris_long_head' in act.output, act.output
        assert _call(node, reset, Trigger.Request()).success
        spin_until(lambda: abs(js.msgs[-1].position[0]) < 0.05, node, 10, 'the knee back at rest')
        with run_executable('activation', env=dom.env) as act:
            spin_until(lambda: js.msgs[-1].position[0] > 0.3, node, 30, 'knee flexion > 0.3 rad (no arguments)')
        assert 'profile paper on 2 muscles: biceps_femoris_long_head, rectus_femoris' in act.output, act.output
        spin_until(lambda: diag.msgs and int(diag_values(diag.msgs[-1])['accepted_activations']) > 0, node, 5,
                   'diagnostics counting accepted activations')
        assert diag_values(diag.msgs[-1])['rejected_unknown_muscle'] == '0'
        node.destroy_node()
    assert sim.returncode == 0, sim.output


def _muscle_set(tm):
    """The /tissue/muscles message the simulator publishes for model ``tm`` (its names and groups)."""
    from tissue_msgs.msg import MuscleSet
    return MuscleSet(model_name=tm.name, muscle_names=list(tm.muscle_names), muscle_groups=list(tm.muscle_groups))


def test_a_timeline_means_the_same_headless_and_through_the_activation_node(knee_model, tmp_path):
    """One activation YAML, two ways: the activation node's messages and the headless solver's
    timeline (what `tissue-sim simulate --timeline` runs) give the same activations, the most
    specific entry setting a muscle (hamstring 0.5, not 0.3 + 0.5 and not the later 'all' 0.3)."""
    import rclpy
    import yaml
    from tissue_msgs.msg import MuscleActivation, MuscleSet
    from tissue_sim.core import solver
    from tissue_sim.core.model import TissueModel
    from tissue_sim.ros.common import qos_latched
    f = tmp_path / 'overlap.yaml'
    f.write_text('muscles:\n  hamstrings: [[0.0, 0.5]]\n  all: [[0.0, 0.3]]\n')
    tm = TissueModel.load(knee_model)
    headless = solver.timeline_function(solver.compile_model(tm, solver.Params.paper()),
                                        yaml.safe_load(f.read_text())['muscles'])
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        topo = node.create_publisher(MuscleSet, '/tissue/muscles', qos_latched())
        topo.publish(_muscle_set(tm))                    # as the simulator does
        got = Collector(node, MuscleActivation, '/tissue/activation')
        with run_executable('activation', '--profile', 'timeline', '--timeline', f, '--wall-time', '--rate', '20',
                            env=dom.env) as act:
            spin_until(lambda: len(got.msgs) >= 3, node, 30, '3 activation messages')
        node.destroy_node()
    assert act.returncode == 0, act.output
    m = got.msgs[-1]
    assert list(m.muscle_names) == list(tm.muscle_names) == ['hamstring', 'quadriceps']
    assert list(m.activations) == pytest.approx(list(headless(1.0))) and list(m.activations) == pytest.approx([0.5, 0.3])


def test_simulator_parameters_are_declared_once():
    """The flags, config/simulator.yaml and the docs table all come from (or are checked against)
    the one declaration of each parameter."""
    import yaml
    from tissue_sim.nodes.simulator import PARAMS, build_parser
    from tissue_sim.ros.common import overrides, params_table, params_yaml
    cfg = rosutil.ROOT / 'src' / 'tissue_sim' / 'tissue_sim' / 'config' / 'simulator.yaml'
    assert yaml.safe_load(cfg.read_text()) == params_yaml('simulator', PARAMS)
    assert params_table(PARAMS) in (rosutil.ROOT / 'docs' / 'ros.md').read_text()
    usage = build_parser().format_help()
    assert all(p.flag in usage for p in PARAMS)
    args = build_parser().parse_args(['--as-fast-as-possible', '--colouring', 'skin_area', '--rate', '0.5',
                                      '--no-markers', '--bone-marker-resolution', '0'])
    assert {p.name: p.value for p in overrides(args, PARAMS)} == {
        'realtime': False, 'marker_colouring': 'skin_area', 'rate': 0.5, 'publish_markers': False,
        'bone_marker_resolution': 0.0}


def test_activation_set_resolves_groups_from_the_models_muscles_then_exits(knee_model):
    """`activation --set GROUP=V ...` waits for the model's muscles (/tissue/muscles), publishes one message naming
    the group's muscles, and exits 0 (its own end through the shared main)."""
    import rclpy
    from tissue_msgs.msg import MuscleActivation, MuscleSet
    from tissue_sim.core.model import TissueModel
    from tissue_sim.ros.common import qos_latched
    tm = TissueModel.load(knee_model)
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        topo = node.create_publisher(MuscleSet, '/tissue/muscles', qos_latched())
        topo.publish(_muscle_set(tm))
        got = Collector(node, MuscleActivation, '/tissue/activation')
        with run_executable('activation', '--set', 'hamstrings=0.7', 'quadriceps=0.2', env=dom.env) as act:
            spin_until(lambda: got.msgs, node, 30, 'the message')
            spin_until(lambda: act.returncode is not None, node, 20, 'the node to exit')
        node.destroy_node()
    assert act.returncode == 0 and 'Traceback' not in act.output, act.output
    assert len(got.msgs) == 1
    assert list(got.msgs[0].muscle_names) == ['hamstring', 'quadriceps']
    assert list(got.msgs[0].activations) == pytest.approx([0.7, 0.2])


def test_activation_follows_the_model_a_new_muscle_set_announces(knee_model, bundled_names_knee):
    """A simulator restarted with another model announces its muscles again (/tissue/muscles): the activation node
    resolves its default muscles (the hamstrings) again, by the new model's names."""
    import rclpy
    from tissue_msgs.msg import MuscleActivation, MuscleSet
    from tissue_sim.core.model import TissueModel
    from tissue_sim.ros.common import qos_latched
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        topo = node.create_publisher(MuscleSet, '/tissue/muscles', qos_latched())
        topo.publish(_muscle_set(TissueModel.load(knee_model)))
        got = Collector(node, MuscleActivation, '/tissue/activation')
        with run_executable('activation', '--profile', 'step', '--rate', '20', env=dom.env) as act:
            spin_until(lambda: got.msgs and list(got.msgs[-1].muscle_names) == ['hamstring'], node, 30,
                       'messages for the first model')
            topo.publish(_muscle_set(TissueModel.load(bundled_names_knee)))
            spin_until(lambda: list(got.msgs[-1].muscle_names) == ['biceps_femoris_long_head'], node, 30,
                       'messages for the second model')
        node.destroy_node()
    assert act.returncode == 0, act.output
    assert list(got.msgs[-1].activations) == pytest.approx([1.0])
    assert act.output.count('profile step on 1 muscles') == 2, act.output
