"""Foundation: the built workspace, its environment file, tissue_msgs over real DDS between two
processes, domain isolation, and the installed executables."""
import os
import re
import subprocess
import sys
import time

import pytest

import rosutil  # noqa: F401  (first: puts the built workspace on this process's paths)
from rosutil import (EXE_DIR, ROOT, VENV_PYTHON, isolated_domain, ros_context, run_executable,
                     spin_until, start_process, wait_for_publishers, wait_for_subscribers)

ECHO = ROOT / 'scripts' / 'activation_echo.py'


def entry_points():
    """(name, module) of every console script declared in src/tissue_sim/setup.py."""
    text = (ROOT / 'src' / 'tissue_sim' / 'setup.py').read_text()
    return re.findall(r"'([\w-]+)\s*=\s*([\w.]+):\w+'", text)


def test_setup_second_run_is_a_no_op():
    """`make setup` twice: the second run installs nothing and builds nothing, and --check agrees."""
    first = subprocess.run(['bash', 'scripts/setup.sh'], cwd=ROOT, capture_output=True, text=True,
                           timeout=900)
    assert first.returncode == 0, first.stdout + first.stderr
    second = subprocess.run(['bash', 'scripts/setup.sh'], cwd=ROOT, capture_output=True, text=True,
                            timeout=120)
    assert second.returncode == 0, second.stdout + second.stderr
    assert 'installing' not in second.stdout and 'building' not in second.stdout, second.stdout
    check = subprocess.run(['bash', 'scripts/setup.sh', '--check'], cwd=ROOT, capture_output=True,
                           text=True, timeout=120)
    assert check.returncode == 0 and 'up to date' in check.stdout, check.stdout + check.stderr


