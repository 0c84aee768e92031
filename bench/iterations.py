#!/usr/bin/env python3
"""How fast the implicit integrator's local/global iteration converges within one step: the experiment of
bench/convergence.py (physical set, hamstrings fully active from rest, implicit, 1 ms) run to step --at, then one
step of the readable reference (`reference.reference_step`) from that state with N iterations for each N, and the
free vertices' distance from the result with the most iterations.

    . ./env.sh && python bench/iterations.py [--refine 3] [--at 150] [--iterations 1,2,4,8,16] [--out DIR] [--quick]

Prints a table; writes DIR/iterations.json and DIR/iterations.png; default DIR bench/out/. Last line: one JSON
object. --quick: the bundled limb (1x), iterations 1,2,4,8. A distance that shrinks slowly with N is the
preconditioner A (implicit.py) being far stiffer than the tissue's soft modes (docs/convergence.md).
"""
from __future__ import annotations

import copy
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

for _v in ('NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_v, '1')
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))

import numpy as np  # noqa: E402

from tissue_sim.core import builder, solver  # noqa: E402
from tissue_sim.core.solver import reference as RF  # noqa: E402


def parse_counts(text: str) -> list[int]:
    try:
        n = sorted({int(v) for v in text.split(',')})
    except ValueError:
        n = []
    if len(n) < 2 or n[0] < 1:
        raise ValueError(f'--iterations {text!r}: expected two or more whole numbers >= 1 separated by commas')
    return n


def main(argv=None) -> int:
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--refine', default='3', help='refinement of the bundled limb (default 3)')
    ap.add_argument('--at', type=bounded(int, low=0), default=150, help='steps of the fast path before the reference step (default 150)')
    ap.add_argument('--iterations', default='1,2,4,8,16', help='iteration counts, comma-separated (default 1,2,4,8,16)')
    ap.add_argument('--out', default=str(ROOT / 'bench' / 'out'), help='folder for iterations.json and .png')
    ap.add_argument('--quick', action='store_true', help='the 1x limb, iterations 1,2,4,8')
    a = ap.parse_args(argv)
    if a.quick:
        a.refine, a.iterations = '1', '1,2,4,8'
    try:
        R = builder.parse_refinements(a.refine)
        counts = parse_counts(a.iterations)
        if len(R) != 1:
            raise ValueError(f'--refine {a.refine!r}: expected one refinement')
        if a.at < 1:
            raise ValueError(f'--at must be >= 1, got {a.at}')
    except ValueError as e:
        print(f'error: {e}', file=sys.stderr)
        return 2
    tm = builder.default_model(refine=R[0])
    sim = solver.compile_model(tm, solver.Params.physical(integrator='implicit', substeps=1))
    st, c = solver.make_state(sim), solver.make_control(sim)
    c.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    solver.step(sim, st, c, n_steps=a.at)
    free = sim.inv_mass > 0
    xs, cpu = {}, {}
    for n in counts:
        s2 = copy.deepcopy(st)
        sim2 = solver.compile_model(tm, dataclasses.replace(sim.params, implicit_iterations=n))
        c0 = time.process_time()
        RF.reference_step(sim2, s2, c.activation)
        cpu[n] = time.process_time() - c0
        xs[n] = s2.x[free].copy()
    last = counts[-1]
    rows = []
    for n in counts:
        d = np.linalg.norm(xs[n] - xs[last], axis=1)
        rows.append({'iterations': n, 'max_mm': round(float(d.max()) * 1e3, 4), 'mean_mm': round(float(d.mean()) * 1e3, 5),
                     'reference_cpu_s': round(cpu[n], 2)})
    knee = float(np.degrees(st.q[list(tm.joint_names).index('knee_r')]))
    print(f'{R[0]:g}x limb ({tm.n_vertices:,} vertices), state after {a.at} steps (knee {knee:.1f} deg), one reference step:')
    print()
    print(f'| iterations | free vertices from the {last}-iteration result: max [mm] | mean [mm] | reference CPU s |')
    print('|---|---|---|---|')
    for r in rows:
        print(f'| {r["iterations"]} | {r["max_mm"]:.3f} | {r["mean_mm"]:.4f} | {r["reference_cpu_s"]:.1f} |')
    per = [(rows[i + 1]['max_mm'] / rows[i]['max_mm']) ** (1.0 / (rows[i + 1]['iterations'] - rows[i]['iterations']))
           for i in range(len(rows) - 2) if rows[i]['max_mm'] > 0]
    factor = round(float(np.exp(np.mean(np.log(per)))), 3) if per else None
    print(f'\nper-iteration factor of the max distance (geometric mean): {factor}')
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {'refine': R[0], 'vertices': int(tm.n_vertices), 'at_step': a.at, 'knee_deg': round(knee, 2), 'rows': rows,
               'per_iteration_factor': factor}
    (out / 'iterations.json').write_text(json.dumps(summary, indent=1))
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot([r['iterations'] for r in rows[:-1]], [r['max_mm'] for r in rows[:-1]], 'o-')
    ax.set_xlabel('local/global iterations')
    ax.set_ylabel(f'max distance from {last} iterations [mm]')
    ax.set_title(f'{R[0]:g}x limb, one step at {a.at} ms')
    fig.tight_layout()
    fig.savefig(out / 'iterations.png', dpi=110)
    print(f'written {out / "iterations.json"}, {out / "iterations.png"}')
    print(json.dumps(summary))
    return 0


if __name__ == '__main__':
    sys.exit(main())
