"""Test set-up: make the source tree's tissue_sim importable (the colcon install symlinks to it)."""
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
