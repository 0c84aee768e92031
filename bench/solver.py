"""Solver benchmark: steps per second (per CPU second) of the default model on one thread, side by side with the
same step in plain numpy (solver.reference_step) and with pypbd's shape matching (PositionBasedDynamics) on the
same cells; then the thread scaling of the step.

    .venv/bin/python bench/solver.py [--model FILE.npz] [--seconds 3] [--fine FILE.npz] [--threads 1,2] [--refine R]
                                     [--quick] [--ab N] [--stages I] [--sizes R,R,...] [--sustained R,R,...]

The physical set runs with its mass_scaled integrator (4 sub-steps) and, beside it, with the implicit integrator (one
sub-step of 1 ms; docs/solver.md "Implicit integrator"). --fine: the same two on a finer model (e.g. from
`tissue-sim build-model --slices 140 --muscle-rays 24 --fat-rays 36 --allow-broken-muscles`), with the factor's size
and the process's peak memory.

Thread scaling (--threads, default 1,2; 'none' skips it): steps per wall second for each number of threads
(Params.threads; 1 is the serial cell kernel, more the parallel one: the same numbers), side by side in one
process per configuration (the thread counts alternate, best of 3 windows each), for the paper set (mass_scaled,
100-step chunks), the physical set (mass_scaled, 4 sub-steps) and the physical set with the implicit integrator,
on the default model and, with --refine R (the bundled limb built R times finer, builder.default_model(refine=R))
or --fine FILE, on a finer model; with each configuration's peak resident memory (its own process:
resource.getrusage ru_maxrss); with --refine R also that limb's --sustained rates (below; `make bench` runs
--refine 2.6). --quick: 1-s windows and the scaling section only. --ab N: only the physical set, mass_scaled (affine
and enclosed volume) beside implicit (all with the hamstring sheath) and implicit without it, N alternating rounds
(ab_rates): the ratio the issue's target is about, on a shared machine. --stages I: the implicit
step's stages timed one by one (stage_times; --refine R: on the refined limb), where its time goes. --sizes R,R,...:
the physical set's implicit step on the bundled limb built R times finer, one thread, with the bytes of the arrays a
step reads and writes (size_scaling): how the cost per vertex changes once those outgrow the processor's caches.
--sustained R,R,...: the physical set's implicit step on the bundled limb built R times finer with each of --threads,
over a whole 1-s full hamstring contraction (ten 100-step windows): steps per wall second, median, slowest and fastest
window, and whether the median keeps real time (sustained_rates): the largest model that runs at real time here.

Model: tissue_sim.core.builder.default_model() (the bundled anatomy); if that is not available,
the builder's synthetic paper-sized limb phantom (tests/phantoms.py). Prints the figures as lines, then as a
markdown table (what docs/solver.md shows), and last one JSON object with them.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

def _refinements(flag: str, text: str) -> list:
    """The refinements R,R,... given to flag (builder.parse_refinements); a bad list: one line, exit 2."""
    from tissue_sim.core.builder import parse_refinements
    try:
        return parse_refinements(text)
    except ValueError:
        print(f'error: {flag} {text!r}: expected refinements >= 1 separated by commas', file=sys.stderr)
        sys.exit(2)


def _max_threads(argv) -> int:
    """The most threads --threads asks for (numba's pool is sized before numba is imported); 1 if none."""
    for i, a in enumerate(argv):
        text = a.split('=', 1)[1] if a.startswith('--threads=') else argv[i + 1] if a == '--threads' and i + 1 < len(argv) else None
        if text is not None:
            try:
                return max([1] + [int(t) for t in text.split(',') if t.strip().isdigit()])
            except ValueError:
                return 1
    return min(2, os.cpu_count() or 1)


for _v in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_v] = '1'                     # one thread for pypbd (OpenMP) and numpy's BLAS
if '--scaling-child' not in sys.argv:        # (a child inherits its parent's setting)
    os.environ['NUMBA_NUM_THREADS'] = str(_max_threads(sys.argv))   # numba's pool; the one-thread rows set threads: 1
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))
sys.path.insert(0, str(ROOT / 'tests'))

import dataclasses  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402

import numpy as np  # noqa: E402

from tissue_sim.core import solver  # noqa: E402
from tissue_sim.core.model import TissueModel  # noqa: E402
from tissue_sim.core.solver import cells as CK  # noqa: E402


def load_model(path):
    if path:
        return TissueModel.load(path), str(path)
    try:
        from tissue_sim.core.builder import default_model
        return default_model(), 'default_model() (bundled anatomy)'
    except Exception as e:  # the bundled anatomy may not exist yet
        from phantoms import make_limb_phantom
        from tissue_sim.core.builder import build_model
        tm, _ = build_model(make_limb_phantom())
        return tm, f'synthetic limb phantom (default_model() unavailable: {type(e).__name__}: {str(e)[:80]})'


def rate(fn, seconds):
    """Calls per second of fn per second of this process's CPU time (best of 3 windows of about
    seconds/3 of wall time). CPU time rather than wall time: the machine is shared, and a process
    that is descheduled is not slower; the wall-time rate is kept in WALL_RATES for the record."""
    fn()
    best, best_wall = 0.0, 0.0
    for _ in range(3):
        n, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds / 3:
            fn()
            n += 1
        cpu = max(time.process_time() - c0, 1e-9)
        best = max(best, n / cpu)
        best_wall = max(best_wall, n / (time.perf_counter() - t0))
    WALL_RATES.append(best_wall)
    return best


WALL_RATES = []


# ------------------------------------------------------------------------------------ pypbd
def pypbd_rate(sim, seconds):
    """pypbd: every cell as a ShapeMatchingConstraint on the same particles (stiffness 1, one
    solver iteration, no gravity); steps per second of its TimeStepController."""
    import pypbd
    model = pypbd.SimulationModel()
    model.init()
    pd = model.getParticles()
    for p in sim.rest:
        pd.addVertex(np.asarray(p, float))
    count = np.bincount(sim.cv, minlength=sim.n_vertices)
    for c in range(sim.n_cells):
        ids = sim.cv[sim.off[c]:sim.off[c + 1]]
        model.addShapeMatchingConstraint(len(ids), [int(i) for i in ids], [int(count[i]) for i in ids], 1.0)
    for i in sim.att_idx:
        pd.setMass(int(i), 0.0)             # bone-attached: kinematic
    simu = pypbd.Simulation.getCurrent()
    simu.initDefault()
    simu.setModel(model)
    ts = simu.getTimeStep()
    try:
        ts.setValueUInt(pypbd.TimeStepController.MAX_ITERATIONS, 1)
        simu.setVecValueReal(pypbd.Simulation.GRAVITATION, [0.0, 0.0, 0.0])
    except Exception:
        pass
    rng = np.random.default_rng(0)
    for i in range(0, sim.n_vertices, 7):       # a deformed start so the constraints do work
        pd.setPosition(int(i), pd.getPosition(int(i)) + rng.normal(scale=1e-3, size=3))
    return rate(lambda: ts.step(model), seconds), len(model.getConstraints())


