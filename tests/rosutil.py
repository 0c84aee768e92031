"""Helpers for tests that use real ROS 2 (rclpy over Fast DDS), shared by every ROS test.

Importing this module makes the built workspace usable in this process even when pytest was not
started from a shell that sourced env.sh: it reads the variables env.sh sets (AMENT_PREFIX_PATH,
LD_LIBRARY_PATH, PYTHONPATH, PATH, ...) into os.environ and sys.path. Import it BEFORE rclpy or
tissue_msgs. If the workspace is not built, every test that imports it is skipped locally with the
command to run; under `make test` (TISSUE_SIM_REQUIRE_WS=1) that is an error instead.

Isolation: every test gets its own ROS_DOMAIN_ID from `isolated_domain()` (a lock file per id
under the temp dir, so concurrent pytest runs on one machine never share an id) and localhost-only
discovery (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST). Nodes in the test process use their own
rclpy Context bound to that domain; subprocesses get `domain.env`.

Typical use::

    from rosutil import isolated_domain, ros_context, run_executable, wait_for_publishers
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('probe', context=ctx)
        sub = node.create_subscription(MuscleActivation, '/tissue/activation', got.append, 10)
        with run_executable('activation', '--help', env=dom.env) as proc: ...
        wait_for_publishers(node, sub, 1, timeout=20)
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV_FILE = ROOT / 'env.sh'
INSTALL = ROOT / 'ros_ws' / 'install'
EXE_DIR = INSTALL / 'tissue_sim' / 'lib' / 'tissue_sim'
VENV_PYTHON = ROOT / '.venv' / 'bin' / 'python'

# Valid domain ids that map to Fast DDS ports on Linux without clashing with the ephemeral port
# range: 0-101 and 215-232. 0 is the default every ROS user is on: never used by tests.
DOMAIN_IDS = tuple(range(1, 102)) + tuple(range(215, 233))
ENV_KEYS = ('TISSUE_SIM_ROOT', 'VIRTUAL_ENV', 'PATH', 'AMENT_PREFIX_PATH', 'CMAKE_PREFIX_PATH',
            'PYTHONPATH', 'LD_LIBRARY_PATH', 'RMW_IMPLEMENTATION', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
            'FASTRTPS_DEFAULT_PROFILES_FILE')


class WorkspaceMissing(RuntimeError):
    """The colcon workspace is not built (run `make setup`)."""


def _read_env_file() -> dict:
    """The variables env.sh sets, read by sourcing it in a clean POSIX shell."""
    if not ENV_FILE.is_file() or not (INSTALL / 'tissue_msgs').is_dir():
        raise WorkspaceMissing(f'{ENV_FILE} or {INSTALL}/tissue_msgs missing: run `make setup`')
    base = {'PATH': '/usr/local/bin:/usr/bin:/bin', 'HOME': os.environ.get('HOME', '/tmp')}
    out = subprocess.run(['sh', '-c', '. "$0" && env -0', str(ENV_FILE)], env=base,
                         capture_output=True, check=True).stdout
    env = dict(item.split('=', 1) for item in out.decode().split('\0') if '=' in item)
    return {k: env[k] for k in ENV_KEYS if k in env}


def _merge_path(name: str, value: str, current: str | None) -> str:
    """env.sh's entries for a ':' list first, then the current ones not already present."""
    if name not in ('PATH', 'AMENT_PREFIX_PATH', 'CMAKE_PREFIX_PATH', 'PYTHONPATH', 'LD_LIBRARY_PATH'):
        return current if (current and name.startswith('ROS_')) else value
    parts = [p for p in value.split(':') if p]
    parts += [p for p in (current or '').split(':') if p and p not in parts]
    return ':'.join(parts)


def activate() -> dict:
    """Apply the workspace environment to this process (os.environ, sys.path); return it."""
    env = _read_env_file()
    os.environ.setdefault('_TISSUE_SIM_LD_AT_START', os.environ.get('LD_LIBRARY_PATH', ''))
    for key, value in env.items():
        os.environ[key] = _merge_path(key, value, os.environ.get(key))
    # rcpputils reads LD_LIBRARY_PATH at call time to find the message typesupport libraries, and
    # ament_index reads AMENT_PREFIX_PATH at call time: setting them now is enough.
    for entry in reversed(env.get('PYTHONPATH', '').split(':')):
        if entry and entry not in sys.path:
            sys.path.insert(0, entry)
    os.environ.pop('ROS_LOCALHOST_ONLY', None)   # deprecated in Jazzy; must not be mixed with the range
    _preload_workspace_libraries()
    return env


