"""tissue_sim demo: the simulator on the bundled lower limb, an activation profile that contracts the
hamstrings, (record:=true) the MCAP recorder, and robot_state_publisher when that package is installed
(a system ROS 2: apt install ros-jazzy-robot-state-publisher; the pip set-up has none): it makes /tf
from /joint_states and the URDF of the model, and the simulator's own TF is switched off (publish_tf
false: one source of TF) and so is its /robot_description (robot_state_publisher publishes the same
URDF there). Without it the simulator publishes /tf, /tf_static and /robot_description itself.

    ros2 launch tissue_sim demo.launch.py
    ros2 launch tissue_sim demo.launch.py params:=paper profile:=step level:=0.5
    ros2 launch tissue_sim demo.launch.py profile:=kick      # a named motion (its own muscles)
    ros2 launch tissue_sim demo.launch.py record:=true output:=/tmp/demo.mcap

One Ctrl-C stops every node (the recorder closes its file). Launch arguments: see
`ros2 launch tissue_sim demo.launch.py --show-args` and docs/ros.md.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    args = [
        DeclareLaunchArgument('model', default_value='', description="model file; '' = the bundled lower limb"),
        DeclareLaunchArgument('params', default_value='physical',
                              description='solver parameter set: physical (SI), paper (Table 2) or a YAML file'),
        DeclareLaunchArgument('publish_markers', default_value='true', description='publish /tissue/markers'),
        DeclareLaunchArgument('profile', default_value='ramp',
                              description='activation profile of the activation node (step, ramp, ramp_hold, sine, paper, ...) '
                                          'or a named motion (knee_flexion, knee_extension, kick, heel_raise, ankle_pump)'),
        DeclareLaunchArgument('muscles', default_value='hamstrings',
                              description='muscles or groups the profile drives (space separated; not used by a motion)'),
        DeclareLaunchArgument('level', default_value='1.0', description='peak activation in [0, 1]'),
        DeclareLaunchArgument('rise', default_value='8.0', description='ramp: rise time [s]'),
        DeclareLaunchArgument('record', default_value='false', description='start the MCAP recorder'),
        DeclareLaunchArgument('output', default_value='tissue_sim_demo.mcap', description='recording path'),
        DeclareLaunchArgument('robot_state_publisher', default_value='auto',
                              description='auto: start robot_state_publisher when its package is installed; '
                                          'true or false: always or never'),
    ]
    recorder = Node(
        package='tissue_sim', executable='recorder', name='recorder', output='screen',
        arguments=['-o', LaunchConfiguration('output')], condition=IfCondition(LaunchConfiguration('record')))
    return LaunchDescription(args + [OpaqueFunction(function=simulator_and_tf), OpaqueFunction(function=activation),
                                     recorder])


def activation(context):
    """The activation node; a named motion drives its own muscles (no --muscles, --rise)."""
    from tissue_sim.core.activation import MOTIONS
    profile = LaunchConfiguration('profile').perform(context)
    args = ['--profile', profile, '--level', LaunchConfiguration('level')]
    if profile not in MOTIONS:
        args += ['--muscles', LaunchConfiguration('muscles'), '--rise', LaunchConfiguration('rise')]
    return [Node(package='tissue_sim', executable='activation', name='activation', output='screen', arguments=args)]


def have_robot_state_publisher() -> bool:
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        get_package_share_directory('robot_state_publisher')
        return True
    except PackageNotFoundError:
        return False


def simulator_and_tf(context):
    """The simulator, and robot_state_publisher (with the simulator's TF off) when it is wanted and
    installed; its robot_description is the URDF of the model the simulator runs."""
    model = LaunchConfiguration('model').perform(context)
    want = LaunchConfiguration('robot_state_publisher').perform(context).lower()
    if want not in ('auto', 'true', 'false'):
        raise ValueError(f'robot_state_publisher:={want}: expected auto, true or false')
    rsp = want == 'true' or (want == 'auto' and have_robot_state_publisher())
    simulator = Node(
        package='tissue_sim', executable='simulator', name='simulator', output='screen',
        parameters=[{'model': model, 'params': LaunchConfiguration('params'),
                     'publish_markers': LaunchConfiguration('publish_markers'),
                     'publish_tf': not rsp, 'publish_robot_description': not rsp}])
    if not rsp:
        return [simulator]
    return [simulator, Node(package='robot_state_publisher', executable='robot_state_publisher',
                            name='robot_state_publisher', output='screen',
                            parameters=[{'robot_description': robot_description(model), 'use_sim_time': True}])]


def robot_description(model: str) -> str:
    """The URDF of the simulator's model: the installed file for the bundled limb (tests/test_urdf.py
    keeps it equal to the generated one), else generated from the model file."""
    from pathlib import Path
    from ament_index_python.packages import get_package_share_directory
    if not model:
        return (Path(get_package_share_directory('tissue_sim')) / 'urdf' / 'lower_limb_r.urdf').read_text()
    from tissue_sim.core import urdf
    from tissue_sim.core.load import load_model
    return urdf.robot_description(load_model(model))

