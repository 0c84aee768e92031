"""No stalls in the frame stream (issue 21, item 6): a demo-like run of the real nodes over DDS
(recorder + simulator on the bundled limb with its defaults, the solver in a thread of its own, markers on, started
paused; activation node; resume, pause, resume, reset through the services) is recorded, and the publish times of
/joint_states (the simulator's DDS source timestamps, as the recorder writes them), from the first frame on, have no
gap above the limit. (The frames of a node stepping in its frame timer, `solver_thread: false`, go out at the start of
each tick, so a resume does not shift them: stepping first, the first frame after a resume came 46-62 ms after the
last paused one.)

Publish times, not log times. The recorder's log time is when a message arrived there; Fast DDS
sometimes delivers a frame to the recorder ~0.3 s late while a node joins the graph (the activation
node here: 321-354 ms in 5 of 26 runs; the frames behind it then arrive at once, none lost), while the
simulator sent every frame on time (source timestamps' largest gap 53 ms in the same runs) and an
independent subscriber saw no gap over 25 ms. The delivery delays are printed, and checked to be
occasional and bounded (below 1 s).

The limit. The requirement is 60 ms (under two frame periods at 34 Hz) on an idle machine; the test
uses it when the machine is idle (1-minute load average below half the CPU count). On a loaded
machine the operating system alone delays a runnable process by tens of milliseconds: 60-111 ms
gaps were measured here with 2 cores shared by 7 jobs in runs whose every gap matched a late timer
tick of the simulator, not a slow frame. There the limit is 250 ms: above those delays, below the
one-time stalls of the issue (0.32 s and 0.68 s on an idle machine). The load is taken when a run
ends; a run over the limit is repeated once (a node's stall shows twice, another process holding a
core for a moment does not). The gaps found are printed either way (pytest -s).

The DDS layer's hold. The simulator times each publish() call and logs one over 100 ms (nodes/simulator.py). In a CI
run of the whole suite on 2026-11-29 the gap at the activation node's join (325 and 320 ms, one in each of the run's
two sequences; gaps of 0.31-0.36 s there had failed CI runs since 2026-11-26, intermittently) was such a call: "publishing on /joint_states
took 320 ms (inside the DDS layer ...)". Fast DDS 2.14 (2.14.5 is the only ros-fastrtps on PyPI) can hold every
publisher of a process for ~1/3 s while it opens a newly discovered participant's shared-memory port
(eProsima/Fast-DDS#6535, open). That is not the node's stall: a gap over the limit passes when a publish() call the
simulator logged as held overlaps it, the hold is under DDS_HOLD_MAX_S and the gap less the hold is under the limit;
at most DDS_HOLDS_MAX holds in a run. Every other gap over the limit fails, the simulator's log lines in the message."""
import os
import re
import signal
import time

import numpy as np
import pytest

import rosutil  # noqa: F401  (activates the workspace before rclpy; skips if not built)
from rosutil import isolated_domain, ros_context, run_executable, spin_until

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DDS_HOLD_MAX_S = 0.5        # the upstream hold is ~1/3 s per port opening (1/3 of Fast DDS's 1-s health-check timeout)
DDS_HOLDS_MAX = 2           # in a run: the recorder and the activation node join while frames flow
_HELD = re.compile(r'\[(\d+)\.(\d+)\] \[simulator\]: publishing on (\S+) took (\d+) ms \(inside the DDS layer')


def dds_holds(output: str) -> list:
    """(start, end) [ns, system clock] of each publish() call the simulator logged as held by the DDS layer (the log
    line's stamp is its end)."""
    holds = []
    for m in _HELD.finditer(output):
        end = int(m.group(1)) * 1_000_000_000 + int(m.group(2).ljust(9, '0')[:9])
        holds.append((end - int(m.group(4)) * 1_000_000, end))
    return holds

def _limit_s() -> tuple[float, bool]:
    """(limit [s], idle): taken when a sequence ends (the 1-minute load average over its run), not
    at collection: in a whole test session the load comes from the session itself."""
    idle = os.getloadavg()[0] < 0.5 * (os.cpu_count() or 1)
    return (0.060 if idle else 0.250), idle


def _call(node, client, req, timeout=20):
    assert client.wait_for_service(timeout_sec=timeout), f'service {client.srv_name} not available'
    fut = client.call_async(req)
    spin_until(fut.done, node, timeout, f'{client.srv_name} reply')
    assert fut.result().success, fut.result().message


