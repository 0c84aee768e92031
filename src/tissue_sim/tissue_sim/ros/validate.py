"""Validation of incoming MuscleActivation messages (ROS-free). A bad message is rejected whole
and counted by reason; the simulation is not touched."""
from __future__ import annotations

import math

REASONS = ('nan', 'inf', 'out_of_range', 'unknown_muscle', 'length_mismatch', 'duplicate_muscle')


def check_activation(names, values, index_of: dict):
    """(indices, values) to apply, or (None, reason, detail) for a rejected message.

    names: the message's muscle_names; values: its activations; index_of: muscle name -> index.
    """
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
        i = index_of.get(n)
        if i is None:
            return None, 'unknown_muscle', f'unknown muscle {n!r}'
        idx.append(i)
    if len(set(idx)) != len(idx):
        return None, 'duplicate_muscle', 'a muscle is named twice'
    return idx, [float(v) for v in values], None
