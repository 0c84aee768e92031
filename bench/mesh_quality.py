#!/usr/bin/env python3
"""Mesh quality of the bundled limb built R times finer, at rest and under load: what the builder's report says
(fat slices on the ray fallback, the fat rings' inner spacing, cells over the shear limit, the fat's volume against
its label) and what a short run does to the cells (the physical set, the hamstrings fully active from rest, implicit
integrator at the set's 1-ms step: cells whose volume falls below 0.2 V0 or inverts, and the least V/V0).

    . ./env.sh && python bench/mesh_quality.py [--refine 1,3,6] [--duration 0.05] [--build NAME=VALUE ...] [--out DIR]
                                               [--quick]

Prints a table; writes DIR/mesh_quality.json and DIR/mesh_quality.png (the least V/V0 over time per refinement);
default DIR bench/out/. Last line: one JSON object. --quick: 1x and 3x (for `make bench`). The run is the experiment of bench/convergence.py (its first
50 ms by default); a cell that inverts there is a mesh defect, not a time-step one (docs/convergence.md). --build
NAME=VALUE (repeatable): a builder setting of the models (e.g. fat_follow=false: what a meshing choice changes).
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

for _v in ('NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_v, '1')
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))

import numpy as np  # noqa: E402

from tissue_sim.core import builder, solver  # noqa: E402
from tissue_sim.core.solver import params as P  # noqa: E402
from tissue_sim.errors import UserError  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from convergence import LOW_VOLUME as LOW, cell_health  # noqa: E402  (the cells' count, one definition)

SAMPLE_EVERY = 5           # steps between volume samples (5 ms at the physical set's 1-ms step)


def measure(R: float, duration: float, build: dict | None = None) -> dict:
    lab, tis = builder.default_inputs()
    tm, rep = builder.build_model(lab, tis, refine=R, **(build or {}))
    q = rep['quality']
    ray_slices = [w for w in rep['warnings'] if 'rays used on this slice' in w]
    sim = solver.compile_model(tm, solver.Params.physical(integrator='implicit', substeps=1))
    st, c = solver.make_state(sim), solver.make_control(sim)
    c.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    n = int(round(duration / sim.params.dt))
    t, least, low, inverted, diverged = [], [], 0, 0, None
    while st.step < n:
        try:
            solver.step(sim, st, c, n_steps=min(SAMPLE_EVERY, n - st.step))
        except solver.DivergenceError as e:
            diverged = int(e.step)
            break
        h = cell_health(sim, st)
        t.append(st.step * sim.params.dt)
        least.append(h['least_volume_ratio'])
        low, inverted = h['below_low'], h['inverted']
    fat = q['shear'].get('fat', {})
    mus = q['shear'].get('muscle', {})
    return {'refine': R, 'vertices': int(tm.n_vertices), 'cells': int(tm.n_cells),
            'fat_ray_slices': len(ray_slices), 'fat_inner_spacing': q['fat_inner_spacing'],
            'fat_volume_ratio': q['volume_ratio'].get('fat'),
            'shear_over_limit': {'fat': fat.get('over_limit', 0), 'muscle': mus.get('over_limit', 0),
                                 'limit': q['shear_limit']},
            'fat_shear_p95': fat.get('p95'),
            'run_s': duration, 'cells_below_0.2': low, 'cells_inverted': inverted,
            'least_volume_ratio': least[-1] if least else None, 'diverged_at_step': diverged,
            'series': {'t_s': t, 'least_volume_ratio': least}}


def main(argv=None) -> int:
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--refine', default='1,3,6', help='refinements of the bundled limb, comma-separated (default 1,3,6)')
    ap.add_argument('--duration', type=bounded(above=0), default=0.05, help='simulated seconds (default 0.05)')
    ap.add_argument('--out', default=str(ROOT / 'bench' / 'out'), help='folder for mesh_quality.json and .png')
    ap.add_argument('--build', action='append', default=[], metavar='NAME=VALUE',
                    help='a builder setting of the models (repeatable; VALUE read as YAML, e.g. fat_follow=false; '
                         'docs/builder.md)')
    ap.add_argument('--quick', action='store_true', help='1x and 3x only')
    a = ap.parse_args(argv)
    if a.quick:
        a.refine = '1,3'
    try:
        refs = builder.parse_refinements(a.refine)
    except ValueError as e:
        print(f'error: {e}', file=sys.stderr)
        return 2
    if not (a.duration > 0):
        print(f'error: --duration must be > 0, got {a.duration}', file=sys.stderr)
        return 2
    try:
        build = P.parse_assignments(a.build, 'builder settings')
        builder.settings_with_defaults(build)
    except (ValueError, UserError) as e:
        print(f'error: --build: {e}', file=sys.stderr)
        return 2
    rows = []
    for R in refs:
        r = measure(R, a.duration, build)
        rows.append(r)
        print(f'{R:g}x: {r["vertices"]:,} vertices, {r["fat_ray_slices"]} fat slices on rays, inner spacing '
              f'{r["fat_inner_spacing"]["min_ratio"]} (slice {r["fat_inner_spacing"]["slice"]}), '
              f'{r["cells_inverted"]} cells inverted at {a.duration:g} s', flush=True)
    print()
    print(f'| model | vertices | fat slices on rays | fat inner spacing, least (slice) | fat volume / label | '
          f'cells over shear {rows[0]["shear_over_limit"]["limit"]:g} (fat / muscle) | fat shear p95 | at {a.duration:g} s: '
          f'cells < {LOW} V0 | inverted | least V/V0 |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        least = 'diverged at step %d' % r['diverged_at_step'] if r['diverged_at_step'] is not None else \
            f'{r["least_volume_ratio"]:.2f}'
        print(f'| {r["refine"]:g}x | {r["vertices"]:,} | {r["fat_ray_slices"]} | {r["fat_inner_spacing"]["min_ratio"]:.3f} '
              f'({r["fat_inner_spacing"]["slice"]}) | {r["fat_volume_ratio"]:.3f} | {r["shear_over_limit"]["fat"]} / '
              f'{r["shear_over_limit"]["muscle"]} | {r["fat_shear_p95"]} | {r["cells_below_0.2"]} | {r["cells_inverted"]} | {least} |')
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {'experiment': 'physical set, implicit x1, hamstrings fully active from rest', 'duration_s': a.duration,
               'build': build, 'rows': rows}
    (out / 'mesh_quality.json').write_text(json.dumps(summary, indent=1))
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for r in rows:
        ax.plot(np.array(r['series']['t_s']) * 1e3, r['series']['least_volume_ratio'], 'o-', ms=3, label=f'{r["refine"]:g}x')
    ax.axhline(0.0, color='k', lw=0.5)
    ax.set_xlabel('time [ms]')
    ax.set_ylabel('least cell volume V/V0')
    ax.set_title('cells under a hamstring contraction (physical set, implicit, 1 ms)')
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / 'mesh_quality.png', dpi=110)
    print(f'written {out / "mesh_quality.json"}, {out / "mesh_quality.png"}')
    print(json.dumps({k: v for k, v in summary.items() if k != 'rows'} |
                     {'rows': [{k: v for k, v in r.items() if k != 'series'} for r in rows]}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
