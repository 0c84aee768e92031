"""Shared plumbing of the tissue_sim nodes: parameters declared once (:class:`Param`: the ROS
parameter with its descriptor, the command-line flag, the YAML and docs table generated from it),
argument parsing beside ROS args, QoS profiles, and the one ``main`` of every node (spin until
SIGINT/SIGTERM or the node's own end, always clean up; set-up errors are one line, exit code 2)."""
from __future__ import annotations

import argparse
import dataclasses
import sys

TOPIC_ACTIVATION = '/tissue/activation'
TOPIC_STATE = '/tissue/state'
TOPIC_TOPOLOGY = '/tissue/topology'
TOPIC_MUSCLES = '/tissue/muscles'
TOPIC_MARKERS = '/tissue/markers'
TOPIC_BONE_MARKERS = '/tissue/bone_markers'
TOPIC_JOINTS = '/joint_states'
TOPIC_CLOCK = '/clock'
TOPIC_DIAGNOSTICS = '/diagnostics'
TOPIC_TF = '/tf'
TOPIC_TF_STATIC = '/tf_static'
TOPIC_ROBOT_DESCRIPTION = '/robot_description'
TISSUE_TOPICS = (TOPIC_STATE, TOPIC_TOPOLOGY, TOPIC_ACTIVATION, TOPIC_JOINTS, TOPIC_DIAGNOSTICS)
TOPIC_TYPES = {      # the types of the topics the nodes publish (a recorder subscribes before they appear)
    TOPIC_STATE: 'tissue_msgs/msg/TissueState', TOPIC_TOPOLOGY: 'tissue_msgs/msg/TissueTopology',
    TOPIC_MUSCLES: 'tissue_msgs/msg/MuscleSet',
    TOPIC_ACTIVATION: 'tissue_msgs/msg/MuscleActivation', TOPIC_JOINTS: 'sensor_msgs/msg/JointState',
    TOPIC_DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray', TOPIC_MARKERS: 'visualization_msgs/msg/MarkerArray',
    TOPIC_BONE_MARKERS: 'visualization_msgs/msg/MarkerArray',
    TOPIC_CLOCK: 'rosgraph_msgs/msg/Clock', TOPIC_TF: 'tf2_msgs/msg/TFMessage',
    TOPIC_TF_STATIC: 'tf2_msgs/msg/TFMessage', TOPIC_ROBOT_DESCRIPTION: 'std_msgs/msg/String'}


def parse_args(parser: argparse.ArgumentParser, argv=None):
    """Parse the non-ROS arguments (``--ros-args ...`` removed). Returns (args, full argv)."""
    from rclpy.utilities import remove_ros_args
    argv = list(sys.argv if argv is None else argv)
    rest = remove_ros_args(args=argv)[1:]
    parser.epilog = (parser.epilog or '') + (
        '\nROS arguments follow --ros-args, e.g. --ros-args -p publish_rate:=34.0 '
        '--params-file simulator.yaml -r __ns:=/left_leg')
    return parser.parse_args(rest), argv


def get_message(type_name: str):
    """Message class of 'pkg/msg/Type' (or 'pkg/Type'); ValueError naming the problem."""
    import importlib
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or parts[1] != 'msg':
        raise ValueError(f'bad message type {type_name!r} (expected pkg/msg/Type)')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2])
    except (ImportError, AttributeError):
        raise ValueError(f'message type {type_name} is not installed (is its package built and sourced?)') from None


def qos_latched():
    """Reliable, transient-local, depth 1: late joiners get the last message (topology)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def qos_stream(depth: int = 10):
    """Reliable, volatile: the per-frame topics (what RViz, Foxglove and the recorder use)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class OwnParticipant:
    """A DDS participant of its own for a node's large messages (the full-mesh markers; a finer model's TissueState): a
    second rclpy context on the node's domain with one node, ``<node name>_<suffix>`` in the node's namespace, whose
    publishers are made on the names the node resolves (its remappings apply).

    Why. Fast DDS puts every sample a participant sends through shared memory into that participant's one segment
    (512 KB, Fast DDS's default; under ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` rmw_fastrtps builds the transports
    itself, so an XML profile cannot enlarge it). A 0.8-MB MarkerArray, sent as fragments that each fill most of the
    segment, left no room for the small samples of the same participant: /joint_states, /tf and /tissue/state
    reached a subscriber in bursts after 150-300-ms gaps while the markers flowed (docs/ros.md "Performance"). From a
    participant of their own the markers use a segment of their own. ``close()`` destroys the node and shuts the
    context down."""

    def __init__(self, node, suffix: str):
        import rclpy
        self._node = node
        self.context = rclpy.Context()
        self.context.init(args=[], domain_id=node.context.get_domain_id())
        self.node = rclpy.create_node(f'{node.get_name()}_{suffix}', namespace=node.get_namespace(),
                                      context=self.context, start_parameter_services=False)

    def create_publisher(self, msg_type, topic: str, qos):
        return self.node.create_publisher(msg_type, self._node.resolve_topic_name(topic), qos)

    def close(self) -> None:
        if self.context.ok():
            self.node.destroy_node()
            self.context.shutdown()


