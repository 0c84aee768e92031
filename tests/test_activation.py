"""The activation module (tissue_sim.core.activation): selectors, the combination rule, timelines,
profiles, validation of an activation command; the same description gives the same activations in
the headless solver and in the activation node."""
import math
from pathlib import Path

import numpy as np
import pytest

from tissue_sim.core import activation as act
from tissue_sim.core.activation import Activations, ActivationError, Muscles

NAMES = ['biceps_femoris_long', 'semitendinosus', 'vastus_lateralis', 'gracilis']
GROUPS = ['hamstrings', 'hamstrings', 'quadriceps', '']


def test_profile_shapes():
    assert act.shape('step', 0.4, start=0.5) == 0.0 and act.shape('step', 0.5, start=0.5, level=0.7) == 0.7
    assert act.shape('step', 2.0, start=0.5, duration=1.0) == 0.0
    assert act.shape('ramp', 1.0, start=0.5, rise=1.0) == pytest.approx(0.5)
    assert act.shape('ramp', 9.0, rise=1.0, level=0.8) == pytest.approx(0.8)
    kw = dict(rise=1.0, hold=2.0, fall=1.0)
    vals = [act.shape('ramp_hold', t, **kw) for t in (0.5, 2.0, 3.5, 5.0)]
    assert vals == pytest.approx([0.5, 1.0, 0.5, 0.0])
    s = [act.shape('sine', t, frequency=0.5) for t in np.linspace(0, 4, 81)]
    assert min(s) == pytest.approx(0.0) and max(s) == pytest.approx(1.0) and s[20] == pytest.approx(1.0)
    with pytest.raises(ActivationError, match='unknown profile'):
        act.shape('zigzag', 1.0)


def test_muscle_selection_and_paper_muscles():
    m = Muscles(NAMES, GROUPS)
    assert m.hamstrings() == ['biceps_femoris_long', 'semitendinosus']
    assert Muscles(NAMES).hamstrings() == ['biceps_femoris_long', 'semitendinosus']   # by name without groups
    assert m.resolve(['quadriceps', 'gracilis']) == ['vastus_lateralis', 'gracilis']
    assert m.resolve(['all']) == NAMES
    assert m.resolve(['biceps_femoris']) == ['biceps_femoris_long']          # a name prefix at a word boundary
    assert m.index('gracilis') == 3
    with pytest.raises(KeyError, match="unknown muscle or group 'soleus'"):
        m.resolve(['soleus'])
    with pytest.raises(ActivationError, match="unknown muscle or group 'semi'"):   # not a word boundary
        m.resolve(['semi'])
    with pytest.raises(ActivationError, match='no hamstrings'):
        Muscles(['a', 'b'], ['', '']).hamstrings()


def test_the_most_specific_entry_sets_a_muscle_whatever_the_order():
    """The combination rule: all < group < name prefix < muscle; entries never add."""
    m = Muscles(NAMES, GROUPS)
    const = lambda v: (lambda t: v)   # noqa: E731
    for entries in ([('all', const(0.3)), ('hamstrings', const(0.5)), ('semitendinosus', const(0.9))],
                    [('semitendinosus', const(0.9)), ('hamstrings', const(0.5)), ('all', const(0.3))]):
        a = Activations(entries, m)
        assert a.names == NAMES
        assert a.values(0.0) == pytest.approx([0.5, 0.9, 0.3, 0.3])
        assert a.full(0.0) == pytest.approx([0.5, 0.9, 0.3, 0.3])
    a = Activations([('biceps_femoris', const(0.2)), ('hamstrings', const(0.6))], m)
    assert a.names == ['biceps_femoris_long', 'semitendinosus'] and a.values(0) == pytest.approx([0.2, 0.6])
    a = Activations([('quadriceps', const(0.4))], m)          # muscles not selected: 0 in the model's vector
    assert a.names == ['vastus_lateralis'] and a.full(1.0) == pytest.approx([0, 0, 0.4, 0])
    a = Activations([('x_y', const(0.1)), ('x_y', const(0.7))], None)     # literal names: the later one wins
    assert a.names == ['x_y'] and a.values(0) == pytest.approx([0.7])