def test_joint_states_have_no_gap_across_start_pause_resume_reset(tmp_path):
    """The sequence runs once more when its largest gap is over the limit (another process of a busy
    machine can hold a core for a moment); a stall of the node shows in both runs and fails."""
    first = _sequence(tmp_path / 'first')
    if first is None:
        return
    again = _sequence(tmp_path / 'again')
    assert again is None, f'{first}\nand again: {again}'


def _sequence(tmp_path):
    """Start paused, resume, pause, resume, reset, with the recorder on; None when the recorded
    /joint_states have no gap over the limit, else what was seen."""
    import rclpy
    from sensor_msgs.msg import JointState
    from std_srvs.srv import SetBool, Trigger
    from tissue_sim.core import mcapio
    tmp_path.mkdir(parents=True, exist_ok=True)
    out = tmp_path / 'run.mcap'
    events = {}
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        js = []
        node.create_subscription(JointState, '/joint_states', js.append, 10)
        pause = node.create_client(SetBool, '/simulator/pause')
        reset = node.create_client(Trigger, '/simulator/reset')

        def wait(seconds, what):
            t0 = time.monotonic()
            spin_until(lambda: time.monotonic() - t0 >= seconds, node, seconds + 5, what)

        with run_executable('recorder', '-o', out, env=dom.env) as rec, \
                run_executable('simulator', '--ros-args', '-p', 'start_paused:=true', env=dom.env,
                               stop_timeout=20) as sim:
            sim.wait_for_output('simulator ready', timeout=240)
            rec.wait_for_output('recording /joint_states', timeout=30)
            wait(1.0, 'paused frames')
            with run_executable('activation', '--profile', 'ramp', '--rise', '2', env=dom.env) as act:
                act.wait_for_output('profile ramp', timeout=60)
                events['resume'] = time.time_ns()
                _call(node, pause, SetBool.Request(data=False))
                spin_until(lambda: js and js[-1].position[js[-1].name.index('knee_r')] > 0.05, node, 30,
                           'the knee to flex')
                wait(1.0, 'running')
                events['pause'] = time.time_ns()
                _call(node, pause, SetBool.Request(data=True))
                wait(0.7, 'paused')
                events['resume again'] = time.time_ns()
                _call(node, pause, SetBool.Request(data=False))
                wait(1.0, 'running')
                events['reset'] = time.time_ns()
                _call(node, reset, Trigger.Request())
                wait(1.5, 'running after the reset')
                events['end'] = time.time_ns()
            sim.stop(signal.SIGINT, timeout=20)
        node.destroy_node()
    assert sim.returncode == 0 and rec.returncode == 0, sim.output + rec.output
    msgs = [(m.publish_time, m.log_time) for m in mcapio.iter_messages(out, ['/joint_states'])]
    sent, got = np.array(msgs, np.int64).T
    keep = sent <= events['end']
    t, got = sent[keep], got[keep]
    gaps = np.diff(t) * 1e-9
    late = (got - t) * 1e-9                 # delivery delay to the recorder
    got_gaps = np.diff(got) * 1e-9
    limit, idle = _limit_s()
    worst = np.argsort(gaps)[::-1][:5]
    at = {k: (v - t[0]) * 1e-9 for k, v in events.items()}
    print(f'\n{len(t)} frames over {(t[-1] - t[0]) * 1e-9:.2f} s; events at ' +
          ', '.join(f'{k} {v:.2f} s' for k, v in at.items()) +
          '\nlargest gaps: ' + ', '.join(f'{1e3 * gaps[i]:.0f} ms at {(t[i + 1] - t[0]) * 1e-9:.2f} s'
                                          for i in worst) +
          f'\np99 {1e3 * np.percentile(gaps, 99):.0f} ms; limit {1e3 * limit:.0f} ms ({"idle" if idle else "loaded"} '
          f'machine, load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)'
          f'\nreceived by the recorder: largest gap {1e3 * got_gaps.max():.0f} ms, delay median '
          f'{1e3 * np.median(late):.1f} ms, max {1e3 * late.max():.0f} ms')
    assert at['resume'] > 0.5 and len(t) > 100        # paused frames, then the whole sequence
    # publish times are the sender's (not the receive time again): before the receive, mostly by well under a frame
    assert (late > 0).mean() > 0.9 and late.min() >= -0.005 and np.median(late) < 0.02 and late.max() < 1.0, (late.min(), np.median(late), late.max())
    # what the simulator said of its frame loop (nodes/simulator.py: a publish() call held by the DDS layer, a late tick)
    said = [ln for ln in sim.output.splitlines() if 'inside the DDS layer' in ln or 'frame tick' in ln]
    holds = dds_holds(sim.output)
    slack = 5_000_000                       # [ns] the log stamp comes a moment after the call returns
    own = []                                # gaps over the limit that no DDS hold explains
    for i in np.flatnonzero(gaps >= limit):
        held = [(a, b) for a, b in holds if a - slack < t[i + 1] and b + slack > t[i]]
        d = max((b - a for a, b in held), default=0) * 1e-9
        if held and d < DDS_HOLD_MAX_S and gaps[i] - d < limit:
            print(f'{1e3 * gaps[i]:.0f} ms gap at {(t[i + 1] - t[0]) * 1e-9:.2f} s: a publish() call held {1e3 * d:.0f} ms '
                  f'inside the DDS layer (eProsima/Fast-DDS#6535), not the node\'s stall')
        else:
            own.append(i)
    assert len(holds) <= DDS_HOLDS_MAX, said
    if not own:
        return None
    i = max(own, key=lambda k: gaps[k])
    return (f'{1e3 * gaps[i]:.0f} ms gap in /joint_states at {(t[i + 1] - t[0]) * 1e-9:.2f} s '
            f'(limit {1e3 * limit:.0f} ms); events at {at}; the simulator logged: {said or "nothing"}')


