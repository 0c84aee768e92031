"""Test set-up: make the source tree's tissue_sim importable (the colcon install symlinks to it); under
scripts/test.sh's first phase give each pytest-xdist worker a numba cache of its own."""
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Under scripts/test.sh's first phase (TISSUE_SIM_TEST_OWN_NUMBA_CACHE=1) each pytest-xdist worker but the first (and
# every process it starts) compiles into and loads from a numba cache of its own, .cache/numba/<worker>; the first
# uses the cache beside the sources, as a serial run does, and leaves it warm for the nodes of the second phase. No
# worker then writes a function's cache while another one writes it too (numba's index of a function's cache is not
# made for that: entries get lost). Set before anything imports numba, which reads NUMBA_CACHE_DIR once.
_WORKER = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
if os.environ.get('TISSUE_SIM_TEST_OWN_NUMBA_CACHE') == '1' and _WORKER != 'gw0' and 'numba' not in sys.modules:
    os.environ['NUMBA_CACHE_DIR'] = str(ROOT / '.cache' / 'numba' / _WORKER)
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
