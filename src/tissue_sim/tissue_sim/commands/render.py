"""`tissue-sim render RUN`: paper-like pictures (Figs. 6-9) and an animation of a run, headless."""
from __future__ import annotations

import time
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'render'
HELP = ('draw a run (MCAP file or run folder) like the paper\'s figures, offscreen: whole limb with translucent '
        'fat (Fig. 6), knee close-up (Fig. 7), skin-area change (Fig. 8), fat deformation d (Fig. 9), animation')


def _floats(text: str) -> list:
    try:
        return [float(v) for v in text.split(',') if v.strip()]
    except ValueError:
        raise UserError(f'--times: expected comma-separated seconds, got {text!r}') from None


def _size(text: str) -> tuple:
    try:
        w, h = (int(v) for v in text.lower().split('x'))
    except ValueError:
        raise UserError(f'--size: expected WIDTHxHEIGHT, got {text!r}') from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise UserError(f'--size {text}: width and height must be 16..8192')
    return w, h


def add_arguments(p):
    from tissue_sim.core.analysis.render import KINDS
    p.add_argument('run', help='run MCAP file, or a folder of them')
    p.add_argument('-o', '--out', help='output folder (default: <run folder>/figures)')
    p.add_argument('--times', help='comma-separated simulated times [s] to draw (default: 4 evenly spread)')
    p.add_argument('-n', '--frames', type=int, default=4, help='number of evenly spread frames (default 4)')
    p.add_argument('--views', default=','.join(KINDS), help=f'comma-separated views (default: all: {",".join(KINDS)})')
    p.add_argument('--size', default='800x600', help='picture size WIDTHxHEIGHT (default 800x600)')
    p.add_argument('--animation', choices=('gif', 'mp4', 'none'), default='gif', help='animation format (default gif)')
    p.add_argument('--anim-frames', type=int, default=48, help='frames in the animation (default 48)')


def run(args) -> int:
    from tissue_sim.commands.analyze import default_out
    from tissue_sim.core import runio
    from tissue_sim.core.analysis import figures, render
    from tissue_sim.core.cdr import CdrError
    path = Path(args.run)
    views = [v.strip() for v in args.views.split(',') if v.strip()]
    bad = [v for v in views if v not in render.KINDS]
    if bad:
        raise UserError(f'--views: unknown view {bad[0]!r}; choose from {", ".join(render.KINDS)}')
    if args.frames < 1 or args.anim_frames < 2:
        raise UserError('--frames must be >= 1 and --anim-frames >= 2')
    out = Path(args.out) if args.out else default_out(path, 'figures')
    t0 = time.monotonic()
    times, size = (_floats(args.times) if args.times else None), _size(args.size)
    try:
        loaded = runio.load_run(path)
        files = figures.render_run(loaded, out, times=times, n_frames=args.frames, size=size, views=views,
                                   animation=None if args.animation == 'none' else args.animation,
                                   anim_frames=args.anim_frames)
    except (runio.RunError, CdrError) as e:
        raise UserError(str(e)) from None
    print(f'rendered {len(files)} files in {time.monotonic() - t0:.1f} s to {out}:')
    for f in files:
        print(f'  {f}')
    return 0
