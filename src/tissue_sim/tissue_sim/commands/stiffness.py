"""`tissue-sim stiffness`: knee joint stiffness under co-contraction of hamstrings and quadriceps
(tissue_sim.core.stiffness; docs/solver.md "Co-contraction stiffness")."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

from tissue_sim.errors import UserError, bounded

NAME = 'stiffness'
HELP = ('measure the knee\'s joint stiffness under co-contraction of hamstrings and quadriceps at several '
        'activation levels (joint lock: hold, step by +-delta, k = -dtau/dtheta) and the free knee\'s drift; '
        'writes a table, a JSON and a plot')


def add_arguments(p):
    p.add_argument('model', nargs='?', help='model file (.npz from build-model); default: the bundled anatomy')
    p.add_argument('-o', '--output', metavar='DIR', default='stiffness',
                   help='output folder for stiffness_<params>.json and .png (default %(default)s)')
    p.add_argument('--params', default='physical', help='paper | physical | parameter file .yaml (default %(default)s)')
    p.add_argument('--levels', default='0,0.25,0.5,1', metavar='LIST',
                   help='hamstring activation levels in [0, 1], comma-separated (default %(default)s); the quadriceps '
                        'get the activation that cancels the hamstrings\' active torque at the angle')
    p.add_argument('--angle', type=float, default=30.0, help='knee flexion angle held [deg] (default %(default)s)')
    p.add_argument('--delta', type=float, default=2.0, help='perturbation +-delta [deg] (default %(default)s)')
    p.add_argument('--settle', type=float, default=0.3, help='hold after each change [s] (default %(default)s)')
    p.add_argument('--free', type=float, default=0.5, help='time the released knee is followed [s] (default %(default)s)')
    p.add_argument('--no-single', action='store_true', help='skip the hamstrings-alone reference')
    p.add_argument('--jobs', type=bounded(int, low=1), default=None, metavar='N',
                   help='levels measured at once, each on a thread of its own (default: the CPUs this process may use)')
    p.add_argument('--json', action='store_true', help='print the result as one JSON object')


def _levels(text: str) -> list:
    try:
        out = [float(v) for v in text.split(',') if v.strip()]
    except ValueError:
        raise UserError(f'--levels: expected comma-separated numbers in [0, 1], got {text!r}') from None
    if not out or any(not (0.0 <= v <= 1.0) for v in out):
        raise UserError(f'--levels {text}: every level must be in [0, 1]')
    return out


def run(args) -> int:
    from tissue_sim.core import solver, stiffness
    from tissue_sim.core.load import load_model, load_params
    levels = _levels(args.levels)
    for name, v, lo, hi in (('--angle', args.angle, 0.0, 180.0), ('--delta', args.delta, 0.0, 20.0),
                            ('--settle', args.settle, 0.0, 10.0), ('--free', args.free, 0.0, 10.0)):
        if not (math.isfinite(v) and lo < v <= hi):
            raise UserError(f'{name} {v}: must be in ({lo:g}, {hi:g}]')
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise UserError(f'-o {out}: exists and is not a folder')
    try:
        tm = load_model(args.model)
        params = load_params(args.params)
        sim = solver.compile_model(tm, params)
    except ValueError as e:
        raise UserError(str(e)) from None
    if stiffness.KNEE not in tm.joint_names:
        raise UserError(f'the model has no joint {stiffness.KNEE!r} (joints: {", ".join(tm.joint_names)})')
    try:
        for g in stiffness.AGONISTS:
            solver.muscle_indices(sim, g)
    except (KeyError, ValueError) as e:
        raise UserError(f'the model needs the groups hamstrings and quadriceps ({e})') from None
    lo, hi = sim.j_range[list(tm.joint_names).index(stiffness.KNEE)]
    if not (math.degrees(lo) <= args.angle - args.delta and args.angle + args.delta <= math.degrees(hi)):
        raise UserError(f'--angle {args.angle:g} +- --delta {args.delta:g} leaves the knee\'s range '
                        f'{math.degrees(lo):g}..{math.degrees(hi):g} deg')
    from rich.console import Console
    con = Console(stderr=args.json)
    t0 = time.perf_counter()
    res = stiffness.measure(sim, levels, angle_deg=args.angle, delta_deg=args.delta, settle=args.settle,
                            free_seconds=args.free, single=not args.no_single,
                            progress=lambda a: con.print(f'  level {a:g} done ({time.perf_counter() - t0:.0f} s)'),
                            jobs=args.jobs)
    res['wall_s'] = round(time.perf_counter() - t0, 1)
    tag = Path(args.params).stem if args.params.endswith(('.yaml', '.yml')) else args.params
    try:
        out.mkdir(parents=True, exist_ok=True)
        jpath, ppath = out / f'stiffness_{tag}.json', out / f'stiffness_{tag}.png'
        jpath.write_text(json.dumps(res, indent=1))
        stiffness.plot(res, ppath)
    except OSError as e:
        raise UserError(f'{out}: cannot write ({e})') from None
    res['files'] = [str(jpath), str(ppath)]
    if args.json:
        print(json.dumps(res))
    else:
        _print(con, res)
        con.print(f'wrote {jpath} and {ppath} ({res["wall_s"]} s)')
    return 1 if any('diverged' in r for r in res['levels']) else 0


def _print(con, res):
    from rich.table import Table
    t = Table(caption='ham a: hamstring activation; quad a: the quadriceps\' balancing it; tau: isometric knee torque; '
                      'k: stiffness; drift: largest excursion of the released knee; ham alone: the hamstrings at ham a '
                      'without the quadriceps (k N m/rad, drift deg)',
              title=f'knee stiffness under co-contraction at {res["angle_deg"]:g} deg (+-{res["delta_deg"]:g} deg), '
                    f'{res["params"]} set; torque + = flexing')
    for c in ('ham a', 'quad a', 'tau N m', 'k N m/rad', 'k N m/deg', 'drift deg', 'ham alone k', 'ham alone drift'):
        t.add_column(c, justify='right')
    for r in res['levels']:
        if 'diverged' in r:
            t.add_row(f'{r["level"]:g}', '', f'diverged: {r["diverged"]}', '', '', '', '', '')
            continue
        h = r.get('hamstrings_only', {})
        t.add_row(f'{r["level"]:g}', f'{r["activations"]["quadriceps"]:.3f}', f'{r["torque_nm"]:+.1f}',
                  f'{r["stiffness_nm_per_rad"]:.1f}', f'{r["stiffness_nm_per_deg"]:.2f}', f'{r["free_drift_max_deg"]:.1f}',
                  f'{h["stiffness_nm_per_rad"]:.1f}' if 'stiffness_nm_per_rad' in h else '-',
                  f'{h["free_drift_max_deg"]:.1f}' if 'free_drift_max_deg' in h else '-')
    con.print(t)
    k = res.get('published_passive_stiffness_nm_per_rad')
    if k is not None:
        con.print(f'relaxed knee at {res["angle_deg"]:g} deg, Riener & Edrich 1999 (all passive structures, hip and ankle 0): '
                  f'k = {k:.1f} N m/rad (level 0 above)')
