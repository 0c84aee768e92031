#!/usr/bin/env bash
# make demo: the main job of tissue_sim, end to end, on the bundled anatomy.
#
#   recorder + simulator + activation run as real ROS 2 nodes over DDS for DEMO_SECONDS of simulated
#   time (default 10); then they are stopped with SIGINT and the run folder is analysed and drawn.
#   The experiment is the paper's (section 4.2): the hamstrings contract, every other muscle passive.
#   Default: the physical (SI) parameter set with the hamstrings' activation ramped 0 -> 1 over 8 s,
#   so the knee flexes progressively to its 120-deg limit (on the 2-core machines measured the simulator
#   node runs it at 0.85-1.00x real time, docs/ros.md: it publishes at 34 Hz regardless and sim time runs slower
#   where the solver cannot keep up). DEMO_PARAMS=paper runs the
#   paper's Table 2 set with the paper's step activation (full from t = 0): faithful, but the knee
#   only swings within 0-8 deg on this anatomy (docs/solver.md).
#
# Run folder: ${TISSUE_SIM_RUNS:-<repo>/runs}/<UTC timestamp>/ with
#   run.mcap        the recording (/tissue/state, /tissue/topology, /tissue/activation, /joint_states,
#                   /diagnostics; rosbag2/Foxglove open it)
#   summary.json    achieved publish rate (seen by a separate subscriber), real-time factor, final knee angle
#   logs/           the nodes' output
#   analysis/, figures/   from `tissue-sim analyze` and `tissue-sim render`
#
# Environment: MOTION (a named motion of tissue_sim.core.activation.MOTIONS: knee_flexion, knee_extension,
# kick, heel_raise, ankle_pump; the activation node runs --profile MOTION and DEMO_SECONDS defaults to the
# motion's duration; unset: the default below), DEMO_SECONDS (sim seconds, default 10), DEMO_MODEL (model .npz; default the bundled
# anatomy), DEMO_PARAMS (physical|paper|file, default physical), DEMO_ACTIVATION (arguments of the
# activation node; default: --profile ramp --rise 8 --others 0 (the node's default muscles are the
# model's hamstrings), or --profile paper with DEMO_PARAMS=paper), DEMO_MARKERS (default 1: also
# record the markers, the soft tissue at DEMO_MARKER_HZ, default 3), ROS_DOMAIN_ID (default:
# derived from the pid), DEMO_TIMEOUT (wall seconds, default 600).
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
if [ -z "${TISSUE_SIM_ROOT:-}" ]; then
  # shellcheck disable=SC1091
  . "$ROOT/env.sh"
fi
SECONDS_SIM="${DEMO_SECONDS:-10}"
PARAMS="${DEMO_PARAMS:-physical}"
MOTION="${MOTION:-}"
if [ -n "$MOTION" ]; then
  # the motion's duration (one definition: tissue_sim.core.activation); an unknown name: one error line, exit 2
  MOTION_S="$(python -c 'import sys; from tissue_sim.core import activation as a
try: print(a.motion(sys.argv[1]).duration)
except a.ActivationError as e: sys.exit(f"demo: error: MOTION={sys.argv[1]}: {e}")' "$MOTION")" || exit 2
  SECONDS_SIM="${DEMO_SECONDS:-$MOTION_S}"
fi
if [ -n "${DEMO_ACTIVATION:-}" ]; then
  read -r -a ACT_ARGS <<<"$DEMO_ACTIVATION"
elif [ -n "$MOTION" ]; then
  ACT_ARGS=(--profile "$MOTION")
elif [ "$PARAMS" = paper ]; then
  ACT_ARGS=(--profile paper)
else
  ACT_ARGS=(--profile ramp --rise 8 --others 0)
fi
TIMEOUT="${DEMO_TIMEOUT:-600}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( 1 + $$ % 101 ))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset ROS_LOCALHOST_ONLY
export PYTHONUNBUFFERED=1
EXE="$ROOT/ros_ws/install/tissue_sim/lib/tissue_sim"
RUNS="${TISSUE_SIM_RUNS:-$ROOT/runs}"
RUN="$RUNS/$(date -u +%Y-%m-%dT%H-%M-%SZ)"
mkdir -p "$RUN/logs"
echo "demo: run folder $RUN (ROS_DOMAIN_ID=$ROS_DOMAIN_ID)"

PIDS=()
cleanup() {
  for pid in "${PIDS[@]}"; do kill -INT "$pid" 2>/dev/null; done
  for pid in "${PIDS[@]}"; do
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
    kill -KILL "$pid" 2>/dev/null
  done
  PIDS=()
}
trap 'cleanup; exit 130' INT TERM
trap cleanup EXIT

