"""Fold-contact benchmark (docs/contact.md "Tissue-tissue contact in the fold"), bundled model: solver steps/s with no
contact, bone contact, bone + fold contact (the physical set's: the flexion side and its 1-mm sheath) and that with the
physical set's wrap surfaces (docs/contact.md "Wrap surfaces") in the same run (paper and physical sets), and with --hold the passive
hamstrings held at 0/30/60/90/120 deg (physical set, neither fold nor sheath, and the physical set's): their length change, semitendinosus's summed
cell lengths, free vertices > 1 mm inside a bone and inverted cells; with --validate DIR, `tissue-sim validate -o DIR`
on the physical set with the fold on (fold_contact 'knee'; --side-only: fold_plane False; --sheath R: the hamstrings
in a sheath of radius R [m] above the knee, --below: below it too) instead.

    .venv/bin/python bench/fold.py [--seconds 6] [--hold]
    .venv/bin/python bench/fold.py --implicit      (the physical set under mass_scaled and implicit, side by side)
    .venv/bin/python bench/fold.py --validate DIR [--side-only] [--sheath R [--below]] [validate options, e.g. --angles 0,30,60,90]

Steps/s as bench/contact.py (per CPU second, one thread, full hamstring activation, windows interleaved).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import contact as B  # noqa: E402  (bench/contact.py: sets one thread, the import path)

import numpy as np  # noqa: E402

from tissue_sim.core import solver  # noqa: E402
from tissue_sim.core.solver import contact  # noqa: E402

HAM = ('biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus', 'semitendinosus')


def chain_length(tm, x, m):
    """Sum over muscle m's cells of the distance between their two ring centroids [m]."""
    tot = 0.0
    for c in np.flatnonzero(tm.cell_muscle == m):
        cv = tm.cell_vertices[tm.cell_offsets[c]:tm.cell_offsets[c + 1]]
        h = len(cv) // 2
        tot += np.linalg.norm(x[cv[h:]].mean(0) - x[cv[:h]].mean(0))
    return tot


def hold(tm, fold, settle=0.5, angles=(0, 30, 60, 90, 120), **kw):
    phys = solver.Params.physical()
    sheath = dict(sheath_group=phys.sheath_group, sheath_below=phys.sheath_below) if fold else dict(sheath_group='', sheath_below='')
    sim = solver.compile_model(tm, solver.Params.physical(fold_contact=fold, **sheath, **kw))
    print(f"integrator {sim.params.integrator}, {sim.n_substeps} sub-step(s)")
    names = list(tm.muscle_names)
    mi = [names.index(n) for n in HAM]
    j = list(tm.joint_names).index('knee_r')
    st, ctl = solver.make_state(sim), solver.make_control(sim)
    ctl.joint_lock[:] = True
    ctl.joint_target[:] = st.q
    print(f'fold_contact={fold!r} ({len(sim.contact.f_idx)} fold vertices): length change [mm] of '
          + ', '.join(HAM) + '; semitendinosus cells summed [mm]')
    cur, dt, L0 = 0.0, sim.params.dt, None
    out = {}
    for deg in angles:
        n = int(math.ceil(abs(deg - cur) / 200 / dt))
        for i in range(n):
            ctl.joint_target[j] = math.radians(cur + (deg - cur) * (i + 1) / n)
            solver.step(sim, st, ctl)
        ctl.joint_target[j] = math.radians(deg)
        solver.step(sim, st, ctl, n_steps=int(settle / dt))
        cur = deg
        L = solver.observe(sim, st)['muscle_lengths'][mi]
        L0 = L.copy() if L0 is None else L0
        pen = contact.mesh_penetration(sim, st)
        bad, r, _ = contact.inverted_cells(sim, st.x)
        print(f'  {deg:4d} deg ' + ' '.join(f'{1e3 * (a - b):+7.1f}' for a, b in zip(L, L0))
              + f'   {1e3 * chain_length(tm, st.x, mi[3]):6.1f}   >1 mm inside a bone: {sum(v[1] for v in pen.values())}'
              f'   inverted cells: {len(bad)}', flush=True)
        out[deg] = L - L0
    return out


