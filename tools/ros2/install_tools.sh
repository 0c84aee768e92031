#!/usr/bin/env bash
# make ros2-tools: the `ros2` command (ros2cli), `rosidl_runtime_py`, the launch system
# (`launch`, `launch_xml`, `launch_yaml`, `launch_ros`, `ros2launch`) and the interface package
# `composition_interfaces` for the pip set-up. None of them is published on PyPI: they are
# installed from their ROS 2 Jazzy sources, either
#   - a local folder of source archives (ROS2_SRC=/path: ros2cli-jazzy.tar.gz, rosidl_runtime_py-
#     jazzy.tar.gz, launch-jazzy.tar.gz, launch_ros-jazzy.tar.gz, rcl_interfaces-jazzy.tar.gz, each
#     unpacking to a folder named after its repository; a SHA256SUMS file beside them is checked), or
#   - the upstream repositories at the commits below (git, on a machine that reaches them).
# Default: ROS2_SRC=../shared/ros2-src when that folder exists, else the repositories.
# The Python packages go into .venv (pip --no-deps, their PyPI dependencies pinned in
# requirements/ros2-tools.txt); composition_interfaces is built with colcon into ros_ws/install
# with the same recipe as the project's messages; env.sh is then rewritten by scripts/setup.sh.
# Nothing of these sources is committed to the repository: they are unpacked under .ros2-tools/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
say() { echo "ros2-tools: $*"; }
die() { echo "ros2-tools: $*" >&2; exit 2; }

# repository | Jazzy branch commit | archive (see docs/ros.md, "The ros2 tools")
REPOS=(
  "ros2cli|https://github.com/ros2/ros2cli|de6cd27284937044d8dff47a617581c28865210c|ros2cli-jazzy.tar.gz"
  "rosidl_runtime_py|https://github.com/ros2/rosidl_runtime_py|df2361f64ecb85f65f4bf22e804424e0f1ac4197|rosidl_runtime_py-jazzy.tar.gz"
  "launch|https://github.com/ros2/launch|09403fcebedb68dd259e9ab6b35bd8712b6596ec|launch-jazzy.tar.gz"
  "launch_ros|https://github.com/ros2/launch_ros|62c56e53e86812023697fe330c83d327f54e7b18|launch_ros-jazzy.tar.gz"
  "rcl_interfaces|https://github.com/ros2/rcl_interfaces|003987ecb81a32802ab27dd6d325b8c6b8b813cc|rcl_interfaces-jazzy.tar.gz"
)
# the Python packages, in install order (folders inside the repositories)
PY_PKGS=(
  rosidl_runtime_py
  ros2cli/ros2cli ros2cli/ros2pkg ros2cli/ros2run ros2cli/ros2node ros2cli/ros2service
  ros2cli/ros2param ros2cli/ros2topic ros2cli/ros2interface
  launch/launch launch/launch_xml launch/launch_yaml launch_ros/launch_ros launch_ros/ros2launch
)

VENV="$ROOT/.venv"
VPY="$VENV/bin/python"
WS="$ROOT/ros_ws"
WORK="$ROOT/.ros2-tools"
[[ -x "$VPY" && -f "$ROOT/env.sh" ]] || die "run 'make setup' first (no .venv or env.sh)"

if [[ -z "${ROS2_SRC:-}" && -d "$ROOT/../shared/ros2-src" ]]; then
  ROS2_SRC="$(cd "$ROOT/../shared/ros2-src" && pwd)"
fi

# What is wanted: the sources' identity (repository commits) + the pinned PyPI dependencies + this script.
want="$( { for r in "${REPOS[@]}"; do echo "$r"; done; cat requirements/ros2-tools.txt; sha256sum <"${BASH_SOURCE[0]}"; } \
         | sha256sum | cut -d' ' -f1)"
PIP_STAMP="$VENV/.tissue_sim-ros2-tools.sha256"
WS_STAMP="$WS/install/.tissue_sim-ros2-tools.sha256"
if [[ "$(cat "$PIP_STAMP" 2>/dev/null)" == "$want" && "$(cat "$WS_STAMP" 2>/dev/null)" == "$want" \
      && -x "$VENV/bin/ros2" && -d "$WS/install/composition_interfaces" ]]; then
  say "up to date"; exit 0
