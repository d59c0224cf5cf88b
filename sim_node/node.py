"""sim_node: a parameter-varied MuJoCo robot on ROS 2, with live physics swaps.

Publishes /joint_states, /zeus/step and /clock; steps on /joint_commands.
In `lockstep` mode every published state waits for the command that answers
its stamp (zero action after `command_timeout`); in `realtime` mode the node
steps on an absolute tick schedule at the control rate times
`real_time_factor`, on the latest command. Both the tick and the lockstep
watchdog are the loop deadline that `zeus_ros.loop_spin.spin_loop` waits for.
The family's physical parameter is a ROS parameter: setting it puts the new
physics into force at the next step boundary, the robot's state carried over.

Episodes and seeds: an episode starts at `~/reset` or after the last one's
last step. A new value of the `seed` parameter restarts the random stream of
initial states at the next episode start; a reset with seed >= 0 does the same
at once (and sets the parameter to it); seed -1 keeps the stream going (see
sim_node.protocol.check_reset_request for what a reset refuses).
"""

# ruff: noqa: E402
# (The stop guard below must come before the heavy imports.)
from __future__ import annotations

import os
import signal
import sys


def _exit_quietly(_signum, _frame) -> None:
    os._exit(0)  # nothing to clean up: no ROS context exists before run_node


# A SIGINT or SIGTERM while MuJoCo, dm_control and rclpy load (seconds on a busy
# machine) must end the node with 0, not an import traceback or -15; run_node
# takes the signals over when it starts. Only when this file is the program
# (`python -m sim_node.node`, or the `sim_node` console script, which imports it
# first thing): imported by anything else, it leaves the signals alone.
if __name__ == '__main__' or os.path.basename(sys.argv[0]) == 'sim_node':
    for _signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(_signum, _exit_quietly)

import time

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Reset

from sim_node.env import ParamEnv
from sim_node.families import FAMILIES, get_family
from sim_node.protocol import (check_reset_request, KEEP_STREAM, loop_problem,
                               parse_command, RecentRises, SEED_MAX)
from zeus_ros.loop_spin import create_loop_subscription, LoopDeadline
from zeus_ros.ros_util import describe as _describe
from zeus_ros.ros_util import (accept_integers_for_doubles, declare_double,
                               declare_thread_priority, diagnostic_array,
                               LOOP_QOS as STATE_QOS, parameter_names, RateMeter, run_node,
                               set_stamp, stamp_ns, ThrottledWarnings, TickLateness,
                               unknown_overrides, UnknownParameters)

MODES = ('lockstep', 'realtime')
# What rclpy declares on every node.
RCLPY_PARAMETERS = ('use_sim_time', 'start_type_description_service')
# The realtime tick sleeps its last millisecond instead of waiting on messages:
# that wait returns up to ~1 ms late (p99) on this machine, a sleep 0.4 ms.
TICK_SLEEP_LEAD_S = 0.001


