"""sim_node: a parameter-varied MuJoCo robot on ROS 2, with live physics swaps.

Publishes /joint_states, /zeus/step and /clock; steps on /joint_commands.
In `lockstep` mode every published state waits for the command that answers
its stamp (zero action after `command_timeout`); in `realtime` mode the node
steps on an absolute tick schedule at the control rate times
`real_time_factor`, on the latest command. Both the tick and the lockstep
watchdog are the loop deadline that `zeus_ros.loop_spin.spin_loop` waits for.
The family's physical parameter is a ROS parameter: setting it puts the new
physics into force at the next step boundary, the robot's state carried over.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Reset

from sim_node.env import ParamEnv
from sim_node.families import FAMILIES, get_family
from sim_node.protocol import parse_command
from zeus_ros.loop_spin import create_loop_subscription, LoopDeadline
from zeus_ros.ros_util import describe as _describe
from zeus_ros.ros_util import (diagnostic_array, LOOP_QOS as STATE_QOS, RateMeter, run_node,
                               set_stamp, stamp_ns, ThrottledWarnings, TickLateness)

MODES = ('lockstep', 'realtime')
# The realtime tick sleeps its last millisecond instead of waiting on messages:
# that wait returns up to ~1 ms late (p99) on this machine, a sleep 0.4 ms.
TICK_SLEEP_LEAD_S = 0.001


class SimNode(Node):
    """Thin ROS shell around `ParamEnv`."""

    def __init__(self):
        super().__init__('sim_node')
        family = self.declare_parameter('family', 'walker-walk-v0', _describe(
            f'Environment family (read-only): one of {", ".join(FAMILIES)}.',
            read_only=True)).value
        self.spec = get_family(family)
        lo, hi = self.spec.live_range
        self.declare_parameter('seed', 0, _describe(
            'Seed of the random stream for initial states; a change applies at the next reset.',
            integer_range=[IntegerRange(from_value=0, to_value=2**31 - 1, step=1)]))
        self.declare_parameter('mode', 'lockstep', _describe(
            'lockstep: wait for the command answering each state; realtime: step on a fixed '
            'schedule at the control rate times real_time_factor.'))
        self.declare_parameter('real_time_factor', 1.0, _describe(
            'realtime mode: simulated seconds per wall-clock second.',
            floating_point_range=[FloatingPointRange(from_value=0.01, to_value=100.0)]))
        self.declare_parameter('command_timeout', 0.5, _describe(
            'Seconds without a (matching) command before a zero action is applied.',
            floating_point_range=[FloatingPointRange(from_value=0.001, to_value=60.0)]))
        self.declare_parameter(self.spec.param_name, float(self.spec.default), _describe(
            f'{self.spec.description} Live swap: takes effect at the next step.',
            floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi)]))
        # The same checks as a live set for what the command line gave at start
        # (a declaration checks only type and range).
        for name in (self.spec.param_name, 'mode'):
            reason = self._parameter_problem(self.get_parameter(name))
            if reason is not None:
                raise ValueError(f'parameter {name}: {reason}')
        self.add_on_set_parameters_callback(self.validate_parameters_callback)
        self.add_post_set_parameters_callback(self.apply_parameters_callback)

        self.env = ParamEnv(family, self._param(self.spec.param_name),
                            seed=self._param('seed'))
        self.dt_ns = int(round(self.env.control_timestep * 1e9))
        self.tick = 0            # published states since start; the sim clock is tick * dt
        self.episode = 0
        self.pending_value: float | None = None
        self.awaited_ns: int | None = None
        self.awaited_since = 0.0
        self.latest_action = np.zeros(self.env.action_dim)
        self.latest_action_time = -np.inf
        self.latest_action_stamp = -1   # realtime: the state the latest command answers
        self.counters = {'rejected': 0, 'stale': 0, 'timeouts': 0, 'instabilities': 0}
        self.warnings = ThrottledWarnings(self.get_logger())
        self.step_rate = RateMeter()  # steps/s; latency = state published -> command in

        self.joint_pub = self.create_publisher(JointState, '/joint_states', STATE_QOS)
        self.step_pub = self.create_publisher(StepInfo, '/zeus/step', STATE_QOS)
        self.clock_pub = self.create_publisher(Clock, '/clock', STATE_QOS)
        create_loop_subscription(self, JointState, '/joint_commands', self.command_callback,
                                 STATE_QOS)
        self.create_service(Reset, '~/reset', self.reset_callback)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_timer(1.0, self.diagnostics_callback)
        self.tick_lateness = TickLateness()  # realtime: tick start - scheduled time
        self._configure_stepping()
        self.env.reset(seed=self._param('seed'))
        self.get_logger().info(
            f'{family}: {self.spec.param_name}={self.env.param_value:g}, '
            f'mode={self._param("mode")}, control period {self.env.control_timestep:g} s')
        self.publish_state(reward=0.0, truncated=False)

    # -- parameters -----------------------------------------------------------
    def _param(self, name: str):
        return self.get_parameter(name).value

    def validate_parameters_callback(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            reason = self._parameter_problem(param)
            if reason is not None:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _parameter_problem(self, param: Parameter) -> str | None:
        if param.name == self.spec.param_name:
            if param.type_ not in (Parameter.Type.DOUBLE, Parameter.Type.INTEGER):
                return f'{param.name} must be a number, got {param.type_.name}'
            return self.spec.check_value(param.value)
        if param.name == 'mode' and param.value not in MODES:
            return f'mode must be one of {MODES}, got {param.value!r}'
        return None

    def apply_parameters_callback(self, params: list[Parameter]) -> None:
        for param in params:
            if param.name == self.spec.param_name:
                self.pending_value = float(param.value)
            elif param.name in ('mode', 'real_time_factor', 'command_timeout'):
                self._configure_stepping()

    def _configure_stepping(self) -> None:
        # Cached for the per-step callbacks (a parameter lookup per message adds up).
        self.mode = self._param('mode')
        self.command_timeout = self._param('command_timeout')
        self.tick_period = self.env.control_timestep / self._param('real_time_factor')
        self.next_tick = time.monotonic() + self.tick_period
        self.tick_lateness.restart()

    def loop_deadline(self) -> LoopDeadline | None:
        """Return when the node must act without a message (see zeus_ros.loop_spin)."""
        if self.mode == 'realtime':
            return LoopDeadline(self.next_tick, self.realtime_tick_callback, TICK_SLEEP_LEAD_S)
        if self.awaited_ns is not None:
            return LoopDeadline(self.awaited_since + self.command_timeout,
                                self.lockstep_timeout_callback)
        return None

    # -- stepping -------------------------------------------------------------
    def command_callback(self, msg: JointState) -> None:
        action, reason = parse_command(msg.name, msg.effort, self.env.actuator_names)
        if reason is not None:
            self.counters['rejected'] += 1
            self.warnings.warn('rejected', f'rejected command ({reason}); applying zero action '
                                   f'[{self.counters["rejected"]} rejected so far]')
            action = np.zeros(self.env.action_dim)
        if self.mode == 'realtime':
            self.latest_action, self.latest_action_time = action, time.monotonic()
            self.latest_action_stamp = stamp_ns(msg.header)
            return
        if stamp_ns(msg.header) != self.awaited_ns:
            self.counters['stale'] += 1
            return
        self.step_rate.record(time.monotonic() - self.awaited_since)
        self.advance(action)

    def lockstep_timeout_callback(self) -> None:
        self.counters['timeouts'] += 1
        self.warnings.warn('timeout', f'no command within {self.command_timeout} s; '
                              'applying zero action')
        self.advance(np.zeros(self.env.action_dim))

    def realtime_tick_callback(self) -> None:
        now = time.monotonic()
        # Ticks stay on an absolute schedule (no drift); a tick more than a
        # period late is a missed deadline, and the schedule restarts from now.
        answered = self.awaited_ns is None or self.latest_action_stamp == self.awaited_ns
        self.tick_lateness.record(now - self.next_tick, self.tick_period, answered)
        self.next_tick += self.tick_period
        if self.next_tick <= now:
            self.next_tick = now + self.tick_period
        age = now - self.latest_action_time
        fresh = age <= self.command_timeout
        self.step_rate.record(age if fresh else 0.0)  # latency here: age of the command used
        self.advance(self.latest_action if fresh else np.zeros(self.env.action_dim))

    def advance(self, action: np.ndarray) -> None:
        """Apply a pending swap, step once, publish; reset at the episode's end."""
        self._apply_pending_swap()
        result = self.env.step(action)
        if result.instability is not None:
            self.counters['instabilities'] += 1
            self.get_logger().warning(f'MuJoCo instability ({result.instability}); '
                                      'episode reset')
            self._start_episode(seed=None)
            return
        self.publish_state(result.reward, result.truncated, result.terminal,
                           applied_action=result.applied_action)
        if result.truncated or result.terminal:
            self._start_episode(seed=None)

    def _apply_pending_swap(self) -> None:
        if self.pending_value is not None and self.pending_value != self.env.param_value:
            old = self.env.param_value
            self.env.set_param(self.pending_value)
            self.get_logger().info(
                f'{self.spec.param_name}: {old:g} -> {self.env.param_value:g} '
                f'at episode {self.episode} step {self.env.step_count}')
        self.pending_value = None

    def _start_episode(self, seed: int | None) -> None:
        self.episode += 1
        self.env.reset(seed=seed)
        self.publish_state(reward=0.0, truncated=False)

    def publish_state(self, reward: float, truncated: bool, terminal: bool = False,
                      applied_action: np.ndarray | None = None) -> None:
        self.tick += 1
        stamp = self.tick * self.dt_ns
        joint_state = JointState(name=list(self.env.joint_names),
                                 position=self.env.joint_positions().tolist(),
                                 velocity=self.env.joint_velocities().tolist())
        set_stamp(joint_state.header, stamp)
        step = StepInfo(episode=self.episode, step=self.env.step_count, reward=float(reward),
                        terminal=bool(terminal), truncated=bool(truncated),
                        applied_action=[] if applied_action is None
                        else applied_action.tolist(),
                        family=self.spec.name, param_names=[self.spec.param_name],
                        param_values=[self.env.param_value])
        step.header = joint_state.header
        clock = Clock()
        clock.clock = joint_state.header.stamp
        # The loop's two messages first; /clock is for tools and sim-time users.
        self.step_pub.publish(step)
        self.joint_pub.publish(joint_state)
        self.clock_pub.publish(clock)
        ends_episode = truncated or terminal
        self.awaited_ns = None if ends_episode else stamp
        self.awaited_since = time.monotonic()

    # -- service ----------------------------------------------------------------
    def reset_callback(self, request: Reset.Request, response: Reset.Response):
        names, values = list(request.param_names), list(request.param_values)
        problem = self._reset_problem(names, values)
        if problem is not None:
            response.success, response.message = False, problem
            return response
        if names:
            result = self.set_parameters([Parameter(n, value=float(v))
                                          for n, v in zip(names, values, strict=True)])[0]
            if not result.successful:
                response.success, response.message = False, result.reason
                return response
            self._apply_pending_swap()
        seed = None if request.seed < 0 else int(request.seed)
        self._start_episode(seed)
        response.success = True
        response.message = (f'episode {self.episode}: seed={request.seed}, '
                            f'{self.spec.param_name}={self.env.param_value:g}')
        return response

    def _reset_problem(self, names: list[str], values: list[float]) -> str | None:
        if len(names) != len(values):
            return f'{len(names)} parameter names but {len(values)} values'
        for name, value in zip(names, values, strict=True):
            if name != self.spec.param_name:
                return f'unknown parameter {name!r}; this family has {self.spec.param_name!r}'
            reason = self.spec.check_value(value)
            if reason is not None:
                return reason
        return None

    def diagnostics_callback(self) -> None:
        problems = self.counters['rejected'] + self.counters['instabilities']
        values = dict(self.counters, episode=self.episode, step=self.env.step_count,
                      mode=self._param('mode'), **{self.spec.param_name: self.env.param_value},
                      **self.step_rate.report(), **self.tick_lateness.report())
        self.diagnostics_pub.publish(diagnostic_array(
            self, 'simulation', self.spec.name, values,
            'bad commands or instabilities seen' if problems else None))


def main(args=None):
    # A bad family or initial parameter value: say which and exit with code 1.
    return run_node(SimNode, args, fatal=(ValueError,))


if __name__ == '__main__':
    sys.exit(main())
