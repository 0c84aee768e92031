"""`tissue-sim build-model`: labelled slices + tissue table -> model file (paper section 2)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'build-model'
HELP = 'build the elastic bone/muscle/fat model from a label volume and a tissue table'


def add_arguments(p):
    from tissue_sim.core.build_settings import DEFAULTS as D
    p.add_argument('labels', nargs='?', help='label volume: .nii/.nii.gz, .npz (labels + affine) or a folder of '
                   'slice_NNNN.png with spacing.yaml (default: the bundled lower limb)')
    p.add_argument('--tissues', metavar='TABLE.yaml', help='tissue table (required with LABELS; default: the bundled one)')
    p.add_argument('-o', '--output', metavar='MODEL', help='model file to write (.npz; default: <table name>.model.npz)')
    g = p.add_argument_group('settings (defaults: a model of the paper\'s Table-1 size; --sections rays: the paper\'s cross-sections)')
    sl = g.add_mutually_exclusive_group()
    sl.add_argument('--slices', type=int, help=f'number of slices evenly over the labelled extent (default {D["slices"]}, the paper\'s)')
    sl.add_argument('--slice-mm', type=float, help='slice spacing [mm] instead (the paper: 25 mm)')
    sl.add_argument('--slice-step', type=int, help='take every Nth slice of the volume instead')
    g.add_argument('--refine', type=float, default=D['refine'], metavar='R',
                   help='R x finer: slice gaps, --muscle-rays and --fat-rays x R (rounded); e.g. --refine 3 on the bundled '
                        'limb: 136 slices, 33 and 36 vertices per muscle and fat ring (default %(default)s)')
    g.add_argument('--muscle-rays', type=int, default=D['muscle_rays'], help='vertices per muscle polygon (default %(default)s)')
    g.add_argument('--fat-rays', type=int, default=D['fat_rays'], help='rays of the fat tube per slice (default %(default)s)')
    g.add_argument('--share-mm', type=float, default=D['share_mm'], help='vertex sharing threshold [mm] (default %(default)s; 0 = off)')
    g.add_argument('--attach-mm', type=float, default=D['attach_mm'], help='bone attachment distance [mm] (default: one pixel)')
    g.add_argument('--no-anchor-muscles', dest='anchor_muscles', action='store_false',
                   help="do not fix muscle end rings to their origin/insertion segments (only bone-touching vertices, as the paper's section 2.4)")
    g.add_argument('--via-points', action=argparse.BooleanOptionalAction, default=D['via_points'],
                   help="fix each muscle's ring nearest each of its via points (tissues.yaml via_points: the source model's "
                        "intermediate path points) to the via point's segment (default on; --no-via-points: only the end "
                        "rings, as the paper; docs/builder.md \"Via points\")")
    g.add_argument('--min-area-mm2', type=float, default=D['min_area_mm2'], help='drop smaller components [mm^2] (default %(default)s)')
    g.add_argument('--min-fat-mm', type=float, default=D['min_fat_mm'], help='minimum fat thickness [mm] (default %(default)s)')
    g.add_argument('--sections', choices=('contour', 'rays'), default=D['sections'],
                   help="cross-sections: the traced label outline (default) or the paper's rays from the centroid")
    g.add_argument('--fat-follow', action=argparse.BooleanOptionalAction, default=D['fat_follow'],
                   help="contour sections: each fat ring's vertices follow their predecessors on the slice below instead of "
                        "an even ring from the least-twist start (default off; fewer sheared fat cells on finer models, "
                        "--refine; docs/builder.md \"Fat tube\")")
    g.add_argument('--max-fragment', type=float, default=D['max_fragment'], metavar='SHARE',
                   help="a piece of a muscle cut off from its main part by slices without its label and holding at most this "
                        "share of its volume is left out with a warning (default %(default)s; 0: every such piece is a break)")
    g.add_argument('--allow-broken-muscles', dest='allow_broken', action='store_true',
                   help='a muscle whose chain breaks between slices: build it in pieces with a warning instead of failing')
    g.add_argument('--shear-limit', type=float, default=D['shear_limit'],
                   help='quality report: warn about cells sheared more than this x their height (default %(default)s)')
    g.add_argument('--ray-hit', choices=('first', 'last'), default=D['ray_hit'], help='boundary crossing used along a ray (default %(default)s)')
    g.add_argument('--ray-origin', choices=('best', 'centroid'), default=D['ray_origin'],
                   help='origin of a region\'s rays (default %(default)s)')
    g.add_argument('--bone-mesh-step', type=int, default=D['bone_mesh_step'], help='marching-cubes step [voxels] (default %(default)s)')
    g.add_argument('--allow-missing', action='store_true', help='table labels absent from the volume: warn, do not fail')
    p.add_argument('--json', action='store_true', help='print the Table-1 summary as one JSON object (keys = Table 1 rows)')
    p.add_argument('--report', metavar='FILE.json', help='write the full quality report (JSON)')
    p.add_argument('--strict', action='store_true', help='fail (exit 2, nothing written) when the quality report warns '
                   '(volume off its label by > 10 %%, a broken muscle, cells over the shear limit, a bone without attached vertices)')
    p.add_argument('--glb', metavar='FILE.glb', help='also export the surfaces (muscles, skin, bones) as GLB')
    p.add_argument('--vtu', metavar='FILE.vtu', help='also export the cells as VTU (ParaView)')


def _settings(args) -> dict:
    return {'slices': args.slices, 'slice_mm': args.slice_mm, 'slice_step': args.slice_step, 'muscle_rays': args.muscle_rays,
            'fat_rays': args.fat_rays, 'share_mm': args.share_mm, 'attach_mm': args.attach_mm, 'anchor_muscles': args.anchor_muscles,
            'via_points': args.via_points, 'min_area_mm2': args.min_area_mm2, 'min_fat_mm': args.min_fat_mm, 'ray_hit': args.ray_hit, 'ray_origin': args.ray_origin,
            'bone_mesh_step': args.bone_mesh_step, 'allow_missing': args.allow_missing, 'sections': args.sections,
            'allow_broken': args.allow_broken, 'shear_limit': args.shear_limit, 'refine': args.refine,
            'max_fragment': args.max_fragment, 'fat_follow': args.fat_follow}


def _check_arguments(args) -> dict:
    """Every output path and option checked before any input is read or anything written (issue 20)."""
    from tissue_sim.core.build_settings import settings_with_defaults
    from tissue_sim.outputs import check_outputs
    if args.bone_mesh_step < 1:
        raise UserError(f'--bone-mesh-step must be an integer >= 1 (voxels), got {args.bone_mesh_step}')
    settings_with_defaults(_settings(args))
    return check_outputs({'-o/--output': (args.output or './<model name>.model.npz', 'model'),
                          '--report': (args.report, 'report'), '--glb': (args.glb, 'GLB export'),
                          '--vtu': (args.vtu, 'VTU export')}, inputs=[args.labels, args.tissues])


def run(args) -> int:
    _check_arguments(args)
    from tissue_sim.core import builder
    if args.labels is None:
        if args.tissues is not None:
            raise UserError('--tissues given without LABELS')
        try:
            labels, tissues = builder.default_inputs()
        except FileNotFoundError as e:
            raise UserError(f'the bundled anatomy is not available ({e}); give LABELS and --tissues') from None
    else:
        if args.tissues is None:
            raise UserError('LABELS needs --tissues TABLE.yaml (the tissue table)')
        labels, tissues = args.labels, args.tissues
    out = Path(args.output) if args.output else None
    if out is not None and out.is_dir():
        raise UserError(f'{out}: is a folder; give a file name for the model')
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    err = Console(stderr=True)
    with Progress(TextColumn('[bold]build-model[/] {task.description}'), BarColumn(), TimeElapsedColumn(),
                  console=err, transient=True, disable=args.json or not err.is_terminal) as bar:
        task = bar.add_task('reading', total=1.0)

        def progress(step, frac):
            weights = {'slices': (0.0, 0.6), 'chains': (0.6, 0.1), 'cells': (0.7, 0.1), 'bones': (0.8, 0.2)}
            a, w = weights.get(step, (0.0, 0.0))
            bar.update(task, completed=a + w * frac, description=step)
        tm, report = builder.build_model(labels, tissues, progress=progress, **_settings(args))
    qwarn = report['quality']['warnings']
    for w in qwarn:
        print(f'warning: {w}', file=sys.stderr)
    if args.strict and qwarn:
        raise UserError(f'--strict: the quality report has {len(qwarn)} warning(s), first: {qwarn[0]}; nothing written')
    if out is None:
        out = Path(f'{tm.name}.model.npz')
    from tissue_sim.outputs import Staged, check_output
    check_output(out, 'model')
    from tissue_sim.core.builder import export
    with Staged() as staged:                  # all outputs or none: a failure leaves nothing written
        try:
            tm.save(staged.path(out))
        except OSError as e:
            raise UserError(f'{out}: cannot write the model ({e.strerror})') from None
        if args.report:
            try:
                staged.path(args.report).write_text(json.dumps(report, indent=1, default=float))
            except OSError as e:
                raise UserError(f'{args.report}: cannot write the report ({e.strerror})') from None
        if args.glb:
            export.to_glb(tm, staged.path(args.glb), name=args.glb)
        if args.vtu:
            export.to_vtu(tm, staged.path(args.vtu), name=args.vtu)
    t1 = report['table1']
    if args.json:
        print(json.dumps(dict(t1, model=str(out), build_s=report['build_s'], closed_surfaces=report['closed_surfaces'],
                              inverted_cells=report['cells']['inverted'], warnings=len(report['warnings']),
                              quality_warnings=qwarn)))
        return 0
    from rich.console import Console
    from rich.table import Table
    con = Console()
    tab = Table(title=f'{tm.name}: {out} ({report["build_s"]:.2f} s)')
    tab.add_column('Table 1 row'); tab.add_column('this model', justify='right'); tab.add_column('paper', justify='right')
    for k, lab in builder.TABLE1_LABELS.items():
        tab.add_row(lab, str(t1[k]), str(builder.PAPER_TABLE1[k]))
    tab.add_row('fat vertices (distinct)', str(t1['fat_vertices_unique']), '')
    tab.add_row('bone-attached vertices', str(t1['bone_attached_vertices']), '')
    con.print(tab)
    c = report['cells']
    con.print(f'cells: {c["count"]}, inverted {c["inverted"]}, dropped degenerate {len(c["dropped_degenerate"])}, '
              f'min volume {c["min_volume_mm3"]} mm^3; surfaces closed: {report["closed_surfaces"]}; '
              f'median polygon/label area {report["areas"]["median_ratio"]}')
    for w in report['warnings']:
        if w not in qwarn:
            con.print(f'[yellow]warning:[/] {w}')
    if report['dropped_components']:
        con.print(f'{len(report["dropped_components"])} small or single-slice components dropped (see --report)')
    return 0
