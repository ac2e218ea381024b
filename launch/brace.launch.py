"""Launch the four nodes of a device (ROS 2 installs with launch_ros).

    ros2 launch brace_control brace.launch.py [config:=<device>.yaml] [sim:=true|false]

The same nodes as ``ros2 run brace_control bringup --processes``: every node reads the
device file as its parameter file. On shutdown the CAN driver node disables its drives
itself; ``brace-bringup`` additionally calls the driver's disable service before it
stops the other nodes.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = ('trajectory_node', 'ik_node', 'can_driver_node', 'kinetics_node')


def generate_launch_description() -> LaunchDescription:
    default_config = os.path.join(get_package_share_directory('brace_control'),
                                  'config', 'lumbar_brace.yaml')
    config = LaunchConfiguration('config')
    sim = LaunchConfiguration('sim')
    actions = [
        DeclareLaunchArgument('config', default_value=default_config,
                              description='device YAML (ROS 2 parameter file)'),
        DeclareLaunchArgument('sim', default_value='true',
                              description='start the simulated brace on the virtual bus'),
    ]
    for name in NODES:
        params = [config]
        if name == 'can_driver_node':
            params.append({'can.sim': sim})
        actions.append(Node(package='brace_control', executable=name, name=name,
                            parameters=params, output='screen', emulate_tty=True))
    return LaunchDescription(actions)
