"""Activation profiles and activation-message validation (ROS-free parts of the nodes)."""
import math

import numpy as np
import pytest

from tissue_sim.ros import profiles as pr
from tissue_sim.ros.validate import check_activation


def test_profile_shapes():
    assert pr.shape('step', 0.4, start=0.5) == 0.0 and pr.shape('step', 0.5, start=0.5, level=0.7) == 0.7
    assert pr.shape('step', 2.0, start=0.5, duration=1.0) == 0.0
    assert pr.shape('ramp', 1.0, start=0.5, rise=1.0) == pytest.approx(0.5)
    assert pr.shape('ramp', 9.0, rise=1.0, level=0.8) == pytest.approx(0.8)
    kw = dict(rise=1.0, hold=2.0, fall=1.0)
    vals = [pr.shape('ramp_hold', t, **kw) for t in (0.5, 2.0, 3.5, 5.0)]
    assert vals == pytest.approx([0.5, 1.0, 0.5, 0.0])
    s = [pr.shape('sine', t, frequency=0.5) for t in np.linspace(0, 4, 81)]
    assert min(s) == pytest.approx(0.0) and max(s) == pytest.approx(1.0) and s[20] == pytest.approx(1.0)
    with pytest.raises(pr.ProfileError, match='unknown profile'):
        pr.shape('zigzag', 1.0)


def test_muscle_selection_and_paper_muscles():
    names = ['biceps_femoris_long', 'semitendinosus', 'vastus_lateralis', 'gracilis']
    groups = ['hamstrings', 'hamstrings', 'quadriceps', '']
    assert pr.paper_muscles(names, groups) == ['biceps_femoris_long', 'semitendinosus']
    assert pr.paper_muscles(names) == ['biceps_femoris_long', 'semitendinosus']   # by name without groups
    assert pr.resolve_muscles(['quadriceps', 'gracilis'], names, groups) == ['vastus_lateralis', 'gracilis']
    assert pr.resolve_muscles(['all'], names, groups) == names
    with pytest.raises(pr.ProfileError, match="no muscle or group 'soleus'"):
        pr.resolve_muscles(['soleus'], names, groups)
    with pytest.raises(pr.ProfileError, match='no hamstrings'):
        pr.paper_muscles(['a', 'b'], ['', ''])


def test_timeline_file(tmp_path):
    f = tmp_path / 't.yaml'
    f.write_text('muscles:\n  hamstrings: [[0.0, 0.0], [1.0, 1.0], [3.0, 1.0], [4.0, 0.0]]\n')
    tl = pr.load_timeline(f)
    k = tl['hamstrings']
    assert [pr.timeline_value(k, t) for t in (-1, 0.5, 2.0, 3.5, 9.0)] == pytest.approx([0, 0.5, 1, 0.5, 0])
    for bad, msg in [('muscles:\n  a: [[0, 2.0]]\n', r'in \[0, 1\]'), ('muscles:\n  a: [[1, 0], [0, 1]]\n', 'must not decrease'),
                     ('x: 1\n', 'expected a mapping'), ('muscles:\n  a: [[0, .nan]]\n', 'non-finite'), (':\n- [', 'not valid YAML')]:
        f.write_text(bad)
        with pytest.raises(pr.ProfileError, match=msg):
            pr.load_timeline(f)
    with pytest.raises(pr.ProfileError, match='no such timeline'):
        pr.load_timeline(tmp_path / 'missing.yaml')


def test_shipped_timelines_load():
    from pathlib import Path
    cfg = Path(pr.__file__).resolve().parents[1] / 'config'
    for name in ('activation_timeline.yaml', 'activation_paper.yaml'):
        assert pr.load_timeline(cfg / name)


def test_parse_set():
    assert pr.parse_set(['a=0.5', 'b=1']) == {'a': 0.5, 'b': 1.0}
    for bad in (['a'], ['a=x'], ['a=1.5'], ['a=-0.1']):
        with pytest.raises(pr.ProfileError):
            pr.parse_set(bad)


@pytest.mark.parametrize('names,values,reason', [
    (['a'], [math.nan], 'nan'), (['a'], [math.inf], 'inf'), (['a'], [-math.inf], 'inf'),
    (['a'], [1.0001], 'out_of_range'), (['a'], [-0.1], 'out_of_range'), (['z'], [0.5], 'unknown_muscle'),
    (['a', 'b'], [0.5], 'length_mismatch'), (['a'], [], 'length_mismatch'), (['a', 'a'], [0.1, 0.2], 'duplicate_muscle'),
])
def test_bad_activation_rejected_with_reason(names, values, reason):
    idx, got, detail = check_activation(names, values, {'a': 0, 'b': 1})
    assert idx is None and got == reason and detail


def test_good_activation():
    assert check_activation(['b', 'a'], [0.0, 1.0], {'a': 0, 'b': 1}) == ([1, 0], [0.0, 1.0], None)
