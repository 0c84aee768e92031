"""Model builder: labelled slice stack + tissue table -> TissueModel (paper section 2, docs/method.md section 1).

Public API::

    from tissue_sim.core.builder import build_model, default_model
    tm, report = build_model('labels.nii.gz', 'tissues.yaml', slice_mm=25, muscle_rays=10)
    tm = default_model()          # the bundled lower limb, default ("paper") settings, cached on disk

See docs/builder.md for the method, the decisions and the Table-1 counting rules.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from tissue_sim.core import numba_cache

numba_cache.install()     # before any kernel of the package is compiled or loaded

from tissue_sim.core.build_settings import DEFAULTS, settings_with_defaults
from .assemble import build
from .io import LabelVolume, load_labels
from .quality import PAPER_TABLE1, TABLE1_LABELS, table1
from .table import load_joints, load_tissue_table

__all__ = ['build_model', 'default_model', 'default_inputs', 'DEFAULTS', 'PAPER_TABLE1', 'TABLE1_LABELS',
           'LabelVolume', 'load_labels', 'load_tissue_table', 'load_joints', 'table1']

BUILDER_VERSION = 20    # bump when the builder's output changes for the same input (invalidates the cache)


def build_model(labels, tissues, progress=None, **settings):
    """Build a TissueModel.

    labels: path (.nii/.nii.gz, .npz, folder of slice PNGs), a LabelVolume, or (array, affine).
    tissues: path of the tissue table (YAML) or an already-parsed dict (its ``joints`` a path or dict).
    settings: see ``DEFAULTS`` (slice_mm, slice_step, muscle_rays, fat_rays, share_mm, attach_mm, ...).
    progress: optional callable(step_name, fraction).
    Returns (TissueModel, report dict). Raises tissue_sim.errors.UserError on bad input.
    """
    if isinstance(labels, tuple):
        vol = load_labels(labels[0], labels[1])
    else:
        vol = load_labels(labels)
    table = load_tissue_table(tissues)
    return build(vol, table, settings, progress)


def default_inputs() -> tuple[Path, Path]:
    """(labels, tissues) of the bundled lower-limb anatomy (tissue_sim/data/lower_limb/).

    Uses ``tissue_sim.core.anatomy`` when it provides the paths, else the data folder directly.
    Raises FileNotFoundError when the bundled anatomy is not there.
    """
    lab = tis = None
    try:
        from tissue_sim.core import anatomy
        for a, b in (('LABELS', 'TISSUES'), ('LABELS_PATH', 'TISSUES_PATH'), ('labels_path', 'tissues_path')):
            la, ti = getattr(anatomy, a, None), getattr(anatomy, b, None)
            if la is not None and ti is not None:
                lab, tis = (la() if callable(la) else la), (ti() if callable(ti) else ti)
                break
    except ImportError:
        pass
    if lab is None:
        d = Path(__file__).resolve().parents[2] / 'data' / 'lower_limb'
        lab, tis = d / 'labels.nii.gz', d / 'tissues.yaml'
    lab, tis = Path(lab), Path(tis)
    for p in (lab, tis):
        if not p.exists():
            raise FileNotFoundError(f'bundled anatomy file {p} is missing')
    return lab, tis


def _cache_dir() -> Path:
    d = os.environ.get('TISSUE_SIM_CACHE')
    if d:
        return Path(d)
    home = Path.home() / '.cache' / 'tissue_sim'
    try:
        home.mkdir(parents=True, exist_ok=True)
        return home
    except OSError:
        return Path(tempfile.gettempdir()) / 'tissue_sim_cache'


def _input_hash(paths, settings) -> str:
    h = hashlib.sha256()
    h.update(json.dumps({'v': BUILDER_VERSION, 's': settings}, sort_keys=True, default=str).encode())
    for p in paths:
        p = Path(p)
        files = sorted(p.rglob('*')) if p.is_dir() else [p]
        for f in files:
            if f.is_file():
                h.update(f.name.encode())
                h.update(f.read_bytes())
    return h.hexdigest()[:16]


def default_model(refresh: bool = False, **settings):
    """The bundled anatomy's TissueModel built with default settings (or the given ones).

    Cached on disk (``$TISSUE_SIM_CACHE`` or ~/.cache/tissue_sim), keyed on the hash of the input
    files (labels, tissue table, joints file and bone meshes), the settings and the builder version.
    """
    from tissue_sim.core.model import ModelError, TissueModel
    lab, tis = default_inputs()
    s = settings_with_defaults(settings)
    hash_paths = [lab, tis.parent]
    key = _input_hash(hash_paths, s)
    cdir = _cache_dir()
    path = cdir / f'default_model_{key}.npz'
    if path.is_file() and not refresh:
        try:
            return TissueModel.load(path)
        except ModelError:
            pass
    tm, _ = build_model(lab, tis, **settings)
    try:
        cdir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f'.tmp{os.getpid()}.npz')
        tm.save(tmp)
        os.replace(tmp, path)
    except OSError:
        pass
    return tm


def parse_refinements(text: str) -> list[float]:
    """'1,3,6' -> [1.0, 3.0, 6.0]: refinements of the bundled limb (``refine`` >= 1) for the benchmarks;
    ValueError naming the text otherwise."""
    import math
    try:
        refs = [float(v) for v in text.split(',')]
    except ValueError:
        refs = []
    if not refs or any(not (math.isfinite(r) and r >= 1) for r in refs):
        raise ValueError(f'--refine {text!r}: expected numbers >= 1 separated by commas')
    return refs
