#!/usr/bin/env python3
"""Benchmark: the simulator node at 34 Hz with full markers, seen from a separate subscriber process.

Starts the installed `simulator` (the bundled anatomy by default; --refine R for the bundled limb
R x finer (`build-model --refine R`), --model FILE or --phantom for the solver's knee phantom scaled up) in its own ROS domain, then this process subscribes to
/joint_states and /tissue/markers for --seconds and reports:

* publish rate and inter-arrival p50/p99 per topic as received here;
* the simulator's CPU share (utime+stime from /proc over the window, % of one core);
* the real-time factor and solver steps/s (from /diagnostics);
* the node's marker build+publish time per frame (mean/max, from /diagnostics; target < 5 ms);
* side by side in this process: building the same MarkerArray as rclpy Python objects and
  serialising it, vs the numpy CDR encoder (ratio).

Run:  . ./env.sh && python bench/ros_rate.py [--seconds 10] [--model FILE | --phantom | --refine R]
      [--params paper|physical|FILE] [--integrator NAME] [--as-fast-as-possible] [--paused] [--no-objects]
Last line: one JSON object.
"""
import argparse
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


def python_object_markers(tm, x, reps=2):
    """Build the same MarkerArray with rclpy Python objects and serialise it (the slow way); only the
    soft-tissue markers are built as objects (the bones would add more), the numpy encoder does all."""
    from geometry_msgs.msg import Point
    from rclpy.serialization import serialize_message
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import Marker, MarkerArray
    from tissue_sim.core import markers as mk
    enc = mk.MarkerArrayEncoder(tm)
    best = 1e9
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
        data = serialize_message(arr)
        best = min(best, time.perf_counter() - t0)
    t0 = time.perf_counter()
    for _ in range(20):
        enc.encode(0, x)
    numpy_s = (time.perf_counter() - t0) / 20
    return best * 1e3, numpy_s * 1e3, enc.nbytes


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=10.0, help='measurement window [s] (default 10)')
    ap.add_argument('--model', default='', help="model file (.npz); '' = the bundled anatomy")
    ap.add_argument('--phantom', action='store_true', help='use the knee phantom with extra muscles and fat')
    ap.add_argument('--refine', type=float, default=1.0, help='the bundled limb R x finer (build-model --refine R; default 1)')
    ap.add_argument('--integrator', default='', help="the parameter set's integrator replaced by this one ('' = the set's)")
    ap.add_argument('--paused', action='store_true',
                    help='start the simulator paused (start_paused:=true): frames and markers without stepping, the '
                         'publishing and transport alone')
    ap.add_argument('--no-objects', action='store_true',
                    help='skip the rclpy Python-object MarkerArray for comparison (seconds per frame on finer models)')
    ap.add_argument('--rate', type=float, default=34.0, help='publish_rate (default 34)')
    ap.add_argument('--colouring', default='none', help='marker colouring (none, skin_area, fat_deformation)')
    ap.add_argument('--params', default='', help="parameter set of the node (paper, physical or a YAML file; '' = the node's default)")
    ap.add_argument('--as-fast-as-possible', action='store_true',
                    help='realtime:=false (steps/s then measures the node\'s stepping, not the real-time pace)')
    a = ap.parse_args()

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import MarkerArray
    from tissue_sim.core.model import TissueModel

    tmp = Path(tempfile.mkdtemp(prefix='ros_rate_'))
    model = a.model
    if a.refine != 1.0 and not (a.model or a.phantom):
        from tissue_sim.core.builder import default_model
        from tissue_sim.errors import UserError
        try:
            model = str(default_model(refine=a.refine).save(tmp / f'bundled_x{a.refine:g}.npz'))
        except UserError as e:
            sys.exit(f'error: {e}')
    if a.integrator:
        from tissue_sim.core.load import load_params
        import dataclasses
        try:
            p = dataclasses.replace(load_params(a.params or 'physical'), integrator=a.integrator).validate()
        except ValueError as e:
            sys.exit(f'error: {e}')
        a.params = str(tmp / 'params.yaml')
        p.to_yaml(a.params)
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
    dom = 1 + os.getpid() % 101
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    env.pop('ROS_LOCALHOST_ONLY', None)
    os.environ.update(ROS_DOMAIN_ID=str(dom), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    log = open(tmp / 'simulator.log', 'w+')
    sim = subprocess.Popen([str(EXE / 'simulator'), '--ros-args', '-p', f'model:={model}',
                            '-p', f'publish_rate:={a.rate}', '-p', f'marker_colouring:={a.colouring}']
                           + (['-p', f'params:={a.params}'] if a.params else [])
                           + (['-p', 'realtime:=false'] if a.as_fast_as_possible else [])
                           + (['-p', 'start_paused:=true'] if a.paused else []),
                           env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        rclpy.init()
        node = rclpy.create_node('ros_rate_probe')
        arr = {'js': [], 'mk': []}
        diag = [None]
        node.create_subscription(JointState, '/joint_states', lambda m: arr['js'].append(time.monotonic()), 10)
        node.create_subscription(MarkerArray, '/tissue/markers', lambda m: arr['mk'].append(time.monotonic()), 10,
                                 raw=True)
        node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diag.__setitem__(0, m), 10)
        t_start = time.monotonic()
        while len(arr['mk']) < 20:
            if sim.poll() is not None or time.monotonic() - t_start > 600:
                log.seek(0)
                sys.exit(f'simulator did not start publishing:\n{log.read()}')
            rclpy.spin_once(node, timeout_sec=0.1)
        c0, w0 = cpu_seconds(sim.pid), time.monotonic()
        n0 = {k: len(v) for k, v in arr.items()}
        while time.monotonic() - w0 < a.seconds:
            rclpy.spin_once(node, timeout_sec=0.05)
        c1, w1 = cpu_seconds(sim.pid), time.monotonic()
        d = {kv.key: kv.value for kv in diag[0].status[0].values} if diag[0] else {}
        js, mkst = stats(arr['js'][n0['js']:]), stats(arr['mk'][n0['mk']:])
        node.destroy_node()
        rclpy.shutdown()
    finally:
        sim.send_signal(signal.SIGINT)
        try:
            sim.wait(15)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
    x = np.asarray(tm.rest_positions, np.float64)
    if a.no_objects:
        py_ms, np_ms, nbytes = float('nan'), float('nan'), 0
    else:
        py_ms, np_ms, nbytes = python_object_markers(tm, x)
    out = {
        'model': tm.name, 'refine': a.refine, 'params': a.params or 'default', 'integrator': a.integrator or 'the set\'s', 'paused': a.paused, 'realtime': not a.as_fast_as_possible, 'vertices': tm.n_vertices, 'surface_triangles': int(len(tm.surface_triangles)),
        'marker_bytes': int(float(d.get('marker_bytes', nbytes))), 'window_s': round(w1 - w0, 2), 'publish_rate_target_hz': a.rate,
        'joint_states': js, 'markers': mkst,
        'simulator_cpu_percent_of_one_core': round(100 * (c1 - c0) / (w1 - w0), 1),
        'real_time_factor': float(d.get('real_time_factor', 'nan')), 'steps_per_s': float(d.get('steps_per_s', 'nan')),
        'node_marker_ms_mean': float(d.get('marker_ms_mean', 'nan')), 'node_marker_ms_max': float(d.get('marker_ms_max', 'nan')),
        'node_marker_encode_ms_mean': float(d.get('marker_encode_ms_mean', 'nan')),
        'load_average_1min': os.getloadavg()[0], 'cpu_count': os.cpu_count(),
        'marker_python_objects_ms': round(py_ms, 1), 'marker_numpy_ms': round(np_ms, 3),
        'numpy_speedup': round(py_ms / np_ms, 1),
        'markers_ok_34hz': bool(mkst['rate_hz'] >= 34.0), 'marker_under_5ms': bool(float(d.get('marker_ms_mean', 'nan')) < 5.0),
    }
    print(f"model {out['model']}: {out['vertices']} vertices, MarkerArray {out['marker_bytes'] / 1e6:.2f} MB")
    print(f"/joint_states  {js['rate_hz']:.2f} Hz  p50 {js['p50_ms']} ms  p99 {js['p99_ms']} ms")
    print(f"/tissue/markers {mkst['rate_hz']:.2f} Hz  p50 {mkst['p50_ms']} ms  p99 {mkst['p99_ms']} ms")
    print(f"simulator CPU {out['simulator_cpu_percent_of_one_core']} % of one core; real-time factor "
          f"{out['real_time_factor']}; {out['steps_per_s']:.0f} steps/s")
    print(f"marker build+publish in the node: mean {out['node_marker_ms_mean']:.2f} ms, max {out['node_marker_ms_max']:.2f} ms "
          f"(encode alone {out['node_marker_encode_ms_mean']:.2f} ms; target < 5 ms); load average {out['load_average_1min']:.1f} on {out['cpu_count']} CPUs\n"
          f"Python objects {py_ms:.1f} ms vs numpy {np_ms:.3f} ms (x{out['numpy_speedup']})")
    print(json.dumps(out))


if __name__ == '__main__':
    main()
