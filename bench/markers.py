#!/usr/bin/env python3
"""Marker encoding cost against model size: the simulator's /tissue/markers MarkerArray (core/markers.py)
on the bundled limb built 1x, 3x and 6x finer (`build-model --refine R`), side by side with the previous
encoding (one `np.take(..., axis=0, out=...)` per marker; the same bytes); optionally what rate a
subscriber sees (bench/ros_rate.py: the real simulator node and a subscriber process over DDS).

    . ./env.sh && python bench/markers.py [--refine 1,3,6] [--ros SECONDS] [--quick]

Per refinement: vertices, soft-tissue triangle corners, message size, CPU ms per encode (no colouring:
what `make demo` publishes; and with the skin_area colouring, the per-vertex measure included), the
previous encoding, ns per corner. Timings are CPU time of this process (best of 5 rounds of repeated
calls; the machine is shared). --ros S: for each model also run bench/ros_rate.py for S seconds (34 Hz,
physical set) and report the rates seen. --quick: 1x and 2x, no --ros (for `make bench`). Last line JSON.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

for _v in ('NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_v, '1')
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))

import numpy as np  # noqa: E402

from tissue_sim.core import markers as mk  # noqa: E402
from tissue_sim.core import measures  # noqa: E402


def cpu_ms(fn, min_s=0.3, rounds=5):
    """CPU milliseconds per call (best of ``rounds`` rounds of at least ``min_s`` CPU seconds each)."""
    fn()
    best = math.inf
    for _ in range(rounds):
        n, c0 = 0, time.process_time()
        while True:
            fn()
            n += 1
            c = time.process_time() - c0
            if c >= min_s / rounds:
                break
        best = min(best, c / n)
    return 1e3 * best


def previous_encode(enc, stamp_ns, x):
    """The encoding before the compiled gather: one np.take per soft-tissue marker, then the bytes."""
    b = enc._buf
    stamp = np.frombuffer(np.array([stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000], '<u4').tobytes(), np.uint8)
    for off in enc._stamp_offsets:
        b[4 + off:12 + off] = stamp
    for m, (kind, k, *_r) in enumerate(enc._layout):
        if kind == 'soft':
            np.take(x, enc._soft[k][0], axis=0, out=enc._points[m])
    return b.tobytes()


def measure(tm, R):
    rng = np.random.default_rng(0)
    x = np.asarray(tm.rest_positions, np.float64) + rng.normal(0, 1e-4, (tm.n_vertices, 3))
    enc = mk.MarkerArrayEncoder(tm, bones=False)               # what the simulator node publishes per frame
    corners = int(len(enc._g_idx))
    new = enc.encode(7, x)
    old = previous_encode(mk.MarkerArrayEncoder(tm, bones=False), 7, x)
    assert new == old, 'the two encodings differ'
    ms_new = cpu_ms(lambda: enc.encode(7, x))
    ms_old = cpu_ms(lambda: previous_encode(enc, 7, x))
    ms_bytes = cpu_ms(lambda: enc._buf.tobytes())
    col = mk.MarkerArrayEncoder(tm, colouring='skin_area', bones=False)
    rest = [None]

    def coloured():
        ratio, rest[0] = measures.skin_area_ratio_per_vertex(tm, x, rest[0])
        return col.encode(7, x, None, mk.diverging_rgba(ratio[col.skin_corners]))
    ms_col = cpu_ms(coloured)
    r = dict(refine=R, vertices=int(tm.n_vertices), surface_triangles=int(len(tm.surface_triangles)), corners=corners,
             markers=int(enc.n_markers), marker_mb=round(enc.nbytes / 1e6, 3), encode_ms=round(ms_new, 3),
             previous_encode_ms=round(ms_old, 3), speedup=round(ms_old / ms_new, 2), bytes_copy_ms=round(ms_bytes, 3),
             skin_area_encode_ms=round(ms_col, 3), ns_per_corner=round(1e6 * ms_new / max(corners, 1), 2),
             previous_ns_per_corner=round(1e6 * ms_old / max(corners, 1), 2))
    print(f'{R:g}x: {r["vertices"]:,} vertices, {corners:,} corners, {r["marker_mb"]} MB: encode {ms_new:.2f} ms '
          f'(previous {ms_old:.2f} ms, x{r["speedup"]}; of it the bytes copy {ms_bytes:.2f} ms), with skin_area '
          f'colouring {ms_col:.2f} ms; {r["ns_per_corner"]} ns per corner', flush=True)
    return r


def ros_rate(R, seconds):
    cmd = [sys.executable, str(ROOT / 'bench' / 'ros_rate.py'), '--seconds', str(seconds), '--refine', str(R),
           '--params', 'physical', '--no-objects']
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=1200)
    try:
        return json.loads(p.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return {'error': (p.stderr or p.stdout).strip().splitlines()[-1:] or ['no output']}


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--refine', default='1,3,6', help='refinements of the bundled limb, comma-separated (default 1,3,6)')
    ap.add_argument('--ros', type=bounded(low=0), default=0.0, metavar='SECONDS',
                    help='also run bench/ros_rate.py for this many seconds per model (0 = not; default)')
    ap.add_argument('--quick', action='store_true', help='1x and 2x, no --ros (make bench)')
    a = ap.parse_args()
    if a.quick:
        a.refine, a.ros = '1,2', 0.0
    from tissue_sim.core.builder import parse_refinements
    try:
        refs = parse_refinements(a.refine)
    except ValueError as e:
        print(f'error: {e}', file=sys.stderr)
        sys.exit(2)
    from tissue_sim.core.builder import default_model
    rows = []
    for R in refs:
        rows.append(measure(default_model(refine=R), R))
        if a.ros > 0:
            rr = ros_rate(R, a.ros)
            rows[-1]['ros'] = rr
            if 'error' in rr:
                print(f'  ros_rate: {rr["error"]}')
            else:
                print(f'  over DDS at 34 Hz: subscriber sees /tissue/markers {rr["markers"]["rate_hz"]} Hz (p99 gap '
                      f'{rr["markers"]["p99_ms"]} ms), /joint_states {rr["joint_states"]["rate_hz"]} Hz; node marker '
                      f'build+publish {rr["node_marker_ms_mean"]:.1f} ms; real-time factor {rr["real_time_factor"]}, '
                      f'{rr["steps_per_s"]:.0f} steps/s, simulator CPU {rr["simulator_cpu_percent_of_one_core"]} %', flush=True)
    print()
    print('| model | vertices | corners | MB per frame | encode [ms] | previous [ms] | with skin_area [ms] | ns/corner |')
    print('|---|---|---|---|---|---|---|---|')
    for r in rows:
        print(f'| {r["refine"]:g}x | {r["vertices"]:,} | {r["corners"]:,} | {r["marker_mb"]} | {r["encode_ms"]} | '
              f'{r["previous_encode_ms"]} | {r["skin_area_encode_ms"]} | {r["ns_per_corner"]} |')
    if any('ros' in r for r in rows):
        print()
        print('| model | /tissue/markers seen [Hz] | p99 gap [ms] | /joint_states [Hz] | node marker ms | real-time factor | steps/s |')
        print('|---|---|---|---|---|---|---|')
        for r in rows:
            rr = r.get('ros', {})
            if 'markers' in rr:
                print(f'| {r["refine"]:g}x | {rr["markers"]["rate_hz"]} | {rr["markers"]["p99_ms"]} | {rr["joint_states"]["rate_hz"]} | '
                      f'{rr["node_marker_ms_mean"]:.1f} | {rr["real_time_factor"]} | {rr["steps_per_s"]:.0f} |')
    out = {'rows': rows, 'load_average_1min': round(os.getloadavg()[0], 2), 'cpu_count': os.cpu_count(),
           'timing': 'CPU ms of this process per call, best of 5 rounds'}
    print(json.dumps(out))


if __name__ == '__main__':
    main()
