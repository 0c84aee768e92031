"""Each merged muscle's normalised fibre length in the bundled limb's rest pose, from the OpenSim source model.

The bundled limb's rest pose is the source model's pose with every coordinate 0 (hip 0, knee 0, ankle 0:
osim.load's pose). There the OpenSim engine (``opensim`` package, requirements/validation.txt) gives each
muscle's path length L_MT, wrapping included (the gastrocnemii wrap over the femoral condyles at full
extension: their straight-line path points are 13-19 mm shorter). With the source model's rigid tendons
(DeGrooteFregly2016 muscles, ignore_tendon_compliance) the fibre length follows from the tendon slack length
L_TS and the constant fibre height L_opt sin(alpha_opt) (the pennation model keeps it constant):

    l = sqrt((L_MT - L_TS)^2 + (L_opt sin alpha_opt)^2) / L_opt,

i.e. (L_MT - L_TS) / cos(alpha) / L_opt. A muscle merged from several OpenSim parts (opensim_parts) gets the
Fmax-weighted mean of its parts' values (as its Fmax is their sum and its optimal fibre length their
volume-weighted mean). The solver starts the muscle's fibre length there (docs/solver.md "Force-length").
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[2] / 'src' / 'tissue_sim'


def _opensim():
    """The opensim module, imported without its side effects on this process's environment (one place:
    tissue_sim.core.validation)."""
    if str(SRC) not in sys.path:
        sys.path.insert(0, str(SRC))
    from tissue_sim.core.validation import _environment_kept, _import_opensim
    try:
        return _import_opensim(), _environment_kept
    except ImportError:
        raise SystemExit('error: the rest fibre lengths need the opensim package '
                         '(pip install --no-deps -r requirements/validation.txt)') from None


def normalised_fibre_length(path_length, tendon_slack, optimal, pennation):
    """Rigid-tendon normalised fibre length: sqrt((L_MT - L_TS)^2 + (L_opt sin a_opt)^2) / L_opt (a path shorter
    than the tendon: the fibre at its height alone, the pennation model's floor)."""
    h = optimal * math.sin(pennation)
    return math.sqrt(max(path_length - tendon_slack, 0.0) ** 2 + h * h) / optimal


def rest_pose(osm, osim_path):
    """(model, state) of the source model with every unlocked coordinate 0 (the bundled limb's rest pose), assembled
    and realized to position; call inside _opensim()'s environment guard."""
    osm.Logger.setLevelString('warn')
    model = osm.Model(str(osim_path))
    state = model.initSystem()
    for c in model.getCoordinateSet():
        if not c.get_locked():
            c.setValue(state, 0.0, False)
    model.assemble(state)
    model.realizePosition(state)
    return model, state


def part_rest_fibre_lengths(osim_path) -> dict:
    """{OpenSim muscle name without '_r': (normalised rest fibre length, Fmax [N])} of the right leg's muscles at
    every coordinate 0."""
    osm, kept = _opensim()
    with kept():
        model, state = rest_pose(osm, osim_path)
        out = {}
        muscles = model.getMuscles()
        for i in range(muscles.getSize()):
            mu = muscles.get(i)
            if mu.getName().endswith('_r'):
                out[mu.getName()[:-2]] = (normalised_fibre_length(
                    mu.getGeometryPath().getLength(state), mu.getTendonSlackLength(), mu.getOptimalFiberLength(),
                    mu.getPennationAngleAtOptimalFiberLength()), mu.getMaxIsometricForce())
    return out


def add_rest_fibre_lengths(table, osim_path):
    """Give each entry of generate.muscle_table its 'rest_fibre_length' (normalised, rounded to 3 decimals): the
    Fmax-weighted mean over its OpenSim parts."""
    parts = part_rest_fibre_lengths(osim_path)
    for t in table:
        ls = [parts[p] for p in t['parts']]
        t['rest_fibre_length'] = round(sum(l * f for l, f in ls) / sum(f for _, f in ls), 3)
    return table
