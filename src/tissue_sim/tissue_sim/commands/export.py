"""`tissue-sim export`: a model file's surfaces to GLB/PLY and its cells to VTU (ParaView)."""
from __future__ import annotations

from tissue_sim.errors import UserError

NAME = 'export'
HELP = 'export a model: surfaces (muscles, skin, bones) to GLB/PLY, cells to VTU for ParaView'


def add_arguments(p):
    p.add_argument('model', help='model file (.npz written by build-model)')
    p.add_argument('--glb', metavar='FILE.glb', help='surfaces as glTF binary')
    p.add_argument('--ply', metavar='FILE.ply', help='surfaces as one PLY with face colours')
    p.add_argument('--vtu', metavar='FILE.vtu', help='cells as a VTK unstructured grid (ParaView)')


def run(args) -> int:
    from tissue_sim.core.builder import export
    from tissue_sim.core.model import ModelError, TissueModel
    if not (args.glb or args.ply or args.vtu):
        raise UserError('nothing to do: give --glb, --ply and/or --vtu')
    try:
        tm = TissueModel.load(args.model)
    except ModelError as e:
        raise UserError(str(e)) from None
    for fmt, fn in (('glb', export.to_glb), ('ply', export.to_ply), ('vtu', export.to_vtu)):
        path = getattr(args, fmt)
        if path:
            fn(tm, path)
            print(f'wrote {path}')
    return 0
