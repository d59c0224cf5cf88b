"""set_param: `ros2 param set NODE NAME VALUE` for a machine without ros2cli.

    python -m zeus_ros.ros_tools.set_param /sim_node friction 0.4

Calls the node's `~/set_parameters` service, as `ros2 param set` does, and
prints the same lines: "Set parameter successful", or "Setting parameter
failed: <the node's reason>" (exit 1). The value is read as YAML, as ros2cli
reads it: `0.4` is a double, `3` an integer, `true` a bool, anything else a
string. DDS discovery follows the environment (`scripts/ros_env.sh` keeps it
on this machine).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import TYPE_CHECKING

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
import yaml  # noqa: E402

if TYPE_CHECKING:
    from rclpy.node import Node


def parse_value(text: str) -> bool | int | float | str:
    """Return the parameter value `text` stands for, read as YAML (ros2cli's rule)."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return value if isinstance(value, bool | int | float | str) else text


def set_parameter(node: Node, target: str, name: str, value: bool | int | float | str,
                  timeout: float) -> tuple[bool, str]:
    """Set one parameter of the node `target`; return (success, reason)."""
    client = node.create_client(SetParameters, f'{target.rstrip("/")}/set_parameters')
    if not client.wait_for_service(timeout_sec=timeout):
        return False, f'node {target} not found (no {client.srv_name} within {timeout:g} s)'
    request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if future.result() is None:
        return False, f'{target} did not answer within {timeout:g} s'
    result = future.result().results[0]
    return result.successful, result.reason


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='set_param', description=__doc__.split('\n')[0])
    parser.add_argument('node', help='fully qualified node name, e.g. /sim_node')
    parser.add_argument('name', help='parameter name')
    parser.add_argument('value', help='new value (YAML: 0.4, 3, true, text)')
    parser.add_argument('--timeout', type=float, default=10.0, help='seconds to wait')
    ns = parser.parse_args(args)
    rclpy.init()
    node = rclpy.create_node('set_param_client')
    try:
        ok, reason = set_parameter(node, ns.node, ns.name, parse_value(ns.value), ns.timeout)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print('Set parameter successful' if ok else f'Setting parameter failed: {reason}')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
