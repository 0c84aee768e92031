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
    from tissue_sim.outputs import Staged, check_outputs
    if not (args.glb or args.ply or args.vtu):
        raise UserError('nothing to do: give --glb, --ply and/or --vtu')
    outs = check_outputs({'--glb': (args.glb, 'GLB export'), '--ply': (args.ply, 'PLY export'),
                          '--vtu': (args.vtu, 'VTU export')}, inputs=[args.model])   # before any work
    try:
        tm = TissueModel.load(args.model)
    except ModelError as e:
        raise UserError(str(e)) from None
    with Staged() as staged:
        for opt, fn in (('--glb', export.to_glb), ('--ply', export.to_ply), ('--vtu', export.to_vtu)):
            if outs[opt] is not None:
                fn(tm, staged.path(outs[opt]), name=outs[opt])
    for p in outs.values():
        if p is not None:
            print(f'wrote {p}')
    return 0
