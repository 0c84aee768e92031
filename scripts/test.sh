#!/usr/bin/env bash
# `make test`: the whole suite in two phases, so that it uses both cores of a 2-core machine.
#   1. every test not marked `ros` on TISSUE_SIM_TEST_WORKERS pytest-xdist workers (default 2), one file per
#      worker at a time (--dist loadfile: a module's fixtures are built once; --no-loadscope-reorder: in the order
#      tests/conftest.py gives them, not the most tests first), all with the numba cache beside the
#      sources (tissue_sim.core.numba_cache makes it safe for processes compiling at once; tests/conftest.py orders
#      the files so that only one worker compiles the solver's step);
#   2. the `ros` tests (real nodes over DDS: mostly waiting on discovery and rates) on as many workers, after
#      phase 1, so that no node shares the cores with a CPU-bound test; first one short headless run compiles
#      what the simulator node runs into the cache beside the sources, if phase 1 left anything of it out.
# TISSUE_SIM_TEST_WORKERS=0 runs everything in one serial pytest. Extra arguments go to both phases; a phase
# that selects no test (pytest's exit 5) is not a failure when the other one ran tests.
set -uo pipefail
workers="${TISSUE_SIM_TEST_WORKERS:-2}"
export TISSUE_SIM_REQUIRE_WS=1
if [ "$workers" = 0 ]; then
  exec python -m pytest "$@"
fi
python -m pytest -m 'not ros' -n "$workers" --dist loadfile --no-loadscope-reorder "$@"; a=$?
if [ "$a" -ne 0 ] && [ "$a" -ne 5 ]; then exit "$a"; fi
warm="$(mktemp -d)"
tissue-sim simulate --duration 0.01 --activate hamstrings=1 -o "$warm/warm.mcap" > /dev/null; w=$?
rm -rf "$warm"
[ "$w" -eq 0 ] || { echo "make test: the simulator's warm-up run failed (exit $w)" >&2; exit "$w"; }
python -m pytest -m ros -n "$workers" "$@"; b=$?
if [ "$b" -ne 0 ] && [ "$b" -ne 5 ]; then exit "$b"; fi
if [ "$a" -eq 5 ] && [ "$b" -eq 5 ]; then echo 'make test: no test selected' >&2; exit 5; fi
exit 0