fi

# ---- 1. sources -------------------------------------------------------------------------------
rm -rf "$WORK"; mkdir -p "$WORK/src"
if [[ -n "${ROS2_SRC:-}" ]]; then
  [[ -d "$ROS2_SRC" ]] || die "ROS2_SRC=$ROS2_SRC is not a folder"
  if [[ -f "$ROS2_SRC/SHA256SUMS" ]]; then
    (cd "$ROS2_SRC" && sha256sum --quiet -c SHA256SUMS) || die "checksum mismatch in $ROS2_SRC (SHA256SUMS)"
  fi
  for r in "${REPOS[@]}"; do
    IFS='|' read -r name url commit archive <<<"$r"
    [[ -f "$ROS2_SRC/$archive" ]] || die "missing $ROS2_SRC/$archive"
    tar -xzf "$ROS2_SRC/$archive" -C "$WORK/src"
    [[ -d "$WORK/src/$name" ]] || die "$archive does not unpack to a folder '$name'"
  done
  say "sources from $ROS2_SRC"
else
  command -v git >/dev/null || die "git is needed to fetch the sources (or set ROS2_SRC to a folder of archives)"
  for r in "${REPOS[@]}"; do
    IFS='|' read -r name url commit archive <<<"$r"
    git init -q "$WORK/src/$name"
    git -C "$WORK/src/$name" fetch -q --depth 1 "$url" "$commit" || die "cannot fetch $url at $commit (set ROS2_SRC to a folder of archives)"
    git -C "$WORK/src/$name" checkout -q FETCH_HEAD
  done
  say "sources from the upstream repositories"
fi

# ---- 2. Python packages into the venv -----------------------------------------------------------
t=$(date +%s)
"$VPY" -m pip install -q --disable-pip-version-check --no-input --no-deps -r requirements/ros2-tools.txt
args=()
for p in "${PY_PKGS[@]}"; do args+=("$WORK/src/$p"); done
"$VPY" -m pip install -q --disable-pip-version-check --no-input --no-deps --no-build-isolation "${args[@]}" \
  >"$WORK/pip.log" 2>&1 || { tail -n 30 "$WORK/pip.log" >&2; die "pip install of the ROS 2 tools failed (log: .ros2-tools/pip.log)"; }
echo "$want" >"$PIP_STAMP"
say "pip install took $(( $(date +%s) - t )) s"

# ---- 3. composition_interfaces with colcon (the project's recipe) --------------------------------
t=$(date +%s)
(
  cd "$WS"
  export VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
  unset PYTHONPATH COLCON_PREFIX_PATH
  "$VENV/bin/colcon" --log-base "$WORK/log" build \
    --base-paths "$WORK/src/rcl_interfaces/composition_interfaces" --build-base "$WORK/build" --install-base "$WS/install" \
    --event-handlers console_cohesion- summary+ status- \
    --cmake-args "-DPython3_EXECUTABLE=$VPY" "-DCMAKE_PROJECT_INCLUDE=$ROOT/cmake/fix_wheel_includes.cmake" \
      "-DBUILD_TESTING=OFF" "-DCMAKE_BUILD_TYPE=Release" '-DCMAKE_INSTALL_RPATH=$ORIGIN;$ORIGIN/../../..' \
    >"$WORK/colcon.out" 2>&1 || { tail -n 40 "$WORK/colcon.out" >&2; die "colcon build of composition_interfaces failed (.ros2-tools/colcon.out)"; }
)
echo "$want" >"$WS_STAMP"
say "composition_interfaces built in $(( $(date +%s) - t )) s"

# ---- 4. env.sh again (it lists every package installed in ros_ws/install) ------------------------
bash scripts/setup.sh >/dev/null
. ./env.sh
ros2 --help >/dev/null || die "'ros2 --help' fails after the install"
say "ready: . ./env.sh; ros2 run tissue_sim simulator; ros2 launch tissue_sim demo.launch.py"
