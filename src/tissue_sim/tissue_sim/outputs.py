"""Output files of the command-line tools: checked before any work, written all or nothing.

``check_outputs`` runs first (before any input is read): each named output must be a file name in
an existing, writable folder, not a folder itself, and no two options may name the same file.
``Staged`` then writes every output to a temporary file beside its target and moves them all into
place only when every one has been written, so a failure leaves no partial output and no earlier
file lost.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from tissue_sim.errors import UserError


def check_output(path, what: str) -> Path:
    """One output file: raise UserError naming the problem unless it can be written."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path('.')
    if p.is_dir():
        raise UserError(f'{p}: is a folder; give a file name for the {what}')
    if not folder.exists():
        raise UserError(f'{p}: cannot write the {what}: folder {folder} does not exist')
    if not folder.is_dir():
        raise UserError(f'{p}: cannot write the {what}: {folder} is not a folder')
    if p.exists() and not p.is_file():
        raise UserError(f'{p}: cannot write the {what}: not a regular file')
    try:            # a real write test (permission bits do not tell for root, read-only mounts, quotas)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f'.{p.name}.', suffix='.check'):
            pass
    except OSError as e:
        raise UserError(f'{p}: cannot write the {what}: folder {folder} is not writable ({e.strerror or e})') from None
    return p


def check_outputs(named: dict, inputs=()) -> dict:
    """{option: (path or None, what)} -> {option: Path or None}, every path checked, none twice and
    none an input file (``inputs``: paths read by the command)."""
    out, seen = {}, {}
    for p in inputs:
        if p is not None:
            seen[os.path.realpath(p)] = f'the input {p}'
    for opt, (path, what) in named.items():
        if path is None or path == '':
            out[opt] = None
            continue
        p = check_output(path, what)
        key = os.path.realpath(p)
        if key in seen:
            raise UserError(f'{p}: {seen[key]} and {opt} name the same file')
        seen[key] = opt
        out[opt] = p
    return out


class Staged:
    """Context manager: ``tmp = staged.path(target)`` gives a temporary file beside ``target`` to
    write; on a clean exit every temporary file replaces its target, on an exception all are removed."""

    def __init__(self):
        self._pairs = []

    def path(self, target) -> Path:
        target = Path(target)
        folder = target.parent if str(target.parent) else Path('.')
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f'.{target.stem}.', suffix=''.join(target.suffixes) or '.tmp')
        os.close(fd)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)         # the mode an ordinary new file gets, not mkstemp's 0600
        self._pairs.append((Path(tmp), target))
        return Path(tmp)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                for tmp, target in self._pairs:
                    os.replace(tmp, target)
            except OSError as e:
                self._cleanup()
                raise UserError(f'{target}: cannot write ({e.strerror or e})') from None
        else:
            self._cleanup()
        return False

    def _cleanup(self):
        for tmp, _ in self._pairs:
            try:
                tmp.unlink()
            except OSError:
                pass
