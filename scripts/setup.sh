#!/usr/bin/env bash
# make setup: from a fresh clone to a built workspace and one environment file, idempotently.
#
#   1. .venv (python3 -m venv) unless it exists
#   2. pip install -r requirements/{ros,core,dev}.txt, only when those files (or the interpreter)
#      changed since the last successful install (stamp: .venv/.tissue_sim-requirements.sha256)
#   3. colcon build --symlink-install of ros_ws/ against the venv's ROS 2 Jazzy wheels, only when
#      a build input changed (stamp: .setup-stamp-build); the wheels' baked include dirs are fixed
#      by cmake/fix_wheel_includes.cmake passed as CMAKE_PROJECT_INCLUDE (nothing in .venv edited)
#   4. env.sh: the one file to source (AMENT_PREFIX_PATH with the venv AND the workspace, PATH,
#      PYTHONPATH, LD_LIBRARY_PATH, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)
#
# Environment knobs: PYTHON (interpreter for the venv, default python3, else python3.12/3.11),
# TISSUE_SIM_FORCE_BUILD=1 (rebuild even if nothing changed), TISSUE_SIM_WHEELHOUSE (local wheel
# directory, default ~/.cache/tissue_sim/wheels; "off" = install straight from the index).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
WS="$ROOT/ros_ws"
PY="${PYTHON:-python3}"
REQS=("$ROOT/requirements/ros.txt" "$ROOT/requirements/core.txt" "$ROOT/requirements/dev.txt")
PIP_STAMP="$VENV/.tissue_sim-requirements.sha256"
BUILD_STAMP="$ROOT/.setup-stamp-build"
T0=$(date +%s.%N)
CHECK=0   # --check: do nothing; exit 0 if everything is up to date, 1 (saying what) if not
case "${1:-}" in
  --check) CHECK=1 ;;
  "") ;;
  *) echo "usage: scripts/setup.sh [--check]" >&2; exit 2 ;;
esac

say() { printf 'setup: %s\n' "$*"; }
die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

# Two `make` runs in the same clone at once must not build over each other.
exec 9>"$ROOT/.setup-stamp.lock"
if command -v flock >/dev/null 2>&1; then flock 9; fi