def test_solver_timeline_uses_the_rule():
    """`tissue-sim simulate` and solver.simulate() combine a timeline by the same rule (they added
    the entries before: hamstrings 0.3 + 0.5 = 0.8)."""
    from tissue_sim.core import solver
    from tissue_sim.core.solver import phantom
    sim = solver.compile_model(phantom.knee(n_gaps=4), solver.Params.paper())
    fn = solver.timeline_function(sim, {'all': [(0, 0.3)], 'hamstrings': [(0, 0.5)]})
    assert fn(1.0) == pytest.approx([0.5, 0.3])
    fn = solver.timeline_function(sim, {'hamstring': [(0, 0), (1, 1)], 'hamstrings': 0.2, 'all': 0.1})
    assert fn(0.5) == pytest.approx([0.5, 0.1])


def test_timeline_file(tmp_path):
    f = tmp_path / 't.yaml'
    f.write_text('muscles:\n  hamstrings: [[0.0, 0.0], [1.0, 1.0], [3.0, 1.0], [4.0, 0.0]]\n')
    tl = act.load_timeline(f)
    k = tl['hamstrings']
    assert [act.timeline_value(k, t) for t in (-1, 0.5, 2.0, 3.5, 9.0)] == pytest.approx([0, 0.5, 1, 0.5, 0])
    for bad, msg in [('muscles:\n  a: [[0, 2.0]]\n', r'in \[0, 1\]'), ('muscles:\n  a: [[1, 0], [0, 1]]\n', 'must not decrease'),
                     ('x: 1\n', 'expected a mapping'), ('muscles:\n  a: [[0, .nan]]\n', 'non-finite'), (':\n- [', 'not valid YAML')]:
        f.write_text(bad)
        with pytest.raises(ActivationError, match=msg):
            act.load_timeline(f)
    with pytest.raises(ActivationError, match='no such timeline'):
        act.load_timeline(tmp_path / 'missing.yaml')


def test_shipped_timelines_load():
    cfg = Path(act.__file__).resolve().parents[1] / 'config'
    for name in ('activation_timeline.yaml', 'activation_paper.yaml'):
        assert act.load_timeline(cfg / name)


def test_profile_entries_default_to_the_hamstrings_of_the_model():
    """A profile without a muscle selection drives the model's hamstrings, whatever their names."""
    bundled_like = Muscles(['biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus',
                            'rectus_femoris'], ['hamstrings', 'hamstrings', 'hamstrings', 'quadriceps'])
    a = Activations(act.profile_entries('ramp', bundled_like, rise=2.0), bundled_like)
    assert a.names == ['biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus']
    assert a.values(1.0) == pytest.approx([0.5, 0.5, 0.5])
    a = Activations(act.profile_entries('paper', bundled_like, others=0.0), bundled_like)
    assert a.names == bundled_like.names and a.values(0.1) == pytest.approx([1, 1, 1, 0])
    with pytest.raises(ActivationError, match='need the model'):
        act.profile_entries('ramp', None)


def test_parse_set():
    assert act.parse_set(['a=0.5', 'b=1']) == {'a': 0.5, 'b': 1.0}
    for bad in (['a'], ['a=x'], ['a=1.5'], ['a=-0.1']):
        with pytest.raises(ActivationError):
            act.parse_set(bad)


@pytest.mark.parametrize('names,values,reason', [
    (['a'], [math.nan], 'nan'), (['a'], [math.inf], 'inf'), (['a'], [-math.inf], 'inf'),
    (['a'], [1.0001], 'out_of_range'), (['a'], [-0.1], 'out_of_range'), (['z'], [0.5], 'unknown_muscle'),
    (['a', 'b'], [0.5], 'length_mismatch'), (['a'], [], 'length_mismatch'), (['a', 'a'], [0.1, 0.2], 'duplicate_muscle'),
])
def test_bad_activation_rejected_with_reason(names, values, reason):
    idx, got, detail = Muscles(['a', 'b']).check(names, values)
    assert idx is None and got == reason and detail


def test_good_activation():
    assert Muscles(['a', 'b']).check(['b', 'a'], [0.0, 1.0]) == ([1, 0], [0.0, 1.0], None)