def _cpu():
    """The processor (its rates differ: see docs/solver.md), the CPU numba compiles for, the kernel's lanes."""
    model = 'unknown'
    try:
        with open('/proc/cpuinfo') as fh:
            model = next((ln.split(':', 1)[1].strip() for ln in fh if ln.startswith('model name')), model)
    except OSError:
        pass
    return {'cpu_model': model, 'llvm_cpu': CK.compile_cpu(), 'lanes_per_block': CK.BLK}


def _cpu_name():
    """lscpu's model name (the processor the figures were measured on), else /proc/cpuinfo's."""
    try:
        out = subprocess.run(['lscpu'], capture_output=True, text=True, timeout=10).stdout
        name = next((ln.split(':', 1)[1].strip() for ln in out.splitlines() if ln.startswith('Model name')), None)
        if name:
            return name
    except (OSError, subprocess.SubprocessError):
        pass
    return _cpu()['cpu_model']


def parse_threads(text):
    """'1,2' -> [1, 2]; 'none' -> []; exit 2 with an error line otherwise."""
    if text.strip().lower() == 'none':
        return []
    try:
        out = [int(t) for t in text.split(',')]
    except ValueError:
        out = []
    if not out or any(n < 1 for n in out):
        print(f'error: --threads {text!r}: expected numbers >= 1 separated by commas, or none', file=sys.stderr)
        sys.exit(2)
    return out


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--model', help='a model .npz (default: the bundled anatomy)')
    ap.add_argument('--seconds', type=bounded(above=0), default=3.0, help='measuring time per figure [s]')
    ap.add_argument('--fine', help='also a finer model .npz: physical set, mass_scaled beside implicit')
    ap.add_argument('--threads', default=None, help="thread counts of the scaling section, e.g. 1,2 (default: 1,2 on a "
                    "machine with 2 or more cores; 'none': skip it)")
    ap.add_argument('--refine', help='the scaling section also on the bundled limb built R times finer (e.g. 3)')
    ap.add_argument('--quick', action='store_true', help='the scaling section only, 1-s windows')
    ap.add_argument('--ab', type=bounded(int, low=0), default=0, metavar='N', help='only the physical set mass_scaled beside implicit '
                    '(with and without the sheath), N alternating rounds of --seconds each (ab_rates)')
    ap.add_argument('--stages', type=bounded(int, low=0, high=20), default=0, metavar='I', help='only the implicit step\'s stages timed on '
                    'their own (I implicit iterations per step, 1-20; with --refine R on the refined limb) (stage_times)')
    ap.add_argument('--sizes', metavar='R,R,...', help='only the implicit step on the bundled limb built R times finer '
                    '(e.g. 1,2,2.6,3): time per step and per vertex beside the working set (size_scaling)')
    ap.add_argument('--sustained', metavar='R,R,...', help='only the implicit step on the bundled limb built R times '
                    'finer, with each of --threads, over a whole 1-s contraction: median steps per wall second and '
                    'whether it keeps real time (sustained_rates)')
    ap.add_argument('--scaling-child', help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.scaling_child:
        return scaling_child(json.loads(args.scaling_child))
    threads = parse_threads(args.threads if args.threads is not None else ','.join(
        str(n) for n in sorted({1, min(2, os.cpu_count() or 1)})))
    if args.refine is not None:
        from tissue_sim.core.builder import parse_refinements
        try:
            refine = parse_refinements(args.refine)
        except ValueError as e:
            print(f'error: {e}', file=sys.stderr)
            sys.exit(2)
        if len(refine) != 1:
            print(f'error: --refine {args.refine!r}: one refinement', file=sys.stderr)
            sys.exit(2)
    for path in (args.model, args.fine):
        if path and not Path(path).is_file():
            print(f'error: {path}: no such model file', file=sys.stderr)
            sys.exit(2)
    if args.sustained is not None:
        sizes = _refinements('--sustained', args.sustained)
        out = {'cpu': _cpu_name(), **_cpu(), 'timing': 'steps per wall second', 'threads': threads}
        print(f'CPU: {out["cpu"]} ({os.cpu_count()} cores; numba compiles for {out["llvm_cpu"]}); load average '
              f'{os.getloadavg()[0]:.1f} at the start')
        out['sustained'] = sustained_rates(sizes, threads)
        print(json.dumps(out))
        return
    if args.sizes is not None:
        sizes = _refinements('--sizes', args.sizes)
        out = {'cpu': _cpu_name(), **_cpu(), 'timing': 'per CPU second of this process, one thread'}
        print(f'CPU: {out["cpu"]} (numba compiles for {out["llvm_cpu"]}); {_caches()}')
        out['sizes'] = size_scaling(sizes, args.seconds)
        print(json.dumps(out))
        return
    if args.quick:
        out = {'cpu': _cpu_name(), **_cpu(), 'timing': 'steps per wall second'}
        print(f'CPU: {out["cpu"]} ({os.cpu_count()} cores; numba compiles for {out["llvm_cpu"]})')
        out['scaling'] = scaling(args, threads, 1.0)
        print()
        print(json.dumps(out))
        return
    tm, source = load_model(args.model)
    print(f'model: {source}: {tm.n_vertices} vertices, {tm.n_cells} cells '
          f'({int(np.sum(tm.cell_tissue == 1))} muscle, {int(np.sum(tm.cell_tissue == 2))} fat), '
          f'{len(tm.cell_vertices)} cell-vertex entries, {tm.n_joints} joints')
    cpu = _cpu()
    print(f'CPU: {cpu["cpu_model"]} (numba compiles for {cpu["llvm_cpu"]}; {cpu["lanes_per_block"]} cells per SIMD block)')
    out = {'model': source, 'vertices': tm.n_vertices, 'cells': tm.n_cells, **cpu}
    ham = [m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]
    if args.ab:
        out['ab'] = ab_rates(tm, args.ab, args.seconds)
        print(json.dumps(out))
        return
    if args.stages:
        if args.refine is not None:
            from tissue_sim.core.builder import default_model
            tm = default_model(refine=float(args.refine))
            print(f'refined x{args.refine}: {tm.n_vertices} vertices, {tm.n_cells} cells')
        out['stages'] = stage_times(tm, args.stages)
        print(json.dumps(out))
        return

    def solver_rate(params, chunk, model=tm):
        sim = solver.compile_model(model, dataclasses.replace(params, threads=1))      # one thread (the serial kernel)
        st, ctrl = solver.make_state(sim), solver.make_control(sim)
        ctrl.activation[[m for m, g in enumerate(model.muscle_groups) if g == 'hamstrings'] or [0]] = 1.0
        if chunk == 1:
            r = rate(lambda: solver.step(sim, st, ctrl), args.seconds)
        else:
            acts = np.tile(ctrl.activation, (chunk, 1))
            from tissue_sim.core.solver.step import _run
            r = chunk * rate(lambda: _run(sim, st, acts, sim.params.dt), args.seconds)
        return sim, r

    sim, r_step = solver_rate(solver.Params.paper(), 1)
    _, r_chunk = solver_rate(solver.Params.paper(), 100)
    r_chunk_wall = 100 * WALL_RATES[-1]
    p = sim.params
    print(f'numba solver, paper params, step() per call : {r_step:9.0f} steps/s  ({p.integrator}, {sim.n_substeps} '
          f'pass(es) per step, omega_max dT = {sim.omega_max * p.dt:.2f} at the true masses)')
    print(f'numba solver, paper params, 100-step chunks : {r_chunk:9.0f} steps/s  (simulate(); real-time factor '
          f'{r_chunk * p.dt:.1f})')
    xsim, r_explicit = solver_rate(solver.Params.paper(integrator='explicit'), 100)
    print(f'numba solver, paper params, explicit        : {r_explicit:9.0f} steps/s  ({xsim.n_substeps} sub-steps per '
          f'step, true masses)')
    phys, r_phys = solver_rate(solver.Params.physical(), 100)
    print(f'numba solver, physical params (make demo)    : {r_phys:9.0f} steps/s  ({phys.n_substeps} sub-steps per '
          f'step; real-time factor {r_phys * phys.params.dt:.2f})')
    _, r_phys_aff = solver_rate(solver.Params.physical(volume_measure='affine'), 100)
    print(f'numba solver, physical params, affine volume : {r_phys_aff:9.0f} steps/s  (volume_measure affine, the '
          f'implicit rows\' measure: the enclosed volume costs {100 * (1 - r_phys / r_phys_aff):.1f} %)')
    _, r_phys_nofat = solver_rate(solver.Params.physical(volume_stiffness_fat=0.0), 100)
    print(f'numba solver, physical params, no fat volume : {r_phys_nofat:9.0f} steps/s  (volume_stiffness_fat 0: the '
          f'fat volume term costs {100 * (1 - r_phys / r_phys_nofat):.1f} %)')
    isim, r_imp = solver_rate(solver.Params.physical(integrator='implicit', substeps=1), 100)
    ifac = implicit_factor(isim)
    print(f'numba solver, physical params, implicit      : {r_imp:9.0f} steps/s  (1 sub-step of 1 ms, one solve, '
          f'{isim.params.implicit_scheme}: {r_imp / r_phys_aff:.2f}x the affine mass_scaled row, {r_imp / r_phys:.2f}x '
          f'the enclosed one; factor {ifac["unknowns"]} unknowns, {ifac["entries"]:,} entries)')
    _, r_imp_be = solver_rate(solver.Params.physical(integrator='implicit', substeps=1, implicit_scheme='euler'), 100)
    print(f'numba solver, physical params, implicit euler: {r_imp_be:9.0f} steps/s  (backward Euler instead of BDF2: '
          f'BDF2 costs {100 * (1 - r_imp / r_imp_be):.1f} %)')
    _, r_imp2 = solver_rate(solver.Params.physical(integrator='implicit', substeps=1, implicit_iterations=2), 100)
    print(f'numba solver, physical params, implicit x2   : {r_imp2:9.0f} steps/s  (2 local/global iterations)')
    # plain numpy: reference_step, the same physics and integrator as the paper-set step (exact rotations by SVD)
    st_np, st_nb = solver.make_state(sim), solver.make_state(sim)
    ctrl = solver.make_control(sim)
    ctrl.activation[ham] = 1.0
    for _ in range(20):
        solver.reference_step(sim, st_np, ctrl.activation)
        solver.step(sim, st_nb, ctrl)
    agree = float(np.abs(st_np.x - st_nb.x).max())
    moved = float(np.abs(st_nb.x - sim.rest).max())
    r_numpy = rate(lambda: solver.reference_step(sim, st_np, ctrl.activation), args.seconds)
    print(f'plain numpy reference_step (batched SVD)     : {r_numpy:9.1f} steps/s  (max |x_numpy - x_numba| after '
          f'20 steps: {agree:.1e} m of {moved:.1e} m motion)')
    try:
        r_pbd, n_con = pypbd_rate(sim, args.seconds)
        print(f'pypbd shape matching ({n_con} constraints, 1 iteration)  : {r_pbd:9.0f} steps/s (one pass over '
              f'all cells per step)')
    except Exception as e:  # report, do not hide
        r_pbd = None
        print(f'pypbd: not timed ({type(e).__name__}: {e})')
    passes = r_chunk * sim.n_substeps           # our passes over all cells per second, full physics
    out.update(steps_per_s=round(r_step), steps_per_s_chunked=round(r_chunk), integrator=p.integrator,
               passes_per_step=sim.n_substeps, substeps=sim.n_substeps, cell_passes_per_s=round(passes),
               real_time_factor=round(r_chunk * p.dt, 2), steps_per_s_explicit=round(r_explicit),
               explicit_substeps=xsim.n_substeps, physical_steps_per_s=round(r_phys),
               physical_substeps=phys.n_substeps, physical_real_time_factor=round(r_phys * phys.params.dt, 2),
               physical_no_fat_volume_steps_per_s=round(r_phys_nofat), physical_affine_steps_per_s=round(r_phys_aff),
               numpy_steps_per_s=round(r_numpy, 1), speedup_vs_numpy=round(r_step / r_numpy, 1), numpy_agreement_m=agree,
               target_steps_per_s=10000, target_met=bool(r_chunk >= 10000), steps_per_s_chunked_wall=round(r_chunk_wall),
               physical_implicit_steps_per_s=round(r_imp), physical_implicit2_steps_per_s=round(r_imp2),
               physical_implicit_euler_steps_per_s=round(r_imp_be),
               implicit_speedup=round(r_imp / r_phys_aff, 2), implicit_speedup_vs_enclosed=round(r_imp / r_phys, 2),
               implicit_factor=ifac,
               cpu_load_1min=round(os.getloadavg()[0], 2), timing='per CPU second of this process, one thread')
    if args.fine:
        out['fine'] = fine_model(args.fine, solver_rate)
    out['scaling'] = scaling(args, threads, args.seconds)
    if args.refine is not None and threads:
        print(f'\nsustained: the refine {refine[0]:g} limb over a whole 1-s contraction (--sustained)')
        out['sustained'] = sustained_rates(refine, threads)
    if r_pbd:
        out.update(pypbd_steps_per_s=round(r_pbd, 1), speedup_vs_pypbd=round(r_chunk / r_pbd, 2),
                   speedup_vs_pypbd_per_pass=round(passes / r_pbd, 2), pypbd_target_met=bool(r_chunk >= 4 * r_pbd))
    print(f'speed-up vs plain numpy (per step() call): {out["speedup_vs_numpy"]}x; vs pypbd per step: '
          f'{out.get("speedup_vs_pypbd")}x (target 4x: {"met" if out.get("pypbd_target_met") else "NOT met"}); '
          f'target 10000 steps/s: {"met" if r_chunk >= 10000 else "NOT met"} ({r_chunk / 100:.0f} %); '
          f'load average {out["cpu_load_1min"]} on {os.cpu_count()} cores')
    print()
    print(markdown_table(out))
    print()
    print(json.dumps(out))


# ------------------------------------------------------------------------------------ thread scaling
SCALING_CONFIGS = (('paper set, mass_scaled', 'paper', {}),
                   ('physical set, mass_scaled x4', 'physical', {}),
                   ('physical set, implicit', 'physical', dict(integrator='implicit', substeps=1)))


def scaling(args, threads, seconds):
    """The thread-scaling section: one child process per (model, configuration) (its own peak memory), the
    thread counts side by side in it. Prints a table; returns the rows."""
    if not threads:
        return []
    models = [('default', {'model': args.model})]
    if args.refine is not None:
        models.append((f'refine {args.refine}', {'refine': float(args.refine)}))
    if args.fine:
        models.append((Path(args.fine).name, {'model': args.fine}))
    cpu = _cpu_name()
    rows = []
    print(f'\nthread scaling: steps per wall second, threads {",".join(map(str, threads))} side by side (best of 3 '
          f'windows of ~{seconds / 3:.1f} s each); {cpu}, {os.cpu_count()} cores, load average '
          f'{os.getloadavg()[0]:.1f} at the start')
    for mname, mspec in models:
        for cname, preset, kw in SCALING_CONFIGS:
            spec = dict(mspec, preset=preset, kw=kw, threads=threads, seconds=seconds)
            env = dict(os.environ, NUMBA_NUM_THREADS=str(max(threads)))
            res = subprocess.run([sys.executable, __file__, '--scaling-child', json.dumps(spec)], capture_output=True,
                                 text=True, env=env)
            lines = [ln for ln in res.stdout.splitlines() if ln.startswith('{')]
            if res.returncode != 0 or not lines:
                r = {'error': (res.stderr.strip().splitlines() or ['no output'])[-1]}
            else:
                r = json.loads(lines[-1])
            r.update(model_name=mname, config=cname)
            rows.append(r)
            if 'error' in r:
                print(f'  {mname:10s} {cname:30s} failed: {r["error"]}')
                continue
            rates = '  '.join(f'{n} thr: {r["rates"][str(n)]:>9}' for n in threads)
            ratio = (f'  x{r["rates"][str(threads[-1])] / r["rates"][str(threads[0])]:.2f}'
                     if all(isinstance(r['rates'][str(n)], float) for n in (threads[0], threads[-1])) else '')
            print(f'  {mname:10s} ({r["vertices"]:,} vertices) {cname:30s} {rates}{ratio}  peak RSS {r["peak_rss_mb"]:.0f} MB')
    print()
    print(scaling_table(rows, threads, cpu))
    return rows


def scaling_table(rows, threads, cpu):
    """The scaling rows as a markdown table (docs/convergence.md shows it)."""
    head = '| model | run | ' + ' | '.join(f'{n} thread{"s" if n > 1 else ""} [steps/s]' for n in threads) + \
        (f' | {threads[-1]} vs {threads[0]} |' if len(threads) > 1 else ' |') + ' peak RSS [MB] |'
    lines = [f'{cpu}; steps per wall second', '', head, '|' + '---|' * (3 + len(threads) + (len(threads) > 1))]
    for r in rows:
        if 'error' in r:
            lines.append(f'| {r["model_name"]} | {r["config"]} | ' + ' | '.join('failed' for _ in threads) + ' |')
            continue
        vals = [r['rates'][str(n)] for n in threads]
        ratio = (f' | {vals[-1] / vals[0]:.2f}x' if all(isinstance(v, float) for v in (vals[0], vals[-1])) else ' | –') \
            if len(threads) > 1 else ''
        lines.append(f'| {r["model_name"]} ({r["vertices"]:,} vertices) | {r["config"]} | '
                     + ' | '.join(f'{v:,.0f}' if isinstance(v, float) else str(v) for v in vals) + ratio
                     + f' | {r["peak_rss_mb"]:.0f} |')
    return '\n'.join(lines)


def scaling_child(spec):
    """One (model, configuration): steps per wall (and CPU) second for each thread count, alternating; the state
    starts afresh every 100 steps (untimed: a fine model that diverges later is still timed, every count times the
    same first 100 ms of the contraction)."""
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if 'refine' in spec:
        from tissue_sim.core.builder import default_model
        tm = default_model(refine=spec['refine'])
    else:
        tm = load_model(spec.get('model'))[0]
    make = solver.Params.physical if spec['preset'] == 'physical' else solver.Params.paper
    ham = [m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]
    sims = {n: solver.compile_model(tm, make(threads=n, **spec['kw'])) for n in spec['threads']}
    sim0 = sims[spec['threads'][0]]
    chunk = 100 if spec['preset'] == 'paper' else 20
    cap = 100
    best, best_cpu = {n: 0.0 for n in sims}, {n: 0.0 for n in sims}
    diverged = {}
    from tissue_sim.core.solver.step import _run
    for _ in range(3):
        for n, sim in sims.items():
            ctrl = solver.make_control(sim)
            ctrl.activation[ham] = 1.0
            acts = np.tile(ctrl.activation, (chunk, 1))
            steps, wall, cpu = 0, 0.0, 0.0
            end = time.perf_counter() + spec['seconds'] / 3
            try:
                while time.perf_counter() < end:
                    st = solver.make_state(sim)
                    _run(sim, st, acts[:1], sim.params.dt)          # warm (compiled, caches)
                    while st.step - 1 + chunk <= cap and time.perf_counter() < end:
                        t0, c0 = time.perf_counter(), time.process_time()
                        _run(sim, st, acts, sim.params.dt)
                        wall += time.perf_counter() - t0
                        cpu += time.process_time() - c0
                        steps += chunk
            except solver.DivergenceError as e:
                diverged[n] = str(e)
            if steps and n not in diverged:
                best[n] = max(best[n], steps / wall)
                best_cpu[n] = max(best_cpu[n], steps / max(cpu, 1e-9))
    rates = {str(n): (round(best[n], 1) if best[n] > 0 else f'diverged: {diverged.get(n)}') for n in sims}
    print(json.dumps({'vertices': int(tm.n_vertices), 'cells': int(tm.n_cells), 'substeps': int(sim0.n_substeps),
                      'rates': rates, 'cpu_rates': {str(n): round(best_cpu[n], 1) for n in sims},
                      'diverged': diverged, 'peak_rss_mb': round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                      'rss_after_import_mb': round(rss0, 1), 'load_average': round(os.getloadavg()[0], 2)}))


def ab_rates(tm, rounds, seconds):
    """--ab N: the physical set under mass_scaled (4 sub-steps) with the affine volume measure, the one the implicit
    integrator holds (the ratio's reference: the same physics), and with the set's enclosed measure, and under implicit
    (1 sub-step; all with the set's hamstring sheath, the implicit one with its correction solve; the set's BDF2 and
    backward Euler), and implicit without the sheath (what the correction costs), full hamstring activation, 100-step chunks, one thread: N rounds, each configuration one window of
    `seconds` in turn (steps per CPU second, best of rate()'s 3 sub-windows), so load changes hit all of them alike.
    Prints each round, the median rates and ratio, and the load average."""
    from tissue_sim.core.solver.step import _run
    confs = (('mass_scaled', dict(volume_measure='affine')), ('mass_scaled, enclosed', {}),
             ('implicit', dict(integrator='implicit', substeps=1)),
             ('implicit, backward Euler', dict(integrator='implicit', substeps=1, implicit_scheme='euler')),
             ('implicit, no sheath', dict(integrator='implicit', substeps=1, sheath_group='', sheath_below='')))
    runs = []
    for name, kw in confs:
        sim = solver.compile_model(tm, solver.Params.physical(threads=1, **kw))
        st, ctrl = solver.make_state(sim), solver.make_control(sim)
        ctrl.activation[[m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]] = 1.0
        acts = np.tile(ctrl.activation, (100, 1))
        runs.append((name, lambda sim=sim, st=st, acts=acts: _run(sim, st, acts, sim.params.dt)))
    rates = {name: [] for name, _ in confs}
    load = [os.getloadavg()[0]]
    for r in range(rounds):
        for name, fn in runs:
            rates[name].append(100 * rate(fn, seconds))
        load.append(os.getloadavg()[0])
        print(f'round {r + 1}: ' + ', '.join(f'{n} {v[-1]:,.0f}' for n, v in rates.items())
              + f' steps/s; implicit/mass_scaled {rates["implicit"][-1] / rates["mass_scaled"][-1]:.2f}; '
              f'load average {load[-1]:.2f}', flush=True)
    med = {n: float(np.median(v)) for n, v in rates.items()}
    ratios = [a / b for a, b in zip(rates['implicit'], rates['mass_scaled'])]
    print('median: ' + ', '.join(f'{n} {v:,.0f}' for n, v in med.items()) + f' steps/s; implicit/mass_scaled: median of '
          f'the rounds\' ratios {np.median(ratios):.2f} (range {min(ratios):.2f}-{max(ratios):.2f}); the sheath '
          f'correction costs {100 * (1 - med["implicit"] / med["implicit, no sheath"]):.1f} % of the implicit step; '
          f'load average {min(load):.2f}-{max(load):.2f}')
    return {'rates': {n: [round(x) for x in v] for n, v in rates.items()}, 'median': {n: round(v) for n, v in med.items()},
            'ratio_median': round(float(np.median(ratios)), 2), 'load_average': [round(x, 2) for x in load]}


def stage_times(tm, iterations, reps=None):
    """--stages I: where the implicit step's time goes (physical set, `integrator: implicit`, I iterations, one
    thread): each stage's kernel called on its own on the state after 200 steps of a full hamstring contraction,
    microseconds per call (CPU time, best of 3 windows; n calls inside one compiled call), beside the whole step (step() in 10-step calls). A step makes
    BDF2's start with its prediction (the physical set's formula; backward Euler: the prediction), I cell passes, one skeleton step, one integration (its bones' poses, the first solve, the
    velocities), I - 1 further solves, the sheath correction, the point via correction and the contact stage."""
    from tissue_sim.core.solver import contact as CT, implicit as IM, skeleton as SK
    from tissue_sim.core.solver.step import _cell_pass
    sim = solver.compile_model(tm, solver.Params.physical(integrator='implicit', substeps=1, threads=1,
                                                          implicit_iterations=iterations))
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.activation[[m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]] = 1.0
    solver.step(sim, st, ctrl, n_steps=200)
    h = sim.params.dt
    cells, tissue, sk, num, scratch, (cg, cw) = st.workspace.arrays(h)
    imp = st.workspace.implicit(h)
    x, v, f = st.x.copy(), st.v.copy(), st.f.copy()
    xn, vn = x.copy(), v.copy()
    lam, act = st.lam.copy(), np.full(sim.n_muscles, 0.5)
    R, t = st.seg_R.copy(), st.seg_t.copy()
    no_lock = np.zeros(sim.n_joints, np.bool_)
    wr = np.zeros((sim.n_segments, 6))

    from numba import njit
    from tissue_sim.core.solver import cells as CK, integration as IK, muscle as MU
    from tissue_sim.core.solver.step import after_cells, muscle_tension
    a_st, mlen, mvel = st.activation.copy(), st.muscle_length.copy(), st.muscle_velocity.copy()
    q, qd, q_target = st.q.copy(), st.qd.copy(), st.q.copy()
    xp, vp, hh = st.x_prev.copy(), st.v_prev.copy(), st.history_h.copy()
    lock_torque = np.zeros(sim.n_joints)

    # Each stage's kernels called n times inside one compiled call (called from Python, each call would unbox the
    # named tuples again: ~18 us for the Implicit tuple alone), on copies where the step would change the state.
    @njit
    def muscles_n(n, act, a_st, h, lam, q, mvel, tissue, num, scratch):
        for _ in range(n):
            MU.advance_activation(act, a_st, h, num.tau_act, num.tau_deact)
            CK.update_contraction(lam, a_st, num.log_c, num.log_r, num.lam_min, h / num.h_ref)
            muscle_tension(q, a_st, mvel, tissue, num, scratch)

    @njit
    def after_cells_n(n, x, f, h, lam, mlen, mvel, tissue, num, scratch):
        for _ in range(n):
            after_cells(x, f, h, lam, mlen, mvel, tissue, num, scratch, True)

    @njit
    def vias_n(n, h, x, f, xn, vn, tissue, seg_R, seg_t, wr):
        for _ in range(n):
            if tissue.via_seg.shape[0] > 0:
                IK.via_forces(f, tissue.via_off, tissue.via_idx, tissue.via_seg, tissue.via_local, seg_R, seg_t,
                              tissue.inv_den, wr)
                xn[:] = x
                IK.hold_via_points(h, xn, vn, tissue.via_off, tissue.via_idx, tissue.via_seg, tissue.via_local,
                                   seg_R, seg_t, tissue.inv_den)

    @njit
    def history_n(n, h, x, v, xn, vn, xp, vp, hh, cw):
        for _ in range(n):
            IM.bdf2_history(h, xn, vn, x, v, hh, cw.moved, cw.n_moved)

    @njit
    def start_n(n, h, x, v, xp, vp, hh, imp):
        for _ in range(n):
            IM.bdf2_start(h, x, v, xp, vp, hh, imp.xh, imp.vh, imp.y, imp.yc, imp.yg, imp.hs)

    @njit
    def predict_n(n, x, v, imp):
        for _ in range(n):
            IM.predict(x, v, imp.y, imp.yc, imp.yg, imp.hs)

    @njit
    def cells_n(n, x, v, f, cells, lam, act, num, work):
        for _ in range(n):
            _cell_pass(x, v, f, cells, lam, act, num.vol_actual, num.iters, num.vol_gain, work)

    @njit
    def skeleton_n(n, h, q, qd, f, x, sk, tissue, num, R, t, scratch, lock, target, lock_torque, wr):
        for _ in range(n):
            q1, qd1 = q.copy(), qd.copy()
            SK.skeleton_step(h, q1, qd1, f, x, sk, tissue.att_idx, tissue.att_seg, num.jdamp, num.lim_wh, num.lim_z,
                             R, t, scratch.skel_work, lock, target, lock_torque, scratch.tau_pe, wr)

    @njit
    def pose_n(n, h, x, xn, vn, tissue, seg_R, seg_t):
        for _ in range(n):
            IK.pose_attached(h, x, xn, vn, tissue.att_idx, tissue.att_seg, tissue.rest, seg_R, seg_t, 1e9)

    @njit
    def solve_n(n, h, x, imp, f, xn, vn):
        for _ in range(n):
            IM._solve(imp, f, xn, imp.y, False, x, vn, 1.0 / h, 1e9)

    @njit
    def sheath_n(n, h, x, xn, vn, imp, seg_R, seg_t, cg, wr):
        for _ in range(n):
            xn[:] = x
            IM.sheath_correct(h, x, xn, vn, imp, seg_R, seg_t, cg, 1e9, wr)

    @njit
    def via_n(n, h, x, xn, vn, imp, via_off, via_idx, via_seg, via_local, seg_R, seg_t):
        for _ in range(n):
            xn[:] = x
            IM.via_correct(h, x, xn, vn, imp, via_off, via_idx, via_seg, via_local, seg_R, seg_t, 1e9)

    @njit
    def contact_n(n, h, x, v, xn, vn, q, sk, seg_R, seg_t, cg, cw, inv_den, wr):
        for _ in range(n):
            xn[:] = x; vn[:] = v
            SK.forward_kinematics(q, sk, cw.R0, cw.t0)
            CT.unmark(cw)
            CT.fold_contact(h, xn, vn, seg_R, seg_t, cg, cw, inv_den, wr)
            CT.wrap_contact(h, xn, vn, seg_R, seg_t, cg, cw, inv_den, wr)
            CT.bone_contact(h, xn, vn, seg_R, seg_t, cg, cw, inv_den, wr)

    @njit
    def copies_n(n, x, v, xn, vn, both):
        for _ in range(n):
            xn[:] = x
            if both:
                vn[:] = v

    stages = [
        ('muscle stages (activation, force-length, tension)',
         lambda n: muscles_n(n, act, a_st, h, lam, st.q, mvel, tissue, num, scratch)),
        ('after the cells (enclosed volume, end rings, velocity)',
         lambda n: after_cells_n(n, x, f, h, lam, mlen, mvel, tissue, num, scratch)),
        ('point via forces and centroids (stages 2, 3b)', lambda n: vias_n(n, h, x, f, xn, vn, tissue, R, t, wr)),
        ('BDF2 history (moved vertices)', lambda n: history_n(n, h, x, v, xn, vn, xp, vp, hh, cw)),
        ('BDF2 start (4 x - x_prev)/3, (4 v - v_prev)/3 and y', lambda n: start_n(n, h, x, v, xp, vp, hh, imp)),
        ('prediction y = x + h v (backward Euler)', lambda n: predict_n(n, x, v, imp)),
        ('cell pass (rotations/polar, forces)', lambda n: cells_n(n, x, v, f, cells, lam, act, num, scratch.cell_work)),
        ('skeleton step', lambda n: skeleton_n(n, h, q, qd, f, x, sk, tissue, num, R, t, scratch, no_lock, q_target,
                                               lock_torque, st.contact_wrench)),
        ('bone-attached vertices posed', lambda n: pose_n(n, h, x, xn, vn, tissue, st.seg_R, st.seg_t)),
        ('solve: rhs + G, G^T, velocities (one)', lambda n: solve_n(n, h, x, imp, f, xn, vn)),
        ('sheath correction (offsets, region solve, velocities)',
         lambda n: sheath_n(n, h, x, xn, vn, imp, st.seg_R, st.seg_t, cg, wr)),
        ('point via correction (centroids, A^-1 C^T, velocities)',
         lambda n: via_n(n, h, x, xn, vn, imp, sim.via_off, sim.via_idx, sim.via_seg, sim.via_local, st.seg_R, st.seg_t)),
        ('fold + bone contact (stage 4)',
         lambda n: contact_n(n, h, x, v, xn, vn, st.q, sk, st.seg_R, st.seg_t, cg, cw, tissue.inv_den, wr)),
    ]
    res = {}
    print(f'implicit step, {iterations} iteration(s), {sim.n_vertices} vertices, {sim.n_cells} cells; factor '
          f'{imp.n_lnz:,} entries, sheath region factor {imp.s_Lx.size + imp.s_ginv.size:,}; microseconds per call '
          '(the harness\'s copies that restore the state between calls subtracted):')
    n = reps or max(5, int(2e5 / sim.n_vertices))
    copy = [1e6 / rate(lambda: copies_n(n, x, v, xn, vn, both), 1.0) / n for both in (False, True)]
    restored = {'point via forces and centroids (stages 2, 3b)': copy[0],
                'sheath correction (offsets, region solve, velocities)': copy[0],
                'point via correction (centroids, A^-1 C^T, velocities)': copy[0], 'fold + bone contact (stage 4)': copy[1]}
    for name, fn in stages:
        res[name] = max(0.0, 1e6 / rate(lambda: fn(n), 1.0) / n - restored.get(name, 0.0))
        print(f'  {name:55s} {res[name]:9.1f}', flush=True)
    whole = 1e6 / (10 * rate(lambda: solver.step(sim, st, ctrl, n_steps=10), 3.0))
    res['whole step'] = whole
    parts = (res['muscle stages (activation, force-length, tension)']
             + iterations * res['after the cells (enclosed volume, end rings, velocity)']
             + res['point via forces and centroids (stages 2, 3b)']
             + (res['BDF2 history (moved vertices)'] + res['BDF2 start (4 x - x_prev)/3, (4 v - v_prev)/3 and y']
                if imp.bdf2 else res['prediction y = x + h v (backward Euler)'])
             + iterations * res['cell pass (rotations/polar, forces)']
             + res['skeleton step'] + res['bone-attached vertices posed']
             + iterations * res['solve: rhs + G, G^T, velocities (one)']
             + res['sheath correction (offsets, region solve, velocities)']
             + res['point via correction (centroids, A^-1 C^T, velocities)'] + res['fold + bone contact (stage 4)'])
    print(f'  {"sum of the parts (x iterations where repeated)":55s} {parts:9.1f}')
    print(f'  {"whole step (step(), 10 per call)":55s} {whole:9.1f}   ({1e6 / whole:,.0f} steps/s; load average '
          f'{os.getloadavg()[0]:.2f})')
    return {k: round(v, 1) for k, v in res.items()}


def _caches() -> str:
    """The processor's L2 and L3 sizes as lscpu reports them (the working set's yardstick), or ''."""
    import subprocess
    try:
        text = subprocess.run(['lscpu'], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return ''
    return '; '.join(' '.join(line.split()) for line in text.splitlines() if line.strip().startswith(('L2', 'L3')))


def working_set(st, h) -> tuple[int, int]:
    """(bytes, of them the contact grids' values) of the arrays the step reads and writes: the Workspace's named
    tuples at h (cells, tissue, skeleton, numbers, scratch, contact), the implicit integrator's, and the State's
    vertex arrays. The grids' values (contact.ContactGrids.g_phi) are sampled only where vertices come near a bone."""
    def size(o):
        if isinstance(o, np.ndarray):
            return o.nbytes
        return sum(size(e) for e in o) if isinstance(o, tuple) else 0
    ws = st.workspace
    state = sum(a.nbytes for a in (st.x, st.v, st.x_back, st.v_back, st.x_prev, st.v_prev, st.f) if a is not None)
    cgrid, _ = ws.arrays(h)[5]
    grids = cgrid.g_phi.nbytes
    return size(tuple(ws.arrays(h))) + size(tuple(ws.implicit(h))) + state, grids


def size_scaling(refinements, seconds):
    """--sizes: per refinement R of the bundled limb, the physical set with the implicit integrator (one sub-step,
    one thread), 10-step calls after 100 steps of a full hamstring contraction: steps per CPU second, µs per step,
    ns per vertex, and the working set (working_set). Where the cost per vertex jumps, the working set has outgrown
    the last-level cache and the step waits on memory."""
    from tissue_sim.core.builder import default_model
    rows = []
    print('refine | vertices | cells | steps/s | us/step | ns/vertex | working set [MB] (of it contact grids)')
    for R in refinements:
        tm = default_model(refine=R)
        sim = solver.compile_model(tm, solver.Params.physical(integrator='implicit', substeps=1, threads=1))
        st, ctrl = solver.make_state(sim), solver.make_control(sim)
        ctrl.activation[[m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]] = 1.0
        solver.step(sim, st, ctrl, n_steps=100)
        r = 10 * rate(lambda: solver.step(sim, st, ctrl, n_steps=10), seconds)
        total, grids = working_set(st, sim.params.dt)
        row = {'refine': R, 'vertices': sim.n_vertices, 'cells': sim.n_cells, 'steps_per_s': round(r, 1),
               'us_per_step': round(1e6 / r, 1), 'ns_per_vertex': round(1e9 / r / sim.n_vertices, 1),
               'working_set_mb': round(total / 1e6, 1), 'contact_grids_mb': round(grids / 1e6, 1)}
        rows.append(row)
        print(f'{R:6g} | {row["vertices"]:8,} | {row["cells"]:5,} | {row["steps_per_s"]:7,.0f} | {row["us_per_step"]:7,.0f} | '
              f'{row["ns_per_vertex"]:9.1f} | {row["working_set_mb"]:.1f} ({row["contact_grids_mb"]:.1f})', flush=True)
    return rows


def sustained_rates(refinements, threads, windows=10, window=100):
    """--sustained: per refinement R of the bundled limb and thread count n, the physical set with the implicit
    integrator (one sub-step) from rest with the hamstrings fully active: 50 steps, then `windows` windows of `window`
    steps (with the defaults the contraction's 0.05-1.05 s, the knee flexing to its stop), each timed on the wall clock.
    Real time: the median window's steps per second times dt >= 1. Prints a markdown table; returns the rows."""
    from tissue_sim.core.builder import default_model
    from tissue_sim.core.validation import KNEE_JOINT
    rows = []
    for R in refinements:
        tm = default_model(refine=R) if R != 1 else default_model()
        ham = [m for m, g in enumerate(tm.muscle_groups) if g == 'hamstrings'] or [0]
        for n in threads:
            sim = solver.compile_model(tm, solver.Params.physical(integrator='implicit', substeps=1, threads=n))
            st, ctrl = solver.make_state(sim), solver.make_control(sim)
            ctrl.activation[ham] = 1.0
            solver.step(sim, st, ctrl, n_steps=50)          # (compiled; the contraction under way)
            r = []
            for _ in range(windows):
                t0 = time.perf_counter()
                solver.step(sim, st, ctrl, n_steps=window)
                r.append(window / (time.perf_counter() - t0))
            med = float(np.median(r))
            rows.append({'refine': R, 'vertices': sim.n_vertices, 'cells': sim.n_cells, 'threads': n,
                         'median': round(med, 1), 'slowest': round(min(r), 1), 'fastest': round(max(r), 1),
                         'real_time': bool(med * sim.params.dt >= 1.0), 'knee_deg': round(float(np.degrees(
                             st.q[list(tm.joint_names).index(KNEE_JOINT)])), 1)})
            print(f'  refine {R:g} ({sim.n_vertices:,} vertices), {n} thread(s): median {med:,.0f}, slowest {min(r):,.0f}, '
                  f'fastest {max(r):,.0f} steps/s; knee at {rows[-1]["knee_deg"]:.0f} deg', flush=True)
    print()
    print('| refine | vertices | cells | threads | median [steps/s] | slowest | fastest | real time |')
    print('|---|---|---|---|---|---|---|---|')
    for w in rows:
        print(f'| {w["refine"]:g} | {w["vertices"]:,} | {w["cells"]:,} | {w["threads"]} | {w["median"]:,.0f} | '
              f'{w["slowest"]:,.0f} | {w["fastest"]:,.0f} | {"yes" if w["real_time"] else "no"} |')
    return rows


def implicit_factor(sim):
    """The implicit integrator's factor at params.dt: unknowns (free vertices + cells), entries, bytes, build time."""
    from tissue_sim.core.solver import implicit as IM
    t0 = time.perf_counter()
    imp = IM.make(sim, sim.params.dt)
    return {'unknowns': int(imp.z.shape[0]), 'entries': int(imp.n_lnz), 'bytes': int(imp.Lx.nbytes + imp.Lj.nbytes +
            imp.Lp.nbytes + imp.ginv.nbytes), 'build_s': round(time.perf_counter() - t0, 3),
            'sheath_entries': int(imp.s_Lx.size + imp.s_ginv.size)}     # the sheath correction's factor (0: none)


def fine_model(path, solver_rate):
    """A finer model: the physical set with mass_scaled (4 sub-steps) and implicit (1 and 2 iterations)."""
    import resource
    from tissue_sim.core.model import TissueModel
    tm = TissueModel.load(path)
    res = {'model': str(path), 'vertices': tm.n_vertices, 'cells': tm.n_cells}
    print(f'fine model {path}: {tm.n_vertices} vertices, {tm.n_cells} cells')
    for name, kw in (('mass_scaled', {}), ('implicit', dict(integrator='implicit', substeps=1)),
                     ('implicit x2', dict(integrator='implicit', substeps=1, implicit_iterations=2))):
        try:
            sim, r = solver_rate(solver.Params.physical(**kw), 20, tm)
            res[name] = round(r, 1)
            extra = ''
            if kw:
                res['implicit_factor'] = implicit_factor(sim)
                extra = f'; factor {res["implicit_factor"]["entries"]:,} entries, {res["implicit_factor"]["bytes"] / 1e6:.1f} MB'
            print(f'fine model, physical params, {name:12s}: {r:9.1f} steps/s ({sim.n_substeps} sub-step(s){extra})')
        except solver.DivergenceError as e:
            res[name] = f'diverged: {e}'
            print(f'fine model, physical params, {name:12s}: {e}')
    res['peak_rss_mb'] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(f'peak resident memory of this process: {res["peak_rss_mb"]} MB')
    return res


def markdown_table(out: dict) -> str:
    """The figures as the markdown table of docs/solver.md (steps per CPU second, one thread)."""
    rt = out['real_time_factor']
    rows = [('paper set, `simulate()` (100-step chunks)', f'{out["steps_per_s_chunked"]:,}',
             f'{out["passes_per_step"]} pass(es) per step; real-time factor {rt}'),
            ('paper set, `step()` per call', f'{out["steps_per_s"]:,}', ''),
            ('paper set, `integrator: explicit`', f'{out["steps_per_s_explicit"]:,}', f'{out["explicit_substeps"]} sub-steps, true masses'),
            ('physical set (`make demo`)', f'{out["physical_steps_per_s"]:,}',
             f'{out["physical_substeps"]} sub-steps; real-time factor {out["physical_real_time_factor"]}'),
            ('physical set, `volume_measure: affine`', f'{out["physical_affine_steps_per_s"]:,}',
             'the implicit integrator\'s volume measure'),
            ('physical set without the fat volume term', f'{out["physical_no_fat_volume_steps_per_s"]:,}',
             '`volume_stiffness_fat: 0` (the paper set has none)'),
            ('physical set, `integrator: implicit`', f'{out["physical_implicit_steps_per_s"]:,}',
             f'1 sub-step, one solve ({out["implicit_factor"]["entries"]:,} factor entries); {out["implicit_speedup"]}x the '
             f'affine row, {out["implicit_speedup_vs_enclosed"]}x the `make demo` row'),
            ('physical set, implicit, 2 iterations', f'{out["physical_implicit2_steps_per_s"]:,}', ''),
            ('plain numpy `reference_step`, paper set', f'{out["numpy_steps_per_s"]:,}',
             f'`step()` is {out["speedup_vs_numpy"]}x faster; positions agree to {out["numpy_agreement_m"]:.0e} m after 20 steps')]
    if out.get('pypbd_steps_per_s'):
        rows.append(('pypbd shape matching, same cells, 1 iteration', f'{out["pypbd_steps_per_s"]:,}',
                     f'the chunked paper set is {out["speedup_vs_pypbd"]}x faster'))
    head = (f'{out["vertices"]:,} vertices, {out["cells"]} cells; {out["cpu_model"]} (`{out["llvm_cpu"]}`, '
            f'{out["lanes_per_block"]} lanes per block); load average {out["cpu_load_1min"]}')
    fine = out.get('fine')
    if fine:
        for name in ('mass_scaled', 'implicit', 'implicit x2'):
            r = fine.get(name)
            rows.append((f'finer model ({fine["vertices"]:,} vertices), physical set, {name}',
                         f'{r:,}' if isinstance(r, float) else 'diverged', '' if isinstance(r, float) else r))
    lines = [head, '', '| run | steps/s | |', '|---|---|---|'] + [f'| {a} | {b} | {c} |' for a, b, c in rows]
    return '\n'.join(lines)


if __name__ == '__main__':
    main()