def test_the_set_up_objects_are_frozen_out_of_the_garbage_collector(monkeypatch):
    """The cause of the stalls found by timing the simulator's frames: the first full (generation-2)
    collection, triggered a few seconds into the run by the frames' allocations, scanned every
    object of the set-up (~140 000: modules, model, compiled kernels) in 54-125 ms. The nodes' main
    freezes them (ros.common.freeze_setup_objects) before spinning: a later full collection scans
    only what the run allocated."""
    import argparse
    import gc
    from tissue_sim.nodes.simulator import Simulator
    from tissue_sim.ros import common
    from rclpy.parameter import Parameter
    seen = {}

    def make(args):
        node = Simulator(parameter_overrides=[Parameter('model', value='phantom:knee')])

        def run():          # in place of rclpy.spin: what a full collection would scan now
            seen.update(frozen=gc.get_freeze_count(), tracked=len(gc.get_objects()))
        node.run = run
        return node
    with isolated_domain() as dom:
        monkeypatch.setenv('ROS_DOMAIN_ID', str(dom.id))
        try:
            assert common.main(make, argparse.ArgumentParser(), ['simulator']) == 0
        finally:
            gc.unfreeze()
    print(f"\nfrozen {seen['frozen']} objects; {seen['tracked']} left to the collector")
    assert seen['frozen'] > 50_000 and seen['tracked'] < 0.02 * seen['frozen'], seen


def test_the_simulator_reports_a_publish_call_the_dds_layer_held_and_a_late_tick():
    """What the stall test prints when it fails: a publish() call over SLOW_PUBLISH_S (here the real /joint_states
    publisher behind a 150-ms wait, standing in for Fast DDS opening a new participant's shared-memory port) is logged
    with its topic, counted and in /diagnostics' publish_call_ms_max; a tick long after the last one is counted."""
    import time as _time
    from rclpy.parameter import Parameter
    from tissue_sim.nodes import simulator as S
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = S.Simulator(context=ctx, parameter_overrides=[Parameter('model', value='phantom:knee')])
        try:
            node.publish_frame(node.state)
            assert node.slow_publishes == 0 and node.publish_call_max < S.SLOW_PUBLISH_S
            pub = node.pub_joints
            real = pub.publish

            class Held:                 # the real publisher, held 150 ms first
                topic_name = node.pub_joints.topic_name

                def publish(self, msg):
                    _time.sleep(0.15)
                    real(msg)
            node.pub_joints = Held()
            node.publish_frame(node.state)
            f = node.figures(_time.monotonic())
            assert node.slow_publishes == 1 and f['slow_publishes'] == 1 and f['publish_call_ms_max'] >= 150.0, f
            node.pub_joints = pub
            node.last_tick = _time.monotonic() - 0.5
            node.tick()
            assert node.late_ticks == 1
            node.tick()
            assert node.late_ticks == 1
        finally:
            node.destroy_node()
