"""`simulator` node: runs the tissue solver in real time and publishes the deformed limb.

Publishes (at ``publish_rate`` Hz of wall time): /clock (sim time), /joint_states,
/tissue/state (TissueState), /tissue/markers (MarkerArray of the whole model), /tf (the moving
segments' frames, sim time), /diagnostics (1 Hz); once (transient-local): /tissue/topology, /tissue/muscles
(the muscle names and groups alone, for the activation node),
/tf_static (the fixed frames, the root segment under ``world`` when the root is fixed) and
/robot_description (the URDF of the model the node runs, tissue_sim.core.urdf). Subscribes to
/tissue/activation. Services ~/reset (std_srvs/Trigger) and ~/pause (std_srvs/SetBool, true = pause).

TF frames are the model's segment names (thigh, shank, foot, patella for the bundled limb) under the root
frame ``world`` (the model frame, the hip joint centre of the bundled limb at its origin); a segment's
frame is its URDF link frame, so robot_state_publisher fed the same /robot_description and
/joint_states gives the same tree (then run the simulator with ``publish_tf: false``).

Timing (tissue_sim.core.realtime): in real-time mode (``realtime: true``) sim time advances by the
wall time x ``rate``, in solver steps of params.dt, at most ``max_steps_per_tick`` steps at a time
(when the solver cannot keep up, sim time falls behind and /diagnostics shows the real-time factor).
With ``realtime: false`` (as fast as possible) the solver steps all the time it has, while frames keep
their rate. With ``solver_thread: true`` (the default; on a machine with two CPUs or more, realtime.usable_cpus)
the solver steps in a thread of its own (realtime.SolverThread: the compiled step releases the GIL) and
each frame publishes the state its last chunk left; with ``false``, or on one CPU, each frame's timer callback
publishes the state its last steps left, then steps (one core).

Parameters (PARAMS below, each declared once) have descriptors (``ros2 param describe /simulator
<name>``), a command-line flag each, and load from YAML with ``--ros-args --params-file
config/simulator.yaml``.
"""
from __future__ import annotations

import argparse
import collections
import sys
import time

import numpy as np
from rclpy.node import Node

from ..core import markers as mk
from ..core import measures, realtime, urdf
from ..core.activation import REASONS, Muscles
from ..core.load import implicit_hint
from ..errors import ArgumentParser
from ..ros.common import (TOPIC_ACTIVATION, TOPIC_CLOCK, TOPIC_DIAGNOSTICS, TOPIC_JOINTS, TOPIC_MARKERS,
                          TOPIC_BONE_MARKERS, TOPIC_ROBOT_DESCRIPTION, TOPIC_STATE, TOPIC_TF, TOPIC_TF_STATIC,
                          TOPIC_MUSCLES, TOPIC_TOPOLOGY, OwnParticipant, Param, add_flags, declare, overrides,
                          qos_latched, qos_stream)
from ..ros.common import main as node_main

SLOW_PUBLISH_S = 0.1        # a publish() call longer than this is logged (the DDS layer held the frame loop)
LATE_TICK_PERIODS = 3.0     # a frame tick this many periods (and 0.1 s) after the last one is logged

