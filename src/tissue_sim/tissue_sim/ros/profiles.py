"""Activation profiles a(t) in [0, 1] (ROS-free). Time t [s] is simulated time (``/clock``).

* ``paper``:      the paper's experiment: the hamstrings at ``level`` from ``start`` (for
                  ``duration`` s, 0 = to the end), every other muscle passive (0).
* ``step``:       0 before ``start``, ``level`` from ``start`` (for ``duration`` s, 0 = forever).
* ``ramp``:       0 before ``start``, linear to ``level`` over ``rise`` s, then held.
* ``ramp_hold``:  linear rise over ``rise`` s, hold ``hold`` s, linear fall over ``fall`` s to 0.
* ``sine``:       level * (1 - cos(2 pi f (t - start))) / 2 from ``start`` (0 before).
* ``timeline``:   per-muscle knots from YAML, linear between knots, held before the first and after the last::

                      muscles:                    # name (or group name, or 'all') -> [[t, a], ...]
                        biceps_femoris_long: [[0.0, 0.0], [0.5, 1.0], [3.0, 1.0], [3.5, 0.0]]
                        quadriceps: [[0.0, 0.1]]
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

PROFILES = ('paper', 'step', 'ramp', 'ramp_hold', 'sine', 'timeline', 'set')
PAPER_MUSCLES = ('biceps_femoris', 'semimembranosus', 'semitendinosus')


class ProfileError(ValueError):
    """A bad profile definition (message names the problem)."""


def shape(kind: str, t: float, *, level=1.0, start=0.0, duration=0.0, rise=1.0, hold=1.0, fall=1.0,
          frequency=0.5) -> float:
    """Value of a scalar profile at time t [s]."""
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
    raise ProfileError(f'unknown profile {kind!r}; expected one of {", ".join(PROFILES)}')


def resolve_muscles(selectors, names, groups=()) -> list[str]:
    """Muscle names selected by names, group names (e.g. 'hamstrings') or 'all'. Unknown -> error."""
    names, groups = list(names), list(groups) or [''] * len(names)
    out = []
    for sel in selectors:
        if sel == 'all':
            hit = names
        elif sel in names:
            hit = [sel]
        else:
            hit = [n for n, g in zip(names, groups) if g == sel]
            if not hit:
                hit = [n for n in names if n.startswith(sel + '_') or n.startswith(sel)]
        if not hit:
            raise ProfileError(f'no muscle or group {sel!r} in the model; muscles: {", ".join(names)}; '
                               f'groups: {", ".join(sorted(set(g for g in groups if g)))}')
        out += [h for h in hit if h not in out]
    return out


def paper_muscles(names, groups=()) -> list[str]:
    """The hamstrings of the paper's experiment: group 'hamstrings' if the model has it, else the
    muscles named biceps_femoris*, semimembranosus*, semitendinosus*."""
    groups = list(groups)
    hit = [n for n, g in zip(names, groups) if g == 'hamstrings']
    if not hit:
        hit = [n for n in names if n.startswith(PAPER_MUSCLES)]
    if not hit:
        raise ProfileError(f'the model has no hamstrings (group "hamstrings" or {", ".join(PAPER_MUSCLES)}); '
                           f'muscles: {", ".join(names)}')
    return hit


def load_timeline(path) -> dict:
    """YAML timeline -> {selector: (times (K,), values (K,))}; checks values and ordering."""
    import yaml
    p = Path(path)
    if not p.is_file():
        raise ProfileError(f'{p}: no such timeline file')
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise ProfileError(f'{p}: not valid YAML ({e})') from None
    if not isinstance(doc, dict) or not isinstance(doc.get('muscles'), dict) or not doc['muscles']:
        raise ProfileError(f'{p}: expected a mapping "muscles: {{name: [[t, a], ...]}}"')
    out = {}
    for name, knots in doc['muscles'].items():
        try:
            k = np.asarray(knots, dtype=float).reshape(-1, 2)
        except (TypeError, ValueError):
            raise ProfileError(f'{p}: muscle {name!r}: knots must be [[t, a], ...] numbers') from None
        if k.size == 0 or not np.all(np.isfinite(k)):
            raise ProfileError(f'{p}: muscle {name!r}: empty or non-finite knots')
        if np.any(np.diff(k[:, 0]) < 0):
            raise ProfileError(f'{p}: muscle {name!r}: knot times must not decrease')
        if np.any((k[:, 1] < 0) | (k[:, 1] > 1)):
            raise ProfileError(f'{p}: muscle {name!r}: activations must be in [0, 1]')
        out[str(name)] = (k[:, 0], k[:, 1])
    return out


def timeline_value(knots, t: float) -> float:
    """Linear between knots; the first value before the first knot, the last after the last."""
    times, values = knots
    return float(np.interp(t, times, values))


def parse_set(items) -> dict:
    """['name=0.5', ...] -> {name: 0.5}; values must be numbers in [0, 1]."""
    out = {}
    for it in items:
        if '=' not in it:
            raise ProfileError(f'--set {it!r}: expected name=value')
        k, v = it.split('=', 1)
        try:
            x = float(v)
        except ValueError:
            raise ProfileError(f'--set {it!r}: {v!r} is not a number') from None
        if not (0.0 <= x <= 1.0):
            raise ProfileError(f'--set {it!r}: activation must be in [0, 1]')
        out[k.strip()] = x
    return out