def test_env_file_sets_workspace_and_venv_under_set_u():
    """env.sh works under `set -u`, chains the venv AND the workspace, and is idempotent."""
    script = ('set -eu; . ./env.sh; . ./env.sh; '
              'printf "%s\\n" "$AMENT_PREFIX_PATH" "$PATH" "$ROS_AUTOMATIC_DISCOVERY_RANGE"; '
              'python -c "from tissue_msgs.msg import MuscleActivation, TissueState, TissueTopology; '
              'import rclpy; print(MuscleActivation.__module__)"')
    env = {'PATH': '/usr/bin:/bin', 'HOME': os.environ.get('HOME', '/tmp')}
    res = subprocess.run(['bash', '-c', script], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    ament, path, rng, module = res.stdout.splitlines()
    prefixes = ament.split(':')
    assert str(ROOT / '.venv') in prefixes
    assert str(ROOT / 'ros_ws' / 'install' / 'tissue_msgs') in prefixes
    assert len(prefixes) == len(set(prefixes)), 'sourcing twice duplicated entries'
    assert path.split(':')[0] == str(EXE_DIR)
    assert rng == 'LOCALHOST'
    assert module.startswith('tissue_msgs.msg')


def test_env_file_names_the_fast_dds_profile_and_fast_dds_parses_it(tmp_path):
    """env.sh names the package's Fast DDS profile (config/fastdds.xml: announcements every 0.5 s, docs/ros.md) unless
    the caller names one; a participant made with it prints no XML parser error (a bad profile prints Fast DDS's
    "XMLPARSER Error" lines, checked here with a copy that has one broken value)."""
    profile = ROOT / 'src' / 'tissue_sim' / 'tissue_sim' / 'config' / 'fastdds.xml'
    node = 'import rclpy; rclpy.init(); rclpy.create_node("profile_probe"); print("made"); rclpy.shutdown()'

    def run(pre=''):
        script = f'set -eu; {pre}. ./env.sh; printf "%s\\n" "$FASTRTPS_DEFAULT_PROFILES_FILE"; python -c \'{node}\''
        env = {'PATH': '/usr/bin:/bin', 'HOME': os.environ.get('HOME', '/tmp'), 'ROS_DOMAIN_ID': '231'}
        res = subprocess.run(['bash', '-c', script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
        assert res.returncode == 0, res.stdout + res.stderr
        return res.stdout.splitlines()[0], res.stdout + res.stderr
    named, out = run()
    assert named == str(profile) and 'made' in out and 'XMLPARSER' not in out, out
    assert '<leaseAnnouncement>' in profile.read_text()
    bad = tmp_path / 'fastdds_bad_profile.xml'
    bad.write_text(profile.read_text().replace('<sec>0</sec>', '<sec>zero</sec>'))
    named, out = run(f'export FASTRTPS_DEFAULT_PROFILES_FILE={bad}; ')
    assert named == str(bad) and 'XMLPARSER' in out, out


def test_message_definitions_are_the_built_ones():
    from tissue_msgs.msg import MuscleActivation, TissueState, TissueTopology
    msg = MuscleActivation(muscle_names=['vastus_lateralis', 'biceps_femoris_lh'],
                           activations=[0.25, 1.0])
    assert msg.get_fields_and_field_types() == {
        'header': 'std_msgs/Header', 'muscle_names': 'sequence<string>',
        'activations': 'sequence<float>'}
    assert 'vertex_positions' in TissueState.get_fields_and_field_types()
    assert 'cell_offsets' in TissueTopology.get_fields_and_field_types()


@pytest.mark.ros
def test_two_processes_exchange_muscle_activation_over_dds():
    """This process publishes MuscleActivation; activation_echo (another process) republishes it;
    this process receives it back: both directions over Fast DDS, matched before publishing."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from tissue_msgs.msg import MuscleActivation

    n_msgs = 25
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('foundation_probe', context=ctx)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        got = []
        pub = node.create_publisher(MuscleActivation, 'activation_in', qos)
        sub = node.create_subscription(MuscleActivation, 'activation_out', got.append, qos)
        with start_process([VENV_PYTHON, ECHO, '--tag', f'echo-{os.getpid()}'], env=dom.env) as echo:
            echo.wait_for_output(r'activation_echo: ready', timeout=30)
            wait_for_subscribers(node, pub, 1, timeout=30)
            wait_for_publishers(node, sub, 1, timeout=30)
            sent = []
            for i in range(n_msgs):
                msg = MuscleActivation()
                msg.header.stamp.sec = 1000 + i
                msg.header.stamp.nanosec = 7 * i
                msg.muscle_names = ['rectus_femoris', 'vastus_medialis', f'm{i}']
                msg.activations = [i / n_msgs, 1.0 - i / n_msgs, 0.5]
                pub.publish(msg)
                sent.append(msg)
            spin_until(lambda: len(got) >= n_msgs, node, timeout=30,
                       what=f'{n_msgs} echoed MuscleActivation messages (got {len(got)})')
            rc = echo.stop()
        node.destroy_node()
    assert rc == 0, echo.output
    assert f'echoed {n_msgs} messages' in echo.output
    assert len(got) == n_msgs
    for s, r in zip(sent, got):    # reliable, one publisher: in order, nothing lost
        assert r.header.frame_id == f'echo-{os.getpid()}'
        assert (r.header.stamp.sec, r.header.stamp.nanosec) == (s.header.stamp.sec, s.header.stamp.nanosec)
        assert list(r.muscle_names) == list(s.muscle_names)
        assert list(r.activations) == pytest.approx(list(s.activations), abs=1e-7)   # float32


@pytest.mark.ros
def test_isolated_domains_do_not_see_each_other():
    """A peer in domain A matches a publisher in A and never one in domain B (positive control
    first, so the negative result is not just slow discovery)."""
    import rclpy
    from tissue_msgs.msg import MuscleActivation

    with isolated_domain() as dom_a, isolated_domain() as dom_b:
        assert dom_a.id != dom_b.id
        with ros_context(dom_a.id) as ctx_a, ros_context(dom_b.id) as ctx_b:
            node_a = rclpy.create_node('probe_a', context=ctx_a)
            node_b = rclpy.create_node('probe_b', context=ctx_b)
            pub_a = node_a.create_publisher(MuscleActivation, 'activation_in', 10)
            pub_b = node_b.create_publisher(MuscleActivation, 'activation_in', 10)
            with start_process([VENV_PYTHON, ECHO], env=dom_a.env) as echo:
                wait_for_subscribers(node_a, pub_a, 1, timeout=30)
                # the peer is discoverable now; give domain B the same second again to leak
                t0 = time.monotonic()
                spin_until(lambda: time.monotonic() - t0 > 1.5, node_b, timeout=5, what='1.5 s')
                assert pub_b.get_subscription_count() == 0
                assert pub_a.get_subscription_count() == 1
                assert echo.returncode is None, echo.output
            node_a.destroy_node()
            node_b.destroy_node()


@pytest.mark.ros
def test_installed_activation_executable_reaches_a_subscriber_in_another_process():
    """The installed `activation` node (its own process, started as `ros2 run` would) publishes
    MuscleActivation that a subscriber in this process receives; SIGINT stops it cleanly."""
    import rclpy
    from tissue_msgs.msg import MuscleActivation

    names = ['vastus_lateralis', 'rectus_femoris']
    with isolated_domain() as dom, ros_context(dom.id) as ctx:
        node = rclpy.create_node('activation_probe', context=ctx)
        got = []
        sub = node.create_subscription(MuscleActivation, '/tissue/activation', got.append, 10)
        with run_executable('activation', '--profile', 'step', '--muscles', *names, '--level', '0.4',
                            '--wall-time', '--rate', '20', env=dom.env) as proc:
            wait_for_publishers(node, sub, 1, timeout=30)
            spin_until(lambda: len(got) >= 3, node, timeout=30, what='3 MuscleActivation messages')
            rc = proc.stop()
        node.destroy_node()
    assert rc == 0, proc.output
    assert 'Traceback' not in proc.output, proc.output
    for msg in got[:3]:
        assert list(msg.muscle_names) == names
        assert list(msg.activations) == pytest.approx([0.4, 0.4], abs=1e-6)


def test_domain_ids_are_exclusive_and_valid():
    held = [rosutil.acquire_domain() for _ in range(5)]
    try:
        ids = [d.id for d in held]
        assert len(set(ids)) == 5
        assert all(1 <= i <= 101 or 215 <= i <= 232 for i in ids)
        for d in held:
            assert d.env['ROS_DOMAIN_ID'] == str(d.id)
            assert d.env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
            assert 'ROS_LOCALHOST_ONLY' not in d.env
    finally:
        for d in held:
            d.release()


def test_every_entry_point_is_installed():
    names = [n for n, _ in entry_points()]
    assert {'simulator', 'activation', 'recorder', 'replay', 'tissue-sim'} <= set(names)
    for name in names:
        assert (EXE_DIR / name).is_file(), f'{EXE_DIR / name} missing: rebuild with make setup'


@pytest.mark.parametrize('name,module', entry_points())
def test_installed_executable_prints_usage(name, module):
    """ros_ws/install/tissue_sim/lib/tissue_sim/<exe> --help prints usage and exits 0."""
    mod_file = ROOT / 'src' / 'tissue_sim' / (module.replace('.', '/') + '.py')
    assert mod_file.exists(), f'entry point {name} names {module}, but {mod_file} does not exist'
    with isolated_domain() as dom:
        res = subprocess.run([EXE_DIR / name, '--help'], env=dom.env, capture_output=True,
                             text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert 'usage' in res.stdout.lower(), res.stdout
    assert 'Traceback' not in res.stderr
