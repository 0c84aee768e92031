#!/usr/bin/env bash
# Install the anatomy source packages (data only, --no-deps) and opensim (the rest fibre lengths) into .venv and regenerate the bundled
# right lower limb in src/tissue_sim/tissue_sim/data/lower_limb (and, with --pictures, docs/img).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
"$PY" -m pip install --quiet --no-deps -r "$ROOT/requirements/anatomy.txt" -r "$ROOT/requirements/validation.txt"
"$PY" "$ROOT/tools/anatomy/generate.py" --out "$ROOT/src/tissue_sim/tissue_sim/data/lower_limb" "$@"
if [[ "${PICTURES:-0}" == "1" ]]; then
  "$PY" "$ROOT/tools/anatomy/pictures.py"
fi
