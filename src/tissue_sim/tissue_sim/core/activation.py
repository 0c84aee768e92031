"""Muscle activations (ROS-free): names and groups, timelines, profiles, validation of a command.

The one place that turns what a user writes (a muscle name, a group, ``all``, a timeline file, a
profile) into activations a(t) in [0, 1] per muscle of a model. ``tissue-sim simulate``, the
solver's ``simulate()``, the ``activation`` node and the ``simulator`` node all go through it.

**Selectors.** A selector names muscles of a model: ``all``; a muscle name (``semitendinosus``);
a group of ``TissueModel.muscle_groups`` (``hamstrings``, ``quadriceps``); or a name prefix that
ends at a word boundary (``biceps_femoris`` selects ``biceps_femoris_long_head`` and
``biceps_femoris_short_head``). Anything else is an error naming the model's muscles and groups.

**Combination rule.** When several entries of one activation description select the same muscle,
the most specific entry sets it; they never add. From least to most specific: ``all``, a group, a
name prefix (a longer prefix is more specific), a muscle name. Between equally specific entries the
later one wins. So ``{all: 0.3, hamstrings: 0.5}`` gives the hamstrings 0.5 and every other muscle
0.3, in whatever order the entries are written.

**Timelines** (``muscles: {selector: [[t, a], ...]}`` in YAML, or a dict of the same): linear
between knots, the first value before the first knot, the last after the last; a bare number is a
constant.

**Profiles** (the ``activation`` node): ``paper`` (the paper's experiment: the hamstrings at
``level``, every other muscle passive), ``step``, ``ramp``, ``ramp_hold``, ``sine``, ``timeline``,
``set`` (see :func:`shape`), and the named motions. Without a muscle selection a shape profile
drives the hamstrings of the model: its group ``hamstrings``, else the muscles named like the
paper's biceps femoris, semimembranosus and semitendinosus.

**Named motions** (:data:`MOTIONS`): timelines of muscle groups, every other muscle passive,
defined here once for the ``activation`` node (``--profile NAME``), ``tissue-sim simulate --motion
NAME`` and ``make demo MOTION=NAME``: ``knee_flexion``, ``knee_extension``, ``kick``,
``heel_raise``, ``ankle_pump`` (:func:`motion_timeline`; docs/ros.md lists them with the angles
they reach on the bundled limb).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

SHAPES = ('paper', 'step', 'ramp', 'ramp_hold', 'sine', 'timeline', 'set')
HAMSTRINGS = 'hamstrings'
PAPER_MUSCLES = ('biceps_femoris', 'semimembranosus', 'semitendinosus')
REASONS = ('nan', 'inf', 'out_of_range', 'unknown_muscle', 'length_mismatch', 'duplicate_muscle')

# specificity of a selector (higher overrides lower)
ALL, GROUP, PREFIX, MUSCLE = 0, 1, 2, 3


class ActivationError(ValueError):
    """A bad activation description (the message names the problem)."""


class UnknownMuscle(ActivationError, KeyError):
    """A selector that names no muscle, group or name prefix of the model."""

    def __str__(self):                  # a plain message, not KeyError's quoted repr
        return str(self.args[0]) if self.args else ''


class Muscles:
    """The muscle names and groups of a model, and the one resolver of selectors."""

    def __init__(self, names, groups=()):
        self.names = [str(n) for n in names]
        groups = [str(g) for g in groups]
        self.groups = groups if len(groups) == len(self.names) else [''] * len(self.names)

    @classmethod
    def of(cls, model) -> 'Muscles':
        """From a TissueModel, a solver SimModel (its ``tissue``) or a decoded topology."""
        model = getattr(model, 'tissue', model)
        return cls(model.muscle_names, getattr(model, 'muscle_groups', ()))

    def __len__(self):
        return len(self.names)

    def _unknown(self, selector, what='muscle or group'):
        groups = sorted(set(g for g in self.groups if g))
        return UnknownMuscle(f'unknown {what} {selector!r}; the model has muscles {", ".join(self.names)}'
                             + (f' and groups {", ".join(groups)}' if groups else ''))

    def index(self, name: str) -> int:
        """Index of a muscle name (exactly); UnknownMuscle (a KeyError) otherwise."""
        try:
            return self.names.index(name)
        except ValueError:
            raise self._unknown(name, 'muscle') from None

    def select(self, selector: str) -> tuple[list[int], tuple]:
        """(indices, specificity) of one selector (see the module's documentation)."""
        if selector == 'all':
            return list(range(len(self.names))), (ALL, 0)
        if selector in self.names:
            return [self.names.index(selector)], (MUSCLE, 0)
        hit = [i for i, g in enumerate(self.groups) if g == selector]
        if hit:
            return hit, (GROUP, 0)
        hit = [i for i, n in enumerate(self.names) if n.startswith(selector + '_')]
        if hit:
            return hit, (PREFIX, len(selector))
        raise self._unknown(selector)

    def indices(self, selector: str) -> list[int]:
        return self.select(selector)[0]

    def resolve(self, selectors) -> list[str]:
        """Muscle names selected by any of ``selectors``, in the model's order of first selection."""
        out = []
        for sel in selectors:
            out += [self.names[i] for i in self.indices(sel) if self.names[i] not in out]
        return out

    def hamstrings(self) -> list[str]:
        """The muscles of the paper's experiment: group 'hamstrings', else the muscles named (or
        prefixed) biceps_femoris, semimembranosus, semitendinosus."""
        hit = [n for n, g in zip(self.names, self.groups) if g == HAMSTRINGS]
        if not hit:
            hit = [n for n in self.names if any(n == p or n.startswith(p + '_') for p in PAPER_MUSCLES)]
        if not hit:
            raise ActivationError(f'the model has no hamstrings (group "{HAMSTRINGS}" or {", ".join(PAPER_MUSCLES)}); '
                                  f'muscles: {", ".join(self.names)}')
        return hit

    def check(self, names, values):
        """Validate an activation command (a MuscleActivation message's names and values).

        Returns (indices, values, None) to apply, or (None, reason, detail) for a command rejected
        whole, reason one of REASONS."""
        names, values = list(names), list(values)
        if len(names) != len(values):
            return None, 'length_mismatch', f'{len(names)} names but {len(values)} activations'
        for v in values:
            if math.isnan(v):
                return None, 'nan', 'activation is NaN'
        for v in values:
            if math.isinf(v):
                return None, 'inf', 'activation is infinite'
        for n, v in zip(names, values):
            if not (0.0 <= v <= 1.0):
                return None, 'out_of_range', f'{n}: activation {v} outside [0, 1]'
        idx = []
        for n in names:
            if n not in self.names:
                return None, 'unknown_muscle', f'unknown muscle {n!r}'
            idx.append(self.names.index(n))
        if len(set(idx)) != len(idx):
            return None, 'duplicate_muscle', 'a muscle is named twice'
        return idx, [float(v) for v in values], None


# ----------------------------------------------------------------------------- combination
class Activations:
    """Activation functions of time for the muscles that entries select, combined by the rule.

    ``entries``: (selector, fn) pairs in order, fn: t [s] -> activation. ``muscles``: a
    :class:`Muscles`, or None to take every selector literally as one muscle name (a node that does
    not know the model yet). ``names``: the muscles set, in the model's order; ``values(t)`` their
    activations; ``full(t)`` the (M,) vector of the model, 0 for the muscles no entry selects."""

    def __init__(self, entries, muscles: Muscles | None):
        won = {}                                  # muscle index -> (specificity, entry number)
        literal = []
        for k, (sel, _) in enumerate(entries):
            if muscles is None:
                if sel not in literal:
                    literal.append(sel)
                idx, spec = [literal.index(sel)], (MUSCLE, 0)
            else:
                idx, spec = muscles.select(sel)
            for i in idx:
                if i not in won or spec >= won[i][0]:
                    won[i] = (spec, k)
        all_names = literal if muscles is None else muscles.names
        self.n_model = len(all_names)
        self.indices = np.array(sorted(won), dtype=np.int64)
        self.names = [all_names[i] for i in self.indices]
        pos = {i: p for p, i in enumerate(self.indices)}
        # one evaluation per entry: the positions (in names) and model indices it sets
        self._parts = []
        for k, (_, fn) in enumerate(entries):
            mine = [i for i in self.indices if won[i][1] == k]
            if mine:
                self._parts.append((fn, np.array([pos[i] for i in mine], np.int64), np.array(mine, np.int64)))

    def values(self, t: float) -> np.ndarray:
        out = np.zeros(len(self.names))
        for fn, p, _ in self._parts:
            out[p] = fn(t)
        return np.clip(out, 0.0, 1.0)

    def full(self, t: float) -> np.ndarray:
        out = np.zeros(self.n_model)
        for fn, _, i in self._parts:
            out[i] = fn(t)
        return np.clip(out, 0.0, 1.0)


def knots(name, pts, source='timeline') -> tuple[np.ndarray, np.ndarray]:
    """Checked (times, values) of a timeline entry: [[t, a], ...] or a bare number (a constant)."""
    if np.isscalar(pts):
        pts = [(0.0, pts)]
    try:
        k = np.asarray(pts, dtype=float).reshape(-1, 2)
    except (TypeError, ValueError):
        raise ActivationError(f'{source}: muscle {name!r}: knots must be [[t, a], ...] numbers') from None
    if k.size == 0 or not np.all(np.isfinite(k)):
        raise ActivationError(f'{source}: muscle {name!r}: empty or non-finite knots')
    if np.any(np.diff(k[:, 0]) < 0):
        raise ActivationError(f'{source}: muscle {name!r}: knot times must not decrease')
    if np.any((k[:, 1] < 0) | (k[:, 1] > 1)):
        raise ActivationError(f'{source}: muscle {name!r}: activations must be in [0, 1]')
    return k[:, 0], k[:, 1]


def timeline_value(k, t: float) -> float:
    """Linear between knots; the first value before the first knot, the last after the last."""
    times, values = k
    return float(np.interp(t, times, values))


def _knot_fn(k):
    times, values = k
    if len(times) == 1:
        v = float(values[0])
        return lambda t: v
    return lambda t: float(np.interp(t, times, values))


def timeline_entries(timeline: dict, source='timeline') -> list:
    """{selector: knots or number} -> [(selector, fn)], each checked."""
    return [(str(sel), _knot_fn(knots(sel, pts, source))) for sel, pts in timeline.items()]


def load_timeline(path) -> dict:
    """YAML timeline file -> {selector: (times (K,), values (K,))}; checks values and ordering."""
    from tissue_sim.core.load import read_yaml
    p = Path(path)
    doc = read_yaml(p, 'timeline', ActivationError)
    if not isinstance(doc, dict) or not isinstance(doc.get('muscles'), dict) or not doc['muscles']:
        raise ActivationError(f'{p}: expected a mapping "muscles: {{name: [[t, a], ...]}}"')
    return {str(name): knots(name, pts, str(p)) for name, pts in doc['muscles'].items()}


def timeline_function(sim, timeline) -> Callable[[float], np.ndarray]:
    """Activation timeline -> function t [s] -> activation (M,) of the solver model ``sim``.

    ``timeline`` is None (all zero), a callable t -> (M,) array, a constant (M,) array, or a dict
    {selector: [(t, value), ...] or value} combined by the module's rule (the most specific entry
    sets a muscle); muscles no entry selects are 0."""
    M = sim.n_muscles
    if timeline is None:
        return lambda t: np.zeros(M)
    if callable(timeline):
        def fn(t):
            a = np.asarray(timeline(t), np.float64)
            if a.shape != (M,) or not np.all(np.isfinite(a)) or np.any((a < 0) | (a > 1)):
                raise ValueError(f'timeline({t}) must give {M} finite activations in [0, 1]')
            return a
        return fn
    if isinstance(timeline, dict):
        return Activations(timeline_entries(timeline), Muscles.of(sim)).full
    a = np.asarray(timeline, np.float64)
    if a.shape != (M,) or np.any((a < 0) | (a > 1)):
        raise ValueError(f'a constant activation must be {M} values in [0, 1]')
    return lambda t: a


# ----------------------------------------------------------------------------- named motions
class Motion(NamedTuple):
    """A named motion: knots [(t [s], a), ...] per selector (linear between, held after the last),
    every muscle no selector names passive (0). ``joint``: the joint it is about (the analysis finds
    the same from a recorded run: the joint that moves most, analysis.plots.main_joint); ``duration``: simulated time [s] that shows the whole motion."""
    description: str
    joint: str
    duration: float
    muscles: dict


def _alternate(first: str, second: str, levels: tuple, period: float, cycles: int, on: float, edge: float) -> dict:
    """Knots of two selectors that take turns: ``first`` from the start of each period, ``second``
    from its middle, at ``levels`` (first's, second's) for ``on`` s with ``edge``-s linear rises and falls."""
    out = {first: [(0.0, 0.0)], second: [(0.0, 0.0)]}
    for c in range(cycles):
        for sel, t0, level in ((first, c * period, levels[0]), (second, c * period + period / 2, levels[1])):
            out[sel] += [(t0, 0.0), (t0 + edge, level), (t0 + edge + on, level), (t0 + 2 * edge + on, 0.0)]
    return out


# Activations: the physical parameter set on the bundled limb (the paper's set moves the knee only a few
# degrees); levels kept where the activated muscles hold their volume (tests/test_motions.py, docs/ros.md).
MOTIONS = {
    'knee_flexion': Motion(
        "the paper's experiment: the hamstrings contract (ramped 0 -> 1 over 1 s, then held), every other "
        'muscle passive: the knee flexes to its 120-deg stop', 'knee_r', 2.0,
        {'hamstrings': [(0.0, 0.0), (1.0, 1.0)]}),
    'knee_extension': Motion(
        'the quadriceps extend the knee from flexion: the hamstrings (0.6) flex it first, from 0.9 s they '
        'relax while the quadriceps ramp to 0.5 (over 0.5 s) and extend it to its 0-deg stop',
        'knee_r', 2.5,
        {'hamstrings': [(0.0, 0.0), (0.3, 0.6), (0.9, 0.6), (1.4, 0.0)],
         'quadriceps': [(0.0, 0.0), (0.9, 0.0), (1.4, 0.5)]}),
    'kick': Motion(
        'a kick: a wind-up flexion (hamstrings 0 -> 0.8 over 0.4 s, held to 0.7 s), then a fast extension '
        '(the hamstrings off and the quadriceps to 0.6 within 50 ms, held to 1.1 s, relaxed by 1.3 s)',
        'knee_r', 1.6,
        {'hamstrings': [(0.0, 0.0), (0.4, 0.8), (0.7, 0.8), (0.75, 0.0)],
         'quadriceps': [(0.0, 0.0), (0.7, 0.0), (0.75, 0.6), (1.1, 0.6), (1.3, 0.0)]}),
    'heel_raise': Motion(
        'a heel raise: the triceps surae (gastrocnemii and soleus) ramp to 0.5 over 0.5 s and hold: the '
        'ankle plantarflexes; the quadriceps ramp to 0.3 with them and hold the knee extended, as standing '
        '(the gastrocnemii cross the knee: alone they flex it ~50 deg)', 'ankle_r', 1.5,
        {'triceps_surae': [(0.0, 0.0), (0.5, 0.5)], 'quadriceps': [(0.0, 0.0), (0.5, 0.3)]}),
    'ankle_pump': Motion(
        'an ankle pump: tibialis anterior (0.8) dorsiflexes the ankle, then the triceps surae (0.5) '
        'plantarflex it, alternating (0.7 s each, a 1.5-s period, two cycles)', 'ankle_r', 3.0,
        _alternate('tibialis_anterior', 'triceps_surae', (0.8, 0.5), 1.5, 2, 0.6, 0.05)),
}
PROFILES = SHAPES + tuple(MOTIONS)


def motion(name: str) -> Motion:
    """The named motion; ActivationError naming the motions otherwise."""
    if name not in MOTIONS:
        raise ActivationError(f'unknown motion {name!r}; expected one of {", ".join(MOTIONS)}')
    return MOTIONS[name]


def motion_timeline(name: str, level: float = 1.0, start: float = 0.0) -> dict:
    """The timeline {selector: [(t, a), ...], 'all': 0.0} of a named motion, its activations scaled
    by ``level`` and its times shifted by ``start`` [s] (what timeline_function and the node take)."""
    if not (0.0 <= level <= 1.0) or not math.isfinite(start):
        raise ActivationError(f'motion {name}: level must be in [0, 1] and start finite')
    tl = {'all': 0.0}
    for sel, pts in motion(name).muscles.items():
        tl[sel] = [(t + start, a * level) for t, a in pts]
    return tl


# ----------------------------------------------------------------------------- profiles
def shape(kind: str, t: float, *, level=1.0, start=0.0, duration=0.0, rise=1.0, hold=1.0, fall=1.0,
          frequency=0.5) -> float:
    """Value of a scalar profile at time t [s].

    ``step``/``paper``: 0 before ``start``, ``level`` from ``start`` (for ``duration`` s, 0 = forever);
    ``ramp``: linear to ``level`` over ``rise`` s, then held; ``ramp_hold``: rise over ``rise`` s, hold
    ``hold`` s, fall over ``fall`` s to 0; ``sine``: level (1 - cos(2 pi f (t - start))) / 2."""
    if t < start:
        return 0.0
    u = t - start
    if kind in ('step', 'paper'):
        return level if (duration <= 0 or u < duration) else 0.0
    if kind == 'ramp':
        return level * min(1.0, u / rise) if rise > 0 else level
    if kind == 'ramp_hold':
        if u < rise:
            return level * u / rise
        if u < rise + hold:
            return level
        if fall > 0 and u < rise + hold + fall:
            return level * (1.0 - (u - rise - hold) / fall)
        return 0.0
    if kind == 'sine':
        return level * 0.5 * (1.0 - math.cos(2.0 * math.pi * frequency * u))
    raise ActivationError(f'unknown profile {kind!r}; expected one of {", ".join(SHAPES)}')


def parse_set(items) -> dict:
    """['name=0.5', ...] -> {name: 0.5}; values must be numbers in [0, 1]."""
    out = {}
    for it in items:
        if '=' not in it:
            raise ActivationError(f'--set {it!r}: expected name=value')
        k, v = it.split('=', 1)
        try:
            x = float(v)
        except ValueError:
            raise ActivationError(f'--set {it!r}: {v!r} is not a number') from None
        if not (0.0 <= x <= 1.0):
            raise ActivationError(f'--set {it!r}: activation must be in [0, 1]')
        out[k.strip()] = x
    return out


def profile_entries(profile: str, muscles: Muscles | None, *, selectors=None, others=None, timeline=None,
                    set_values=None, **shape_kw) -> list:
    """The (selector, fn) entries of a profile (what the ``activation`` node publishes).

    ``selectors``: the muscles a shape profile drives (default: :meth:`Muscles.hamstrings`, which
    needs ``muscles``); ``others``: a constant for every muscle not selected (an ``all`` entry, the
    least specific); ``timeline``: {selector: knots} for ``timeline``; ``set_values``: for ``set``.
    A named motion (:data:`MOTIONS`) takes ``level`` (scales its activations) and ``start`` (shifts
    it) of the keywords; its other muscles are passive unless ``others`` says otherwise."""
    entries = [] if others is None else [('all', lambda t, v=float(others): v)]
    if profile == 'set':
        return entries + [(n, lambda t, v=float(v): v) for n, v in set_values.items()]
    if profile == 'timeline':
        return entries + timeline_entries(timeline)
    if profile in MOTIONS:
        if selectors:
            raise ActivationError(f'motion {profile}: its muscles are part of it (no muscle selection)')
        tl = motion_timeline(profile, shape_kw.get('level', 1.0), shape_kw.get('start', 0.0))
        if others is not None:
            tl['all'] = float(others)
        return timeline_entries(tl, f'motion {profile}')
    if profile not in PROFILES:
        raise ActivationError(f'unknown profile {profile!r}; expected one of {", ".join(PROFILES)}')
    shape(profile, 0.0, **shape_kw)           # checks the keywords
    if selectors is None:
        if muscles is None:
            raise ActivationError('the default muscles (the hamstrings) need the model\'s muscle names')
        selectors = muscles.hamstrings()
    return entries + [(s, lambda t, kind=profile: shape(kind, t, **shape_kw)) for s in selectors]
