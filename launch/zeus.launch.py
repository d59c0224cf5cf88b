"""Start sim_node, context_node and policy_node with a family, a checkpoint and a mode.

Usage: ros2 launch zeus_ros zeus.launch.py weights:=<checkpoint> family:=walker-walk-v0
mode:=lockstep [thread_priority:=50] [composed:=true]

composed:=true runs the three nodes in one process (`zeus_ros.ros_tools.composed`, as
`bringup --composed`): the same nodes and topics, on one loop thread.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, LogInfo, RegisterEventHandler
from launch.conditions import IfCondition, UnlessCondition
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

if TYPE_CHECKING:
    from launch import LaunchContext
    from launch.events.process import ProcessExited


class NodeFailed(RuntimeError):
    """A node of the graph exited with an error: the launch fails with it."""


def exit_problem(name: str, returncode: int | None) -> str | None:
    """Why the launch must fail when `name` exited with `returncode` (None: a clean stop)."""
    if returncode in (0, None):
        return None
    how = f'was killed by signal {-returncode}' if returncode < 0 else \
        f'exited with code {returncode}'
    return f'{name} {how}; stopping the launch (its message is above)'


# ARG001: OnProcessExit's on_exit signature.
def _end_launch(event: ProcessExited, context: LaunchContext):  # noqa: ARG001
    # An exception raised in an event handler makes LaunchService.run return 1,
    # which `ros2 launch` returns; a clean exit just shuts the others down.
    problem = exit_problem(event.action.name, event.returncode)
    if problem is not None:
        raise NodeFailed(problem)
    return [LogInfo(msg=f'{event.action.name} stopped; shutting down'),
            EmitEvent(event=Shutdown(reason=f'{event.action.name} stopped'))]


def composed_ros_arguments(config: str, family: LaunchConfiguration, weights: LaunchConfiguration,
                           mode: LaunchConfiguration, priority: LaunchConfiguration,
                           backend: LaunchConfiguration | str = 'torch') -> list:
    """Return the one process's ROS arguments: the config file, then each node's values.

    Given by node name (-p sim_node:mode:=...), since one `parameters` dict would
    go to all three nodes and each refuses the others' parameters; later
    arguments win, so the launch arguments override the file.
    """
    controller = {'weights': weights, 'backend': backend}
    values = {'sim_node': {'family': family, 'mode': mode}, 'context_node': controller,
              'policy_node': controller}
    arguments = ['--params-file', config]
    for node, params in values.items():
        for key, value in {**params, 'thread_priority': priority}.items():
            arguments += ['-p', [f'{node}:{key}:=', value]]
    return arguments


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory('zeus_ros'), 'config', 'zeus.yaml')
    family = LaunchConfiguration('family')
    weights, backend = LaunchConfiguration('weights'), LaunchConfiguration('backend')
    controller = {'weights': weights, 'backend': backend}
    mode = LaunchConfiguration('mode')
    thread_priority = LaunchConfiguration('thread_priority')
    separate = UnlessCondition(LaunchConfiguration('composed'))
    priority = {'thread_priority': thread_priority}
    nodes = [
        Node(package='zeus_ros', executable='sim_node', name='sim_node', output='screen',
             parameters=[config, {'family': family, 'mode': mode}, priority],
             condition=separate),
        Node(package='zeus_ros', executable='context_node', name='context_node',
             output='screen', parameters=[config, controller, priority],
             condition=separate),
        Node(package='zeus_ros', executable='policy_node', name='policy_node',
             output='screen', parameters=[config, controller, priority],
             condition=separate),
        # No `name`: a node-name remapping would rename all three nodes.
        Node(package='zeus_ros', executable='composed', output='screen',
             ros_arguments=composed_ros_arguments(config, family, weights, mode,
                                                  thread_priority, backend),
             condition=IfCondition(LaunchConfiguration('composed'))),
    ]
    # Like bringup: when one node ends, the whole launch ends, and a node that
    # FAILED (exit code not 0) makes `ros2 launch` itself exit non-zero.
    shutdown_on_exit = [
        RegisterEventHandler(OnProcessExit(target_action=node, on_exit=_end_launch))
        for node in nodes
    ]
    return LaunchDescription([
        DeclareLaunchArgument('family', default_value='walker-walk-v0',
                              description='environment family the weights were trained on'),
        DeclareLaunchArgument('weights', description='checkpoint directory'),
        DeclareLaunchArgument('backend', default_value='torch',
                              description="what runs the controllers' networks: torch or "
                                          'onnx (ONNX Runtime)'),
        DeclareLaunchArgument('mode', default_value='lockstep',
                              description='lockstep or realtime'),
        DeclareLaunchArgument('thread_priority', default_value='0',
                              description='SCHED_FIFO priority of every node (1-99; 0 = '
                                          'normal scheduler); 50 suits realtime mode'),
        DeclareLaunchArgument('composed', default_value='false',
                              description='true: the three nodes in one process (same '
                                          'topics, on DDS)'),
        *nodes,
        *shutdown_on_exit,
    ])
