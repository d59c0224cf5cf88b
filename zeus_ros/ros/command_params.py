"""The command interface's parameters, shared by sim_node, policy_node and context_node (#49).

`command_type` (joint_state | float64_array), `command_topic` (empty: the
type's default), `command_units` (normalised | actuator) and `joints` (the
declared joint order of a command; empty: the checkpoint's actuator order).
All read-only: a controller and the robot agree on them once, at start-up.
`CommandPort` wraps the message types: it builds the message for an action
and reads an action back from one, whatever the type.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from zeus_ros.ros.commands import (ActuatorUnits, choose, command_topic, COMMAND_TYPES,
                                   COMMAND_UNITS, CommandCodec, DEFAULT_COMMAND_TOPICS,
                                   make_codec)
from zeus_ros.ros.timing import Decimator
from zeus_ros.ros.util import describe, set_stamp, stamp_ns

MESSAGE_TYPES = {'joint_state': JointState, 'float64_array': Float64MultiArray}


@dataclass(frozen=True)
class CommandPort:
    """A command type, its topic and its codec: messages <-> normalised actions."""

    command_type: str
    topic: str
    codec: CommandCodec

    @property
    def message_type(self) -> type:
        """The ROS message class of this command type."""
        return MESSAGE_TYPES[self.command_type]

    def message(self, action: np.ndarray, stamp: int) -> JointState | Float64MultiArray:
        """Return the command message for a normalised action answering the state `stamp`."""
        values = self.codec.encode(action)
        if self.command_type == 'float64_array':
            return Float64MultiArray(data=values)   # no header: ros2_control's form
        msg = JointState(name=self.codec.joint_names, effort=values)
        set_stamp(msg.header, stamp)
        return msg

    def action(self, msg: JointState | Float64MultiArray
               ) -> tuple[np.ndarray | None, str | None, int | None]:
        """Return (normalised action or None, why not, stamp or None) of a command message."""
        if self.command_type == 'float64_array':
            return (*self.codec.decode(list(msg.data)), None)
        values, reason = by_name(list(msg.name), list(msg.effort), self.codec.joint_names)
        if reason is not None:
            return None, reason, stamp_ns(msg.header)
        return (*self.codec.decode(values), stamp_ns(msg.header))


def by_name(names: Sequence[str], values: Sequence[float],
            joints: Sequence[str]) -> tuple[list[float] | None, str | None]:
    """Return `values` put in the order of `joints` (names in any order), or (None, why)."""
    if sorted(names) != sorted(joints) or len(set(names)) != len(names):
        return None, f'names {list(names)} are not the joints {list(joints)}'
    if len(values) != len(names):
        return None, f'{len(values)} efforts for {len(names)} names'
    return [values[names.index(j)] for j in joints], None


def declare_command_parameters(node: Node) -> None:
    """Declare the four command parameters (before a node's check of unknown overrides)."""
    node.declare_parameter('command_type', 'joint_state', describe(
        f'Command message: {" or ".join(COMMAND_TYPES)} (std_msgs/Float64MultiArray, as '
        "ros2_control's forward_command_controller takes it); read-only.",
        read_only=True))
    node.declare_parameter('command_topic', '', describe(
        'Command topic; empty: ' + ', '.join(f'{t} for {k}' for k, t in
                                             DEFAULT_COMMAND_TOPICS.items()) + '; read-only.',
        read_only=True))
    node.declare_parameter('command_units', 'normalised', describe(
        f'Command values: {" or ".join(COMMAND_UNITS)} (actuator: efforts in the joints\' '
        "units, gear * ctrl from the model's control range and gear); read-only.",
        read_only=True))
    node.declare_parameter('joints', Parameter.Type.STRING_ARRAY, describe(
        "Joint order of a command (each actuator once); unset: the checkpoint's actuator "
        'order; read-only.', read_only=True))


def command_port(node: Node, actuator_names: Sequence[str],
                 units: ActuatorUnits | None) -> CommandPort:
    """Return the port the (declared) command parameters describe.

    CommandSetupError (one line, exit 1 through run_node) for a command type
    or units mode it does not know, a `joints` mapping that leaves an actuator
    out or names an unknown one, or actuator units the model does not record.
    """
    command_type = node.get_parameter('command_type').value
    # Declared without a value (rclpy cannot type an empty list): unset is the default.
    try:
        joints = node.get_parameter('joints').value or []
    except ParameterUninitializedException:
        joints = []
    choose(command_type, COMMAND_TYPES, 'command_type')
    codec = make_codec(actuator_names, list(joints),
                       node.get_parameter('command_units').value, units)
    return CommandPort(command_type,
                       command_topic(command_type, node.get_parameter('command_topic').value),
                       codec)


def declare_command_port(node: Node, actuator_names: Sequence[str],
                         units: ActuatorUnits | None) -> CommandPort:
    """Declare the command parameters and return the port they describe (see command_port)."""
    declare_command_parameters(node)
    return command_port(node, actuator_names, units)


def declare_decimator(node: Node, trained_period_s: float | None) -> Decimator:
    """Declare `control_period` and return the decimator it gives (see ros.timing)."""
    value = node.declare_parameter('control_period', 0.0, describe(
        'Seconds between the states acted on, kept by stamp (faster states are skipped): '
        "0 = every state (the sim's loop), -1 = the weights' trained control period (a "
        'robot at its own rate); read-only.', read_only=True)).value
    period = (trained_period_s or 0.0) if value < 0 else float(value)
    return Decimator(round(period * 1e9))


def units_of(low: Sequence[float] | None, high: Sequence[float] | None,
             gear: Sequence[float] | None) -> ActuatorUnits | None:
    """Return the actuator units a checkpoint or model records (None: it records none)."""
    if low is None or high is None or gear is None:
        return None
    return ActuatorUnits.of(low, high, gear)
