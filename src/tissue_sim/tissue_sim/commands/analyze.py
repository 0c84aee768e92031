"""`tissue-sim analyze RUN`: tables, summary and plots of a recorded or headless run (paper section 4)."""
from __future__ import annotations

import time
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'analyze'
HELP = ('measure a run (MCAP file or run folder): per fat cell skin-area change and deformation degree d '
        '(paper eq. 2 and rotation-free), per muscle length/volume, joint angles; writes CSV/Parquet tables, '
        'summary.json and plots')


def add_arguments(p):
    p.add_argument('run', help='run MCAP file, or a folder of them (split recording / run folder)')
    p.add_argument('-o', '--out', help='output folder (default: <run folder>/analysis)')
    p.add_argument('--stride', type=int, default=1, help='analyse every N-th frame (default 1)')
    p.add_argument('--no-plots', action='store_true', help='tables and summary only')
    p.add_argument('--figures', action='store_true',
                   help='also draw the paper-like pictures (as `tissue-sim render`, default views) into <out>/figures, '
                        'from the same loaded run and measures')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress bar')


def default_out(run: Path, sub: str) -> Path:
    """<run folder>/<sub>: the run's own folder for a folder, the file's folder for a file."""
    return (run if run.is_dir() else run.parent) / sub


def run(args) -> int:
    from tissue_sim.core import runio
    from tissue_sim.core.analysis import measure, tables
    from tissue_sim.core.cdr import CdrError
    path = Path(args.run)
    if args.stride < 1:
        raise UserError('--stride must be >= 1')
    out = Path(args.out) if args.out else default_out(path, 'analysis')
    t0 = time.monotonic()
    try:
        total = runio.count_states(path)
        from rich.console import Console
        from rich.progress import Progress
        with Progress(console=Console(stderr=True), disable=args.quiet) as prog:
            task = prog.add_task('reading frames', total=total)
            loaded = runio.load_run(path, stride=args.stride, progress=lambda i: prog.update(task, completed=i + 1))
            task = prog.add_task("measuring frames", total=loaded.n_frames)
            m = measure.measure(loaded, progress=lambda: prog.advance(task))
    except (runio.RunError, CdrError) as e:
        raise UserError(str(e)) from None
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f'{out}: cannot create the output folder ({e.strerror})') from None
    files = tables.write_tables(m, out)
    files.append(tables.write_summary(m, out, path))
    if not args.no_plots:
        from tissue_sim.core.analysis import plots
        files += plots.all_plots(m, out)
    if args.figures:
        from tissue_sim.core.analysis import figures
        try:
            files += figures.render_run(loaded, out / "figures", measures=m)
        except runio.RunError as e:
            raise UserError(str(e)) from None
    s = tables.summary(m)
    print(f'analysed {m.n_frames} frames ({s["duration_s"]:.3f} s of simulated time) of model {m.model_name!r} '
          f'in {time.monotonic() - t0:.1f} s')
    for n, j in s['joints'].items():
        print(f'  joint {n}: {j["min_deg"]:.1f} .. {j["max_deg"]:.1f} deg')
    if s.get('main_joint'):
        print(f'  main joint {s["main_joint"]}; pictures at frames {", ".join(map(str, s["picture_frames"]))}')
    if s['fat']:
        f = s['fat']
        if f['area_ratio_min'] is not None:
            print(f'  skin area ratio: {f["area_ratio_min"]:.3f} .. {f["area_ratio_max"]:.3f}')
        print(f'  fat d (paper) max {f["d_paper_max_m"] * 1000:.2f} mm, rotation-free max {f["d_rotfree_max_m"] * 1000:.2f} mm')
    print(f'wrote {len(files)} files to {out}:')
    for f in files:
        print(f'  {f}')
    return 0