def _preload_workspace_libraries() -> None:
    """Load the workspace's shared libraries (tissue_msgs typesupports) into this process.

    rosidl's typesupport dispatch dlopen()s `libtissue_msgs__rosidl_typesupport_fastrtps_c.so` by
    bare name, which the dynamic loader resolves with the LD_LIBRARY_PATH of process START (or
    an already loaded library of that name). A pytest not started from a shell that sourced
    env.sh lacks it, so load them now by full path; their $ORIGIN rpath resolves each other.
    Subprocesses do not need this: they get LD_LIBRARY_PATH in their environment.
    """
    import ctypes
    start_ld = os.environ.get('_TISSUE_SIM_LD_AT_START', '')
    for lib in sorted(INSTALL.glob('*/lib/lib*.so')):
        if str(lib.parent) in start_ld.split(':'):
            continue
        ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)


try:
    WORKSPACE_ENV = activate()
except WorkspaceMissing as exc:
    if os.environ.get('TISSUE_SIM_REQUIRE_WS') == '1':
        raise
    import pytest
    pytest.skip(str(exc), allow_module_level=True)


# ---------------------------------------------------------------------------------------------
# Isolated domains
# ---------------------------------------------------------------------------------------------
_LOCK_DIR = Path(tempfile.gettempdir()) / 'tissue_sim-ros-domains'
_counter = itertools.count()


class Domain:
    """A ROS_DOMAIN_ID held exclusively by this process (flock) until `release()`."""

    def __init__(self, domain_id: int, lock_fd: int):
        self.id = domain_id
        self._fd = lock_fd
        self.env = ros_env(domain_id)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)          # closing drops the flock
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()

    def __repr__(self):
        return f'Domain({self.id})'


def acquire_domain() -> Domain:
    """Take a domain id no other live process on this machine holds (through this helper).

    The search starts at an offset derived from the pid and a per-process counter, so parallel
    runs usually get different ids at the first try; the lock makes it certain.
    """
    _LOCK_DIR.mkdir(parents=True, exist_ok=True)
    start = (os.getpid() * 7 + next(_counter) * 13) % len(DOMAIN_IDS)
    for k in range(len(DOMAIN_IDS)):
        did = DOMAIN_IDS[(start + k) % len(DOMAIN_IDS)]
        fd = os.open(_LOCK_DIR / f'{did}.lock', os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EAGAIN, errno.EACCES):
                continue
            raise
        return Domain(did, fd)
    raise RuntimeError(f'all {len(DOMAIN_IDS)} ROS domain ids are held by other test processes')


def isolated_domain() -> Domain:
    """Context manager: `with isolated_domain() as dom:` -> dom.id, dom.env (for subprocesses)."""
    return acquire_domain()


def ros_env(domain_id: int, extra: dict | None = None) -> dict:
    """Environment for a subprocess that runs ROS in `domain_id`, discovering on localhost only."""
    env = dict(os.environ)
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.pop('ROS_STATIC_PEERS', None)
    env.pop('FASTDDS_DEFAULT_PROFILES_FILE', None)      # FASTRTPS_DEFAULT_PROFILES_FILE: env.sh's, as activate() set it
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', RCUTILS_COLORIZED_OUTPUT='0')
    if extra:
        env.update(extra)
    return env


