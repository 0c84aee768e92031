"""Each muscle's normalised fibre length in the rest pose (docs/solver.md "Force-length", docs/FORMATS.md
rest_fibre_length): the anatomy generator's values against an independent OpenSim evaluation of the source model, the
tissue table's field carried into the model (1.0 where a table has none), saved and loaded, used by the solver."""
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from phantoms import make_phantom
from tissue_sim.core import model as M, solver
from tissue_sim.core.builder import build_model
from tissue_sim.core.solver import muscle as MU
from tissue_sim.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / 'src/tissue_sim/tissue_sim/data/lower_limb/tissues.yaml'
P = {'slice_mm': 25.0, 'muscle_rays': 10, 'min_area_mm2': 20.0, 'sections': 'rays'}


def _bundled_labels():
    return {e['name']: e for e in yaml.safe_load(BUNDLED.read_text())['labels'].values() if e['tissue'] == 'muscle'}


@pytest.mark.slow
def test_generator_values_match_opensim_normalised_fibre_length():
    """The generator's rest fibre length (path length and the rigid-tendon pennation formula, tools/anatomy/fibres.py)
    equals the normalised fibre length OpenSim's own DeGrooteFregly2016 muscle reports after equilibrating at every
    coordinate 0, for a straight-path muscle (biceps femoris long head), a wrapping one (semimembranosus, over the
    condyles) and a merged one (gluteus maximus: the Fmax-weighted mean of glmax1-3); the committed tissues.yaml holds
    them (3 decimals)."""
    for pkg in ('opensim', 'Pose2Sim'):
        if importlib.util.find_spec(pkg) is None:
            pytest.skip(f'{pkg} not installed (make anatomy-deps validation-deps)')
    from tissue_sim.core import validation as V
    sys.path.insert(0, str(ROOT / 'tools' / 'anatomy'))
    import fibres
    path = V.source_model_path()
    gen = fibres.part_rest_fibre_lengths(path)
    osim = V._import_opensim()
    with V._environment_kept():
        osim.Logger.setLevelString('warn')
        model = osim.Model(str(path))
        state = model.initSystem()
        for c in model.getCoordinateSet():
            if not c.get_locked():
                c.setValue(state, 0.0, False)
        model.assemble(state)
        ms = model.getMuscles()
        for i in range(ms.getSize()):
            ms.get(i).setActivation(state, 0.5)
        model.equilibrateMuscles(state)
        model.realizeDynamics(state)
        ref = {n: (ms.get(n + '_r').getNormalizedFiberLength(state), ms.get(n + '_r').getMaxIsometricForce())
               for n in ('bflh', 'semimem', 'glmax1', 'glmax2', 'glmax3')}
    for n in ('bflh', 'semimem', 'glmax1'):
        assert gen[n][0] == pytest.approx(ref[n][0], abs=1e-6), n
    assert ref['bflh'][0] == pytest.approx(0.738, abs=0.01) and ref['semimem'][0] == pytest.approx(0.692, abs=0.01)
    table = _bundled_labels()
    glmax = sum(ref[p][0] * ref[p][1] for p in ('glmax1', 'glmax2', 'glmax3')) / sum(ref[p][1] for p in ('glmax1', 'glmax2', 'glmax3'))
    for name, value in (('biceps_femoris_long_head', ref['bflh'][0]), ('semimembranosus', ref['semimem'][0]),
                        ('gluteus_maximus', glmax)):
        assert table[name]['rest_fibre_length'] == pytest.approx(value, abs=6e-4), name


def test_bundled_table_and_model_carry_the_rest_fibre_lengths(default_tm):
    table = _bundled_labels()
    assert all('rest_fibre_length' in e for e in table.values())
    for m, name in enumerate(default_tm.muscle_names):
        assert default_tm.muscle_rest_fibre_length[m] == table[name]['rest_fibre_length'], name
    # the source model's knee flexors start short of their optimal length at full extension
    assert default_tm.muscle_rest_fibre_length[default_tm.muscle_index('semimembranosus')] < 0.8
    sim = solver.compile_model(default_tm, solver.Params.physical(rest_fibre_length=0.0))     # each muscle's own
    assert np.array_equal(MU.rest_fibre_lengths(sim), default_tm.muscle_rest_fibre_length)
    # the observed fibre length comes from the muscle paths (muscle_paths.yaml, the same source-model paths fitted by
    # polynomials): at rest it is the table's to the fit error and the table's rounding (measured max 0.0045)
    assert np.allclose(solver.observe(sim, solver.make_state(sim))['fibre_lengths'], default_tm.muscle_rest_fibre_length,
                       rtol=0, atol=6e-3)
    assert solver.Params().rest_fibre_length == 0.0
    assert solver.Params.physical().rest_fibre_length == 0.0                # the physical set: each muscle's own
    over = solver.compile_model(default_tm, solver.Params.physical(rest_fibre_length=1.0))     # an override
    assert np.all(MU.rest_fibre_lengths(over) == 1.0)


def test_table_field_into_the_model_and_its_default(tmp_path):
    lab, aff, tab = make_phantom('column')
    assert 'rest_fibre_length' not in tab['labels'][11]
    tm, _ = build_model((lab, aff), tab, **P)                         # a table without the field: 1.0
    assert np.all(tm.muscle_rest_fibre_length == 1.0)
    tab['labels'][11]['rest_fibre_length'] = 0.7
    tm, _ = build_model((lab, aff), tab, **P)
    assert tm.muscle_rest_fibre_length[tm.muscle_index('flexor')] == 0.7
    assert tm.muscle_rest_fibre_length[tm.muscle_index('extensor')] == 1.0
    again = M.TissueModel.load(tm.save(tmp_path / 'm.npz'))
    assert np.array_equal(again.muscle_rest_fibre_length, tm.muscle_rest_fibre_length)
    # a model file written before the field existed loads with 1.0
    arrays = {k: v for k, v in np.load(tmp_path / 'm.npz').items() if k != 'muscle_rest_fibre_length'}
    np.savez_compressed(tmp_path / 'old.npz', **arrays)
    assert np.all(M.TissueModel.load(tmp_path / 'old.npz').muscle_rest_fibre_length == 1.0)
    tab['labels'][11]['rest_fibre_length'] = 3.0
    with pytest.raises(UserError, match='rest_fibre_length must be in'):
        build_model((lab, aff), tab, **P)
