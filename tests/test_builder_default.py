"""The bundled lower limb with default ("paper") settings: a model of the paper's size (Table 1)."""
import json

import numpy as np
import pytest

from tissue_sim.core import builder
from tissue_sim.core import model as M

try:
    builder.default_inputs()
    HAVE_ANATOMY = True
except FileNotFoundError:
    HAVE_ANATOMY = False

pytestmark = pytest.mark.skipif(not HAVE_ANATOMY, reason='bundled anatomy (data/lower_limb) not present')


@pytest.fixture(scope='module')
def default(tmp_path_factory):
    import os
    d = tmp_path_factory.mktemp('cache')
    old = os.environ.get('TISSUE_SIM_CACHE')
    os.environ['TISSUE_SIM_CACHE'] = str(d)
    try:
        tm = builder.default_model()
        again = builder.default_model()
    finally:
        if old is None:
            os.environ.pop('TISSUE_SIM_CACHE')
        else:
            os.environ['TISSUE_SIM_CACHE'] = old
    return tm, again, d


def test_paper_size(default):
    tm, _, _ = default
    t = builder.table1(tm)
    assert t['bones'] == 6
    for k in ('muscles', 'muscle_cells', 'muscle_vertices', 'fat_cells', 'fat_vertices', 'shared_vertices'):
        p = builder.PAPER_TABLE1[k]
        assert 0.75 * p <= t[k] <= 1.25 * p, (k, t[k], p)


def test_valid_cells_and_attachment(default):
    from tissue_sim.core.builder.quality import cell_volumes, surface_checks
    tm, _, _ = default
    tm.validate()
    assert np.all(cell_volumes(tm) > 0)
    assert all(v['watertight'] for v in surface_checks(tm).values())
    # both the thigh and the shank carry attached soft tissue; hamstrings exist
    segs = set(tm.vertex_segment[tm.vertex_segment >= 0].tolist())
    assert {tm.segment_names.index('thigh'), tm.segment_names.index('shank')} <= segs
    assert sum(g == 'hamstrings' for g in tm.muscle_groups) >= 3
    assert tm.n_joints >= 1 and M.JOINT_HINGE in tm.joint_type.tolist()


def test_cached_on_disk(default):
    tm, again, d = default
    assert again.content_hash() == tm.content_hash()
    assert len(list(d.glob('default_model_*.npz'))) == 1


def test_cli_without_labels(tmp_path, capsys):
    from tissue_sim.cli import main
    assert main(['build-model', '-o', str(tmp_path / 'm.npz'), '--json']) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d['fat_cells'] == 540 and d['bones'] == 6