@contextlib.contextmanager
def ros_context(domain_id: int):
    """An initialised rclpy Context bound to `domain_id` (no signal handlers); shut down after."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    # The domain also comes from the environment for anything that reads it.
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


# ---------------------------------------------------------------------------------------------
# Waiting (never sleeping blindly)
# ---------------------------------------------------------------------------------------------
def spin_until(predicate, nodes, timeout: float, what: str, context=None, period: float = 0.05):
    """Spin `nodes` (one or a list) until predicate() is true; AssertionError naming `what` if not
    within `timeout` seconds. Returns the elapsed time [s]."""
    from rclpy.executors import SingleThreadedExecutor
    nodes = nodes if isinstance(nodes, (list, tuple)) else [nodes]
    ctx = context or nodes[0].context
    ex = SingleThreadedExecutor(context=ctx)
    for n in nodes:
        ex.add_node(n)
    t0 = time.monotonic()
    try:
        while True:
            if predicate():
                return time.monotonic() - t0
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f'timed out after {timeout:.1f} s waiting for {what}')
            ex.spin_once(timeout_sec=period)
    finally:
        for n in nodes:
            ex.remove_node(n)
        ex.shutdown()


def wait_for_subscribers(node, publisher, count: int = 1, timeout: float = 20.0) -> float:
    """Spin until `publisher` has matched at least `count` subscriptions."""
    return spin_until(lambda: publisher.get_subscription_count() >= count, node, timeout,
                      f'{count} subscription(s) to match publisher on {publisher.topic_name}')


def wait_for_publishers(node, subscription, count: int = 1, timeout: float = 20.0) -> float:
    """Spin until `subscription` has matched at least `count` publishers."""
    return spin_until(lambda: subscription.get_publisher_count() >= count, node, timeout,
                      f'{count} publisher(s) to match subscription on {subscription.topic_name}')


def assert_own_participant(node, topic: str, node_name: str, other_topic: str, other_node: str) -> None:
    """The graph says ``topic`` is published by ``node_name`` alone and ``other_topic`` by ``other_node``, from two
    DDS participants (ros.common.OwnParticipant): their writers' GUID prefixes, the first 12 bytes of an endpoint's
    GUID, which name its participant, differ."""
    def info(t, who):       # the endpoint shows before its node's name does (ros_discovery_info comes later)
        seen = []
        try:
            spin_until(lambda: seen.append([p.node_name for p in node.get_publishers_info_by_topic(t)]) or
                       seen[-1] == [who], node, 20, f'{who} as the one publisher of {t}')
        except AssertionError as e:
            raise AssertionError(f'{e}; the graph: {seen[-1] if seen else None}') from None
        return bytes(node.get_publishers_info_by_topic(t)[0].endpoint_gid[:12])
    assert info(topic, node_name) != info(other_topic, other_node)

# ---------------------------------------------------------------------------------------------
# Processes
# ---------------------------------------------------------------------------------------------
class Proc:
    """A started child process whose merged stdout/stderr is collected by a thread."""

    def __init__(self, argv, env, cwd=None):
        self.argv = [str(a) for a in argv]
        self.popen = subprocess.Popen(self.argv, env=env, cwd=cwd, stdin=subprocess.DEVNULL,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      start_new_session=True)
        self._lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for raw in self.popen.stdout:
            with self._cond:
                self._lines.append(raw.decode(errors='replace'))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    @property
    def output(self) -> str:
        with self._cond:
            return ''.join(self._lines)

    @property
    def returncode(self):
        return self.popen.poll()

    def wait_for_output(self, pattern: str, timeout: float = 20.0) -> re.Match:
        """Wait until the output matches regex `pattern`; AssertionError (with the output so far)
        if the process exits or `timeout` passes first."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                m = rx.search(''.join(self._lines))
                if m:
                    return m
                left = deadline - time.monotonic()
                if left <= 0 or (self.popen.poll() is not None and not self._reader.is_alive()):
                    raise AssertionError(f'{self.argv[0]}: no output matching {pattern!r} '
                                         f'(exit {self.popen.poll()}); output:\n{"".join(self._lines)}')
                self._cond.wait(min(left, 0.2))

    def stop(self, sig=signal.SIGINT, timeout: float = 10.0) -> int:
        """Send `sig` (SIGINT: a clean rclpy shutdown); escalate to SIGTERM then SIGKILL."""
        for s, t in ((sig, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.popen.poll() is not None:
                break
            with contextlib.suppress(ProcessLookupError):
                self.popen.send_signal(s)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.popen.wait(t)
        self.popen.wait()
        self._reader.join(5)
        return self.popen.returncode


def exe_path(name: str) -> Path:
    """The installed console script ros_ws/install/tissue_sim/lib/tissue_sim/<name>."""
    return EXE_DIR / name


@contextlib.contextmanager
def start_process(argv, env=None, cwd=None, stop_signal=signal.SIGINT, stop_timeout: float = 10.0):
    """Start argv; yield a Proc; stop it with `stop_signal` on exit (also on test failure)."""
    proc = Proc(argv, env if env is not None else dict(os.environ), cwd)
    try:
        yield proc
    finally:
        proc.stop(stop_signal, stop_timeout)


def run_executable(name: str, *args, env=None, cwd=None, stop_timeout: float = 10.0):
    """Context manager: start the installed executable `name` (as `ros2 run tissue_sim name`
    would, but directly so that SIGINT reaches the node) and stop it with SIGINT."""
    path = exe_path(name)
    if not path.exists():
        raise FileNotFoundError(f'{path} not installed: run `make setup`')
    return start_process([path, *args], env=env, cwd=cwd, stop_timeout=stop_timeout)
