"""A stand-in for a ros2_control robot: a MuJoCo cheetah that is not sim_node (#49).

It behaves as mujoco_ros2_control with a joint_state_broadcaster and a
forward_command_controller for effort would, and nothing more:

* publishes /joint_states only (every joint: position, velocity, effort),
  one per `state_period` simulated seconds (default 0.01, the cheetah's
  trained control period; 0.005 is twice the trained rate), stamped with its
  own simulated clock, from its own wall-clock timer: free-running at
  `real_time_factor` times real time (1.0: 100 Hz for 0.01 s), whether or not
  anyone answers;
* applies the latest std_msgs/Float64MultiArray on
  /forward_effort_controller/commands as joint efforts (N m) in the order of
  its `joints` parameter, held until the next one (zero before the first);
  a command of the wrong length or with a non-finite value is dropped;
* changes its own ground friction through its own parameter `friction`
  (`ros2 param set /standin_robot friction 0.2`): geom_friction is a field
  MuJoCo lets change between steps.

No StepInfo, no reward, no episodes, no lockstep. The body is the
cheetah-run-wide-friction family's model (same MJCF, so the weights trained
on that family fit); the stepping, the state and the interface are its own.

argv: none; ROS parameters friction, state_period, real_time_factor, seed, joints.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from echo_node import run   # this directory: the helpers are run as scripts
from sim_node.env import build_model
from sim_node.families import get_sim_family

FAMILY = 'cheetah-run-wide-friction'
QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
SETTLE_STEPS = 200    # as dm_control's cheetah settles a random pose before an episode


class StandInRobot(Node):
    """The robot: physics on a wall-clock timer, ros2_control's topics."""

    def __init__(self):
        super().__init__('standin_robot')
        spec = get_sim_family(FAMILY)
        friction = self.declare_parameter('friction', float(spec.live_params[0].default)).value
        factor = self.declare_parameter('real_time_factor', 1.0).value
        self.dt = float(self.declare_parameter('state_period', 0.01).value)
        seed = self.declare_parameter('seed', 0).value
        self.model = build_model(spec, float(friction))
        # States faster than the model's 0.01 s step: a finer step (a robot's own loop).
        self.model.opt.timestep = min(self.model.opt.timestep, self.dt)
        self.data = mujoco.MjData(self.model)
        self.actuators = [self.model.actuator(i).name for i in range(self.model.nu)]
        joints = self.declare_parameter('joints', self.actuators).value
        self.order = [self.actuators.index(j) for j in joints]   # a bad name ends it
        self.joint_names = [self.model.joint(i).name for i in range(self.model.njnt)]
        self.gear = self.model.actuator_gear[:, 0].copy()
        self.effort = np.zeros(self.model.nu)
        self.substeps = round(self.dt / self.model.opt.timestep)
        self.tick = 0
        self.commands = self.dropped = 0
        self._settle(np.random.default_rng(seed))
        self.state_pub = self.create_publisher(JointState, '/joint_states', QOS)
        self.create_subscription(Float64MultiArray, '/forward_effort_controller/commands',
                                 self.command_callback, QOS)
        self.add_on_set_parameters_callback(self.parameters_callback)
        self.create_timer(self.dt / float(factor), self.tick_callback)
        self.get_logger().info(f'friction {friction}, {factor / self.dt:g} Hz, '
                               f'joints {joints}')

    def _settle(self, rng: np.random.Generator) -> None:
        limited = self.model.jnt_limited == 1
        low, high = self.model.jnt_range[limited].T
        self.data.qpos[limited] = rng.uniform(low, high)
        mujoco.mj_step(self.model, self.data, SETTLE_STEPS)

    def command_callback(self, msg: Float64MultiArray) -> None:
        values = np.asarray(msg.data, dtype=np.float64)
        if values.shape != (len(self.order),) or not np.all(np.isfinite(values)):
            self.dropped += 1
            return
        self.effort = np.zeros(self.model.nu)
        self.effort[self.order] = values
        self.commands += 1

    def tick_callback(self) -> None:
        # ctrl = effort / gear: the motor's force is gear * ctrl (clamped to ctrlrange).
        self.data.ctrl[:] = self.effort / self.gear
        mujoco.mj_step(self.model, self.data, self.substeps)
        self.tick += 1
        msg = JointState(name=self.joint_names, position=self.data.qpos.tolist(),
                         velocity=self.data.qvel.tolist(),
                         effort=self.data.qfrc_actuator.tolist())
        stamp = self.tick * round(self.dt * 1e9)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        self.state_pub.publish(msg)

    def parameters_callback(self, params) -> SetParametersResult:
        for param in params:
            if param.name == 'friction':
                value = float(param.value)
                if not (math.isfinite(value) and value > 0.0):
                    return SetParametersResult(successful=False, reason='friction must be > 0')
                # Sliding friction of every geom: the cheetah's and the ground's,
                # as the family's MJCF edit sets both (a contact takes the larger).
                self.model.geom_friction[:, 0] = value
                self.get_logger().info(f'friction -> {value:g} at tick {self.tick}')
        return SetParametersResult(successful=True)


if __name__ == '__main__':
    run(StandInRobot)
