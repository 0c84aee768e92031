"""tissue_sim demo: the simulator on the bundled lower limb, an activation profile that contracts the
hamstrings, and (record:=true) the MCAP recorder.

    ros2 launch tissue_sim demo.launch.py
    ros2 launch tissue_sim demo.launch.py params:=paper profile:=step level:=0.5
    ros2 launch tissue_sim demo.launch.py record:=true output:=/tmp/demo.mcap

One Ctrl-C stops every node (the recorder closes its file). Launch arguments: see
`ros2 launch tissue_sim demo.launch.py --show-args` and docs/ros.md.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
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
                              description='activation profile of the activation node (step, ramp, ramp_hold, sine, paper, ...)'),
        DeclareLaunchArgument('muscles', default_value='hamstrings',
                              description='muscles or groups the profile drives (space separated)'),
        DeclareLaunchArgument('level', default_value='1.0', description='peak activation in [0, 1]'),
        DeclareLaunchArgument('rise', default_value='8.0', description='ramp: rise time [s]'),
        DeclareLaunchArgument('record', default_value='false', description='start the MCAP recorder'),
        DeclareLaunchArgument('output', default_value='tissue_sim_demo.mcap', description='recording path'),
    ]
    simulator = Node(
        package='tissue_sim', executable='simulator', name='simulator', output='screen',
        parameters=[{'model': LaunchConfiguration('model'), 'params': LaunchConfiguration('params'),
                     'publish_markers': LaunchConfiguration('publish_markers')}])
    activation = Node(
        package='tissue_sim', executable='activation', name='activation', output='screen',
        arguments=['--profile', LaunchConfiguration('profile'), '--muscles', LaunchConfiguration('muscles'),
                   '--level', LaunchConfiguration('level'), '--rise', LaunchConfiguration('rise')])
    recorder = Node(
        package='tissue_sim', executable='recorder', name='recorder', output='screen',
        arguments=['-o', LaunchConfiguration('output')], condition=IfCondition(LaunchConfiguration('record')))
    return LaunchDescription(args + [simulator, activation, recorder])