stop() {  # stop PID: SIGINT, wait up to 15 s, then SIGKILL
  kill -INT "$1" 2>/dev/null
  for _ in $(seq 75); do kill -0 "$1" 2>/dev/null || return 0; sleep 0.2; done
  echo "demo: pid $1 did not stop on SIGINT; killing it" >&2
  kill -KILL "$1" 2>/dev/null
}

if [ -z "${DEMO_MODEL:-}" ] && ! python -c 'from tissue_sim.core import builder; builder.default_inputs()' 2>/dev/null; then
  echo "demo: the bundled anatomy (tissue_sim/data/lower_limb) is missing: run \`make anatomy\` or set DEMO_MODEL=<model.npz>"
  exit 1
fi

# Recorded besides the tissue topics: the TF tree, the robot description and the bone markers (once),
# and the soft-tissue markers, which the simulator publishes at DEMO_MARKER_HZ (its marker_rate: the
# full mesh is ~0.8 MB a frame, ~0.15 MB compressed; at the default 3 Hz a run is ~1.8 MB/s on disk,
# 1.4 of it /tissue/state, and the recorder is not flooded with 26 MB/s it would drop), so the run
# opens in Foxglove's 3D panel (bones move with /tf at the full frame rate). DEMO_MARKERS=0: no markers.
REC_TOPICS=(--topics /tf /tf_static /robot_description)
if [ "${DEMO_MARKERS:-1}" = 1 ]; then
  REC_TOPICS+=(/tissue/bone_markers /tissue/markers)
fi
"$EXE/recorder" -o "$RUN/run.mcap" "${REC_TOPICS[@]}" --meta "demo_seconds=$SECONDS_SIM" \
  >"$RUN/logs/recorder.log" 2>&1 &
REC=$!; PIDS+=("$REC")

MARKER_HZ="${DEMO_MARKER_HZ:-3}"; [[ "$MARKER_HZ" == *.* ]] || MARKER_HZ="$MARKER_HZ.0"   # a ROS double
SIM_P=(-p "params:=$PARAMS" -p "marker_rate:=$MARKER_HZ")
[ -n "${DEMO_MODEL:-}" ] && SIM_P+=(-p "model:=$DEMO_MODEL")
"$EXE/simulator" --ros-args --params-file "$ROOT/src/tissue_sim/tissue_sim/config/simulator.yaml" \
  "${SIM_P[@]}" -p start_paused:=true >"$RUN/logs/simulator.log" 2>&1 &
SIM=$!; PIDS+=("$SIM")

echo "demo: loading the model (a first run builds the bundled anatomy and compiles the solver: about 1.5 minutes on 2 cores)"
for _ in $(seq $((TIMEOUT * 5))); do
  grep -q 'simulator ready' "$RUN/logs/simulator.log" && break
  if ! kill -0 "$SIM" 2>/dev/null; then
    echo "demo: the simulator stopped:"; cat "$RUN/logs/simulator.log"; exit 1
  fi
  sleep 0.2
done
grep -q 'simulator ready' "$RUN/logs/simulator.log" || { echo "demo: simulator not ready in ${TIMEOUT} s"; exit 1; }
grep -m1 "model '" "$RUN/logs/simulator.log" | sed 's/^.*\]: /demo: /'

echo "demo: activation ${ACT_ARGS[*]}"
"$EXE/activation" "${ACT_ARGS[@]}" >"$RUN/logs/activation.log" 2>&1 &
ACT=$!; PIDS+=("$ACT")

# Watch from a separate process: resume the (paused) simulator once the recorder is connected and
# the activation node publishes (it has the model's muscles: the profile starts at sim time 0),
# measure what a subscriber receives, stop at DEMO_SECONDS of sim time.
python - "$RUN" "$SECONDS_SIM" "$TIMEOUT" "$PARAMS" "${ACT_ARGS[*]}" <<'PY'
import json, sys, time
from pathlib import Path
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from diagnostic_msgs.msg import DiagnosticArray
from std_srvs.srv import SetBool
from tissue_msgs.msg import MuscleActivation
run, sim_seconds, timeout = Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node('demo_monitor')
arr, js_last, diag = [], [None], [None]
node.create_subscription(JointState, '/joint_states', lambda m: (arr.append(time.monotonic()), js_last.__setitem__(0, m)), 10)
node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diag.__setitem__(0, m), 10)
acts = []
node.create_subscription(MuscleActivation, '/tissue/activation', acts.append, 10)
pause = node.create_client(SetBool, '/simulator/pause')
t0 = time.monotonic()
def spin_until(cond, limit, what):
    while not cond():
        if time.monotonic() - t0 > limit:
            sys.exit(f'demo: timed out waiting for {what}')
        rclpy.spin_once(node, timeout_sec=0.05)
