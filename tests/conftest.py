"""Test set-up: make the source tree's tissue_sim importable (the colcon install symlinks to it)."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / 'src' / 'tissue_sim'
if str(SRC) not in sys.path:
    sys.path.insert(0, str(SRC))
