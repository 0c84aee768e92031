"""`tissue-sim validate`: the bundled knee's mechanics against its source OpenSim model (docs/validation.md)."""
from __future__ import annotations

import json
import time
from pathlib import Path

from tissue_sim.errors import UserError, bounded

NAME = 'validate'
HELP = ('compare the bundled knee with its source OpenSim model (Rajagopal 2016): muscle lengths and moment '
        'arms, passive and active, isometric flexion torque; writes a table, a JSON and a plot')


def add_arguments(p):
    p.add_argument('-o', '--output', metavar='DIR', default='validation',
                   help='output folder for validation_<params>.json and .png (default %(default)s)')
    p.add_argument('--params', default='physical', help='parameter set: physical | paper (default %(default)s)')
    p.add_argument('--angles', default='0:120:10', metavar='LIST',
                   help='knee flexion angles [deg]: comma-separated, or START:STOP:STEP (default %(default)s)')
    p.add_argument('--settle', type=float, default=1.0, metavar='S',
                   help='time the knee is held at each angle before measuring [s] (default %(default)s)')
    p.add_argument('--ramp-speed', type=float, default=200.0, metavar='DEG_S',
                   help='speed at which the held knee moves from one angle to the next [deg/s] (default %(default)s)')
    p.add_argument('--osim', metavar='FILE.osim', help='source OpenSim model (default: pose2sim 0.10.49\'s '
                   'Model_Pose2Sim_muscles_flex.osim)')
    p.add_argument('--passive', action='store_true',
                   help='instead: the passive knee moment (tissue + passive fibre force, no activation) held at each angle '
                        '(default 0:120:15, settle 0.5 s) against the source model with passive fibre force on and '
                        'Riener & Edrich 1999; writes passive_<params>.json and .png')
    p.add_argument('--kinematics', action='store_true',
                   help='instead: the source model\'s own moment arms with its walker knee, with the plain hinge of the '
                        'paper set and with its wrap objects removed (no elastic model); writes kinematics.json and .png')
    p.add_argument('--no-via-points', dest='via_points', action='store_false',
                   help='the bundled limb built without the builder setting via_points (only the muscles\' end rings fixed to '
                        'their bones, as the paper; docs/builder.md "Via points")')
    p.add_argument('--build', action='append', default=[], metavar='NAME=VALUE',
                   help='a builder setting of the bundled limb (repeatable; VALUE read as YAML, e.g. fat_follow=true; '
                        'docs/builder.md): validates that build instead of the default one; the JSON records them')
    p.add_argument('--set', action='append', default=[], metavar='NAME=VALUE', dest='overrides',
                   help='change a field of the parameter set (repeatable; VALUE read as YAML, e.g. wrap_surfaces= or '
                        'fold_contact=knee; docs/solver.md); the JSON records them')
    p.add_argument('--active-sets', dest='grouping', metavar='groups|others',
                   help='which knee muscles contract together in the active sweeps besides the hamstrings: each '
                        'anatomical group on its own, antagonists at rest (groups, the default), or all of them at once '
                        '(others) (docs/validation.md "Active sweeps")')
    p.add_argument('--jobs', type=bounded(int, low=1), default=None, metavar='N',
                   help='sweeps held at once, each on a thread of its own (default: the CPUs this process may use)')
    p.add_argument('--strict', action='store_true', help='exit 1 when a target fails (default: report only)')
    p.add_argument('--quiet', action='store_true', help='print only the targets')