@dataclasses.dataclass(frozen=True)
class Param:
    """One node parameter, declared once: the ROS parameter (with its descriptor: description, range,
    choices, read-only) and its command-line flag ``--name-with-dashes`` (bools: ``--name`` /
    ``--no-name``), plus ``aliases``: extra option strings, or (option, value) pairs for a flag that
    sets a fixed value (``('--as-fast-as-possible', False)``)."""
    name: str
    default: object
    description: str
    lo: float | None = None
    hi: float | None = None
    step: float | None = None
    choices: tuple = ()
    read_only: bool = False
    aliases: tuple = ()

    @property
    def flag(self) -> str:
        return '--' + self.name.replace('_', '-')

    def descriptor(self):
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
        d = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.choices:
            d.additional_constraints = 'one of: ' + ', '.join(self.choices)
        if isinstance(self.default, bool) or (self.lo is None and self.hi is None):
            pass
        elif isinstance(self.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(self.lo), to_value=float(self.hi),
                                                         step=float(self.step or 0.0))]
        elif isinstance(self.default, int):
            d.integer_range = [IntegerRange(from_value=int(self.lo), to_value=int(self.hi), step=int(self.step or 0))]
        return d


def declare(node, specs) -> dict:
    """Declare every Param of ``specs`` on ``node``; returns {name: value} (overrides applied).
    A value outside ``choices`` is a ValueError naming the parameter."""
    out = {}
    for p in specs:
        value = node.declare_parameter(p.name, p.default, p.descriptor()).value
        if p.choices and value not in p.choices:
            raise ValueError(f'parameter {p.name}={value!r}: expected one of {", ".join(p.choices)}')
        out[p.name] = value
    return out


def add_flags(parser: argparse.ArgumentParser, specs) -> argparse.ArgumentParser:
    """One command-line flag per Param (default None: not given) and its aliases; an epilog saying so."""
    for p in specs:
        strings = [a for a in p.aliases if isinstance(a, str)]
        if isinstance(p.default, bool):
            parser.add_argument(p.flag, *strings, dest=p.name, action=argparse.BooleanOptionalAction,
                                default=None, help=f'{p.description} (default {str(p.default).lower()})')
        else:
            parser.add_argument(p.flag, *strings, dest=p.name, type=type(p.default), default=None,
                                choices=p.choices or None, metavar=None if p.choices else p.name.upper(),
                                help=f'{p.description} (default {p.default!r})'.replace('%', '%%'))
        for a in p.aliases:
            if not isinstance(a, str):
                flag, value = a
                parser.add_argument(flag, dest=p.name, action='store_const', const=value,
                                    help=f'{p.name}:={str(value).lower()}')
    parser.epilog = (parser.epilog or '') + (
        'Each option above sets the ROS parameter of its name (dashes as underscores; ros2 param describe); '
        'an option given here overrides --ros-args -p and --params-file.')
    return parser


def overrides(args, specs) -> list:
    """rclpy Parameters for the flags given on the command line."""
    from rclpy.parameter import Parameter
    return [Parameter(p.name, value=getattr(args, p.name)) for p in specs if getattr(args, p.name, None) is not None]


def params_yaml(node_name: str, specs) -> dict:
    """The {node: {ros__parameters: {name: default}}} of a --params-file with every default."""
    return {node_name: {'ros__parameters': {p.name: p.default for p in specs}}}


def params_table(specs) -> str:
    """Markdown table of the parameters (docs/ros.md carries it; a test keeps them equal)."""
    def fmt(v):
        return f"`'{v}'`" if v == '' else (f'`{str(v).lower()}`' if isinstance(v, bool) else f'`{v}`')
    rows = ['| parameter | default | run time | flags | |', '|---|---|---|---|---|']
    for p in specs:
        first = f'--[no-]{p.flag[2:]}' if isinstance(p.default, bool) else p.flag
        flags = ', '.join([f'`{first}`'] + [f'`{a if isinstance(a, str) else a[0]}`' for a in p.aliases])
        rows.append(f'| `{p.name}` | {fmt(p.default)} | {"" if p.read_only else "yes"} | {flags} | {p.description} |')
    return '\n'.join(rows) + '\n'


def _is_rcl_error(e) -> bool:
    try:
        from rclpy._rclpy_pybind11 import RCLError
    except ImportError:
        return False
    return isinstance(e, RCLError)