PARAMS = (
    Param('model', '', "model file (.npz); '' = the bundled lower limb; phantom:knee = the solver's knee phantom",
          read_only=True),
    Param('params', 'physical', "solver parameters: physical (SI), paper (the paper's Table 2: the reproduction "
          'setting) or a YAML file', read_only=True),
    Param('dt', 0.0, "solver step [s]; 0 = the parameter set's dt", lo=0.0, hi=0.01, read_only=True),
    Param('publish_rate', 34.0, 'floor on frames published per second of wall time [Hz]; frames are scheduled '
          f'{100 * (realtime.HEADROOM - 1):.0f} % above it so timer jitter never drops below it',
          lo=1.0, hi=240.0, read_only=True),
    Param('rate', 1.0, 'sim seconds per wall second in real-time mode', lo=0.001, hi=100.0),
    Param('realtime', True, 'true: sim time follows wall time x rate; false: as fast as possible',
          aliases=(('--as-fast-as-possible', False),)),
    Param('publish_markers', True, 'publish /tissue/markers (full deformed mesh)', aliases=(('--no-markers', False),)),
    Param('marker_rate', 0.0, 'publish /tissue/markers at most this often [Hz of wall time]; 0 = every frame '
          '(a full-mesh frame is ~0.8 MB: a recorder or a remote viewer may want fewer)', lo=0.0, hi=240.0),
    Param('markers_own_participant', True, 'publish /tissue/markers from a DDS participant of its own '
          '(node <name>_markers): the full-mesh frames then do not hold up the small topics in Fast DDS\'s shared '
          'memory (ros.common.OwnParticipant); false: from the node\'s participant', read_only=True),
    Param('publish_state', True, 'publish /tissue/state (compact state, for recording)'),
    Param('state_own_participant_bytes', 262144, 'publish /tissue/state from a DDS participant of its own (node '
          '<name>_state) when a TissueState is larger than this [bytes] (a finer model\'s: 1.6 MB on the 6x limb, '
          'against the bundled limb\'s 55 kB), as the markers: it then does not hold up the small topics; -1 = never',
          lo=-1, hi=2 ** 31 - 1, read_only=True),
    Param('marker_colouring', 'none', 'skin colouring: none, skin_area (Fig. 8) or fat_deformation (Fig. 9)',
          choices=mk.COLOURINGS, read_only=True, aliases=('--colouring',)),
    Param('colour_scale', 0.2, 'skin_area: area change at full colour (0.2 = +-20 %); fat_deformation: d at full '
          'red [m]', lo=1e-6, hi=10.0),
    Param('marker_resolution', 0.0, "the soft tissue's markers drawn on a display surface decimated by vertex "
          'clustering on a grid of this size [m] (each cluster at its vertex nearest its mean; for finer models); 0 = '
          'the full surface', lo=0.0, hi=0.05, read_only=True),
    Param('bone_marker_resolution', 0.003, 'bone meshes in the markers are simplified by vertex clustering on a '
          'grid of this size [m]; 0 = full meshes', lo=0.0, hi=0.05, read_only=True),
    Param('publish_tf', True, 'publish /tf (moving segments, each frame) and /tf_static (fixed ones); false when '
          'robot_state_publisher makes the tree from /joint_states', read_only=True),
    Param('publish_robot_description', True, 'publish the URDF of the model on /robot_description (transient local)',
          read_only=True),
    Param('frame_id', 'world', 'frame of positions and markers (REP-103)', read_only=True),
    Param('max_steps_per_tick', 2000, 'cap on solver steps per published frame (per chunk of the solver thread)',
          lo=1, hi=1000000),
    Param('solver_thread', True, 'step the solver in a thread of its own beside the frame loop (two cores: stepping '
          'and publishing in parallel; a process allowed one CPU steps in the frame timer all the same); false: '
          'in the frame timer callback, between publishes (one core)', read_only=True),
    Param('solver_nice', 0, "the solver thread's nice increment (Linux, its thread only): > 0 gives the frame loop the "
          'CPU first where cores are short, at the cost of the real-time factor', lo=0, hi=19, read_only=True),
    Param('start_paused', False, 'start paused (resume with ~/pause false)', read_only=True),
    Param('diagnostics_period', 1.0, 'seconds between /diagnostics', lo=0.1, hi=60.0),
)


