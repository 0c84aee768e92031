"""core/markers: the compiled corner gather writes the same bytes as one np.take per marker, and
refuses positions of the wrong shape (issue 23: marker encoding on finer models)."""
import numpy as np
import pytest

from tissue_sim.core import markers as mk
from tissue_sim.core.solver import phantom


@pytest.mark.parametrize('colouring', ['none', 'fat_deformation'])
def test_gather_matches_per_marker_take(colouring):
    tm = phantom.knee(n_gaps=4, extra_muscles=2, fat_sectors=6)
    enc = mk.MarkerArrayEncoder(tm, colouring=colouring)
    x = np.asarray(tm.rest_positions) + np.random.default_rng(3).normal(0, 1e-3, (tm.n_vertices, 3))
    rgba = None if enc.skin_corners is None else mk.sequential_rgba(np.linspace(0, 1, len(enc.skin_corners)), 1.0)
    data = enc.encode(5, x, None, rgba)
    soft = [(m, k) for m, (kind, k, *_r) in enumerate(enc._layout) if kind == 'soft']
    assert soft and len(enc._g_idx) == sum(len(enc._soft[k][0]) for _, k in soft)
    pay = np.frombuffer(data, np.uint8)[4:]
    for m, k in soft:
        off, n = enc._layout[m][3], enc._layout[m][4]
        got = pay[off:off + 24 * n].copy().view(np.float64).reshape(n, 3)
        np.testing.assert_array_equal(got, np.take(x, enc._soft[k][0], axis=0))
    # a second frame with other positions overwrites every corner
    data2 = enc.encode(6, x + 1.0, None, rgba)
    assert len(data2) == len(data) and data2 != data


def test_positions_of_the_wrong_shape_are_refused():
    tm = phantom.knee(n_gaps=4)
    enc = mk.MarkerArrayEncoder(tm)
    x = np.asarray(tm.rest_positions)
    with pytest.raises(ValueError, match='marker positions'):
        enc.encode(0, x[:-1])
    with pytest.raises(ValueError, match='marker positions'):
        enc.encode(0, x[:, :2])