spin_until(lambda: pause.service_is_ready(), timeout, 'the simulator pause service')
act_pubs = lambda: node.count_publishers('/tissue/activation')
rec_subs = lambda: node.count_subscribers('/tissue/state')
spin_until(lambda: act_pubs() >= 1 and rec_subs() >= 1, timeout, 'activation node and recorder to connect')
spin_until(lambda: len(acts) >= 1, timeout, 'the activation node to publish')
spin_until(lambda: len(arr) >= 1, timeout, 'frames')
fut = pause.call_async(SetBool.Request(data=False))
spin_until(lambda: fut.done(), 30, 'resume')
print(f'demo: running {sim_seconds:g} s of simulated time', flush=True)
w0 = time.monotonic(); n0 = len(arr)
sim0 = js_last[0].header.stamp.sec + js_last[0].header.stamp.nanosec * 1e-9
def sim_now():
    s = js_last[0].header.stamp
    return s.sec + s.nanosec * 1e-9
last_print = 0
while sim_now() - sim0 < sim_seconds:
    if time.monotonic() - w0 > timeout:
        print(f'demo: wall timeout after {timeout:.0f} s at sim time {sim_now():.2f} s', flush=True)
        break
    rclpy.spin_once(node, timeout_sec=0.05)
    if time.monotonic() - last_print > 2.0:
        last_print = time.monotonic()
        print(f'  sim t = {sim_now():5.2f} s   knee = {js_last[0].position[0]:+.3f} rad', flush=True)
w1 = time.monotonic()
ts = [t for t in arr[n0:] if t <= w1]
rate = (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 2 else 0.0
gaps = sorted(b - a for a, b in zip(ts, ts[1:]))
dvals = {kv.key: kv.value for kv in diag[0].status[0].values} if diag[0] else {}
summary = {
    'params': sys.argv[4],
    'activation': sys.argv[5],
    'sim_seconds': round(sim_now() - sim0, 4),
    'wall_seconds': round(w1 - w0, 3),
    'publish_rate_hz': round(rate, 2),
    'publish_rate_target_hz': 34.0,
    'inter_arrival_p99_ms': round(1e3 * gaps[int(0.99 * (len(gaps) - 1))], 2) if gaps else None,
    'inter_arrival_max_ms': round(1e3 * gaps[-1], 2) if gaps else None,
    'real_time_factor': round((sim_now() - sim0) / (w1 - w0), 4),
    'final_knee_angle_rad': round(float(js_last[0].position[0]), 5),
    'final_knee_angle_deg': round(float(js_last[0].position[0]) * 57.29577951308232, 2),
    'joint': js_last[0].name[0],
    'final_joint_angles_deg': {n: round(float(p) * 57.29577951308232, 2) for n, p in zip(js_last[0].name, js_last[0].position)
                               if not n.endswith(('_tx', '_ty', '_tz'))},     # (a path's translations are metres)
    'marker_encode_publish_ms_mean': float(dvals.get('marker_ms_mean', 'nan')),
    'diagnostics_level': ord(diag[0].status[0].level) if diag[0] else None,   # 0 OK, 1 WARN, 2 ERROR
    'diagnostics_message': diag[0].status[0].message if diag[0] else '',
    'mcap': 'run.mcap',
}
(run / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
node.destroy_node()
rclpy.shutdown()
PY
MON=$?

stop "$ACT"; stop "$SIM"; stop "$REC"
PIDS=()
[ $MON -eq 0 ] || { echo "demo: the run did not complete (see $RUN/logs)"; exit 1; }
tail -1 "$RUN/logs/recorder.log" | sed 's/^/demo: /'

python - "$RUN/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print('demo summary')
print(f"  parameters           {s['params']}; activation: {s['activation']}")
print(f"  simulated            {s['sim_seconds']:.2f} s in {s['wall_seconds']:.2f} s of wall time")
print(f"  publish rate         {s['publish_rate_hz']:.2f} Hz seen by a subscriber (floor {s['publish_rate_target_hz']:g} Hz), p99 gap {s['inter_arrival_p99_ms']} ms, max {s['inter_arrival_max_ms']} ms")
print(f"  real-time factor     {s['real_time_factor']:.3f}")
print(f"  final knee angle     {s['final_knee_angle_rad']:+.4f} rad ({s['final_knee_angle_deg']:+.1f} deg, {s['joint']})")
print("  final joint angles   " + ', '.join(f"{n} {v:+.1f} deg" for n, v in s['final_joint_angles_deg'].items()))
PY

if tissue-sim analyze --help >/dev/null 2>&1; then
  echo "demo: tissue-sim analyze"
  tissue-sim analyze -q "$RUN/run.mcap" -o "$RUN/analysis" || echo "demo: analyze failed (see above)"
fi
if tissue-sim render --help >/dev/null 2>&1; then
  echo "demo: tissue-sim render"
  tissue-sim render "$RUN/run.mcap" -o "$RUN/figures" || echo "demo: render failed (see above)"
fi
echo "demo: files written under $RUN:"
(cd "$RUN" && find . -type f | sort | sed 's|^\./|  |')
