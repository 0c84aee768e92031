"""`tissue-sim export-run RUN`: frames of a run as GLB/PLY meshes and a VTU series (.pvd) for ParaView."""
from __future__ import annotations

import time
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'export-run'
HELP = ('export frames of a run (MCAP file or run folder): GLB/PLY meshes (skin, muscles, posed bones) and a '
        'VTU time series with per-cell area ratio and d (cells.pvd, opens in ParaView)')


def add_arguments(p):
    p.add_argument('run', help='run MCAP file, or a folder of them')
    p.add_argument('-o', '--out', help='output folder (default: <run folder>/export)')
    p.add_argument('--times', help='comma-separated simulated times [s] for the GLB/PLY meshes (default: 4 evenly spread)')
    p.add_argument('--formats', default='glb,ply,vtu', help='comma-separated: glb, ply, vtu (default all)')
    p.add_argument('--stride', type=int, default=1, help='VTU series: every N-th frame (default 1)')


def run(args) -> int:
    import numpy as np

    from tissue_sim.commands.analyze import default_out
    from tissue_sim.commands.render import _floats
    from tissue_sim.core import runio
    from tissue_sim.core.analysis import export, figures
    from tissue_sim.core.analysis.plots import pick_motion_frames
    from tissue_sim.core.cdr import CdrError
    path = Path(args.run)
    fmts = [f.strip().lower() for f in args.formats.split(',') if f.strip()]
    bad = [f for f in fmts if f not in ('glb', 'ply', 'vtu')]
    if bad or not fmts:
        raise UserError(f'--formats: unknown format {bad[0] if bad else "(none)"!r}; choose from glb, ply, vtu')
    if args.stride < 1:
        raise UserError('--stride must be >= 1')
    out = Path(args.out) if args.out else default_out(path, 'export')
    t0 = time.monotonic()
    files = []
    try:
        loaded = runio.load_run(path)
        out.mkdir(parents=True, exist_ok=True)
        mesh_fmts = [f for f in fmts if f in ('glb', 'ply')]
        if mesh_fmts:
            chosen = figures.frames_at_times(loaded.times, _floats(args.times)) if args.times else pick_motion_frames(loaded.times, loaded.joint_positions, 4)
            for i in chosen:
                files += export.write_meshes(loaded.model, loaded.frames[i], loaded.segment_poses[i], out,
                                             f'frame_{int(loaded.frame_index[i]):05d}', mesh_fmts)
        if 'vtu' in fmts:
            files += export.write_vtu_series(loaded, out / 'vtu', frames=np.arange(0, loaded.n_frames, args.stride))
    except (runio.RunError, CdrError) as e:
        raise UserError(str(e)) from None
    except OSError as e:
        raise UserError(f'{out}: cannot write ({e.strerror or e})') from None
    print(f'exported {len(files)} files in {time.monotonic() - t0:.1f} s to {out}')
    for f in files if len(files) <= 20 else files[:8] + files[-4:]:
        print(f'  {f}')
    if len(files) > 20:
        print(f'  ... ({len(files) - 12} more)')
    return 0
