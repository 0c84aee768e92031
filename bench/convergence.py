#!/usr/bin/env python3
"""Mesh convergence of the knee motion: an experiment of the physical set (--motion step: the hamstrings fully active
from t = 0; demo: make demo's, the hamstrings ramped 0 -> 1 over 8 s) on the bundled limb built 1x, 3x and 6x finer
(`build-model --refine R`), one integrator.

    . ./env.sh && python bench/convergence.py [--refine 1,3,6] [--motion step|demo] [--integrator NAME]
                                              [--substeps unscaled|set|matched|N] [--duration S] [--out DIR] [--quick]
                                              [--set NAME=VALUE ...] [--isometric] [--build NAME=VALUE ...] [--torques]
                                              [--time-reference N]

For each refinement: vertices, cells, sub-steps per 1-ms step, steps per CPU second (one thread, the
stepping alone), the knee angle every 10 ms (or the step where the run diverged), the cells inside out at the end
(V/V0 < 0; a finer limb's defects show there). Then the knee-angle differences between successive refinements (max
and RMS over the run, degrees): a converging scheme shows them shrinking (the flag: both, pair after pair). Writes DIR/convergence.json and DIR/convergence.png (knee angle vs time per
refinement); default DIR bench/out/. Last line: one JSON object.

--integrator: default 'implicit' where core/solver has it (issue 23), else the physical set's own
'mass_scaled'. --substeps: 'unscaled' (default with mass_scaled) = the fewest sub-steps at which the
mass scaling adds less than 0.1 % of the tissue's mass, i.e. the present scheme converged in time (on
the default model it agrees with 'explicit' to 0.05 deg); 'set' = the parameter set's own (physical: 4;
with explicit: automatic); 'matched' = the set's own x omega_max(R) / omega_max(1); an integer N = N for
every model. The mass scaling adds mass where a vertex's cells are too stiff for the sub-step
(h^2 kappa / limit^2): at the physical set's 4 sub-steps that is +207 % of the free tissue's mass on the
default model and grows with refinement (cells stiffer and lighter): +2,285 % at 3x, +9,024 % at 6x;
each run reports its added mass. --quick: 1x and 2x, 0.3 s (for `make bench`). --set NAME=VALUE (repeatable): a Params
field of the physical set changed (what a term costs: the same table with and without it). --isometric: the knee held
at 0 deg by the joint lock; the series compared is the hamstrings' knee torque [N m] instead of the angle. --build
NAME=VALUE (repeatable): a builder setting of the models (e.g. point_vias=false). --torques: the knee torque of each
source the skeleton step takes (torque_sources), printed every 30 ms (--motion demo: 250 ms) and in the JSON: where a
lag comes from.
--time-reference N: each model also run at N sub-steps per step, and the table gives each model's difference to that
run (max / RMS): the time step's share of the differences, apart from the mesh's (docs/convergence.md).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

for _v in ('NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_v, '1')
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))

import numpy as np  # noqa: E402

from tissue_sim.core import solver  # noqa: E402
from tissue_sim.core.solver import params as P  # noqa: E402

SAMPLE_EVERY = 10          # steps between knee samples (10 ms at the physical set's 1-ms step)
SERIES = {False: ('knee_deg', 'deg'), True: ('knee_torque_Nm', 'N m')}   # what a run records (--isometric: True)
# The experiments (--motion): the hamstrings' activation timeline (core.activation's knots: linear between, the last
# held), every other muscle passive, and the simulated time a run covers by default.
MOTIONS = {
    'step': ({'hamstrings': [(0.0, 1.0)]}, 0.3,
             'physical set, hamstrings fully active from t = 0 (tissue-sim simulate --params physical --activate '
             'hamstrings=1)'),
    'demo': ({'hamstrings': [(0.0, 0.0), (8.0, 1.0)]}, 10.0,
             "physical set, hamstrings ramped 0 -> 1 over 8 s (make demo's default activation: the activation node's "
             '--profile ramp --rise 8 --others 0)'),
}
LOW_VOLUME = 0.2           # cells below this share of their rest volume are counted at the end (cell_health)
UNSCALED_TOL = 1e-3        # --substeps unscaled: mass_scaled adds less than this share of the true mass


def default_integrator() -> str:
    return 'implicit' if 'implicit' in P.INTEGRATORS else 'mass_scaled'


def added_mass_share(sim, n_sub) -> float:
    """Mass the mass_scaled integrator adds at n_sub sub-steps per step, as a share of the free vertices' true
    mass (SimModel.inv_denominator); 0 for the other integrators."""
    if sim.params.integrator != 'mass_scaled':
        return 0.0
    free = np.asarray(sim.inv_mass) > 0
    den = 1.0 / np.asarray(sim.inv_denominator(sim.params.dt / n_sub))[free]
    return float(den.sum() / np.asarray(sim.mass)[free].sum() - 1.0)


def unscaled_substeps(sim, tol=UNSCALED_TOL) -> int:
    """The fewest sub-steps at which mass_scaled adds less than ``tol`` of the true mass (the scheme then
    integrates the true masses: the time-converged reference of the present scheme)."""
    n = max(1, int(sim.omega_max * sim.params.dt / sim.params.stability_limit))
    while added_mass_share(sim, n) >= tol:
        n += 1
    return n


def cell_moments(tm):
    """(volume (C,) [m^3], J (C,) [m^2]: sum over a cell's vertices of |X_i - centroid|^2) at rest."""
    from tissue_sim.core.builder.quality import cell_volumes
    off, cv = np.asarray(tm.cell_offsets, np.int64), np.asarray(tm.cell_vertices, np.int64)
    X = np.asarray(tm.rest_positions, np.float64)
    sizes = np.diff(off)
    J = np.zeros(len(sizes))
    for n in np.unique(sizes):
        cells = np.flatnonzero(sizes == n)
        P = X[cv[off[cells][:, None] + np.arange(n)[None, :]]]
        J[cells] = ((P - P.mean(axis=1, keepdims=True)) ** 2).sum(axis=(1, 2))
    return np.abs(cell_volumes(tm)), J


def moment_ratio(tm, params):
    """Per tissue (muscle, fat): sum over cells of k J / sum of E V, for the 'modulus' stiffness of
    core/solver/model.py (k = E cbrt(V) 4 / n x cell_k_scale): the shape-matching energy of a uniform strain
    over the continuum's (1/2 E eps^2 V, up to a constant). A mesh-independent stiffness keeps it constant."""
    V, J = cell_moments(tm)
    n = np.diff(np.asarray(tm.cell_offsets))
    mus = np.asarray(tm.cell_tissue) == 1
    E = np.where(mus, params.youngs_muscle, params.youngs_fat)
    k = E * np.cbrt(V) * 4.0 / n * np.asarray(tm.cell_k_scale)
    return {t: float((k * J)[sel].sum() / (E * V)[sel].sum()) for t, sel in (('muscle', mus), ('fat', ~mus))}


def with_moment_stiffness(tm, params, c):
    """The model with cell_k_scale set so that every cell's k J = c[tissue] E V (the experiment of
    --stiffness moment: the same stiffness per volume on every mesh; c from the default model)."""
    import dataclasses as dc
    V, J = cell_moments(tm)
    n = np.diff(np.asarray(tm.cell_offsets))
    mus = np.asarray(tm.cell_tissue) == 1
    want = np.where(mus, c['muscle'], c['fat']) * V / J            # k / E wanted
    return dc.replace(tm, cell_k_scale=want / (np.cbrt(V) * 4.0 / n))


def run_one(tm, params, duration, label, isometric=False, torques=False, motion='step'):
    """Knee angle [deg] every SAMPLE_EVERY steps of the experiment `motion` (MOTIONS; isometric: the knee held at 0 deg
    by the joint lock, the knee torque [N m, flexing +] the hamstrings produce), steps per CPU second, divergence. torques:
    also, per sample, the knee torque of each source the skeleton step takes (torque_sources; its cost is in the
    CPU time then)."""
    sim = solver.compile_model(tm, params)
    knee = list(tm.joint_names).index('knee') if 'knee' in tm.joint_names else 0
    ham = MOTIONS[motion][0]
    warm = solver.make_state(sim)
    solver.step(sim, warm, solver.make_control(sim))          # numba compile / caches outside the timing
    t, q, diverged, src = [], [], None, []
    n = int(round(duration / params.dt))
    st = None
    c0, w0 = time.process_time(), time.perf_counter()
    last = w0
    try:
        if isometric:
            st, ctl = solver.make_state(sim), solver.make_control(sim)
            ctl.activation[solver.muscle_indices(sim, 'hamstrings')] = 1.0
            ctl.joint_lock[knee], ctl.joint_target[knee] = True, 0.0
            t.append(0.0), q.append(0.0)
            for k in range(n // SAMPLE_EVERY):
                solver.step(sim, st, ctl, n_steps=SAMPLE_EVERY)
                t.append(round((k + 1) * SAMPLE_EVERY * params.dt, 6))
                q.append(-float(st.joint_lock_torque[knee]))        # the lock's torque holds the knee: minus it flexes
        else:
            for tt, st in solver.simulate(sim, duration, ham, every=SAMPLE_EVERY, output='state'):   # (observe() costs
                t.append(round(float(tt), 6))                                                   # ~4 ms: not timed)
                q.append(float(np.degrees(st.q[knee])))
                if torques:
                    src.append(torque_sources(sim, st, knee))
                if time.perf_counter() - last > 60:
                    last = time.perf_counter()
                    print(f'  {label}: t {tt:.2f} s, knee {q[-1]:.1f} deg, {time.process_time() - c0:.0f} CPU s', flush=True)
    except solver.DivergenceError as e:
        diverged = {'step': e.step, 'time_s': round(e.step * params.dt, 4), 'cause': e.cause}
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    mesh = cell_health(sim, st) if st is not None and diverged is None else None
    done = (len(t) - 1) * SAMPLE_EVERY if diverged is None else diverged['step']
    out = dict(label=label, vertices=int(tm.n_vertices), cells=int(tm.n_cells), integrator=params.integrator,
               substeps=int(sim.n_substeps), added_mass_percent=round(100 * added_mass_share(sim, sim.n_substeps), 3), omega_max_dt=round(float(sim.omega_max * params.dt), 2),
               steps=int(done), steps_requested=n, cpu_s=round(cpu, 2), wall_s=round(wall, 2),
               steps_per_cpu_s=round(done / max(cpu, 1e-9), 1), t=t, series=SERIES[isometric][0],
               diverged=diverged, cells_at_end=mesh)
    out[out['series']] = [round(v, 4) for v in q]
    if torques:
        out['torque_sources_Nm'] = {k: [round(d[k], 3) for d in src] for k in TORQUE_SOURCES}
    fin = f'{q[-1]:.1f} {SERIES[isometric][1]} at {t[-1]:.2f} s' if q else '-'
    print(f'{label}: {out["vertices"]:,} vertices, {out["cells"]:,} cells, {params.integrator} x{out["substeps"]} '
          f'(omega_max dT {out["omega_max_dt"]}, added mass {out["added_mass_percent"]} %): '
          f'{out["steps_per_cpu_s"]:.1f} steps/CPU s, knee {fin}'
          + (f'; cells at the end: {mesh["inverted"]} inverted '
             f'({", ".join(f"{k} {v}" for k, v in mesh["inverted_by_segment"].items()) or "none"}), '
             f'{mesh["below_low"]} below {LOW_VOLUME:g} V0 (least V/V0 {mesh["least_volume_ratio"]:.2f})' if mesh else '')
          + (f'; DIVERGED at step {diverged["step"]} ({diverged["cause"]})' if diverged else ''), flush=True)
    return out, sim


def cell_health(sim, st) -> dict:
    """The cells' state at the end of a run (the finer limbs' meshes, docs/convergence.md): how many are inside out
    (V/V0 <= 0, contact.inverted_cells), split fat / muscle and by the segment of the bone nearest each one's rest
    centroid, how many are below LOW_VOLUME of their rest volume, and the least V/V0."""
    from scipy.spatial import cKDTree

    from tissue_sim.core.solver.contact import inverted_cells
    tm = sim.tissue
    _, _, r = inverted_cells(sim, st.x)
    fat = np.asarray(tm.cell_muscle) < 0
    inv = r <= 0
    where = {}
    if inv.any() and len(tm.bone_vertices):     # each inverted cell by the segment of the bone nearest its rest centroid
        off, cv = np.asarray(tm.cell_offsets), np.asarray(tm.cell_vertices)
        cells = np.flatnonzero(inv)
        cen = np.array([tm.rest_positions[cv[off[c]:off[c + 1]]].mean(0) for c in cells])
        seg_of_vertex = np.repeat(np.asarray(tm.bone_segment), np.diff(tm.bone_vertex_offsets))
        near = seg_of_vertex[cKDTree(tm.bone_vertices).query(cen)[1]]
        for sgm, n in zip(*np.unique(near, return_counts=True)):
            where[tm.segment_names[sgm]] = int(n)
    return {'inverted': int(inv.sum()), 'inverted_fat': int((inv & fat).sum()), 'inverted_muscle': int((inv & ~fat).sum()),
            'inverted_by_segment': where, 'below_low': int((r < LOW_VOLUME).sum()), 'low_volume': LOW_VOLUME,
            'least_volume_ratio': round(float(r.min()), 4)}


TORQUE_SOURCES = ('tissue on bound vertices', 'point via rings', 'contact and sheath reaction', 'passive fibres')


def torque_sources(sim, st, knee) -> dict:
    """The knee's generalized force [N m, flexing +] from each thing the skeleton step takes, at the state of a
    sample: the cells' forces on the bone-attached vertices (State.f, this sub-step's evaluation), the point via rings'
    net pull (integration.via_forces), the contact stages' and the sheath correction's reaction left for the next
    sub-step (State.contact_wrench) and the passive fibre force (reference.passive_joint_torques)."""
    from tissue_sim.core.solver import measures as ME, reference as RF
    tissue = ME.joint_torques(sim, st, st.f, vias=False)[knee]
    return {TORQUE_SOURCES[0]: float(tissue), TORQUE_SOURCES[1]: float(ME.joint_torques(sim, st, st.f)[knee] - tissue),
            TORQUE_SOURCES[2]: float(ME.wrench_torques(sim, st, st.contact_wrench)[knee]),
            TORQUE_SOURCES[3]: float(RF.passive_joint_torques(sim, st.q)[knee]) if sim.params.passive_force_length and sim.params.specific_tension > 0 else 0.0}


def torque_table(r, every=3) -> str:
    """A run's torque sources every `every` samples, as a markdown table."""
    ts = r['torque_sources_Nm']
    rows = ['| t [s] | knee [deg] | ' + ' | '.join(TORQUE_SOURCES) + ' |', '|---' * (2 + len(TORQUE_SOURCES)) + '|']
    for i in range(every - 1, len(ts[TORQUE_SOURCES[0]]), every):
        rows.append(f'| {r["t"][i + 1]:.2f} | {r["knee_deg"][i + 1]:.1f} | '
                    + ' | '.join(f'{ts[k][i]:.1f}' for k in TORQUE_SOURCES) + ' |')
    return '\n'.join(rows)


def differences(a, b):
    """Max and RMS |knee_a - knee_b| [deg; N m with --isometric] over the samples both runs reached (keys max_deg,
    rms_deg either way)."""
    k = a['series']
    n = min(len(a[k]), len(b[k]))
    if n < 2:
        return None
    d = np.abs(np.asarray(a[k][:n]) - np.asarray(b[k][:n]))
    return {'max_deg': round(float(d.max()), 3), 'rms_deg': round(float(np.sqrt(np.mean(d ** 2))), 3),
            'up_to_s': a['t'][n - 1]}


def shrinking(diffs) -> bool:
    """Whether the differences between successive refinements shrink: both the max and the RMS of each pair below
    the pair's before it (at least two pairs, every run compared)."""
    if len(diffs) < 2 or not all(diffs):
        return False
    return all(b['max_deg'] < a['max_deg'] and b['rms_deg'] < a['rms_deg'] for a, b in zip(diffs, diffs[1:]))


def plot(runs, path, title):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    for r in runs:
        lab = f'{r["label"]}: {r["vertices"]:,} vertices, x{r["substeps"]}'
        if r['diverged']:
            lab += f' (diverged at step {r["diverged"]["step"]})'
        ax.plot(r['t'], r[r['series']], label=lab)
    ax.set_xlabel('time [s]')
    ax.set_ylabel('knee flexion [deg]' if runs[0]['series'] == 'knee_deg' else 'knee torque, flexing + [N m]')
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def markdown(out) -> str:
    unit = 'deg' if not out['runs'] or out['runs'][0]['series'] == 'knee_deg' else 'N m'
    tr = next((r['time_reference']['substeps'] for r in out['runs'] if r.get('time_reference')), None)
    rows = [f'| model | vertices | cells | integrator, sub-steps | added mass | steps/CPU s | knee at end | '
            f'cells inverted at end (fat / muscle; least V/V0) | diff. to next finer: max / RMS [{unit}] |'
            + (f' at x{tr}: end; diff. max / RMS [{unit}] |' if tr else ''),
            '|---|---|---|---|---|---|---|---|---|' + ('---|' if tr else '')]
    for i, r in enumerate(out['runs']):
        d = out['differences'][i] if i < len(out['differences']) else None
        k = r['series']
        end = f'{r[k][-1]:.1f} {SERIES[k != "knee_deg"][1]} at {r["t"][-1]:.2f} s' if r[k] else '-'
        if r['diverged']:
            end += f', diverged at step {r["diverged"]["step"]}'
        dd = f'{d["max_deg"]} / {d["rms_deg"]}' if d else '-'
        m = r.get('cells_at_end')
        inv = (f'{m["inverted"]} ({m["inverted_fat"]} / {m["inverted_muscle"]}; {m["least_volume_ratio"]:.2f})'
               if m else '-')
        ref = r.get('time_reference')
        td = ''
        if tr:
            rd = ref['difference'] if ref else None
            td = (f' {ref["at_end"]:.1f}; {rd["max_deg"]} / {rd["rms_deg"]} |' if rd and ref['at_end'] is not None
                  else ' - |')
        rows.append(f'| {r["label"]} | {r["vertices"]:,} | {r["cells"]:,} | {r["integrator"]} x{r["substeps"]} | '
                    f'{r["added_mass_percent"]:g} % | {r["steps_per_cpu_s"]:,.1f} | {end} | {inv} | {dd} |' + td)
    return '\n'.join(rows)


def bad_argument(msg: str):
    """A bad argument: one line on stderr, exit 2, nothing written."""
    print(f'error: {msg}', file=sys.stderr)
    sys.exit(2)


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--refine', default='1,3,6', help='refinements of the bundled limb, comma-separated (default 1,3,6)')
    ap.add_argument('--integrator', default=None, choices=P.INTEGRATORS,
                    help=f'time integrator (default {default_integrator()}, the fastest stable one here)')
    ap.add_argument('--substeps', default=None,
                    help="'unscaled' (mass_scaled adding < 0.1 %% of the mass: time-converged; default with mass_scaled), "
                         "'set' (the parameter set's own; default otherwise), 'matched' (omega_max h of the default model) or an integer")
    ap.add_argument('--motion', choices=tuple(MOTIONS), default='step',
                    help="'step' (default): the hamstrings fully active from t = 0; 'demo': make demo's activation, the "
                         'hamstrings ramped 0 -> 1 over 8 s')
    ap.add_argument('--duration', type=bounded(above=0), default=None,
                    help="simulated seconds (default: 0.3 with --motion step, the knee flexes to ~60 deg; 10 with demo)")
    ap.add_argument('--out', default=str(ROOT / 'bench' / 'out'), help='folder for convergence.json and .png')
    ap.add_argument('--stiffness', choices=('as-is', 'moment'), default='as-is',
                    help="'as-is': the models' own stiffness (default); 'moment' (an experiment): each cell's passive "
                         "stiffness set so that k J = c E V with c of the default model (mesh-independent)")
    ap.add_argument('--active-length', choices=P.ACTIVE_LENGTHS, default=None,
                    help="the active tension's rest length (Params.active_length; default: the physical set's): 'chord' or "
                         "'path' (along each muscle's smoothed centre line)")
    ap.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                    help='a Params field of the physical set (repeatable; VALUE read as YAML, e.g. bone_contact=false, '
                         "fold_contact=''): what a term costs in accuracy, run with and without it")
    ap.add_argument('--isometric', action='store_true',
                    help='the knee held at 0 deg (joint lock) instead: the knee torque of the fully active hamstrings '
                         '[N m] over time, compared between the models as the angle is')
    ap.add_argument('--build', action='append', default=[], metavar='NAME=VALUE',
                    help='a builder setting of the models (repeatable; VALUE read as YAML, e.g. point_vias=false; '
                         'docs/builder.md): what a modelling choice costs')
    ap.add_argument('--torques', action='store_true',
                    help='also the knee torque of each source the skeleton step takes (the bound vertices, the point '
                         'via rings, the contact and sheath reaction, the passive fibres), printed every 30 ms (--motion '
                         'demo: 250 ms; its cost is '
                         'in the steps/CPU s then)')
    ap.add_argument('--time-reference', type=bounded(int, low=1), default=None, metavar='N',
                    help='also run each model at N sub-steps per step and give its difference to that run (the time '
                         "step's share of the differences)")
    ap.add_argument('--quick', action='store_true', help='refine 1,2 and 0.3 s (make bench)')
    a = ap.parse_args()
    if a.quick:
        a.refine, a.duration, a.motion = '1,2', 0.3, 'step'
    if a.duration is None:
        a.duration = MOTIONS[a.motion][1]
    if a.isometric and a.motion != 'step':
        bad_argument('--isometric holds the knee under the step activation: it takes --motion step')
    from tissue_sim.core.builder import parse_refinements
    try:
        refs = parse_refinements(a.refine)
    except ValueError as e:
        bad_argument(str(e))
    if not (0 < a.duration <= 10):
        bad_argument('--duration must be in (0, 10] s')
    integ = a.integrator or default_integrator()
    mode = a.substeps or ('unscaled' if integ == 'mass_scaled' else 'set')
    if mode not in ('set', 'matched', 'unscaled') and not (mode.isdigit() and int(mode) >= 1):
        bad_argument(f"--substeps {mode!r}: expected set, matched, unscaled or an integer >= 1")
    if a.time_reference is not None and a.time_reference < 2:
        bad_argument(f'--time-reference {a.time_reference}: expected an integer >= 2 (sub-steps per step)')
    if mode in ('matched', 'unscaled') and integ != 'mass_scaled':
        bad_argument(f'--substeps {mode} is for mass_scaled (explicit takes its stable sub-steps itself: set)')
    from tissue_sim.core.builder import default_model
    from tissue_sim.errors import UserError
    try:
        build = P.parse_assignments(a.build, 'builder settings')
        base = P.Params.from_assignments('physical', a.set, integrator=integ)
    except ValueError as e:
        bad_argument(str(e))      # (names builder settings or solver parameters)
    if a.active_length:
        base = dataclasses.replace(base, active_length=a.active_length).validate()
    if integ == 'explicit' and mode == 'set':
        base = dataclasses.replace(base, substeps=0).validate()      # true masses: automatic sub-steps (stability)
    runs, omega1 = [], None
    c_ref = moment_ratio(default_model(), base)
    for R in refs:
        t0 = time.perf_counter()
        try:
            tm = default_model(refine=R, **build)
        except UserError as e:        # a bad builder setting: one line, exit 2
            bad_argument(f'--build: {e}')
        ratio = moment_ratio(tm, base)
        if a.stiffness == 'moment':
            tm = with_moment_stiffness(tm, base, c_ref)
        print(f'refine {R:g}: model ready in {time.perf_counter() - t0:.1f} s; passive stiffness sum kJ / sum EV: muscle '
              f'{ratio["muscle"]:.2f}, fat {ratio["fat"]:.2f} (default model {c_ref["muscle"]:.2f}, {c_ref["fat"]:.2f})'
              + ('; set to the default model\'s per cell (--stiffness moment)' if a.stiffness == 'moment' else ''), flush=True)
        params = base
        if mode.isdigit():
            params = dataclasses.replace(base, substeps=int(mode)).validate()
        elif mode == 'unscaled':
            params = dataclasses.replace(base, substeps=unscaled_substeps(solver.compile_model(tm, base))).validate()
        elif mode == 'matched':
            if omega1 is None:
                omega1 = solver.compile_model(default_model(), base).omega_max
            sub = max(1, base.substeps or 1)
            w = solver.compile_model(tm, dataclasses.replace(base, substeps=1).validate()).omega_max
            params = dataclasses.replace(base, substeps=int(math.ceil(sub * w / omega1 - 1e-9))).validate()
        r, _ = run_one(tm, params, a.duration, f'{R:g}x', isometric=a.isometric, torques=a.torques and not a.isometric,
                       motion=a.motion)
        if a.time_reference:       # the same model at N sub-steps: the time step's share of the differences
            ref, _ = run_one(tm, dataclasses.replace(params, substeps=a.time_reference).validate(), a.duration,
                             f'{R:g}x at x{a.time_reference}', isometric=a.isometric, motion=a.motion)
            k = r['series']
            r['time_reference'] = {'substeps': a.time_reference, 'at_end': ref[k][-1] if ref[k] else None,
                                   'diverged': ref['diverged'], 'difference': differences(r, ref)}
            d = r['time_reference']['difference']
            if d:
                print(f'{R:g}x against x{a.time_reference}: max {d["max_deg"]}, RMS {d["rms_deg"]} (up to {d["up_to_s"]} s)',
                      flush=True)
        if 'torque_sources_Nm' in r:
            print(f'{R:g}x: knee torque by source [N m, flexing +]:\n'
                  + torque_table(r, every=3 if a.motion == 'step' else 25), flush=True)
        r['refine'] = R
        r['stiffness_moment_ratio'] = {k: round(v, 3) for k, v in ratio.items()}
        runs.append(r)
    diffs = [differences(runs[i], runs[i + 1]) for i in range(len(runs) - 1)]
    cpu = 'unknown'
    try:
        with open('/proc/cpuinfo') as fh:
            cpu = next((ln.split(':', 1)[1].strip() for ln in fh if ln.startswith('model name')), cpu)
    except OSError:
        pass
    out = {'experiment': MOTIONS[a.motion][2] + ('; the knee held at 0 deg, its torque' if a.isometric else ''),
           'motion': a.motion, 'integrator': integ, 'substeps_mode': mode,
           'duration_s': a.duration, 'time_reference_substeps': a.time_reference, 'stiffness': a.stiffness, 'set': list(a.set), 'build': build, 'isometric': a.isometric, 'active_length': base.active_length, 'runs': runs, 'differences': diffs, 'cpu_model': cpu,
           'load_average_1min': round(os.getloadavg()[0], 2), 'timing': 'steps per CPU second of this process, one thread'}
    out['differences_shrink'] = shrinking(diffs)
    od = Path(a.out)
    od.mkdir(parents=True, exist_ok=True)
    (od / 'convergence.json').write_text(json.dumps(out, indent=1))
    try:
        plot(runs, od / 'convergence.png', f'knee {"torque held at 0 deg" if a.isometric else "flexion"}, hamstrings '
             f'{"ramped over 8 s" if a.motion == "demo" else "fully active"}; {integ}, sub-steps {mode}' + (f'; {" ".join(a.set + a.build)}' if a.set or a.build else '')
             + f'; active length {base.active_length}'
             + ('; stiffness per volume as the default model' if a.stiffness == 'moment' else ''))
    except Exception as e:  # report, do not hide
        print(f'plot not written ({type(e).__name__}: {e})')
    print()
    print(markdown(out))
    print()
    for i, d in enumerate(diffs):
        if d:
            print(f'{runs[i]["label"]} vs {runs[i + 1]["label"]}: max {d["max_deg"]} deg, RMS {d["rms_deg"]} deg '
                  f'(up to {d["up_to_s"]} s)')
    print(f'differences shrink with refinement (max and RMS): {out["differences_shrink"]}; {cpu}; load average '
          f'{out["load_average_1min"]}; written {od / "convergence.json"}, {od / "convergence.png"}')
    slim = dict(out, runs=[{k: v for k, v in r.items() if k not in ('t', r['series'])} for r in runs])
    print(json.dumps(slim))


if __name__ == '__main__':
    main()