def _shutdown_race(e) -> bool:
    """Whether e, raised by the executor, is SIGINT/SIGTERM stopping the node rather than a fault: an RCLError once
    rclpy's handler has shut the context down, or the RuntimeError of pybind11 ('Unable to convert call argument')
    that a KeyboardInterrupt becomes when it lands inside a subscription's take_message. rclpy shuts the context down
    from its own thread, so that one may come first: up to 1 s is given for the context to go down (seen in 3 of 8
    `ros2 launch` stops of the activation node)."""
    import time
    import rclpy
    if type(e) is RuntimeError and 'Unable to convert call argument' in str(e):
        end = time.monotonic() + 1.0
        while rclpy.ok() and time.monotonic() < end:
            time.sleep(0.01)
        return not rclpy.ok()
    return _is_rcl_error(e) and not rclpy.ok()


def ignore_further_interrupts() -> None:
    """A stop is under way: later SIGINTs are ignored. `ros2 launch` forwards a Ctrl-C to its processes
    while the terminal's (or a killpg's) reaches them too, and a user presses it twice: rclpy chains each
    SIGINT to Python's KeyboardInterrupt, which would cut ``on_shutdown`` short (a recorder's file left
    unfinished) or, raised after main returns, make Python kill itself with SIGINT (exit code -2, which
    launch reports as a crash). SIGTERM and SIGKILL still end a shutdown that hangs."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def spin(node, on_shutdown=None, run=None) -> int:
    """Run the node (``run()``, default rclpy.spin(node)) until SIGINT/SIGTERM (rclpy's handlers),
    shutdown or the node's own end (SystemExit); always run ``on_shutdown``, destroy the node and
    shut rclpy down (further SIGINTs ignored from then on: :func:`ignore_further_interrupts`)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    rc = 0
    try:
        run() if run is not None else rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException, SystemExit):
        pass
    except Exception as e:                  # the executor racing SIGINT/SIGTERM (_shutdown_race): a stop
        if not _shutdown_race(e):
            raise
    finally:
        ignore_further_interrupts()
        try:
            if on_shutdown is not None:
                on_shutdown()
        finally:
            try:
                node.destroy_node()
            except Exception:
                pass
            if rclpy.ok():
                rclpy.shutdown()
    return rc


def main_wrapper(fn):
    """Run a node's main; a UserError/ValueError in set-up is one 'error:' line and exit code 2. A
    SIGINT/SIGTERM during set-up is a stop, as it is later: 'stopped' and exit code 0, no traceback
    (before rclpy.init it raises KeyboardInterrupt; after it, rclpy's handler shuts the context down and
    the next rclpy call, e.g. creating the node, raises RCLError or NotInitializedException)."""
    def wrapped(*args, **kw):
        from ..errors import UserError
        from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
        try:
            return fn(*args, **kw) or 0
        except KeyboardInterrupt:
            ignore_further_interrupts()
            print('stopped', file=sys.stderr)
            return 0
        except Exception as e:
            import rclpy
            from rclpy.exceptions import NotInitializedException
            if (_is_rcl_error(e) or isinstance(e, NotInitializedException)) and not rclpy.ok():
                print('stopped', file=sys.stderr)
                return 0
            if isinstance(e, (UserError, ValueError, FileNotFoundError, InvalidParameterValueException,
                              InvalidParameterTypeException)):
                return _setup_error(e)
            raise
    return wrapped


def _setup_error(e) -> int:
    print(f'error: {e}', file=sys.stderr)
    try:
        import rclpy
        if rclpy.ok():
            rclpy.shutdown()
    except Exception:
        pass
    return 2


def freeze_setup_objects() -> None:
    """Collect the set-up's garbage, then move every object left (modules, the model, compiled
    kernels: ~140 000 objects in the simulator) to the collector's permanent generation. Without it
    the first full (generation-2) collection comes a few seconds into the run, when the frames'
    allocations trigger it, and scans them all: 54-125 ms measured in the simulator (a frame is
    29 ms), a stall in /joint_states. Frozen objects are never scanned; what the run allocates is
    collected as usual."""
    import gc
    gc.collect()
    gc.freeze()


@main_wrapper
def main(make_node, parser: argparse.ArgumentParser, argv=None, check=None) -> int:
    """The one main of the nodes: parse the options beside the ROS arguments (``check(args)`` may
    reject them), rclpy.init, ``make_node(args)`` (an rclpy Node; its optional ``run()`` replaces
    rclpy.spin, its optional ``on_shutdown()`` runs at the end) and spin it (:func:`spin`)."""
    args, argv = parse_args(parser, argv)
    if check is not None:
        check(args)
    import rclpy
    rclpy.init(args=argv)
    try:
        node = make_node(args)
    except KeyError as e:               # a bad name in set-up: one line, like a ValueError
        raise ValueError(str(e).strip('"\'')) from None
    freeze_setup_objects()
    return spin(node, on_shutdown=getattr(node, 'on_shutdown', None), run=getattr(node, 'run', None))
