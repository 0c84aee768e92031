"""Shared plumbing of the tissue_sim nodes: argument parsing beside ROS args, QoS profiles,
parameter descriptors, and a spin loop that shuts down cleanly on SIGINT/SIGTERM."""
from __future__ import annotations

import argparse
import sys

TOPIC_ACTIVATION = '/tissue/activation'
TOPIC_STATE = '/tissue/state'
TOPIC_TOPOLOGY = '/tissue/topology'
TOPIC_MARKERS = '/tissue/markers'
TOPIC_JOINTS = '/joint_states'
TOPIC_CLOCK = '/clock'
TOPIC_DIAGNOSTICS = '/diagnostics'
TISSUE_TOPICS = (TOPIC_STATE, TOPIC_TOPOLOGY, TOPIC_ACTIVATION, TOPIC_JOINTS, TOPIC_DIAGNOSTICS)


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


def declare(node, name, default, description, *, lo=None, hi=None, step=None, choices=None, read_only=False):
    """Declare a parameter with a descriptor (description, range, read-only); returns its value."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    d = ParameterDescriptor(description=description, read_only=read_only)
    if choices:
        d.additional_constraints = 'one of: ' + ', '.join(choices)
    if isinstance(default, bool):
        pass
    elif isinstance(default, float) and (lo is not None or hi is not None):
        d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=float(step or 0.0))]
    elif isinstance(default, int) and (lo is not None or hi is not None):
        d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=int(step or 0))]
    value = node.declare_parameter(name, default, d).value
    if choices and value not in choices:
        raise ValueError(f'parameter {name}={value!r}: expected one of {", ".join(choices)}')
    return value


def _is_rcl_error(e) -> bool:
    try:
        from rclpy._rclpy_pybind11 import RCLError
    except ImportError:
        return False
    return isinstance(e, RCLError)


def spin(node, on_shutdown=None) -> int:
    """Spin until SIGINT/SIGTERM (rclpy's handlers) or shutdown; always run ``on_shutdown``."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    rc = 0
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as e:                  # a callback racing SIGINT sees the context already shut down
        if rclpy.ok() or not _is_rcl_error(e):
            raise
    finally:
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
    def wrapped(argv=None):
        from ..errors import UserError
        from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
        try:
            return fn(argv) or 0
        except KeyboardInterrupt:
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
