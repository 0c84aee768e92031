"""Test set-up: make the source tree's tissue_sim importable (the colcon install symlinks to it); order the files so
that pytest-xdist's two workers do not both compile the solver's step at the start."""
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / 'src' / 'tissue_sim'
if str(SRC) not in sys.path:
    sys.path.insert(0, str(SRC))


@pytest.fixture(scope='session')
def default_tm():
    """The bundled lower-limb model (tissue_sim.core.builder.default_model()), built once per test session."""
    from tissue_sim.core import builder
    try:
        return builder.default_model()
    except FileNotFoundError as e:
        pytest.skip(f'bundled anatomy not available: {e}')


# Every process compiles into and loads from the numba cache beside the sources; tissue_sim.core.numba_cache makes
# that safe for processes that compile at the same time. Under `make test` (scripts/test.sh: --dist loadfile
# --no-loadscope-reorder; without the latter pytest-xdist hands out the files with the most tests first and this
# order is lost) the first file goes to one worker and the second to the other: the first compiles the step (about
# 100 s on a cold cache with the other worker busy) while the second, the anatomy regenerated from its sources (about
# 60 s), and the next two, builders of finer and of the default model (about 40 s), need no step, so the other worker
# loads the step from the cache instead of compiling it too. The fifth, with its ~30-s subprocess (the 16-lane layout's
# cell kernels compiled for another CPU name), goes to the worker that frees first rather than at the end of the run,
# where the other worker would wait for it. Otherwise the files keep pytest's order, in the ROS phase too (where it keeps the
# `ros2 topic hz` test, late in the run, off the cores the demos' pictures take early: docs/history.md, stop 61).
FIRST_FILES = ('test_solver.py', 'test_anatomy.py', 'test_builder_fine.py', 'test_builder_default.py',
               'test_solver_kernel.py')


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(FIRST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))     # stable: the rest keep their order
