"""What a run starts from (ROS-free): the model and the solver parameter set, named as a user names
them on the command line (``tissue-sim simulate``) or as node parameters (``simulator``)."""
from __future__ import annotations

import dataclasses

PARAM_SETS = ('paper', 'physical')


def read_yaml(path, what: str, error=ValueError):
    """The YAML document of a user's file (parameter set, activation timeline, ...); ``error`` (a
    ValueError subclass) with one line naming the file when it is missing or not valid YAML."""
    import yaml
    from pathlib import Path
    p = Path(path)
    if not p.is_file():
        raise error(f'{p}: no such {what} file')
    try:
        return yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise error(f'{p}: not valid YAML ({e})') from None


def load_model(spec: str | None = None):
    """The TissueModel named by ``spec``: a model file (.npz from ``tissue-sim build-model``);
    ``None`` or ``''`` = the bundled lower limb; ``phantom:knee`` = the solver's analytic knee
    phantom. ModelError (a ValueError) naming the problem otherwise."""
    from tissue_sim.core.model import ModelError, TissueModel
    if not spec:
        from tissue_sim.core import builder
        try:
            return builder.default_model()
        except FileNotFoundError as e:
            raise ModelError(f'the bundled anatomy is not available ({e}); give a model file') from None
    if spec.startswith('phantom:'):
        from tissue_sim.core.solver import phantom
        kind = spec.split(':', 1)[1]
        if kind != 'knee':
            raise ModelError(f'unknown phantom {kind!r} (knee)')
        return phantom.knee(n_gaps=12)
    return TissueModel.load(spec)


def load_params(spec: str | None = 'paper', dt: float | None = None, overrides=()):
    """The solver Params named by ``spec``: ``paper`` (Inaba et al. Table 2; also ``None``/``''``),
    ``physical`` (SI), or a YAML parameter file; then ``overrides``, NAME=VALUE changes of its fields (a command's
    repeatable --set; each VALUE read as YAML); ``dt`` > 0 replaces the set's step [s].
    ValueError naming the problem otherwise."""
    from tissue_sim.core.solver import Params
    from tissue_sim.core.solver.params import parse_assignments
    if not spec or spec == 'paper':
        p = Params.paper()
    elif spec == 'physical':
        p = Params.physical()
    else:
        p = Params.from_yaml(spec)
    if overrides:
        p = Params.from_dict({**p.to_dict(), **parse_assignments(overrides, 'solver parameters')})
    if dt:
        p = dataclasses.replace(p, dt=float(dt)).validate()
    return p


def implicit_hint(params) -> str:
    """What a divergence message adds under the explicit schemes ('' under the implicit one): the implicit integrator,
    stable at the set's own step on finer models (docs/solver.md "Implicit integrator"), and how to select it."""
    if params.integrator == 'implicit':
        return ''
    return ('; the implicit integrator is stable at the set\'s own step on finer models: --set integrator=implicit '
            '--set substeps=1 (tissue-sim simulate), or integrator: implicit and substeps: 1 in a parameter file '
            '(docs/solver.md "Implicit integrator")')
