#!/usr/bin/env python3
"""Benchmark: the simulator node at 34 Hz with full markers, seen from a separate subscriber process.

Starts the installed `simulator` (the bundled anatomy by default; --refine R for the bundled limb
R x finer (`build-model --refine R`; a list 1,2,3 runs each), --model FILE or --phantom for the solver's knee
phantom scaled up) in its own ROS domain, then this process subscribes to /joint_states, /tissue/state, /tf and
/tissue/markers for --seconds and reports:

* publish rate and inter-arrival p50/p99 per topic as received here;
* the simulator's CPU share (utime+stime from /proc over the window, % of one core);
* the real-time factor, solver steps/s, the share of wall time the stepping thread spent stepping and its steps
  per CPU second (the figure bench/solver.py gives for the bare solver), the frame's build+publish time (from
  /diagnostics);
* the node's marker build+publish time per frame (mean/max, from /diagnostics; target < 5 ms), per 10k vertices,
  and the MarkerArray's bytes (with --marker-resolution M the node's display surface on an M-metre grid);
* side by side in this process: building the same MarkerArray as rclpy Python objects and
  serialising it, vs the numpy CDR encoder (ratio).

--compare runs each configuration twice, the solver in a thread of its own (solver_thread: true, the node's default)
and in the frame timer's callback (solver_thread: false), one after the other: the old and the new stepping
loop side by side under the same load. --participants both runs each configuration with the markers from a DDS
participant of their own (markers_own_participant: true, the default) and from the node's, one after the other: the
small topics' p99 gaps show what the markers' shared-memory traffic does to them. Several runs print a markdown
table of them at the end.

Run:  . ./env.sh && python bench/ros_rate.py [--seconds 10] [--model FILE | --phantom | --refine R[,R...]]
      [--params paper|physical|FILE] [--integrator NAME] [--as-fast-as-possible] [--paused] [--no-objects]
      [--compare | --no-solver-thread] [--participants own|shared|both] [--marker-resolution M] [--solver-only]
Last line: one JSON object (a list of them with several runs).
"""
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXE = ROOT / 'ros_ws' / 'install' / 'tissue_sim' / 'lib' / 'tissue_sim'


def cpu_seconds(pid):
    with open(f'/proc/{pid}/stat') as f:
        parts = f.read().rsplit(')', 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf('SC_CLK_TCK')


def stats(ts):
    ts = np.asarray(ts)
    if ts.size < 3:
        return dict(rate_hz=0.0, p50_ms=None, p99_ms=None, n=int(ts.size))
    gaps = np.diff(ts) * 1e3
    return dict(rate_hz=round(float((ts.size - 1) / (ts[-1] - ts[0])), 3), p50_ms=round(float(np.percentile(gaps, 50)), 2),
                p99_ms=round(float(np.percentile(gaps, 99)), 2), max_ms=round(float(gaps.max()), 2), n=int(ts.size))


def python_object_markers(tm, x, reps=2, resolution=0.0):
    """Build the soft tissue's MarkerArray with rclpy Python objects and serialise it (the slow way; reps 0:
    not at all), and with the numpy CDR encoder the node uses; returns (ms, ms, the encoder's bytes)."""
    from geometry_msgs.msg import Point
    from rclpy.serialization import serialize_message
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import Marker, MarkerArray
    from tissue_sim.core import markers as mk
    enc = mk.MarkerArrayEncoder(tm, bones=False, soft_resolution=resolution)   # what the node encodes each frame
                                                                                # (the bones go once)
    best = float('nan') if reps == 0 else 1e9
    for _ in range(reps):
        t0 = time.perf_counter()
        arr = MarkerArray()
        for k, (idx, name) in enumerate(enc._soft):
            m = Marker()
            m.header.frame_id = 'world'
            m.ns, m.id, m.type = f'tissue/{name}', k, Marker.TRIANGLE_LIST
            m.scale.x = m.scale.y = m.scale.z = 1.0
            m.color = ColorRGBA(r=0.8, g=0.2, b=0.2, a=1.0)
            m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in x[idx]]
            arr.markers.append(m)
        serialize_message(arr)                       # (timed: the encoding the node pays)
        best = min(best, time.perf_counter() - t0)
    enc.encode(0, x)                                  # (first call: allocations)
    t0 = time.perf_counter()
    for _ in range(20):
        enc.encode(0, x)
    numpy_s = (time.perf_counter() - t0) / 20
    return best * 1e3, numpy_s * 1e3, enc.nbytes