def run(args) -> int:
    from tissue_sim.core import validation as V
    try:
        angles = V.parse_angles(args.angles)
        if args.osim and not Path(args.osim).is_file():
            raise V.ValidationError(f'--osim {args.osim}: no such file')
        if args.overrides and args.kinematics:
            raise V.ValidationError('--set and --kinematics: --kinematics evaluates the source model only')
        if args.grouping is not None and (args.passive or args.kinematics):
            raise V.ValidationError('--active-sets: only the moment-arm and torque sweeps have active sets, not '
                                    '--passive or --kinematics')
        if args.jobs is not None and (args.passive or args.kinematics):
            raise V.ValidationError('--jobs: --passive holds one sweep and --kinematics none')
        if args.grouping is not None:
            V.check_grouping(args.grouping)                  # a bad name: one line, before anything runs
        if not args.kinematics:
            V.parameter_set(args.params, args.overrides)     # a bad --set: one line, before anything runs
    except V.ValidationError as e:
        raise UserError(str(e)) from None
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise UserError(f'-o {out}: exists and is not a folder')
    from rich.console import Console
    con = Console()
    t0 = time.perf_counter()
    seen = set()

    def progress(kind, deg):          # (called from the sweeps' threads: once per sweep)
        if not args.quiet and kind not in seen:
            seen.add(kind)
            con.print(f'  holding the knee: {kind} ...')

    if args.passive and args.kinematics:
        raise UserError('--passive and --kinematics: choose one')
    if not args.via_points and args.kinematics:
        raise UserError('--no-via-points and --kinematics: --kinematics evaluates the source model only')
    if args.build and args.kinematics:
        raise UserError('--build and --kinematics: --kinematics evaluates the source model only')
    model, build = None, _build_settings(args)
    if build:
        from tissue_sim.core.builder import default_model
        model = default_model(**build)
    if args.passive:
        return _run_passive(args, con, out, V, progress, model, build)
    if args.kinematics:
        return _run_kinematics(args, con, out, V, angles)
    try:
        res = V.run_validation(args.params, angles, args.settle, args.ramp_speed, osim_path=args.osim, model=model,
                               progress=progress, overrides=args.overrides, grouping=args.grouping or 'groups',
                               jobs=args.jobs)
    except V.ValidationError as e:
        raise UserError(str(e)) from None
    res['wall_s'] = round(time.perf_counter() - t0, 1)
    res['build'] = build
    jpath, ppath = _write(out, f'validation_{args.params}', res, V.jsonable, V.plot)
    _print(con, res, args.quiet)
    con.print(f'wrote {jpath} and {ppath} ({res["wall_s"]} s)')
    failed = [k for k, v in res['targets'].items() if v['pass'] is False]
    return 1 if (args.strict and failed) else 0


def _build_settings(args) -> dict:
    """The builder settings of --build (and --no-via-points) as a dict, checked before anything runs: UserError naming
    the bad one (one line, exit 2)."""
    from tissue_sim.core.builder import settings_with_defaults
    from tissue_sim.core.solver.params import parse_assignments
    try:
        build = parse_assignments(args.build, '--build')
    except ValueError as e:
        raise UserError(str(e)) from None
    if not args.via_points:
        build['via_points'] = False
    try:
        settings_with_defaults(build)
    except UserError as e:
        raise UserError(f'--build: {e}') from None
    return build


