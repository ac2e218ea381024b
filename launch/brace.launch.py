"""Launch the nodes of a device (ROS 2 installs with launch_ros).

    ros2 launch brace_control brace.launch.py [config:=<device>.yaml] [sim:=true|false]
                                              [manual_lifecycle:=false|true]

The same nodes as ``ros2 run brace_control bringup --processes``: every node reads the
device file as its parameter file. ``can_driver_node`` is a lifecycle node
(``launch_ros.actions.LifecycleNode``, started with ``--manual-lifecycle`` so that launch,
not the executable, drives it): launch emits ``configure`` at start and ``activate`` once the
driver reports *inactive* (the pattern of ros2/demos ``lifecycle_py``). With
``manual_lifecycle:=true`` it stays unconfigured for the operator's ``ros2 lifecycle set
/can_driver_node configure`` / ``activate`` (README, "Operator's sequence"). On shutdown the
driver node disables its drives itself (the lifecycle shutdown transition); ``brace-bringup``
additionally calls the driver's disable service before it stops the other nodes.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.conditions import UnlessCondition
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

from brace_control.nodes import DRIVER_NODE as DRIVER, NODE_NAMES as NODES


def generate_launch_description() -> LaunchDescription:
    default_config = os.path.join(get_package_share_directory('brace_control'),
                                  'config', 'lumbar_brace.yaml')
    config = LaunchConfiguration('config')
    sim = LaunchConfiguration('sim')
    manual = LaunchConfiguration('manual_lifecycle')
    actions = [
        DeclareLaunchArgument('config', default_value=default_config,
                              description='device YAML (ROS 2 parameter file)'),
        DeclareLaunchArgument('sim', default_value='true',
                              description='start the simulated brace on the virtual bus'),
        DeclareLaunchArgument('manual_lifecycle', default_value='false',
                              description='leave can_driver_node unconfigured (ros2 lifecycle set)'),
    ]
    for name in NODES:
        if name != DRIVER:
            actions.append(Node(package='brace_control', executable=name, name=name,
                                parameters=[config], output='screen', emulate_tty=True))
            continue
        driver = LifecycleNode(package='brace_control', executable=name, name=name, namespace='',
                               arguments=['--manual-lifecycle'],
                               parameters=[config, {'can.sim': sim}],
                               output='screen', emulate_tty=True)
        configure = EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(driver),
                                                transition_id=Transition.TRANSITION_CONFIGURE),
                              condition=UnlessCondition(manual))
        activate = RegisterEventHandler(
            OnStateTransition(target_lifecycle_node=driver, start_state='configuring',
                              goal_state='inactive',
                              entities=[EmitEvent(event=ChangeState(
                                  lifecycle_node_matcher=matches_action(driver),
                                  transition_id=Transition.TRANSITION_ACTIVATE))]),
            condition=UnlessCondition(manual))
        # the handler first, so that it sees the inactive state the configure leads to
        actions += [activate, driver, configure]
    return LaunchDescription(actions)
