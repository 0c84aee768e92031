"""`tissue-sim`: the command-line front end of the ROS-free core.

Each subcommand lives in ``tissue_sim.commands.<module>`` and defines ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``. Bad input raises ``UserError``: it is printed as
one ``error:`` line and the process exits with its code (2), never with a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from tissue_sim import __version__
from tissue_sim.errors import ArgumentParser, UserError

COMMAND_MODULES = ('build_model', 'make_anatomy', 'simulate', 'analyze', 'render', 'export', 'export_run',
                   'info', 'repair', 'validate', 'stiffness')


def _commands():
    mods = []
    for name in COMMAND_MODULES:
        try:
            mods.append(importlib.import_module(f'tissue_sim.commands.{name}'))
        except ModuleNotFoundError as e:
            if e.name != f'tissue_sim.commands.{name}':
                raise
    return mods


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog='tissue-sim', description='Elastic bone/muscle/fat model of a lower limb: '
                       'build it from labelled slices, simulate it, analyse the deformation.')
    p.add_argument('--version', action='version', version=f'tissue-sim {__version__}')
    sub = p.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for mod in _commands():
        sp = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(sp)
        sp.set_defaults(_run=mod.run)
    return p


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:         # --help, --version, or the parser's one-line error (ArgumentParser): its exit code
        return e.code if isinstance(e.code, int) else 0
    try:
        return int(args._run(args) or 0)
    except UserError as e:
        print(f'tissue-sim {args.command}: error: {e}', file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f'tissue-sim {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
