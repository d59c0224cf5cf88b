"""A controller of its own process: answers every /joint_states with a zero command.

argv: node name, then the actuator names. Two of these on one sim are the
second controller of issue #39.4 (each answers every state: one is stale).
"""

import sys

from echo_node import run   # this directory: the helpers are run as scripts
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


class AnswerNode(Node):

    def __init__(self, name: str, actuators: list[str]):
        super().__init__(name)
        self.actuators = actuators
        self.command_pub = self.create_publisher(JointState, '/joint_commands', QOS)
        self.create_subscription(JointState, '/joint_states', self.answer, QOS)

    def answer(self, state: JointState) -> None:
        command = JointState(name=self.actuators, effort=[0.0] * len(self.actuators))
        command.header = state.header
        self.command_pub.publish(command)


if __name__ == '__main__':
    run(lambda: AnswerNode(sys.argv[1], sys.argv[2:]))
