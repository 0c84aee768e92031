"""`tissue-sim repair RUN`: rewrite a recording cut short (a killed recorder) into a complete MCAP."""
from __future__ import annotations

import os
import re
from pathlib import Path

from tissue_sim.errors import UserError

NAME = 'repair'
HELP = ('rewrite an MCAP recording cut short by a kill (no summary/footer, last chunk cut) into a complete MCAP '
        '(summary, indexes, footer) that rosbags, the mcap readers and ros2 bag read, keeping every complete message')


def add_arguments(p):
    p.add_argument('run', help='the MCAP file to repair')
    p.add_argument('-o', '--output', metavar='OUT.mcap', help='where to write the repaired file '
                   '(default: RUN with the suffix .repaired.mcap next to it)')
    p.add_argument('--in-place', action='store_true', help='replace RUN by the repaired file (written to a '
                   'temporary file beside it, then renamed over RUN)')
    p.add_argument('--force', action='store_true', help='overwrite OUT if it exists; repair a complete file too')


def _default_output(src: Path) -> Path:
    m = re.search(r'_(\d+)\.mcap$', src.name)
    if m and any(f != src for f in src.parent.glob(src.name[:m.start()] + '_*.mcap')):
        raise UserError(f'{src} is part of a split recording (its folder is read as one run): give -o OUT '
                        'outside that folder, or --in-place')
    stem = src.name[:-5] if src.name.endswith('.mcap') else src.name
    return src.with_name(f'{stem}.repaired.mcap')


def run(args) -> int:
    from tissue_sim.core import mcapio
    src = Path(args.run)
    if src.is_dir():
        raise UserError(f'{src}: a folder; repair its files one at a time (the last one of a killed split recording)')
    if not src.is_file():
        raise UserError(f'{src}: no such file')
    if args.in_place and args.output:
        raise UserError('give either -o OUT or --in-place, not both')
    if args.output and Path(args.output).resolve() == src.resolve():
        raise UserError(f'{args.output}: the output is the input; use --in-place to replace it')
    try:
        complete = mcapio.is_complete(src)
        head = mcapio.iter_salvage(src)
        next(head)                                       # an MCAP file with its header: else one line, exit 2
        head.close()
    except mcapio.McapIOError as e:
        raise UserError(str(e)) from None
    except OSError as e:
        raise UserError(f'{src}: cannot read ({e.strerror or e})') from None
    if complete and not args.force:
        print(f'{src}: complete (summary and footer present): nothing to repair')
        return 0
    dst = src if args.in_place else (Path(args.output) if args.output else _default_output(src))
    if not args.in_place:
        if dst.exists() and not args.force:
            raise UserError(f'{dst} exists; give another -o OUT or --force to overwrite it')
    tmp = dst.with_name(f'.{dst.name}.repair-{os.getpid()}.tmp')
    try:
        rep = mcapio.repair(src, tmp)
        os.replace(tmp, dst)
    except mcapio.McapIOError as e:
        raise UserError(str(e)) from None
    except OSError as e:
        raise UserError(f'{dst}: cannot write ({e.strerror or e})') from None
    finally:
        if tmp.exists():
            tmp.unlink()
    span = ('' if rep.start_ns is None else
            f', log times {rep.start_ns / 1e9:.3f} to {rep.end_ns / 1e9:.3f} s')
    print(f'repaired {src} -> {dst}: kept {rep.messages} complete messages{span}')
    for topic, n in sorted(rep.counts.items()):
        print(f'  {topic}: {n}')
    cut = rep.size_in - rep.used_bytes
    if rep.complete:
        print('  the input was complete; rewritten on request (--force)')
    else:
        print(f'  the input ended without summary/footer: {rep.used_bytes} of {rep.size_in} bytes were whole records'
              + (f'; the cut tail of {cut} bytes gave {rep.from_cut_chunk} more complete messages (from the cut chunk), '
                 'the rest of it was dropped' if cut > 0 else ''))
    return 0