def build_parser():
    p = ArgumentParser(prog='simulator', description=__doc__.split('\n')[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    return add_flags(p, PARAMS)


class Simulator(Node):
    def __init__(self, **kw):
        from diagnostic_msgs.msg import DiagnosticArray
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from std_srvs.srv import SetBool, Trigger
        from tf2_msgs.msg import TFMessage
        from tissue_msgs.msg import MuscleActivation, MuscleSet, TissueState, TissueTopology
        from visualization_msgs.msg import MarkerArray
        from ..core import solver, tissue_cdr
        from ..core.load import load_model, load_params
        super().__init__('simulator', **kw)
        self.solver, self.tcdr, self.TFMessage = solver, tissue_cdr, TFMessage
        self.P = P = declare(self, PARAMS)
        t0 = time.monotonic()
        self.tm = load_model(P['model'])
        self.params = load_params(P['params'], P['dt'])
        self.sim = solver.compile_model(self.tm, self.params)
        self.state = solver.make_state(self.sim)
        self.ctrl = solver.make_control(self.sim)
        self.dt = self.params.dt
        self.muscles = Muscles.of(self.tm)
        self.frame_id = P['frame_id']
        # the soft tissue each frame; the bones once, in their segments' TF frames (/tissue/bone_markers)
        self.marker_enc = mk.MarkerArrayEncoder(self.tm, self.frame_id, P['marker_colouring'],
                                                bone_resolution=P['bone_marker_resolution'],
                                                soft_resolution=P['marker_resolution'],
                                                bones=False) if P['publish_markers'] else None
        self._rest_area = None
        self._fat_def = None
        # warm every path of a frame before the clock starts (no first-frame or first-step stall): the
        # kernels (numba compile) on a scratch state, timing a few steps; the marker colours (their rest
        # references come from the start state, as the first frame would take them) and encoder; the TF
        # message. (ros.common.main then freezes the set-up's objects out of the garbage collector.)
        self.step_ctrl = solver.make_control(self.sim)    # the activations of the steps under way (a copy)
        self.steps_done = 0
        self.pacer = realtime.Pacer(self.run_steps, self.dt)
        warm = solver.make_state(self.sim)
        try:
            solver.step(self.sim, warm, self.ctrl, self.dt)
            self.pacer.warm_up(lambda k: solver.step(self.sim, warm, self.ctrl, self.dt, n_steps=k))
        except solver.DivergenceError as e:     # (from rest: the model cannot run with these parameters at all)
            from ..errors import UserError
            raise UserError(f'the model does not run with these parameters: from rest, {e}'
                            f'{implicit_hint(self.params) or "; more substeps may help"}') from None
        if self.marker_enc is not None:
            self.marker_enc.encode(0, warm.x, solver.observe(self.sim, warm)['segment_poses'],
                                   self.corner_colours(self.state.x))
        self.tf_message(0, range(self.tm.n_segments), self.state)
        self.get_logger().info(f'model {self.tm.name!r}: {self.tm.n_vertices} vertices, {self.tm.n_cells} cells, '
                               f'{self.tm.n_muscles} muscles; params {self.params.preset}, dt {self.dt:g} s; '
                               f'ready in {time.monotonic() - t0:.1f} s')
        # publishers
        self.Clock, self.JointState, self.DiagnosticArray = Clock, JointState, DiagnosticArray
        self.pub_clock = self.create_publisher(Clock, TOPIC_CLOCK, qos_stream(1))
        self.pub_joints = self.create_publisher(JointState, TOPIC_JOINTS, qos_stream())
        self.state_bytes = len(self.tcdr.encode_frame(self.tm, self.state, solver.observe(self.sim, self.state),
                                                      self.ctrl.activation, stamp_ns=0, frame_id=self.frame_id))
        limit = int(P['state_own_participant_bytes'])
        self.state_participant = OwnParticipant(self, 'state') if 0 <= limit < self.state_bytes else None
        self.pub_state = (self.state_participant or self).create_publisher(TissueState, TOPIC_STATE, qos_stream())
        self.markers_participant = (OwnParticipant(self, 'markers') if self.marker_enc is not None
                                    and P['markers_own_participant'] else None)
        self.pub_markers = (self.markers_participant or self).create_publisher(MarkerArray, TOPIC_MARKERS,
                                                                               qos_stream(2))
        self.pub_bone_markers = (self.create_publisher(MarkerArray, TOPIC_BONE_MARKERS, qos_latched())
                                 if self.marker_enc is not None else None)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, qos_stream())
        self.pub_topo = self.create_publisher(TissueTopology, TOPIC_TOPOLOGY, qos_latched())
        self.MuscleSet = MuscleSet
        self.pub_muscles = self.create_publisher(MuscleSet, TOPIC_MUSCLES, qos_latched())
        # /tf at depth 10, not tf2's 100: beside the 0.8 MB markers a depth-100 writer reached a subscriber of both in
        # bursts (7-19 Hz, gaps of 1-3 s; Fast DDS), depth 10 at 34 Hz (also to a depth-100 subscriber)
        self.pub_tf = self.create_publisher(TFMessage, TOPIC_TF, qos_stream(10)) if P['publish_tf'] else None
        self.pub_tf_static = (self.create_publisher(TFMessage, TOPIC_TF_STATIC, qos_latched())
                              if P['publish_tf'] else None)
        self.pub_description = (self.create_publisher(String, TOPIC_ROBOT_DESCRIPTION, qos_latched())
                                if P['publish_robot_description'] else None)
        self.tf_moving = [s for s in range(self.tm.n_segments)
                          if not urdf.is_static(self.tm, s, self.params.fixed_root)]
        self.create_subscription(MuscleActivation, TOPIC_ACTIVATION, self.on_activation, qos_stream())
        self.create_service(Trigger, '~/reset', self.on_reset)
        self.create_service(SetBool, '~/pause', self.on_pause)
        self.publish_topology()
        if self.pub_description is not None:
            self.pub_description.publish(String(data=urdf.robot_description(self.tm)))
        fixed = [s for s in range(self.tm.n_segments) if s not in self.tf_moving]
        if self.pub_tf_static is not None and fixed:
            self.pub_tf_static.publish(self.tf_message(0, fixed, self.state))
        # bookkeeping
        self.paused = bool(P['start_paused'])
        self.diverged = ''
        self.rejected = {r: 0 for r in REASONS}
        self.accepted = 0
        self.publish_times = collections.deque(maxlen=512)
        self.marker_ms = collections.deque(maxlen=256)          # build + publish [ms]
        self.marker_encode_ms = collections.deque(maxlen=256)   # build only (colours + numpy CDR) [ms]
        self.step_wall = 0.0            # wall seconds spent stepping (the solver thread's chunks or the ticks' steps)
        self.step_cpu = 0.0             # CPU seconds of the stepping thread spent stepping
        self.publish_cost = 0.0         # a frame's build + publish [s of wall time], running mean
        self.publish_cpu = 0.0          # ... [s of the frame loop's CPU time]
        self.publish_call_max = 0.0     # the longest single publish() call [s] in the diagnostics window
        self.slow_publishes = 0         # publish() calls over SLOW_PUBLISH_S so far
        self.late_ticks = 0             # frame ticks over LATE_TICK_PERIODS periods after the last so far
        self.period = realtime.frame_period(P['publish_rate'])
        self.stepper = None
        self.frame = self.state                 # the state of the last frame published
        threaded = P['solver_thread'] and realtime.usable_cpus() >= 2
        if P['solver_thread'] and not threaded:
            self.get_logger().info('solver_thread: this process may run on one CPU only: the solver steps in the frame '
                                   'timer (solver_thread false)')
        if threaded:
            sys.setswitchinterval(realtime.GIL_SWITCH)
            self.stepper = realtime.SolverThread(self.pacer, self.state.copy, self.period, paused=self.paused,
                                                 nice=int(P['solver_nice']), on_error=self.on_step_error)
            self.stepper_settings()
            self.stepper.start()
        self.last_tick = time.monotonic()
        self.t_start = self.last_tick
        self.sim_t_start = self.state.time
        self.last_diag = self.last_tick
        self.diag_window = (self.last_tick, self.state.time, 0, 0.0, 0.0)   # wall, sim time, steps, stepping wall, cpu
        self.timer = self.create_timer(self.period, self.tick)
        print(f'simulator ready: publishing at {P["publish_rate"]:g} Hz', flush=True)

    # ------------------------------------------------------------------ inputs
    def on_activation(self, msg):
        idx, values, detail = self.muscles.check(msg.muscle_names, msg.activations)
        if idx is None:
            reason = values
            self.rejected[reason] += 1
            self.get_logger().warning(f'rejected activation message ({reason}): {detail}',
                                      throttle_duration_sec=2.0)
            return
        self.ctrl.activation[idx] = values
        self.accepted += 1

    def run_steps(self, k: int) -> None:
        """k solver steps of the state under the activations commanded now (copied: a message arriving
        while the solver thread steps changes the next chunk, not the one under way)."""
        self.step_ctrl.activation[:] = self.ctrl.activation
        self.solver.step(self.sim, self.state, self.step_ctrl, self.dt, n_steps=k)
        self.steps_done += k

    def on_reset(self, req, resp):
        if self.stepper is not None:
            with self.stepper.hold():
                self.solver.reset(self.sim, self.state)
                self.stepper.refresh()
        else:
            self.solver.reset(self.sim, self.state)
        self.ctrl.activation[:] = 0.0
        self.diverged = ''
        self.pacer.reset()
        resp.success, resp.message = True, 'state and activations reset to rest; sim time 0'
        self.get_logger().info('reset')
        return resp

    def on_pause(self, req, resp):
        if not req.data and self.diverged:
            resp.success, resp.message = False, f'diverged ({self.diverged}): call ~/reset first'
            return resp
        self.paused = bool(req.data)
        self.pacer.reset()
        if self.stepper is not None:
            self.stepper.set_paused(self.paused)
        resp.success, resp.message = True, 'paused' if self.paused else 'running'
        return resp

    def on_step_error(self, e):
        """A failed step in the solver thread (realtime.SolverThread: it has paused itself)."""
        self.report_failure(e)

    def report_failure(self, e):
        if isinstance(e, self.solver.DivergenceError):
            self.diverged = str(e)
            self.get_logger().error(f'solver diverged: {e}; paused (call ~/reset){implicit_hint(self.params)}')
        elif isinstance(e, ValueError):      # should not happen: activations are validated on arrival
            self.diverged = f'solver refused the step: {e}'
            self.get_logger().error(self.diverged)
        else:
            self.diverged = f'solver failed: {e!r}'
            self.get_logger().error(self.diverged)
        self.paused = True

    def on_shutdown(self):
        if self.stepper is not None:
            self.stepper.stop()

    def destroy_node(self):
        for participant in (self.markers_participant, self.state_participant):
            if participant is not None:
                participant.close()
        return super().destroy_node()

    def stepper_settings(self):
        st = self.stepper
        st.realtime = bool(self.get_parameter('realtime').value)
        st.rate = float(self.get_parameter('rate').value)
        st.cap = int(self.get_parameter('max_steps_per_tick').value)

    # ------------------------------------------------------------------ loop
    def advance(self, now):
        """The solver steps of one frame (core.realtime.Pacer) when the solver has no thread of its own;
        a failure pauses the node. Returns the state to publish."""
        wall_dt = now - self.last_tick
        self.last_tick = now
        if self.stepper is not None:
            self.stepper_settings()
            self.step_wall, self.step_cpu = self.stepper.step_wall, self.stepper.step_cpu
            return self.stepper.latest
        if self.paused or self.diverged:
            return self.state
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            self.pacer.advance(wall_dt, realtime=self.get_parameter('realtime').value,
                               rate=float(self.get_parameter('rate').value),
                               cap=int(self.get_parameter('max_steps_per_tick').value),
                               budget=realtime.step_budget(self.period, self.publish_cost))
        except (self.solver.DivergenceError, ValueError) as e:
            self.report_failure(e)
        self.step_wall += time.perf_counter() - t0
        self.step_cpu += time.thread_time() - c0
        return self.state

    def tick(self):
        """One frame. Stepping in this callback (no solver thread), the frame publishes what the last tick's steps
        left and then steps: every frame goes out at the start of its tick, paused or running, so frames stay a
        period apart across a resume (stepping first, the first frame after a resume went out a whole budget of
        steps later than the paused ones before it: a 46-62 ms gap). With the solver thread, the thread's latest."""
        now = time.monotonic()
        since = now - self.last_tick        # (advance below sets last_tick; before the first tick it is t_start)
        if self.last_tick != self.t_start and since > max(0.1, LATE_TICK_PERIODS * self.period):
            self.late_ticks += 1
            self.get_logger().warning(f'frame tick {1e3 * since:.0f} ms after the last one (timer '
                                      f'period {1e3 * self.period:.0f} ms; a held publish() call is logged before it)')
        if self.stepper is None:
            self.publish_checked(self.state, now)
            self.advance(now)
        else:
            self.publish_checked(self.advance(now), now)

    def publish_checked(self, st, now):
        """Publish the frame of ``st`` unless its positions are not finite (then pause: never publish NaN)."""
        self.frame = st
        if not np.isfinite(st.x).all():               # never publish NaN
            if not self.diverged:
                self.diverged = 'non-finite vertex positions'
                self.paused = True
                self.get_logger().error('non-finite positions; paused (call ~/reset)')
            self.maybe_diagnostics(now)
            return
        t0, c0 = time.perf_counter(), time.thread_time()
        self.publish_frame(st)
        self.publish_cost = 0.8 * self.publish_cost + 0.2 * (time.perf_counter() - t0)
        self.publish_cpu = 0.8 * self.publish_cpu + 0.2 * (time.thread_time() - c0)
        self.publish_times.append(time.monotonic())
        self.maybe_diagnostics(now)

    def send(self, pub, msg):
        """pub.publish(msg), timed: a call over SLOW_PUBLISH_S (the DDS layer blocking the frame loop, e.g. while a
        participant joins) is logged with its topic and counted; the longest call goes to /diagnostics."""
        t0 = time.perf_counter()
        pub.publish(msg)
        dt = time.perf_counter() - t0
        self.publish_call_max = max(self.publish_call_max, dt)
        if dt > SLOW_PUBLISH_S:
            self.slow_publishes += 1
            self.get_logger().warning(f'publishing on {pub.topic_name} took {1e3 * dt:.0f} ms (inside the DDS '
                                      f'layer: the frame loop waited)')

    def publish_frame(self, st):
        """Publish the frame of state ``st`` (the solver thread's latest copy, or the state itself)."""
        obs = self.solver.observe(self.sim, st)
        stamp = int(round(st.time * 1e9))
        clock = self.Clock()
        clock.clock.sec, clock.clock.nanosec = stamp // 1_000_000_000, stamp % 1_000_000_000
        self.send(self.pub_clock, clock)
        js = self.JointState()
        js.header.stamp = clock.clock
        js.header.frame_id = self.frame_id
        js.name, js.position, js.velocity = urdf.joint_states(self.sim, obs['joint_positions'], obs['joint_velocities'])
        self.send(self.pub_joints, js)
        if self.pub_tf is not None and self.tf_moving:
            self.send(self.pub_tf, self.tf_message(stamp, self.tf_moving, st))
        if self.get_parameter('publish_state').value:
            self.send(self.pub_state, self.tcdr.encode_frame(self.tm, st, obs, self.ctrl.activation,
                                                             stamp_ns=stamp, frame_id=self.frame_id))
        if self.marker_enc is not None and self.get_parameter('publish_markers').value and self.marker_due():
            t0 = time.perf_counter()
            rgba = self.corner_colours(st.x)
            data = self.marker_enc.encode(stamp, st.x, obs['segment_poses'], rgba)
            t1 = time.perf_counter()
            self.send(self.pub_markers, data)
            t2 = time.perf_counter()
            self.marker_ms.append(1e3 * (t2 - t0))
            self.marker_encode_ms.append(1e3 * (t1 - t0))

    def marker_due(self) -> bool:
        """Whether this frame carries markers (``marker_rate``: at most that many per second of wall time)."""
        rate = float(self.get_parameter('marker_rate').value)
        if rate <= 0.0:
            return True
        now = time.monotonic()
        if now - getattr(self, '_last_marker_t', -1e9) < 0.98 / rate:
            return False
        self._last_marker_t = now
        return True

    def tf_message(self, stamp_ns: int, segments, st):
        """TFMessage of the given segments' transforms (urdf.tf_transforms: each under its parent
        segment, the root under ``world``) in state ``st``, stamped ``stamp_ns``."""
        from geometry_msgs.msg import TransformStamped
        tfs = urdf.tf_transforms(self.tm, st.seg_R, st.seg_t)
        msg = self.TFMessage()
        for s in segments:
            parent, child, t, q = tfs[s]
            ts = TransformStamped()
            ts.header.stamp.sec, ts.header.stamp.nanosec = stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000
            ts.header.frame_id, ts.child_frame_id = parent, child
            tr, rot = ts.transform.translation, ts.transform.rotation
            tr.x, tr.y, tr.z = (float(v) for v in t)
            rot.x, rot.y, rot.z, rot.w = (float(v) for v in q)
            msg.transforms.append(ts)
        return msg

    def corner_colours(self, x):
        enc = self.marker_enc
        if enc.colouring == 'none' or enc.skin_corners is None:
            return None
        scale = float(self.get_parameter('colour_scale').value)
        if enc.colouring == 'skin_area':
            ratio, self._rest_area = measures.skin_area_ratio_per_vertex(self.tm, x, self._rest_area)
            return mk.diverging_rgba(ratio[enc.skin_corners], span=scale)
        if self._fat_def is None:
            self._fat_def = measures.FatDeformation(self.tm)
        d = self._fat_def(x)
        return mk.sequential_rgba(d[enc.skin_corners], scale)

    def publish_topology(self):
        model_hash = self.tcdr.hash_of(self.tm)
        self.pub_topo.publish(self.tcdr.encode_topology(self.tm, parameters_yaml=self.params.to_yaml(),
                                                        model_hash=model_hash, stamp_ns=0, frame_id=self.frame_id))
        muscles = self.MuscleSet(model_name=self.tm.name, model_hash=model_hash,
                                 muscle_names=list(self.tm.muscle_names), muscle_groups=list(self.tm.muscle_groups))
        muscles.header.frame_id = self.frame_id
        self.pub_muscles.publish(muscles)
        if self.pub_bone_markers is not None:
            self.pub_bone_markers.publish(mk.bone_marker_array(
                self.tm, bone_resolution=float(self.get_parameter('bone_marker_resolution').value)))

    # ------------------------------------------------------------------ diagnostics
    def figures(self, now) -> dict:
        w0, s0, n0, sw0, sc0 = self.diag_window
        span = max(now - w0, 1e-9)
        recent = [t for t in self.publish_times if t > now - max(span, 1.0)]
        rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 2 else 0.0
        return dict(publish_rate_hz=rate, real_time_factor=(self.frame.time - s0) / span,
                    steps_per_s=(self.steps_done - n0) / span, sim_time=self.frame.time,
                    stepping_share=(self.step_wall - sw0) / span,
                    steps_per_cpu_s=(self.steps_done - n0) / max(self.step_cpu - sc0, 1e-9), frame_ms=1e3 * self.publish_cost, frame_cpu_ms=1e3 * self.publish_cpu,
                    solver_thread=self.stepper is not None,
                    marker_ms_mean=float(np.mean(self.marker_ms)) if self.marker_ms else 0.0,
                    marker_ms_max=float(np.max(self.marker_ms)) if self.marker_ms else 0.0,
                    marker_encode_ms_mean=float(np.mean(self.marker_encode_ms)) if self.marker_encode_ms else 0.0,
                    marker_bytes=self.marker_enc.nbytes if self.marker_enc is not None else 0,
                    publish_call_ms_max=1e3 * self.publish_call_max, slow_publishes=self.slow_publishes,
                    late_ticks=self.late_ticks)

    def maybe_diagnostics(self, now):
        if now - self.last_diag < float(self.get_parameter('diagnostics_period').value):
            return
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
        f = self.figures(now)
        self.diag_window = (now, self.frame.time, self.steps_done, self.step_wall, self.step_cpu)
        self.publish_call_max = 0.0
        self.last_diag = now
        target = float(self.P['publish_rate'])
        if self.diverged:
            level, message = DiagnosticStatus.ERROR, f'diverged: {self.diverged}'
        elif self.paused:
            level, message = DiagnosticStatus.OK, 'paused'
        elif f['publish_rate_hz'] < 0.95 * target:
            level, message = DiagnosticStatus.WARN, f'publishing at {f["publish_rate_hz"]:.1f} Hz < {target:g} Hz'
        elif self.get_parameter('realtime').value and f['real_time_factor'] < 0.95 * self.get_parameter('rate').value:
            level, message = DiagnosticStatus.WARN, f'real-time factor {f["real_time_factor"]:.2f}: solver cannot keep up'
        else:
            level, message = DiagnosticStatus.OK, 'running'
        st = DiagnosticStatus(level=level, name='tissue_sim: simulator', message=message, hardware_id=self.tm.name)
        vals = dict(f, paused=self.paused, accepted_activations=self.accepted,
                    knee_angle=float(self.frame.q[0]) if self.frame.q.size else 0.0,
                    **{f'rejected_{k}': v for k, v in self.rejected.items()})
        st.values = [KeyValue(key=k, value=(f'{v:.6g}' if isinstance(v, float) else str(v))) for k, v in vals.items()]
        arr = self.DiagnosticArray()
        stamp = int(round(self.frame.time * 1e9))
        arr.header.stamp.sec, arr.header.stamp.nanosec = stamp // 1_000_000_000, stamp % 1_000_000_000
        arr.status = [st]
        self.pub_diag.publish(arr)


def main(argv=None):
    return node_main(lambda args: Simulator(parameter_overrides=overrides(args, PARAMS)), build_parser(), argv)


if __name__ == '__main__':
    raise SystemExit(main())