def measure(a, model, tm, params, solver_thread, own_participant=True):
    """One run of the simulator node: the figures of the module docstring as a dict."""
    import rclpy
    import rclpy.executors
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage
    from tissue_msgs.msg import TissueState
    from visualization_msgs.msg import MarkerArray
    tmp = Path(tempfile.mkdtemp(prefix='ros_rate_'))
    sys.path.insert(0, str(ROOT / 'tests'))
    from rosutil import acquire_domain      # a domain id no other process holds (the tests' lock files): another
    dom = acquire_domain()                  # simulator in the same domain would mix its topics into these
    env = dom.env
    os.environ.update(ROS_DOMAIN_ID=str(dom.id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    log = open(tmp / 'simulator.log', 'w+')
    sim = subprocess.Popen([str(EXE / 'simulator'), '--ros-args', '-p', f'model:={model}',
                            '-p', f'publish_rate:={a.rate}', '-p', f'marker_colouring:={a.colouring}',
                            '-p', f'solver_thread:={str(solver_thread).lower()}',
                            '-p', f'markers_own_participant:={str(own_participant).lower()}',
                            '-p', f'marker_resolution:={float(a.marker_resolution)}']
                           + (['-p', f'params:={params}'] if params else [])
                           + (['-p', 'realtime:=false'] if a.as_fast_as_possible else [])
                           + (['-p', 'start_paused:=true'] if a.paused else []),
                           env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    topics = {'js': (JointState, '/joint_states'), 'state': (TissueState, '/tissue/state'), 'tf': (TFMessage, '/tf'),
              'mk': (MarkerArray, '/tissue/markers')}
    try:
        rclpy.init()
        node = rclpy.create_node('ros_rate_probe')
        arr = {k: [] for k in topics}
        diag = [None]
        for k, (typ, name) in topics.items():
            node.create_subscription(typ, name, lambda m, k=k: arr[k].append(time.monotonic()), 10, raw=True)
        node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diag.__setitem__(0, m), 10)
        ex = rclpy.executors.SingleThreadedExecutor()      # one executor for the run: rclpy.spin_once(node) makes a
        ex.add_node(node)                                  # wait set per call and takes one message, the first topic first
        t_start = time.monotonic()
        while len(arr['mk']) < 20:
            if sim.poll() is not None or time.monotonic() - t_start > 900:
                log.seek(0)
                sys.exit(f'simulator did not start publishing:\n{log.read()}')
            ex.spin_once(timeout_sec=0.1)
        c0, w0 = cpu_seconds(sim.pid), time.monotonic()
        n0 = {k: len(v) for k, v in arr.items()}
        diag[0] = None
        while time.monotonic() - w0 < a.seconds or (diag[0] is None and time.monotonic() - w0 < a.seconds + 5):
            ex.spin_once(timeout_sec=0.05)
        c1, w1 = cpu_seconds(sim.pid), time.monotonic()
        d = {kv.key: kv.value for kv in diag[0].status[0].values} if diag[0] else {}
        rates = {k: stats(arr[k][n0[k]:]) for k in topics}
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown()
    finally:
        sim.send_signal(signal.SIGINT)
        try:
            sim.wait(15)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
        dom.release()
    x = np.asarray(tm.rest_positions, np.float64)
    if a.no_objects:
        py_ms, np_ms, nbytes = python_object_markers(tm, x, reps=0, resolution=a.marker_resolution)
    else:
        py_ms, np_ms, nbytes = python_object_markers(tm, x, resolution=a.marker_resolution)
    num = lambda k: float(d.get(k, 'nan'))      # noqa: E731
    per10k = 1e4 / tm.n_vertices
    js, mkst = rates['js'], rates['mk']
    out = {
        'model': tm.name, 'refine': a.refine_now, 'params': a.params or 'default', 'integrator': a.integrator or "the set's",
        'solver_thread': solver_thread, 'markers_own_participant': own_participant, 'paused': a.paused, 'realtime': not a.as_fast_as_possible,
        'vertices': tm.n_vertices, 'surface_triangles': int(len(tm.surface_triangles)),
        'marker_resolution': a.marker_resolution,
        'marker_bytes': int(float(d.get('marker_bytes', nbytes))), 'window_s': round(w1 - w0, 2),
        'publish_rate_target_hz': a.rate,
        'joint_states': js, 'tissue_state': rates['state'], 'tf': rates['tf'], 'markers': mkst,
        'simulator_cpu_percent_of_one_core': round(100 * (c1 - c0) / (w1 - w0), 1),
        'real_time_factor': num('real_time_factor'), 'steps_per_s': num('steps_per_s'),
        'stepping_share': num('stepping_share'), 'steps_per_cpu_s': num('steps_per_cpu_s'),
        'frame_ms': num('frame_ms'), 'frame_cpu_ms': num('frame_cpu_ms'),
        'node_marker_ms_mean': num('marker_ms_mean'), 'node_marker_ms_max': num('marker_ms_max'),
        'node_marker_encode_ms_mean': num('marker_encode_ms_mean'),
        'node_marker_ms_per_10k_vertices': round(num('marker_ms_mean') * per10k, 3),
        'marker_bytes_per_vertex': round(float(d.get('marker_bytes', nbytes)) / tm.n_vertices, 1),
        'load_average_1min': os.getloadavg()[0], 'cpu_count': os.cpu_count(),
        'marker_python_objects_ms': round(py_ms, 1), 'marker_numpy_ms': round(np_ms, 3),
        'marker_numpy_ms_per_10k_vertices': round(np_ms * per10k, 3),
        'numpy_speedup': round(py_ms / np_ms, 1),
        'markers_ok_34hz': bool(mkst['rate_hz'] >= 34.0), 'marker_under_5ms': bool(num('marker_ms_mean') < 5.0),
    }
    print(f"model {out['model']} (refine {out['refine']:g}): {out['vertices']} vertices, MarkerArray "
          f"{out['marker_bytes'] / 1e6:.2f} MB; solver_thread {solver_thread}; markers_own_participant {own_participant}")
    for k, name in (('js', '/joint_states'), ('state', '/tissue/state'), ('tf', '/tf'), ('mk', '/tissue/markers')):
        r = rates[k]
        print(f"{name:16s} {r['rate_hz']:.2f} Hz  p50 {r['p50_ms']} ms  p99 {r['p99_ms']} ms")
    print(f"simulator CPU {out['simulator_cpu_percent_of_one_core']} % of one core; real-time factor "
          f"{out['real_time_factor']}; {out['steps_per_s']:.0f} steps/s; stepping {out['stepping_share']:.2f} of wall time "
          f"at {out['steps_per_cpu_s']:.0f} steps per CPU second; frame {out['frame_ms']:.2f} ms "
          f"({out['frame_cpu_ms']:.2f} ms CPU)")
    print(f"marker build+publish in the node: mean {out['node_marker_ms_mean']:.2f} ms, max {out['node_marker_ms_max']:.2f} ms "
          f"(encode alone {out['node_marker_encode_ms_mean']:.2f} ms; target < 5 ms; "
          f"{out['node_marker_ms_per_10k_vertices']:.2f} ms per 10k vertices); load average "
          f"{out['load_average_1min']:.1f} on {out['cpu_count']} CPUs\n"
          f"Python objects {py_ms:.1f} ms vs numpy {np_ms:.3f} ms (x{out['numpy_speedup']})", flush=True)
    return out


def solver_only(model, params, seconds, windows=3):
    """The solver alone, in this process, with no ROS: steps per wall second and per CPU second of (a) one
    solver.step() call per step on this thread (bench/solver.py's figure for the physical set), (b) the simulator's
    stepping path: realtime.SolverThread as fast as possible (Pacer batches, the activations copied per batch, a
    copy of the state after each chunk), this thread idle; (c) the same thread while this thread encodes the
    node's frames (observe, TissueState, MarkerArray: the frame loop's work without the transport). Windows
    alternate (a, b, c, a, b, c, ...) so that all see the same load; best of ``windows`` each."""
    from tissue_sim.core import markers as mk, realtime, solver, tissue_cdr
    from tissue_sim.core.load import load_model, load_params
    tm = load_model(model)
    sim = solver.compile_model(tm, load_params(params or 'physical', 0.0))
    dt = sim.params.dt
    ctrl = solver.make_control(sim)
    enc = mk.MarkerArrayEncoder(tm, bones=False)
    best = {k: [0.0, 0.0] for k in ('a', 'b', 'c')}

    def one_thread(state):
        n, t0, c0 = 0, time.perf_counter(), time.thread_time()
        while time.perf_counter() - t0 < seconds:
            solver.step(sim, state, ctrl, dt)
            n += 1
        return n / (time.perf_counter() - t0), n / max(time.thread_time() - c0, 1e-9)

    def threaded(state, frames):
        step_ctrl, done = solver.make_control(sim), [0]

        def run_steps(k):
            step_ctrl.activation[:] = ctrl.activation
            solver.step(sim, state, step_ctrl, dt, n_steps=k)
            done[0] += k
        pacer = realtime.Pacer(run_steps, dt)
        pacer.warm_up(lambda k: solver.step(sim, solver.make_state(sim), ctrl, dt, n_steps=k))
        th = realtime.SolverThread(pacer, state.copy, realtime.frame_period(34.0))
        th.realtime = False
        old = sys.getswitchinterval()
        sys.setswitchinterval(realtime.GIL_SWITCH)
        t0 = time.perf_counter()
        th.start()
        try:
            while time.perf_counter() - t0 < seconds:
                if frames:
                    st = th.latest
                    obs = solver.observe(sim, st)
                    tissue_cdr.encode_frame(tm, st, obs, ctrl.activation, stamp_ns=0)
                    enc.encode(0, st.x, obs['segment_poses'])
                time.sleep(1.0 / 34.0 if not frames else 0.01)
        finally:
            th.stop()
            sys.setswitchinterval(old)
        return done[0] / (time.perf_counter() - t0), done[0] / max(th.step_cpu, 1e-9)

    state = solver.make_state(sim)
    solver.step(sim, state, ctrl, dt, n_steps=10)
    for _ in range(windows):
        for k, fn in (('a', lambda: one_thread(state)), ('b', lambda: threaded(state, False)),
                      ('c', lambda: threaded(state, True))):
            w, c = fn()
            best[k] = [max(best[k][0], w), max(best[k][1], c)]
    out = {'solver_step_per_call': best['a'], 'node_thread_idle_main': best['b'], 'node_thread_beside_frames': best['c'],
           'load_average_1min': os.getloadavg()[0], 'vertices': tm.n_vertices, 'params': params or 'physical'}
    names = {'solver_step_per_call': 'solver.step() per step, this thread', 'node_thread_idle_main': 'node path: SolverThread, main idle',
             'node_thread_beside_frames': 'node path: SolverThread beside frame encoding'}
    for k, name in names.items():
        print(f'{name:48s} {out[k][0]:7.0f} steps per wall s  {out[k][1]:7.0f} steps per CPU s (best of {windows})')
    print(f'load average {out["load_average_1min"]:.1f} on {os.cpu_count()} CPUs', flush=True)
    return out


TABLE = (('refine', 'refine', '{:g}'), ('vertices', 'vertices', '{}'),
         ('marker resolution m', 'marker_resolution', '{:g}'),
         ('solver thread', 'solver_thread', '{}'),
         ('markers own participant', 'markers_own_participant', '{}'),
         ('RTF', 'real_time_factor', '{:.2f}'), ('steps/s', 'steps_per_s', '{:.0f}'),
         ('stepping share', 'stepping_share', '{:.2f}'), ('steps/CPU-s', 'steps_per_cpu_s', '{:.0f}'),
         ('CPU % of a core', 'simulator_cpu_percent_of_one_core', '{:.0f}'),
         ('/joint_states Hz', ('joint_states', 'rate_hz'), '{:.1f}'), ('/tissue/state Hz', ('tissue_state', 'rate_hz'), '{:.1f}'),
         ('/tf Hz', ('tf', 'rate_hz'), '{:.1f}'), ('/tissue/markers Hz', ('markers', 'rate_hz'), '{:.1f}'),
         ('/joint_states p99 ms', ('joint_states', 'p99_ms'), '{}'), ('/tissue/state p99 ms', ('tissue_state', 'p99_ms'), '{}'),
         ('/tf p99 ms', ('tf', 'p99_ms'), '{}'), ('markers p99 ms', ('markers', 'p99_ms'), '{}'), ('frame ms', 'frame_ms', '{:.1f}'), ('frame CPU ms', 'frame_cpu_ms', '{:.1f}'),
         ('marker build+publish ms', 'node_marker_ms_mean', '{:.2f}'),
         ('... per 10k vertices', 'node_marker_ms_per_10k_vertices', '{:.2f}'),
         ('numpy encode ms per 10k vertices', 'marker_numpy_ms_per_10k_vertices', '{:.3f}'),
         ('MarkerArray MB', 'marker_bytes', '{:.2f}'), ('load avg', 'load_average_1min', '{:.1f}'))


def table(runs) -> str:
    def cell(r, key, fmt):
        v = r[key[0]][key[1]] if isinstance(key, tuple) else r[key]
        if key == 'marker_bytes':
            v = v / 1e6
        try:
            return fmt.format(v)
        except (TypeError, ValueError):
            return str(v)
    lines = ['| ' + ' | '.join(h for h, _, _ in TABLE) + ' |', '|' + '---|' * len(TABLE)]
    lines += ['| ' + ' | '.join(cell(r, k, f) for _, k, f in TABLE) + ' |' for r in runs]
    return '\n'.join(lines)


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=bounded(above=0), default=10.0, help='measurement window [s] (default 10)')
    ap.add_argument('--model', default='', help="model file (.npz); '' = the bundled anatomy")
    ap.add_argument('--phantom', action='store_true', help='use the knee phantom with extra muscles and fat')
    ap.add_argument('--refine', default='1', help='the bundled limb R x finer (build-model --refine R; default 1); '
                    'a list 1,2,3 runs each')
    ap.add_argument('--integrator', default='', help="the parameter set's integrator replaced by this one ('' = the set's)")
    ap.add_argument('--substeps', type=bounded(int, low=1), default=None,
                    help="sub-steps per step with --integrator (default: the set's; implicit: 1, as bench/solver.py)")
    ap.add_argument('--paused', action='store_true',
                    help='start the simulator paused (start_paused:=true): frames and markers without stepping, the '
                         'publishing and transport alone')
    ap.add_argument('--no-objects', action='store_true',
                    help='skip the rclpy Python-object MarkerArray for comparison (seconds per frame on finer models)')
    ap.add_argument('--rate', type=bounded(above=0), default=34.0, help='publish_rate (default 34)')
    ap.add_argument('--marker-resolution', type=bounded(low=0), default=0.0, metavar='M',
                    help="the node's marker_resolution: the soft tissue's markers on a display surface decimated on a "
                         'grid of M metres (default 0: the full surface)')
    ap.add_argument('--colouring', default='none', help='marker colouring (none, skin_area, fat_deformation)')
    ap.add_argument('--params', default='', help="parameter set of the node (paper, physical or a YAML file; '' = the node's default)")
    ap.add_argument('--as-fast-as-possible', action='store_true',
                    help='realtime:=false (steps/s then measures the node\'s stepping, not the real-time pace)')
    g = ap.add_mutually_exclusive_group()
    g.add_argument('--compare', action='store_true', help='each run with the solver thread and without it (side by side)')
    g.add_argument('--no-solver-thread', action='store_true', help='solver_thread:=false (step in the frame timer)')
    ap.add_argument('--participants', choices=('own', 'shared', 'both'), default='own',
                    help="the markers from a DDS participant of their own (markers_own_participant:=true, the node's "
                         "default), from the node's (shared), or each run with both, one after the other")
    ap.add_argument('--solver-only', action='store_true',
                    help='no ROS: the node\'s stepping path against one solver.step() per step, in this process (solver_only())')
    a = ap.parse_args()

    from tissue_sim.core.builder import parse_refinements
    from tissue_sim.core.model import TissueModel
    from tissue_sim.errors import UserError
    try:
        refines = parse_refinements(a.refine)
    except (UserError, ValueError) as e:
        sys.exit(f'error: {e}')
    tmp = Path(tempfile.mkdtemp(prefix='ros_rate_'))
    params = a.params
    if a.integrator:
        from tissue_sim.core.load import load_params
        import dataclasses
        try:
            kw = dict(substeps=1) if a.integrator == 'implicit' else {}
            kw.update({} if a.substeps is None else dict(substeps=a.substeps))
            p = dataclasses.replace(load_params(a.params or 'physical'), integrator=a.integrator, **kw).validate()
            # implicit: one sub-step of dt, the sheath kept (its correction solve), as bench/solver.py runs it
        except ValueError as e:
            sys.exit(f'error: {e}')
        params = str(tmp / 'params.yaml')
        p.to_yaml(params)
    runs = []
    for r in refines:
        a.refine_now = r
        model = a.model
        if r != 1.0 and not (a.model or a.phantom):
            from tissue_sim.core.builder import default_model
            try:
                model = str(default_model(refine=r).save(tmp / f'bundled_x{r:g}.npz'))
            except UserError as e:
                sys.exit(f'error: {e}')
        if a.phantom:
            from tissue_sim.core.solver import phantom
            model = str(phantom.knee(n_gaps=20, extra_muscles=8, fat_sectors=12).save(tmp / 'phantom.npz'))
        if not model:
            from tissue_sim.core.load import load_model
            from tissue_sim.core.model import ModelError
            try:
                model = str(load_model('').save(tmp / 'bundled.npz'))
            except ModelError as e:
                sys.exit(f'{e} (or run with --phantom)')
        tm = TissueModel.load(model)
        if a.solver_only:
            runs.append(solver_only(model, params, max(1.0, a.seconds / 3)))
            continue
        for threaded in ((False, True) if a.compare else (not a.no_solver_thread,)):
            for own in {'own': (True,), 'shared': (False,), 'both': (True, False)}[a.participants]:
                runs.append(measure(a, model, tm, params, threaded, own))
    if len(runs) > 1:
        print(table(runs))
    print(json.dumps(runs[0] if len(runs) == 1 else runs))


if __name__ == '__main__':
    main()