# ---- 0. prerequisites (checked only when something has to be built) ------------------------
need_tools() {
  local missing=()
  command -v cmake >/dev/null 2>&1 || missing+=(cmake)
  command -v cc >/dev/null 2>&1 || command -v gcc >/dev/null 2>&1 || missing+=("C compiler (gcc)")
  command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1 || missing+=("C++ compiler (g++)")
  if ((${#missing[@]})); then
    die "missing build tools: ${missing[*]}. Debian/Ubuntu: sudo apt-get install -y build-essential cmake python3-dev python3-venv"
  fi
}

# ---- 1. venv --------------------------------------------------------------------------------
py_ok() { "$1" -c 'import sys; sys.exit(0 if (3, 10) <= sys.version_info[:2] <= (3, 12) else 1)' 2>/dev/null; }
if [[ $CHECK == 1 && ! -x "$VENV/bin/python" ]]; then say "out of date: no .venv"; exit 1; fi
if [[ ! -x "$VENV/bin/python" ]]; then
  # The ROS 2 Jazzy wheels exist for cp310-cp312: take python3 if it is one of those, else a
  # python3.12 / python3.11 on PATH (e.g. Debian 13 or Ubuntu 24.10 have 3.13 as python3).
  if [[ -z "${PYTHON:-}" ]]; then
    for cand in python3 python3.12 python3.11; do
      if command -v "$cand" >/dev/null 2>&1 && py_ok "$cand"; then PY="$cand"; break; fi
    done
  fi
  command -v "$PY" >/dev/null 2>&1 || die "no '$PY' on PATH (Python 3.11 or 3.12 needed; set PYTHON=...)"
  py_ok "$PY" || die "$PY is Python $("$PY" -c 'import sys; print(sys.version.split()[0])'); the ROS 2 Jazzy wheels need 3.10-3.12: install python3.12 or python3.11 (or set PYTHON=...)"
  say "creating $VENV with $("$PY" -c 'import sys; print(sys.executable, sys.version.split()[0])')"
  "$PY" -m venv "$VENV" || { rm -rf "$VENV"; die "python -m venv failed (Debian/Ubuntu: sudo apt-get install -y python3-venv)"; }
fi
VPY="$VENV/bin/python"
PYVER="$("$VPY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"

# ---- 2. pinned Python packages -----------------------------------------------------------------
req_hash="$( { cat "${REQS[@]}"; "$VPY" -c 'import sys; print(sys.version)'; } | sha256sum | cut -d' ' -f1)"
if [[ $CHECK == 1 && "$(cat "$PIP_STAMP" 2>/dev/null || true)" != "$req_hash" ]]; then
  say "out of date: requirements/*.txt not installed"; exit 1
fi
if [[ "$(cat "$PIP_STAMP" 2>/dev/null || true)" != "$req_hash" ]]; then
  say "installing pinned requirements into .venv (requirements/*.txt changed or first run)"
  t=$(date +%s)
  # Through a local wheelhouse (all pinned wheels, empy's built from its sdist): a second clone on
  # the same machine installs from it without the network. TISSUE_SIM_WHEELHOUSE=off: plain pip.
  pip_q=(--disable-pip-version-check --no-input -q)
  req_args=(-r "$ROOT/requirements/ros.txt" -r "$ROOT/requirements/core.txt" -r "$ROOT/requirements/dev.txt")
  WH="${TISSUE_SIM_WHEELHOUSE:-${XDG_CACHE_HOME:-$HOME/.cache}/tissue_sim/wheels}"
  if [[ "$WH" == off ]]; then
    "$VPY" -m pip install "${pip_q[@]}" "${req_args[@]}"
  elif "$VPY" -m pip install "${pip_q[@]}" --no-index --find-links "$WH" "${req_args[@]}" 2>/dev/null; then
    say "installed from the wheelhouse $WH"
  else
    mkdir -p "$WH"
    say "filling the wheelhouse $WH (downloads ~400 MB once)"
    if "$VPY" -m pip wheel "${pip_q[@]}" --find-links "$WH" -w "$WH" "${req_args[@]}"; then
      "$VPY" -m pip install "${pip_q[@]}" --no-index --find-links "$WH" "${req_args[@]}"
    else
      say "wheelhouse failed; installing directly from the index"
      "$VPY" -m pip install "${pip_q[@]}" "${req_args[@]}"
    fi
  fi
  echo "$req_hash" >"$PIP_STAMP"
  say "pip install took $(( $(date +%s) - t )) s"
  rm -f "$BUILD_STAMP"   # new wheels: rebuild the workspace against them
fi

# ---- 3. colcon build -------------------------------------------------------------------------------
# Build inputs: everything colcon reads that --symlink-install does not make live (the message
# definitions, CMake, package manifests, setup.py/cfg, entry points), the fix file and the wheels.
build_inputs() {
  cd "$ROOT"
  {
    echo "$req_hash"
    sha256sum scripts/setup.sh
    find src/tissue_msgs src/pip_only cmake -type f \( -name '*.msg' -o -name '*.srv' -o -name '*.txt' -o -name '*.xml' -o -name '*.cmake' \) -print0 \
      | sort -z | xargs -0 sha256sum
    sha256sum src/tissue_sim/package.xml src/tissue_sim/setup.py src/tissue_sim/setup.cfg
    find src/tissue_sim/resource -type f -print0 | sort -z | xargs -0 -r sha256sum
    # new/removed python modules do not need a rebuild (develop install), new data files may
    find src/tissue_sim/tissue_sim/data src/tissue_sim/tissue_sim/config src/tissue_sim/launch src/tissue_sim/description -type f 2>/dev/null | sort
    ls -l ros_ws/src
  } | sha256sum | cut -d' ' -f1
}
build_hash="$(build_inputs)"
installed_ok() {
  [[ -f "$WS/install/tissue_msgs/share/tissue_msgs/package.xml" ]] &&
  [[ -f "$WS/install/tissue_sim/share/tissue_sim/package.xml" ]] &&
  [[ -d "$WS/install/tissue_sim/lib/tissue_sim" ]] &&
  [[ -f "$WS/install/tf2_msgs/share/tf2_msgs/package.xml" ]]
}
if [[ $CHECK == 1 ]]; then
  if [[ "$(cat "$BUILD_STAMP" 2>/dev/null || true)" != "$build_hash" ]] || ! installed_ok || [[ ! -f "$ROOT/env.sh" ]]; then
    say "out of date: ros_ws needs a colcon build"; exit 1
  fi
  say "up to date"; exit 0
fi
if [[ "${TISSUE_SIM_FORCE_BUILD:-0}" == 1 || "$(cat "$BUILD_STAMP" 2>/dev/null || true)" != "$build_hash" ]] || ! installed_ok; then
  need_tools
  say "building ros_ws with colcon (against the venv's ROS 2 Jazzy wheels)"
  t=$(date +%s)
  rm -f "$BUILD_STAMP"
  mkdir -p "$WS/log"
  # The $ORIGIN rpath lets the message libraries (lib/) and their Python extensions
  # (lib/pythonX.Y/site-packages/tissue_msgs/) find each other without LD_LIBRARY_PATH.
  (
    cd "$WS"
    export VIRTUAL_ENV="$VENV"
    export PATH="$VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$VENV"
    export CMAKE_PREFIX_PATH="$VENV"
    unset PYTHONPATH COLCON_PREFIX_PATH
    "$VENV/bin/colcon" --log-base "$WS/log" build \
      --base-paths "$WS/src" "$ROOT/src/pip_only" --build-base "$WS/build" --install-base "$WS/install" \
      --symlink-install --event-handlers console_cohesion- summary+ status- \
      --cmake-args \
        "-DPython3_EXECUTABLE=$VPY" \
        "-DCMAKE_PROJECT_INCLUDE=$ROOT/cmake/fix_wheel_includes.cmake" \
        "-DBUILD_TESTING=OFF" \
        "-DCMAKE_BUILD_TYPE=Release" \
        '-DCMAKE_INSTALL_RPATH=$ORIGIN;$ORIGIN/../../..' \
      >"$WS/log/setup-colcon.out" 2>&1 || {
        tail -n 60 "$WS/log/setup-colcon.out" >&2
        die "colcon build failed (full output: ros_ws/log/setup-colcon.out)"
      }
  ) || exit 1
  say "colcon build took $(( $(date +%s) - t )) s"
  echo "$build_hash" >"$BUILD_STAMP"
fi

# ---- 4. env.sh ---------------------------------------------------------------------------------------
ENV_TMP="$ROOT/env.sh.tmp.$$"
{
  cat <<EOF
# tissue_sim environment, generated by \`make setup\` (scripts/setup.sh). Do not edit; re-run make setup.
# Source it from any POSIX shell, also under \`set -u\`:   . ./env.sh
# Gives: the venv's Python with ROS 2 Jazzy (rclpy, Fast DDS), the built ros_ws packages
# (tissue_msgs, tissue_sim) on AMENT_PREFIX_PATH/PYTHONPATH, the tissue_sim executables on PATH.
TISSUE_SIM_ROOT='$ROOT'
_ts_venv='$VENV'
EOF
  cat <<'EOF'
export TISSUE_SIM_ROOT
_ts_prepend() { # _ts_prepend VAR DIR: put DIR in front of the ':' list in VAR, once
  eval "_ts_cur=\${$1:-}"
  case ":$_ts_cur:" in
    *":$2:"*) ;;
    *) if [ -n "$_ts_cur" ]; then _ts_cur="$2:$_ts_cur"; else _ts_cur="$2"; fi
       eval "$1=\$_ts_cur"; eval "export $1" ;;
  esac
  unset _ts_cur
}
VIRTUAL_ENV="$_ts_venv"
export VIRTUAL_ENV
_ts_prepend PATH "$_ts_venv/bin"
_ts_prepend AMENT_PREFIX_PATH "$_ts_venv"
_ts_prepend CMAKE_PREFIX_PATH "$_ts_venv"
_ts_prepend LD_LIBRARY_PATH "$_ts_venv/lib"
EOF
  # The workspace packages: what colcon's install/setup.sh would do, from colcon's declarative
  # hook files (share/<pkg>/package.dsv and the .dsv hooks it lists), in dependency order.
  "$VPY" - "$WS/install" <<'EOF'
import os
import sys
from pathlib import Path

install = Path(sys.argv[1])
pkgs = {p.name: [d for d in p.read_text().strip().split(':') if d]
        for p in install.glob('*/share/colcon-core/packages/*')}
order, seen = [], set()
def visit(name):
    if name in seen or name not in pkgs:
        return
    seen.add(name)
    for dep in pkgs[name]:
        visit(dep)
    order.append(name)
for name in sorted(pkgs):
    visit(name)
ops = ('prepend-non-duplicate', 'prepend-non-duplicate-if-exists', 'append-non-duplicate')
def dsv(prefix, path):
    for line in path.read_text().splitlines():
        kind, _, rest = line.partition(';')
        if kind == 'source':    # as colcon does: a shell hook with a sibling .dsv is read from that
            hook = (prefix / rest).with_suffix('.dsv')    # not resolved: may be a symlink
            if hook.is_file():
                yield from dsv(prefix, hook)
        elif kind in ops:
            var, _, value = rest.partition(';')
            for v in value.split(';'):
                full = os.path.normpath(prefix / v) if v else str(prefix)
                if kind.endswith('if-exists') and not Path(full).exists():
                    continue
                yield var, full
for name in order:          # later packages end up in front, as with colcon's setup.sh
    prefix = install / name
    print(f'# {name}')
    for var, value in dict.fromkeys(dsv(prefix, prefix / 'share' / name / 'package.dsv')):
        if any(c in value for c in "'\\\n"):
            raise SystemExit(f'setup: unsupported character in path {value!r}')
        print(f"_ts_prepend {var} '{value}'")
    exe_dir = prefix / 'lib' / name
    if exe_dir.is_dir():
        print(f"_ts_prepend PATH '{exe_dir}'")
EOF
  cat <<'EOF'
unset -f _ts_prepend
unset _ts_venv
# Local-only DDS discovery unless the caller chose otherwise (do not mix with ROS_LOCALHOST_ONLY).
: "${ROS_AUTOMATIC_DISCOVERY_RANGE:=LOCALHOST}"
export ROS_AUTOMATIC_DISCOVERY_RANGE
: "${RMW_IMPLEMENTATION:=rmw_fastrtps_cpp}"
export RMW_IMPLEMENTATION
EOF
  # Fast DDS's participant profile, unless the caller names one: announcements every 0.5 s (config/fastdds.xml)
  printf ': "${FASTRTPS_DEFAULT_PROFILES_FILE:=%s}"\nexport FASTRTPS_DEFAULT_PROFILES_FILE\n' \
    "$ROOT/src/tissue_sim/tissue_sim/config/fastdds.xml"
} >"$ENV_TMP"
if cmp -s "$ENV_TMP" "$ROOT/env.sh"; then rm -f "$ENV_TMP"; else mv -f "$ENV_TMP" "$ROOT/env.sh"; fi

say "ready in $(awk -v a="$T0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }') s; use it with:  . ./env.sh"