class SimNode(Node):
    """Thin ROS shell around `ParamEnv`."""

    def __init__(self):
        # Undeclared names then reach validate_parameters_callback, which answers
        # with the valid ones (rclpy's own answer: 'undeclared parameter(s): []').
        super().__init__('sim_node', allow_undeclared_parameters=True)
        self._declare_parameters()   # sets self.spec
        accept_integers_for_doubles(self)
        self.add_on_set_parameters_callback(self.validate_parameters_callback)
        self.add_post_set_parameters_callback(self.apply_parameters_callback)

        self.stream_seed = self._param('seed')   # where the current stream started
        self.env = ParamEnv(self.spec.name, self._param(self.spec.param_name),
                            seed=self.stream_seed)
        self.dt_ns = int(round(self.env.control_timestep * 1e9))
        self.tick = 0            # published states since start; the sim clock is tick * dt
        self.episode = 0
        self.pending_value: float | None = None
        self.pending_seed: int | None = None
        self.awaited_ns: int | None = None
        self.awaited_since = 0.0
        self.latest_action = np.zeros(self.env.action_dim)
        self.latest_action_time = -np.inf
        self.latest_action_stamp = -1   # realtime: the state the latest command answers
        # Totals since start; the diagnostics level reads their recent rises.
        self.counters = {'rejected': 0, 'stale': 0, 'timeouts': 0, 'instabilities': 0,
                         'steps': 0, 'answered': 0, 'late_ticks': 0}
        self.recent = RecentRises()
        self.warnings = ThrottledWarnings(self.get_logger())
        self.step_rate = RateMeter()  # steps/s; latency = state published -> command in
        self._create_interfaces()
        self.tick_lateness = TickLateness()  # realtime: tick start - scheduled time
        self._configure_stepping()
        self.env.reset(seed=self.stream_seed)
        self.get_logger().info(
            f'{self.spec.name}: {self.spec.param_name}={self.env.param_value:g}, '
            f'mode={self._param("mode")}, control period {self.env.control_timestep:g} s')
        self.publish_state(reward=0.0, truncated=False)

    def _create_interfaces(self) -> None:
        self.joint_pub = self.create_publisher(JointState, '/joint_states', STATE_QOS)
        self.step_pub = self.create_publisher(StepInfo, '/zeus/step', STATE_QOS)
        self.clock_pub = self.create_publisher(Clock, '/clock', STATE_QOS)
        create_loop_subscription(self, JointState, '/joint_commands', self.command_callback,
                                 STATE_QOS)
        self.create_service(Reset, '~/reset', self.reset_callback)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_timer(1.0, self.diagnostics_callback)

    # -- parameters -----------------------------------------------------------
    def _declare_parameters(self) -> None:
        """Declare every parameter and check what start-up gave, before anything runs."""
        self.spec = get_family(self.declare_parameter('family', 'walker-walk-v0', _describe(
            f'Environment family (read-only): one of {", ".join(FAMILIES)}.',
            read_only=True)).value)
        lo, hi = self.spec.live_range
        self.declare_parameter('seed', 0, _describe(
            'Seed of the random stream of initial states; a new value restarts the stream '
            'at the next episode start.',
            integer_range=[IntegerRange(from_value=0, to_value=SEED_MAX, step=1)]))
        self.declare_parameter('mode', 'lockstep', _describe(
            'lockstep: wait for the command answering each state; realtime: step on a fixed '
            'schedule at the control rate times real_time_factor.'))
        declare_double(self, 'real_time_factor', 1.0, _describe(
            'realtime mode: simulated seconds per wall-clock second.',
            floating_point_range=[FloatingPointRange(from_value=0.01, to_value=100.0)]))
        declare_double(self, 'command_timeout', 0.5, _describe(
            'Seconds without a (matching) command before a zero action is applied.',
            floating_point_range=[FloatingPointRange(from_value=0.001, to_value=60.0)]))
        declare_double(self, self.spec.param_name, self.spec.default, _describe(
            f'{self.spec.description} Live swap: takes effect at the next step.',
            floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi)]))
        declare_thread_priority(self)
        unknown = unknown_overrides(self)
        if unknown:
            raise UnknownParameters(f'unknown parameter {", ".join(unknown)} for '
                                    f'{self.spec.name}; {self._parameters_text()}')
        # The same checks as a live set (a declaration checks only type and range).
        for name in (self.spec.param_name, 'mode'):
            reason = self._parameter_problem(self.get_parameter(name))
            if reason is not None:
                raise ValueError(f'parameter {name}: {reason}')

    def _parameters_text(self) -> str:
        others = [name for name in parameter_names(self) if name != self.spec.param_name]
        others.sort(key=lambda name: name in RCLPY_PARAMETERS)  # the sim's own first
        return (f"its parameters: {self.spec.param_name} (the family's physical parameter), "
                f'{", ".join(others)}')

    def _param(self, name: str):
        return self.get_parameter(name).value

    def validate_parameters_callback(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            reason = self._parameter_problem(param)
            if reason is not None:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _parameter_problem(self, param: Parameter) -> str | None:
        if not self.has_parameter(param.name):
            return f'{self.spec.name} has no parameter {param.name!r}; {self._parameters_text()}'
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
            elif param.name == 'seed':
                self.pending_seed = int(param.value)
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
        self.counters['answered'] += 1
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
        self.counters['answered'] += int(answered)
        self.counters['late_ticks'] += int(now - self.next_tick > self.tick_period)
        self.next_tick += self.tick_period
        if self.next_tick <= now:
            self.next_tick = now + self.tick_period
        age = now - self.latest_action_time
        fresh = age <= self.command_timeout
        self.step_rate.record(age if fresh else 0.0)  # latency here: age of the command used
        self.advance(self.latest_action if fresh else np.zeros(self.env.action_dim))

    def advance(self, action: np.ndarray) -> None:
        """Apply a pending swap, step once, publish; start the next episode at the end."""
        self.counters['steps'] += 1
        self._apply_pending_swap(f'episode {self.episode} step {self.env.step_count}')
        result = self.env.step(action)
        if result.instability is not None:
            self.counters['instabilities'] += 1
            self.get_logger().warning(f'MuJoCo instability ({result.instability}); '
                                      'episode reset')
            self._start_episode()
            return
        self.publish_state(result.reward, result.truncated, result.terminal,
                           applied_action=result.applied_action)
        if result.truncated or result.terminal:
            self._start_episode()

    def _apply_pending_swap(self, where: str) -> None:
        if self.pending_value is not None and self.pending_value != self.env.param_value:
            old = self.env.param_value
            self.env.set_param(self.pending_value)
            self.get_logger().info(
                f'{self.spec.param_name}: {old:g} -> {self.env.param_value:g} at {where}')
        self.pending_value = None

    def _start_episode(self) -> None:
        """Begin the next episode: pending swap, pending seed (else the stream goes on), step 0."""
        self.episode += 1
        self._apply_pending_swap(f'the start of episode {self.episode}')
        seed, self.pending_seed = self.pending_seed, None
        if seed is not None:
            self.stream_seed = seed
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
        problem = (check_reset_request(request.seed, names, values, self.spec)
                   or self._set_for_reset(request.seed, names, values))
        if problem is not None:
            self.warnings.warn('reset', f'reset refused: {problem}')
            response.success, response.message = False, problem
            return response
        restarts = self.pending_seed is not None
        self._start_episode()
        stream = (f'stream restarted at seed {self.stream_seed}' if restarts
                  else f'stream of seed {self.stream_seed} continued')
        response.success, response.episode = True, self.episode
        response.message = (f'episode {self.episode}: {stream}, '
                            f'{self.spec.param_name}={self.env.param_value:g}')
        self.get_logger().info(f'reset to {response.message}')
        return response

    def _set_for_reset(self, seed: int, names: list[str], values: list[float]) -> str | None:
        """Set a checked request's values as parameters, so they read back; return a refusal."""
        params = [Parameter(name, Parameter.Type.DOUBLE, float(value))
                  for name, value in zip(names, values, strict=True)]
        if seed != KEEP_STREAM:
            params.append(Parameter('seed', Parameter.Type.INTEGER, int(seed)))
        if not params:
            return None
        result = self.set_parameters_atomically(params)
        return None if result.successful else result.reason

    def diagnostics_callback(self) -> None:
        recent = self.recent.rises(time.monotonic(), self.counters)
        values = dict(self.counters, episode=self.episode, step=self.env.step_count,
                      mode=self._param('mode'), **{self.spec.param_name: self.env.param_value},
                      window_s=self.recent.window_s, recent_steps=recent['steps'],
                      recent_answered=recent['answered'],
                      **self.step_rate.report(), **self.tick_lateness.report())
        self.diagnostics_pub.publish(diagnostic_array(
            self, 'simulation', self.spec.name, values,
            loop_problem(recent, self.recent.window_s)))


def main(args=None):
    # A bad family, initial parameter value or unknown parameter: say which, exit 1.
    return run_node(SimNode, args, fatal=(ValueError,))


if __name__ == '__main__':
    sys.exit(main())