def _write(out, stem, res, jsonable, plot):
    """out/stem.json and out/stem.png of a result; UserError naming the folder if they cannot be written."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        jpath, ppath = out / f'{stem}.json', out / f'{stem}.png'
        jpath.write_text(json.dumps(jsonable(res), indent=1))
        plot(res, ppath)
    except OSError as e:
        raise UserError(f'{out}: cannot write ({e})') from None
    return jpath, ppath


def _run_kinematics(args, con, out, V, angles):
    t0 = time.perf_counter()
    try:
        res = V.run_kinematics(angles, osim_path=args.osim)
    except V.ValidationError as e:
        raise UserError(str(e)) from None
    res['wall_s'] = round(time.perf_counter() - t0, 1)
    jpath, ppath = _write(out, 'kinematics', res, V.jsonable, V.plot_kinematics)
    from rich.table import Table
    t = Table(title='source model moment arms [mm] (+ flexor): walker knee / plain hinge (the paper set\'s knee) / '
                    'walker knee without the wrap objects')
    shown = [i for i, a in enumerate(res['angles_deg']) if a % 30 == 0] or list(range(len(res['angles_deg'])))
    t.add_column('muscle')
    for i in shown:                                     # (every angle is in the JSON)
        t.add_column(f'{res["angles_deg"][i]:g}°', justify='right')
    for name, d in res['muscles'].items():
        t.add_row(name, *(f'{d["walker_moment_arm"][i] * 1e3:+.1f} / {d["hinge_moment_arm"][i] * 1e3:+.1f} / '
                          f'{d["unwrapped_moment_arm"][i] * 1e3:+.1f}' for i in shown))
    if not args.quiet:
        con.print(t)
    n_out = sum(not r['within_tolerance'] for r in res['hamstrings'])
    con.print(f'the plain hinge changes {len(res["sign_changes"])} moment-arm signs: '
              + (', '.join(f'{c["muscle"]} {c["angle_deg"]:g}°' for c in res['sign_changes']) or 'none'))
    con.print(f'target hamstrings on the plain hinge: {n_out} of {len(res["hamstrings"])} outside ±'
              f'{V.MOMENT_ARM_TOLERANCE:.0%} of the walker knee\'s: '
              + ', '.join(f'{r["muscle"]} {r["angle_deg"]:g}° {r["rel_difference"]:+.0%}' for r in res['hamstrings']
                          if not r['within_tolerance']))
    con.print(f'without the wrap objects {len(res["wrap_sign_changes"])} moment-arm signs change: '
              + (', '.join(f'{c["muscle"]} {c["angle_deg"]:g}° ({c["walker_mm"]:+.1f} -> {c["unwrapped_mm"]:+.1f} mm)'
                           for c in res['wrap_sign_changes']) or 'none'))
    con.print(f'wrote {jpath} and {ppath} ({res["wall_s"]} s)')
    return 0


def _run_passive(args, con, out, V, progress, model=None, build=None):
    angles = None if args.angles == '0:120:10' else V.parse_angles(args.angles)
    settle = 0.5 if args.settle == 1.0 else args.settle
    t0 = time.perf_counter()
    try:
        res = V.run_passive_validation(args.params, angles, settle, args.ramp_speed, osim_path=args.osim,
                                       model=model, progress=progress, overrides=args.overrides)
    except V.ValidationError as e:
        raise UserError(str(e)) from None
    res['wall_s'] = round(time.perf_counter() - t0, 1)
    res['build'] = build or {}
    jpath, ppath = _write(out, f'passive_{args.params}', res, V.jsonable, V.plot_passive)
    from rich.table import Table
    pc = res['passive_curve']
    t = Table(title=f'passive knee moment [N m] (+ flexing), hip 0, ankle 0, params {res["params"]} (passive fibres '
                    + (f'on: {pc["curve"]}, k {pc["k"]:g}, eps0 {pc["eps0"]:g})' if res['passive_force_length'] else 'off)'))
    header, rows = V.passive_rows(res)
    for c in header:
        t.add_column(c, justify='right')
    for r in rows:
        t.add_row(*r)
    con.print(t)
    if not res['rms_vs_opensim_Nm']:
        con.print('[yellow]the paper set is dimensionless: its moments are not newton metres, the comparison is n/a[/]')
    else:
        con.print('RMS vs Riener & Edrich: ' + ', '.join(f'{k} {v:.1f}' for k, v in res['rms_vs_riener_edrich_Nm'].items())
                  + ' N m; vs OpenSim: ' + ', '.join(f'{k} {v:.1f}' for k, v in res['rms_vs_opensim_Nm'].items()) + ' N m')
    con.print('ankle at knee 0, fibres only [N m] (+ dorsiflexing), ours / ' + ' / '.join(res['variants']) + ': ' + '; '.join(
        f'{a:g}°: {res["ankle"]["fibres_Nm"][i]:.1f} / ' + ' / '.join(f'{d["ankle_fibres_Nm"][i]:.0f}' for d in res['variants'].values())
        + f' (OpenSim {res["ankle"]["opensim_Nm"][i]:.0f}, R&E {res["ankle"]["riener_edrich_Nm"][i]:.1f})'
        for i, a in enumerate(res['ankle']['angles_deg'])))
    if res['diverged']:
        con.print(f'[red]the sweep diverged: {res["diverged"]}[/]')
    con.print(f'wrote {jpath} and {ppath} ({res["wall_s"]} s)')
    return 0


def _print(con, res, quiet):
    from rich.table import Table

    from tissue_sim.core import validation as V
    if not quiet:
        t = Table(title=f'knee muscles vs OpenSim ({res["opensim"]["version"]}), params {res["params"]}: '
                        'length ratio, moment arm r = -dL/dθ (r F = torque / force of its cells), force / Fmax '
                        '(active set fully active)')
        for c in V.TABLE_HEADER:
            t.add_column(c, justify='left' if c == 'muscle' else 'right')
        for r in V.table_rows(res):
            t.add_row(*r)
        con.print(t)
        t = Table(title='isometric knee-flexion torque, all hamstrings fully active (+ flexes)')
        for c in V.TORQUE_HEADER:
            t.add_column(c, justify='right')
        for r in V.torque_rows(res):
            t.add_row(*r)
        con.print(t)
    for kind, d in res.get('diverged', {}).items():
        if d:
            con.print(f'[red]the {kind} sweep diverged at {d["at_deg"]:g}° ({d["error"]}): NaN from there on[/]')
    tg = res['targets']
    mark = {True: '[green]PASS[/]', False: '[red]FAIL[/]', None: '[yellow]n/a[/]'}
    ms = tg['moment_arm_signs']
    con.print(f'{mark[ms["pass"]]} every knee muscle\'s moment arm has the source model\'s sign '
              f'({len(ms["wrong"])} wrong (muscle, mode, angle); resolution of each sweep\'s holds: '
              + ', '.join(f'{k} {v:.1f}' for k, v in ms['resolution_mm'].items()) + ' mm'
              + (f', {ms["undecided"]} where the source model\'s is within it' if ms.get('undecided') else '') + ')')
    hm = tg['hamstring_moment_arms']
    nbad = sum(not r['pass'] for r in hm['rows'])
    con.print(f'{mark[hm["pass"]]} hamstring moment arms within ±{hm["tolerance"]:.0%} of the source model at 0/30/60/90° '
              f'passive and active ({nbad} of {len(hm["rows"])} outside'
              + (f'; not sampled: {hm["angles_not_sampled"]}' if hm['angles_not_sampled'] else '') + ')')
    hf = tg['hamstring_force']
    con.print(f'{mark[hf["pass"]]} each hamstring ≥ {hf["min_fraction"]:.0%} of Fmax near its optimal length: '
              + ', '.join(f'{r["muscle"]} {r["force_fraction"]:.0%} at {r["angle_deg"]:g}° (active tension '
                                   f'{r["tension_fraction"]:.0%}, OpenSim {r["opensim_active_fraction"]:.0%})' for r in hf['rows'])
              + (f' ({hf["note"]})' if hf['note'] else ''))
    pt = tg['peak_torque']
    con.print(f'{mark[pt["pass"]]} peak isometric flexion torque {pt["peak_Nm"]:.1f} N m at {pt["at_deg"]:g}° '
              f'(adult range {pt["range_Nm"][0]:g}-{pt["range_Nm"][1]:g} N m)' + (f' ({pt["note"]})' if pt['note'] else ''))
    ts = tg['torque_shape']
    con.print(f'{mark[ts["pass"]]} torque-angle shape: peak at {ts["peak_at_deg"]:g}° (published: small to moderate '
              f'flexion, ≤ {V.SHAPE_PEAK_MAX_DEG:g}°; OpenSim {ts["opensim_peak_at_deg"]:g}°), '
              f'{"falling" if ts["falls_after_peak"] else "not falling"} after it')
    me = res.get('moment_arm_error')
    if me and me['mean_abs_mm'] is not None:
        worst = sorted(((v, k) for k, v in me['per_muscle_mm'].items() if v is not None), reverse=True)[:3]
        con.print(f'moment arms against the source model (a summary, not a target): mean |ours - OpenSim| '
                  f'{me["mean_abs_mm"]:.2f} mm over {me["n"]} (muscle, mode, angle); largest '
                  + ', '.join(f'{k} {v:.1f}' for v, k in worst) + ' mm')