def implicit_vs_mass_scaled(tm, duration=1.0, every=0.05):
    """The physical set as it is (fold + sheath) under its mass_scaled integrator, under the implicit one (one
    1-ms sub-step, the sheath correction: docs/solver.md "Implicit integrator") and under explicit at true masses
    (64 sub-steps: the reference without added mass; its automatic 43 diverged in the hold): the passive hold's hamstring length changes and the knee
    of a full hamstring contraction from rest (every `every` s for `duration` s), side by side."""
    held, knee = {}, {}
    for name, kw in (('mass_scaled', {}), ('implicit', dict(integrator='implicit', substeps=1)),
                     ('explicit', dict(integrator='explicit', substeps=64))):
        try:
            held[name] = hold(tm, 'knee', **kw)
        except solver.DivergenceError as e:        # (explicit at its automatic 43 sub-steps: at step 501)
            print(f'{name}: {e}')
            held[name] = {deg: np.full(4, np.nan) for deg in held['mass_scaled']}
        sim = solver.compile_model(tm, solver.Params.physical(**kw))
        knee[name] = np.degrees([o['joint_positions'][0] for _, o in solver.simulate(
            sim, duration, {'hamstrings': [(0.0, 1.0)]}, every=int(round(every / sim.params.dt)), output='obs')])
    print('hamstring length change [mm] at each angle, mass_scaled / implicit / explicit at true masses '
          '(max |implicit - mass_scaled|, max |implicit - explicit|):')
    for deg in held['mass_scaled']:
        a, b, c = held['mass_scaled'][deg], held['implicit'][deg], held['explicit'][deg]
        print(f'  {deg:4d} deg ' + '  '.join(f'{1e3 * u:+6.1f}/{1e3 * w:+6.1f}/{1e3 * e:+6.1f}' for u, w, e in zip(a, b, c))
              + f'   ({1e3 * np.abs(a - b).max():.1f} mm, {1e3 * np.abs(c - b).max():.1f} mm)')
    print(f'knee [deg] every {every} s, full hamstring activation from rest:')
    for name in knee:
        print(f'  {name:11s} ' + ' '.join(f'{v:6.1f}' for v in knee[name]))
    for ref in ('mass_scaled', 'explicit'):
        d = np.abs(knee['implicit'] - knee[ref])
        print(f'  max |implicit - {ref}| {d.max():.2f} deg at {every * int(d.argmax()):.2f} s', flush=True)


def validate(out_dir, side_only, sheath, below, rest):
    """tissue-sim validate -o out_dir (options rest) with Params.physical() turning the fold on."""
    physical = solver.Params.physical.__func__

    def with_fold(cls, **kw):
        kw.setdefault('fold_contact', 'knee')
        kw.setdefault('fold_plane', not side_only)
        if sheath:
            kw.setdefault('sheath_group', 'hamstrings')
            kw.setdefault('sheath_radius', sheath)
            kw.setdefault('sheath_below', 'hamstrings' if below else '')
        return physical(cls, **kw)
    solver.Params.physical = classmethod(with_fold)
    from tissue_sim.cli import main as cli
    return cli(['validate', '-o', out_dir] + rest)


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=bounded(above=0), default=6.0, help='measuring time per configuration [s]')
    ap.add_argument('--hold', action='store_true', help='also the passive hold, fold off and on')
    ap.add_argument('--validate', metavar='DIR', help='run tissue-sim validate -o DIR with the fold on instead')
    ap.add_argument('--side-only', action='store_true', help='with --validate: fold_plane False')
    ap.add_argument('--below', action='store_true', help='with --sheath: also below the knee (sheath_below)')
    ap.add_argument('--implicit', action='store_true', help='the physical set (fold + sheath) under mass_scaled and '
                    'implicit: the passive hold and a full hamstring contraction, side by side (nothing else)')
    ap.add_argument('--sheath', type=bounded(low=0), default=0.0, metavar='R', help='with --validate: the hamstrings in a sheath of radius R [m]')
    a, rest = ap.parse_known_args()
    if a.validate:
        return validate(a.validate, a.side_only, a.sheath, a.below, rest)
    if rest:
        ap.error(f'unrecognised arguments: {" ".join(rest)}')
    from tissue_sim.core.builder import default_model
    tm = default_model()
    if a.implicit:
        return implicit_vs_mass_scaled(tm)
    print(f'{"set":10s} {"no contact":>11s} {"bone":>9s} {"bone+fold":>10s} {"+wrap":>9s} {"cost all":>9s} {"fold":>6s} '
          f'{"wrap":>6s}   (steps/s per CPU s)')
    for preset in ('paper', 'physical'):
        P = getattr(solver.Params, preset)
        phys = solver.Params.physical()
        none = dict(fold_contact='', sheath_group='', sheath_below='', wrap_surfaces='')
        fold = dict(fold_contact='knee', fold_plane=False, sheath_group=phys.sheath_group, sheath_below=phys.sheath_below,
                    sheath_radius=phys.sheath_radius)   # the physical set's
        sims = [solver.compile_model(tm, P(bone_contact=False, **none)), solver.compile_model(tm, P(bone_contact=True, **none)),
                solver.compile_model(tm, P(bone_contact=True, **fold, wrap_surfaces='')),
                solver.compile_model(tm, P(bone_contact=True, **fold, wrap_surfaces=phys.wrap_surfaces))]
        best, _ = B.steps_per_s(sims, a.seconds)
        print(f'{preset:10s} {best[0]:11.0f} {best[1]:9.0f} {best[2]:10.0f} {best[3]:9.0f} {100 * (1 - best[3] / best[0]):8.1f}% '
              f'{100 * (1 - best[2] / best[1]):5.1f}% {100 * (1 - best[3] / best[2]):5.1f}%', flush=True)
    if a.hold:
        for fold in ('', 'knee'):
            hold(tm, fold)


if __name__ == '__main__':
    sys.exit(main())
