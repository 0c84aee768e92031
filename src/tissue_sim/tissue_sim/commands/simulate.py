"""`tissue-sim simulate`: headless run of the solver (no ROS) under an activation timeline."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from tissue_sim.errors import UserError

NAME = 'simulate'
HELP = ('run the elastic muscle model headless (no ROS) under muscle activations; save the run as MCAP '
        '(what analyze, render and export-run read) or its observation arrays as .npz')


def add_arguments(p):
    p.add_argument('model', nargs='?', help='model file (.npz from build-model); default: the bundled anatomy; '
                   '"phantom:knee" for the solver\'s analytic knee phantom')
    p.add_argument('--duration', type=float, default=None,
                   help="simulated time [s] (default 3, or the motion's own duration with --motion)")
    p.add_argument('--activate', action='append', default=[], metavar='NAME=A[@T0[-T1]]',
                   help='activation A in [0, 1] of a muscle, a group (e.g. hamstrings) or "all", from T0 (default 0) '
                        'to T1 (default: the end) [s]; repeatable. A muscle selected by several entries takes the most '
                        'specific one (muscle > name prefix > group > all), as in the activation node')
    p.add_argument('--motion', metavar='NAME',
                   help='a named motion (the activation node\'s --profile NAME): knee_flexion, knee_extension, kick, '
                        'heel_raise, ankle_pump (tissue_sim.core.activation.MOTIONS; docs/ros.md); --activate entries '
                        'are added to it')
    p.add_argument('--timeline', metavar='FILE.yaml', help='timeline file, same format as the activation node: muscles: {name or group: [[t, a], ...]} (piecewise linear)')
    p.add_argument('--params', default=None,
                   help='paper | physical | parameter file .yaml (default paper; physical with --motion, the set the '
                        'motions are made for)')
    p.add_argument('--set', action='append', default=[], metavar='NAME=VALUE', dest='overrides',
                   help='change a field of the parameter set (repeatable; VALUE read as YAML), e.g. --set '
                        'integrator=implicit --set substeps=1 (docs/solver.md "Parameter sets")')
    p.add_argument('--dt', type=float, help='step [s] (default: the parameter set\'s dt)')
    p.add_argument('--every', type=int, default=10, help='record every N steps (default %(default)s)')
    p.add_argument('--positions', action='store_true', help='.npz output: also record all vertex positions (large)')
    p.add_argument('-o', '--output', metavar='RUN.mcap|OBS.npz',
                   help='RUN.mcap: the run in the recorder\'s format (topology + a TissueState per recorded step; '
                        'analyze/render/export-run read it); OBS.npz: the observation arrays only (not a run)')
    p.add_argument('--json', action='store_true', help='print the summary as one JSON object')


def _parse_activation(spec: str, duration: float):
    if '=' not in spec:
        raise UserError(f'--activate {spec!r}: expected NAME=A[@T0[-T1]]')
    name, rest = spec.split('=', 1)
    t0, t1 = 0.0, None
    if '@' in rest:
        rest, when = rest.split('@', 1)
        try:
            if '-' in when:
                a, b = when.split('-', 1)
                t0, t1 = float(a), float(b)
            else:
                t0 = float(when)
        except ValueError:
            raise UserError(f'--activate {spec!r}: bad time {when!r}') from None
    try:
        a = float(rest)
    except ValueError:
        raise UserError(f'--activate {spec!r}: activation {rest!r} is not a number') from None
    if not (0.0 <= a <= 1.0):
        raise UserError(f'--activate {spec!r}: activation must be in [0, 1]')
    eps = 1e-6
    pts = [(0.0, 0.0)] if t0 > 0 else []
    pts += [(max(t0 - eps, 0.0), 0.0)] if t0 > 0 else []
    pts += [(t0, a)]
    if t1 is not None:
        if t1 <= t0:
            raise UserError(f'--activate {spec!r}: T1 must be after T0')
        pts += [(t1, a), (t1 + eps, 0.0)]
    return name.strip(), pts


def _load(args):
    """(model, params, activation function's timeline) of the command line; UserError naming a problem."""
    from tissue_sim.core.activation import load_timeline, motion_timeline
    from tissue_sim.core.load import load_model, load_params
    try:
        tm = load_model(args.model)
        params = load_params(args.params, args.dt, args.overrides)
        # the same timeline file format as `activation --profile timeline` (muscles: {name: [[t, a], ...]})
        timeline = {name: list(zip(times.tolist(), values.tolist()))
                    for name, (times, values) in (load_timeline(args.timeline) if args.timeline else {}).items()}
        if args.motion:
            timeline = motion_timeline(args.motion)
    except ValueError as e:               # ModelError, ActivationError, a bad parameter file
        raise UserError(str(e)) from None
    for spec in args.activate:
        name, pts = _parse_activation(spec, args.duration)
        old = timeline.get(name)
        timeline[name] = pts if old is None or isinstance(old, (int, float)) else list(old) + pts
    return tm, params, timeline


def run(args) -> int:
    from tissue_sim.core.activation import MOTIONS, timeline_function
    from tissue_sim.core.load import implicit_hint
    if args.motion is not None and args.timeline:
        raise UserError('--motion and --timeline exclude each other')
    if args.motion is not None and args.motion not in MOTIONS:
        raise UserError(f'--motion {args.motion!r}: unknown motion; expected one of {", ".join(MOTIONS)}')
    if args.params is None:
        args.params = 'physical' if args.motion else 'paper'
    if args.duration is None:
        args.duration = MOTIONS[args.motion].duration if args.motion else 3.0
    if not (args.duration > 0 and math.isfinite(args.duration)):
        raise UserError('--duration must be > 0')
    if args.every < 1:
        raise UserError('--every must be >= 1')
    if args.dt is not None and not (0 < args.dt < 1):
        raise UserError('--dt must be in (0, 1) s')
    if args.output and Path(args.output).suffix not in ('.mcap', '.npz'):
        raise UserError(f'-o {args.output}: expected RUN.mcap (a run) or OBS.npz (observation arrays)')
    tm, params, timeline = _load(args)
    from tissue_sim.core import solver
    try:
        sim = solver.compile_model(tm, params)
        fn = timeline_function(sim, timeline)
    except ValueError as e:
        raise UserError(str(e)) from None
    rec = {k: [] for k in ('time', 'joint_positions', 'joint_velocities', 'muscle_lengths', 'muscle_volumes',
                           'muscle_stretch', 'kinetic_energy', 'elastic_energy', 'segment_poses', 'activation')}
    positions = []
    failure = None
    st = solver.make_state(sim)
    out = Path(args.output) if args.output else None
    writer = _open_run(out, tm, sim, args.motion) if out is not None and out.suffix == '.mcap' else None
    t_wall = time.perf_counter()
    try:
        for t, o in solver.simulate(sim, args.duration, fn, every=args.every, state=st, output='obs'):
            act = fn(t)
            for k in rec:
                rec[k].append(act if k == 'activation' else o[k])
            if args.positions:
                positions.append(st.x.astype(np.float32))
            if writer is not None:
                writer.write_frame(st, o, act)
    except solver.DivergenceError as e:
        failure = str(e) + implicit_hint(sim.params)
    finally:
        if writer is not None:
            writer.close()
    wall = time.perf_counter() - t_wall
    arr = {k: np.asarray(v) for k, v in rec.items()}
    summary = _summary(sim, arr, wall, failure)
    summary['motion'] = args.motion
    if out is not None and writer is None:
        extra = {'positions': np.asarray(positions)} if args.positions else {}
        try:
            np.savez_compressed(out, **arr, **extra, joint_names=np.array(tm.joint_names, dtype=str),
                                muscle_names=np.array(tm.muscle_names, dtype=str), model_name=np.array(tm.name),
                                model_hash=np.array(tm.content_hash()), params_yaml=np.array(sim.params.to_yaml()),
                                summary_json=np.array(json.dumps(summary)))
        except OSError as e:
            raise UserError(f'{out}: cannot write ({e})') from None
    if out is not None:
        summary['output'] = str(out)
    if args.json:
        print(json.dumps(summary))
    else:
        _print_summary(tm, summary)
    if failure:
        raise UserError(failure, exit_code=1)
    return 0


def _open_run(out: Path, tm, sim, motion=None):
    """The run MCAP writer (the recorder's format: topology, then one TissueState per recorded step)."""
    from tissue_sim.core import mcapio, runio
    try:
        return runio.RunWriter(out, tm, parameters_yaml=sim.params.to_yaml(),
                               metadata={'source': 'tissue-sim simulate', **({'motion': motion} if motion else {})})
    except (OSError, mcapio.McapIOError) as e:
        raise UserError(f'{out}: cannot write ({e})') from None


def _summary(sim, arr, wall, failure):
    tm = sim.tissue
    q = np.degrees(arr['joint_positions']) if arr['joint_positions'].size else np.zeros((1, sim.n_joints))
    L, V = arr['muscle_lengths'], arr['muscle_volumes']
    t_end = float(arr['time'][-1]) if arr['time'].size else 0.0
    n_steps = t_end / (sim.params.dt)
    return {
        'model': tm.name, 'params': sim.params.preset, 'simulated_s': t_end, 'wall_s': round(wall, 3),
        'real_time_factor': round(t_end / wall, 3) if wall > 0 else None,
        'steps_per_s': round(n_steps / wall) if wall > 0 else None, 'substeps': sim.n_substeps,
        'diverged': failure,
        'joints': {n: {'start_deg': float(q[0, j]), 'end_deg': float(q[-1, j]), 'min_deg': float(q[:, j].min()),
                       'max_deg': float(q[:, j].max())} for j, n in enumerate(tm.joint_names)},
        'muscles': {n: {'length_change_pct': float(100 * (L[-1, m] / L[0, m] - 1)) if L[0, m] > 0 else None,
                        'max_volume_change_pct': float(100 * np.abs(V[:, m] / V[0, m] - 1).max()) if V[0, m] > 0 else None}
                    for m, n in enumerate(tm.muscle_names)},
    }


def _print_summary(tm, s):
    from rich.console import Console
    from rich.table import Table
    con = Console()
    con.print(f'[bold]{s["model"]}[/] ({s["params"]} parameters): {s["simulated_s"]:.3f} s simulated in '
              f'{s["wall_s"]:.2f} s wall, real-time factor {s["real_time_factor"]}, {s["steps_per_s"]} steps/s, '
              f'{s["substeps"]} sub-step(s) per step')
    t = Table(title='joints [deg]')
    for c in ('joint', 'start', 'end', 'min', 'max'):
        t.add_column(c, justify='right' if c != 'joint' else 'left')
    for n, j in s['joints'].items():
        t.add_row(n, *(f'{j[k]:.1f}' for k in ('start_deg', 'end_deg', 'min_deg', 'max_deg')))
    con.print(t)
    t = Table(title='muscles')
    for c in ('muscle', 'length change %', 'max |volume change| %'):
        t.add_column(c, justify='right' if c != 'muscle' else 'left')
    for n, m in s['muscles'].items():
        lc, vc = m['length_change_pct'], m['max_volume_change_pct']
        if lc is not None and (abs(lc) > 0.05 or len(s['muscles']) <= 12):
            t.add_row(n, f'{lc:+.1f}', f'{vc:.2f}')
    con.print(t)
    if s['diverged']:
        con.print(f'[bold red]{s["diverged"]}[/]')
    if s.get('output'):
        con.print(f'run written to {s["output"]}')
