"""Bone-contact benchmark: solver steps/s with contact on and off in the same run (paper and physical
sets, bundled model), and with --penetration the free vertices inside the bones and the inverted
cells over an active 0-120 deg flexion and a passive sweep (physical set), and over the paper set's 3-s
hamstring contraction, contact on and off.

    .venv/bin/python bench/contact.py [--seconds 6] [--penetration]
    .venv/bin/python bench/contact.py --ankle [--set NAME=VALUE ...]

--ankle: only the physical set's active run (full hamstring activation from rest), its first 1.5 s sampled
every 25 ms: knee and ankle angle and velocity, V/V0 of the ankle's front fat (cells 380, 388), every
inverted cell (the ankle fat's transient after the knee's 120-deg stop, docs/contact.md "Ankle fat"), the
knee's peak, steps per CPU second; --set overrides a Params field of the physical set (repeatable).

Steps/s are per CPU second of this process on one thread (bench/solver.py's measure), best of 4
windows, the contact-off and contact-on windows interleaved; tests/sub-step = the broad phase's vertex-grid
tests per stage-4 call with contact on (the State's workspace counts them). The issue
allows contact to cost at most 30 % of the paper set's steps/s. The last line of the output is one
JSON object with the figures.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

for _v in ('NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_v] = '1'
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))

import numpy as np  # noqa: E402

from tissue_sim.core import solver  # noqa: E402
from tissue_sim.core.model import JOINT_HINGE  # noqa: E402
from tissue_sim.core.solver import contact  # noqa: E402


def steps_per_s(sims, seconds, rounds=4):
    """Steps per CPU second of each sim (full hamstring activation from rest, the knee moves), best of
    `rounds` windows of seconds / rounds each, the sims' windows interleaved (a load change on the
    shared machine then hits both alike)."""
    runs = []
    for sim in sims:
        st, ctl = solver.make_state(sim), solver.make_control(sim)
        ctl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
        solver.step(sim, st, ctl, n_steps=20)          # compiled, warm
        runs.append((sim, st, ctl))
    best = [0.0] * len(sims)
    for _ in range(rounds):
        for k, (sim, st, ctl) in enumerate(runs):
            n, t0, c0 = 0, time.perf_counter(), time.process_time()
            while time.perf_counter() - t0 < seconds / rounds:
                solver.step(sim, st, ctl, n_steps=20)
                n += 20
            best[k] = max(best[k], n / max(time.process_time() - c0, 1e-9))
    stats = [st.workspace.contact.stats for _, st, _ in runs]     # broad phase: (calls, vertex-grid tests) per state
    return best, [float(s[1] / s[0]) if s[0] else 0.0 for s in stats]


def knee(sim):
    tm = sim.tissue
    return [j for j, n in enumerate(tm.joint_names) if 'knee' in n and tm.joint_type[j] == JOINT_HINGE][0]


def _record(sim, st, label, rows):
    pen = contact.mesh_penetration(sim, st)
    bad, ratio, _ = contact.inverted_cells(sim, st.x)
    rows.append(dict(at=label, knee_deg=round(math.degrees(st.q[knee(sim)]), 1),
                     inside={b: v[0] for b, v in pen.items() if v[0]},
                     deeper_1mm=sum(v[1] for v in pen.values()),
                     max_depth_mm=round(1e3 * max(v[2] for v in pen.values()), 2),
                     inverted=len(bad), min_ratio=round(float(ratio.min()), 3) if len(bad) else None,
                     inverted_cells=[int(c) for c in bad]))


def active_run(sim, duration=3.0):
    """Full hamstring activation from rest (the CLI's --activate hamstrings=1), recorded every 0.5 s; each row
    also gives the knee's peak angle so far (checked every 10 steps) and the kinetic energy."""
    rows = []
    st, ctl = solver.make_state(sim), solver.make_control(sim)
    ctl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    steps = int(round(0.5 / sim.params.dt))
    j, peak = knee(sim), 0.0
    for k in range(int(round(duration / 0.5))):
        for _ in range(steps // 10):
            solver.step(sim, st, ctl, n_steps=10)
            peak = max(peak, math.degrees(st.q[j]))
        _record(sim, st, f't={(k + 1) * 0.5:.1f}s', rows)
        rows[-1].update(peak_knee_deg=round(peak, 2), kinetic_J=round(solver.kinetic_energy(sim, st), 3))
    return rows


def passive_sweep(sim, sweep_s=1.2, hold_s=1.0):
    """No activation; the knee driven from 0 to 120 deg at constant rate over sweep_s (joint set every
    step, its velocity the ramp's), then held at 120 deg for hold_s; recorded every 30 deg and at the end."""
    rows = []
    j = knee(sim)
    st, ctl = solver.make_state(sim), solver.make_control(sim)
    dt = sim.params.dt
    top = math.radians(120.0)
    n = int(round(sweep_s / dt))
    rate = top / (n * dt)
    q = st.q.copy()
    qd = np.zeros_like(q)
    marks = {int(round(n * a / 120.0)): a for a in (30, 60, 90, 120)}
    for i in range(1, n + 1):
        q[j], qd[j] = rate * i * dt, rate
        solver.set_joint_positions(sim, st, q, qd)
        solver.step(sim, st, ctl)
        if i in marks:
            _record(sim, st, f'{marks[i]} deg', rows)
    qd[j] = 0.0
    q[j] = top
    for i in range(int(round(hold_s / dt))):
        solver.set_joint_positions(sim, st, q, qd)
        solver.step(sim, st, ctl)
    _record(sim, st, f'120 deg held {hold_s:g}s', rows)
    return rows


def ankle_transient(sim, duration=1.5, every=0.025, watch=(380, 388)):
    """Full hamstring activation from rest, sampled every `every` s: (rows, {cell: [(t, V/V0)]}, knee peak [deg],
    steps per CPU second (the steps alone), (least V/V0 of any cell at any step, its time, the cell)). Each row:
    t, knee and ankle angle [deg] and velocity [deg/s], V/V0 of the watched cells, the inverted cells."""
    tm = sim.tissue
    names = list(tm.joint_names)
    jk, ja = knee(sim), names.index('ankle_r')
    st, ctl = solver.make_state(sim), solver.make_control(sim)
    ctl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    solver.step(sim, st, ctl)                                   # compiled
    n = int(round(every / sim.params.dt))
    rows, inv, peak, cpu = [], {}, math.degrees(st.q[jk]), 0.0
    low = (math.inf, 0.0, -1)                                   # every step: (least V/V0 of any cell, t, cell)
    for k in range(int(round(duration / every))):
        for _ in range(n if k else n - 1):
            c0 = time.process_time()
            solver.step(sim, st, ctl)
            cpu += time.process_time() - c0
            peak = max(peak, math.degrees(st.q[jk]))
            r = contact.inverted_cells(sim, st.x)[2]
            c = int(np.argmin(r))
            if r[c] < low[0]:
                low = (float(r[c]), st.step * sim.params.dt, c)
        t = (k + 1) * every
        bad, ratio, allr = contact.inverted_cells(sim, st.x)
        for c, r in zip(bad, ratio):
            inv.setdefault(int(c), []).append((round(t, 3), round(float(r), 3)))
        rows.append(dict(t=round(t, 3), knee=math.degrees(st.q[jk]), knee_vel=math.degrees(st.qd[jk]),
                         ankle=math.degrees(st.q[ja]), ankle_vel=math.degrees(st.qd[ja]),
                         watch={c: float(allr[c]) for c in watch if c < len(allr)}, inverted=[int(c) for c in bad]))
    steps = int(round(duration / every)) * n - 1
    return rows, inv, peak, steps / max(cpu, 1e-9), low


def ankle_main(sets):
    from tissue_sim.core.builder import default_model
    try:
        params = solver.Params.from_assignments('physical', sets)
    except ValueError as e:
        print(f'error: --set: {e}', file=sys.stderr)
        sys.exit(2)
    kw = {k: getattr(params, k) for k in (a.partition('=')[0].strip() for a in sets)}
    sim = solver.compile_model(default_model(), params)
    rows, inv, peak, sps, least = ankle_transient(sim)
    print(f'physical set{" with " + str(kw) if kw else ""}: full hamstring activation from rest, every 25 ms')
    print(f'  {"t":>6s} {"knee":>7s} {"knee/s":>8s} {"ankle":>7s} {"ankle/s":>8s}  V/V0 watched   inverted')
    for r in rows:
        if r['inverted'] or 0.4 <= r['t'] <= 1.0:
            w = ' '.join(f'{c}:{v:.3f}' for c, v in r['watch'].items())
            print(f'  {r["t"]:6.3f} {r["knee"]:7.2f} {r["knee_vel"]:8.1f} {r["ankle"]:7.2f} {r["ankle_vel"]:8.1f}'
                  f'  {w}   {r["inverted"]}')
    low = min((v for s in inv.values() for _, v in s), default=None)
    print(f'inverted: {({c: (s[0][0], s[-1][0]) for c, s in inv.items()}) or "none"}, min V/V0 {low}, '
          f'knee peak {peak:.2f} deg, {sps:.0f} steps per CPU s')
    print(f'every step: least V/V0 {least[0]:.3f} (cell {least[2]} at {least[1]:.3f} s)')
    print(json.dumps(dict(params=kw, inverted=inv, min_ratio=low, knee_peak_deg=round(peak, 3),
                          knee_end_deg=round(rows[-1]['knee'], 3), steps_per_cpu_s=round(sps, 1),
                          least_every_step=dict(ratio=round(least[0], 4), t=round(least[1], 3), cell=least[2]))))


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=bounded(above=0), default=6.0, help='measuring time per configuration [s]')
    ap.add_argument('--penetration', action='store_true', help='also run the active flexion and passive sweep')
    ap.add_argument('--ankle', action='store_true', help="only the ankle fat's transient (physical set, every 25 ms)")
    ap.add_argument('--set', action='append', default=[], metavar='NAME=VALUE', help='with --ankle: a Params field')
    a = ap.parse_args()
    if a.ankle:
        return ankle_main(a.set)
    from tissue_sim.core.builder import default_model
    tm = default_model()
    out = dict(model='default_model()', speed={})
    print(f'{"set":10s} {"contact off":>14s} {"contact on":>14s} {"cost":>7s} {"tests/sub-step":>15s}   '
          f'(steps/s per CPU s, one thread)')
    for preset in ('paper', 'physical'):
        sims = [solver.compile_model(tm, getattr(solver.Params, preset)(bone_contact=on)) for on in (False, True)]
        best, tests = steps_per_s(sims, a.seconds)
        r = dict(zip(('off', 'on'), best))
        cost = 1.0 - r['on'] / r['off']
        out['speed'][preset] = dict(off=round(r['off'], 1), on=round(r['on'], 1), cost=round(cost, 4),
                                    tests_per_substep=round(tests[1], 1))
        print(f'{preset:10s} {r["off"]:14.1f} {r["on"]:14.1f} {100 * cost:6.1f}% {tests[1]:15.1f}')
    out['paper_cost_within_30pct'] = out['speed']['paper']['cost'] <= 0.30
    if a.penetration:
        out['penetration'] = {}
        for preset in ('physical', 'paper'):
            for on in (False, True):
                sim = solver.compile_model(tm, getattr(solver.Params, preset)(bone_contact=on))
                key = 'on' if on else 'off'
                runs = dict(active=active_run(sim))
                if preset == 'physical':
                    runs['passive'] = passive_sweep(sim)
                out['penetration'].setdefault(preset, {})[key] = runs
                for kind, rows in runs.items():
                    print(f'\n{preset} set, contact {key}, {kind}:')
                    print(f'  {"at":18s} {"knee":>6s} {"peak":>6s} {">1mm":>5s} {"max mm":>7s} {"inv":>4s} {"min V/V0":>8s}'
                          f'  inside')
                    for row in rows:
                        print(f'  {row["at"]:18s} {row["knee_deg"]:6.1f} {row.get("peak_knee_deg", ""):>6} '
                              f'{row["deeper_1mm"]:5d} {row["max_depth_mm"]:7.2f} {row["inverted"]:4d} '
                              f'{str(row["min_ratio"]):>8s}  {row["inside"]}')
    print(json.dumps(out))


if __name__ == '__main__':
    main()
