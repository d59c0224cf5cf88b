"""sim_node: a parameter-varied MuJoCo robot on ROS 2, with live physics swaps.

Publishes /joint_states, /zeus/step and /clock; steps on /joint_commands.
For a controller written for a ros2_control robot: `command_type`
float64_array takes std_msgs/Float64MultiArray (default topic
/forward_effort_controller/commands; `joints` order, `command_units`), which
answers the state awaited; `publish_step_info` false leaves /zeus/step out.
In `lockstep` mode every published state waits for the command that answers
its stamp (zero action after `command_timeout`); in `realtime` mode the node
steps on an absolute tick schedule at the control rate times
`real_time_factor`, on the latest command. Both the tick and the lockstep
watchdog are the loop deadline that `zeus_ros.ros.loop_spin.spin_loop` waits for.
The family's physical parameters (one for most families; goal_x and goal_y for
sawyer-peg-v0) are ROS parameters: setting one, or several at once, puts the
new physics into force at the next step boundary, the robot's state carried over.

Pause and step: `~/pause`, `~/resume` and `~/step` (zeus_ros.ros.pause).

Episodes and seeds: an episode starts at `~/reset` or after the last one's
last step. A new value of the `seed` parameter restarts the random stream of
initial states at the next episode start; a reset with seed >= 0 does the same
at once (and sets the parameter to it); seed -1 keeps the stream going (see
zeus_ros.ros.protocol.check_reset_request for what a reset refuses).
"""

# ruff: noqa: E402
# (The stop guard below must come before the heavy imports.)
from __future__ import annotations

import os
import signal
import sys


def _exit_quietly(_signum: int, _frame: FrameType | None) -> None:
    os._exit(0)  # nothing to clean up: no ROS context exists before run_node


# A SIGINT or SIGTERM while MuJoCo, dm_control and rclpy load (seconds on a busy
# machine) must end the node with 0, not an import traceback or -15; run_node
# takes the signals over when it starts. Only when this file is the program
# (`python -m zeus_ros.nodes.sim_node`, or the `sim_node` console script, which imports it
# first thing): imported by anything else, it leaves the signals alone.
if __name__ == '__main__' or os.path.basename(sys.argv[0]) == 'sim_node':
    for _signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(_signum, _exit_quietly)
    # Its launcher's end ends it too, even while it imports (zeus_ros.ros.parent_watch).
    from zeus_ros.ros.parent_watch import end_with_launcher
    end_with_launcher()

import threading
import time
from typing import Sequence, TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_parameters
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Reset

from sim_node.env import make_env
from sim_node.families import get_sim_family, SIM_FAMILIES, SimFamily
from sim_node.family_edits import load_family_file
from sim_node.stepper import MODES, PublishedState, SimStepper, StepOutcome
from sim_node.swaps import format_values, SwapQueue
from zeus_ros.ros.camera import CameraPublisher
from zeus_ros.ros.command_params import command_port, declare_command_parameters, units_of
from zeus_ros.ros.graph import publisher_names
from zeus_ros.ros.loop_spin import create_loop_subscription, LoopDeadline
from zeus_ros.ros.pause import PauseServices
from zeus_ros.ros.protocol import (AchievedRealTimeFactor, check_reset_request, command_problem,
                                   KEEP_STREAM, loop_problem, parse_command, RecentCounts,
                                   SEED_MAX)
from zeus_ros.ros.util import declare_executor, describe as _describe
from zeus_ros.ros.util import (accept_integers_for_doubles, declare_double,
                               declare_thread_priority, diagnostic_array, FirstContact,
                               LOOP_QOS as STATE_QOS, parameter_names, RateMeter, run_node,
                               set_stamp, stamp_ns, ThrottledWarnings, TickLateness,
                               unknown_overrides, UnknownParameters)

if TYPE_CHECKING:
    from types import FrameType

    import numpy as np

# What rclpy declares on every node.
RCLPY_PARAMETERS = ('use_sim_time', 'start_type_description_service')
# ~/reset keeps up to 1000 waiting requests, as rclpy's parameter services do:
# the services default keeps 10, and a burst of 200 resets from one client got
# 10 answers, the rest dropped without a word (issue #17.4). A client sending
# bursts needs as deep a history itself (qos_profile_parameters).
RESET_QOS = qos_profile_parameters
# The realtime tick sleeps its last millisecond instead of waiting on messages:
# that wait returns up to ~1 ms late (p99) on this machine, a sleep 0.4 ms.
TICK_SLEEP_LEAD_S = 0.001


class SimNode(Node):
    """Thin ROS adapter around `SimStepper`: messages, parameters and the reset service."""

    def __init__(self):
        # Undeclared names then reach validate_parameters_callback, which answers
        # with the valid ones (rclpy's own answer: 'undeclared parameter(s): []').
        super().__init__('sim_node', allow_undeclared_parameters=True)
        self._declare_parameters()   # sets self.spec
        accept_integers_for_doubles(self)
        self.add_on_set_parameters_callback(self.validate_parameters_callback)
        self.add_post_set_parameters_callback(self.apply_parameters_callback)

        seed = self._param('seed')
        self.env = make_env(self.spec.name, tuple(self._param(n) for n in self.live_names),
                            seed=seed)
        self.swaps = SwapQueue(self.env.prepare_values)   # builds swapped physics off the loop
        self.stepper = SimStepper(self.env, self.publish_state, self.swaps, seed=seed)
        self.recent = RecentCounts()   # the diagnostics level reads the counters' recent rises
        self.warnings = ThrottledWarnings(self.get_logger())
        # The first states go out before a controller has matched (issue #38.5).
        self.first_command = FirstContact(self.get_logger(), self.warnings,
                                          'waiting for the first command: zero actions '
                                          'meanwhile, one per command_timeout')
        self.achieved_rtf = AchievedRealTimeFactor()
        self.step_rate = RateMeter()  # steps/s; latency = state published -> command in
        self.tick_lateness = TickLateness()  # realtime: tick start - scheduled time
        self._create_interfaces()
        self._configure_stepping()
        self.get_logger().info(
            f'{self.spec.name}: {self._values_text(self.env.param_values)}, '
            f'mode={self.stepper.mode}, control period {self.env.control_timestep:g} s')
        self.stepper.start()
        # Held while the stepper changes the physics; the camera copies qpos under it
        # and renders from its own copy, so stepping never waits on a frame.
        self.physics_lock = threading.Lock()
        self.camera = CameraPublisher(self, lambda: self.env.physics, self._param('camera_rate'),
                                      lock=self.physics_lock,
                                      get_stamp_ns=lambda: self.stepper.tick * self.stepper.dt_ns,
                                      camera=self.env.default_camera, start=False)

    def on_started(self) -> None:
        """Start the camera once the node passed its start-up checks (run_node calls it).

        A sim that still may refuse to run (its name taken) draws no frame.
        """
        self.camera.start()

    def _create_interfaces(self) -> None:
        self.joint_pub = self.create_publisher(JointState, '/joint_states', STATE_QOS)
        self.publish_step_info = self._param('publish_step_info')
        self.step_pub = self.create_publisher(StepInfo, '/zeus/step', STATE_QOS) \
            if self.publish_step_info else None
        self.clock_pub = self.create_publisher(Clock, '/clock', STATE_QOS)
        # Sawyer's hand deltas have no control range or gear: normalised commands only.
        units = getattr(self.env, 'actuator_units', (None, None, None))
        self.port = command_port(self, self.env.actuator_names, units_of(*units))
        self.command_sub = create_loop_subscription(self, self.port.message_type,
                                                    self.port.topic, self.command_callback,
                                                    STATE_QOS)
        self.create_service(Reset, '~/reset', self.reset_callback, qos_profile=RESET_QOS)
        self.pause = PauseServices(self, self.stepper)   # ~/pause, ~/resume, ~/step
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_timer(1.0, self.diagnostics_callback)

    def destroy_node(self) -> None:
        if hasattr(self, 'camera'):
            self.camera.close()
        self.swaps.close()
        super().destroy_node()

    # -- parameters -----------------------------------------------------------
    def _declare_family(self) -> SimFamily:
        """Return the family: a built-in by name, or the one a family file declares."""
        path = self.declare_parameter('family_file', '', _describe(
            'A family file (YAML; docs: "Your robot") to run instead of a built-in family '
            "(read-only; empty: none). Its parameters become this node's live parameters.",
            read_only=True)).value
        from_file = load_family_file(path) if path else None   # FamilyFileError: one line
        name = self.declare_parameter(
            'family', from_file.name if from_file else 'walker-walk-v0', _describe(
                f'Environment family (read-only): one of {", ".join(SIM_FAMILIES)}, or the '
                'name of the family file given as family_file.', read_only=True)).value
        if from_file is not None and name != from_file.name:
            raise ValueError(f'parameter family: {name!r}, but family_file {path} declares '
                             f'{from_file.name!r}; give one of them')
        return get_sim_family(name)

    def _declare_parameters(self) -> None:
        """Declare every parameter and check what start-up gave, before anything runs."""
        self.spec = self._declare_family()
        self.live_names = self.spec.param_names
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
        declare_double(self, 'camera_rate', 0.0, _describe(
            'Frames per second on /camera/image_raw and /camera/camera_info, rendered '
            'off-screen on a thread of their own; 0 = off (nothing created). Read-only.',
            read_only=True,
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=60.0)]))
        for live in self.spec.live_params:
            declare_double(self, live.name, live.default, _describe(
                f'{live.description} Live swap: takes effect at a step boundary once its '
                'model is compiled (a few ms; lockstep: the next step).',
                floating_point_range=[FloatingPointRange(from_value=live.live_range[0],
                                                         to_value=live.live_range[1])]))
        self.declare_parameter('publish_step_info', True, _describe(
            'false: publish no /zeus/step, as a ros2_control robot publishes none '
            '(read-only).', read_only=True))
        declare_command_parameters(self)
        declare_thread_priority(self)
        declare_executor(self)
        unknown = unknown_overrides(self)
        if unknown:
            raise UnknownParameters(f'unknown parameter {", ".join(unknown)} for '
                                    f'{self.spec.name}; {self._parameters_text()}')
        # The same checks as a live set (a declaration checks only type and range).
        if not isinstance(self._param('publish_step_info'), bool):
            raise ValueError('parameter publish_step_info: must be true or false')
        for name in (*self.spec.param_names, 'mode'):
            reason = self._parameter_problem(self.get_parameter(name))
            if reason is not None:
                raise ValueError(f'parameter {name}: {reason}')

    def _parameters_text(self) -> str:
        live = self.spec.param_names
        others = [name for name in parameter_names(self) if name not in live]
        others.sort(key=lambda name: name in RCLPY_PARAMETERS)  # the sim's own first
        what = ("the family's physical parameter" if len(live) == 1
                else "the family's live parameters")
        return f'its parameters: {", ".join(live)} ({what}), {", ".join(others)}'

    def _values_text(self, values: Sequence[float]) -> str:
        return ', '.join(f'{n}={v:g}' for n, v in zip(self.live_names, values, strict=True))

    def _live_changes(self, params: list[Parameter]) -> dict[str, float]:
        return {p.name: float(p.value) for p in params if p.name in self.live_names}

    def _param(self, name: str):
        return self.get_parameter(name).value

    def validate_parameters_callback(self, params: list[Parameter]) -> SetParametersResult:
        reasons = (self._parameter_problem(param) for param in params)
        reason = next((r for r in reasons if r is not None), None)
        changes = self._live_changes(params)
        if reason is None and changes:   # several at once are one swap
            reason = self.stepper.swap_refusal(self.stepper.with_changes(changes))  # queue full
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def _parameter_problem(self, param: Parameter) -> str | None:
        if not self.has_parameter(param.name):
            return f'{self.spec.name} has no parameter {param.name!r}; {self._parameters_text()}'
        if param.name in self.live_names:
            if param.type_ not in (Parameter.Type.DOUBLE, Parameter.Type.INTEGER):
                return f'{param.name} must be a number, got {param.type_.name}'
            return self.spec.check_param(param.name, param.value)
        if param.name == 'mode' and param.value not in MODES:
            return f'mode must be one of {MODES}, got {param.value!r}'
        return None

    def apply_parameters_callback(self, params: list[Parameter]) -> None:
        changes = self._live_changes(params)
        if changes:
            self.stepper.request_swap(self.stepper.with_changes(changes))
        for param in params:
            if param.name == 'seed':
                self.stepper.pending_seed = int(param.value)
            elif param.name in ('mode', 'real_time_factor', 'command_timeout'):
                self._configure_stepping()

    def _configure_stepping(self) -> None:
        self.stepper.configure(self._param('mode'), self._param('command_timeout'),
                               self._param('real_time_factor'), time.monotonic())
        self.tick_lateness.restart()

    def loop_deadline(self) -> LoopDeadline | None:
        """Return when the node must act without a message (see zeus_ros.ros.loop_spin)."""
        when = self.stepper.deadline()
        if when is None:
            return None
        lead = TICK_SLEEP_LEAD_S if self.stepper.mode == 'realtime' else 0.0
        return LoopDeadline(when, self.deadline_callback, lead)

    # -- stepping -------------------------------------------------------------
    def command_callback(self, msg: JointState | Float64MultiArray) -> None:
        self.first_command.seen()
        action, reason, stamp = self._parse(msg)
        with self.physics_lock:
            outcome = self.stepper.on_command(stamp, action, time.monotonic())
        self._report(outcome)
        if reason is not None:
            self.warnings.warn('rejected', f'rejected command ({reason}); applying zero action '
                                   f'[{self.stepper.counters["rejected"]} rejected so far]')

    def _parse(self, msg: JointState | Float64MultiArray
               ) -> tuple[np.ndarray | None, str | None, int]:
        """Return (action, why not, the stamp it answers) of a command of the declared type."""
        if self.port.command_type == 'joint_state' and self.port.codec.units is None \
                and list(self.port.codec.order) == sorted(self.port.codec.order):
            # Today's form, as it always was read (names in any order, normalised).
            action, reason = parse_command(msg.name, msg.effort, self.env.actuator_names)
            return action, reason, stamp_ns(msg.header)
        action, reason, stamp = self.port.action(msg)
        if stamp is None:
            # Unstamped (ros2_control's form): it answers the state awaited, or the newest.
            stamp = self.stepper.awaited_ns
            stamp = self.stepper.tick * self.stepper.dt_ns if stamp is None else stamp
        return action, reason, stamp

    def deadline_callback(self) -> None:
        with self.physics_lock:
            outcome = self.stepper.on_deadline(time.monotonic())
        self._report(outcome)

    def _report(self, outcome: StepOutcome) -> None:
        """Feed the meters and the log with what the stepper did."""
        self.pause.after_step()   # answers a ~/step whose last step this was
        if outcome.latency_s is not None:
            self.step_rate.record(outcome.latency_s)
        if outcome.tick_late_s is not None:
            self.tick_lateness.record(outcome.tick_late_s, self.stepper.tick_period,
                                      outcome.answered)
        if outcome.timed_out:
            self.first_command.timed_out('timeout', 'no command within '
                                         f'{self.stepper.command_timeout} s; applying zero action')
        for swap in outcome.swaps:
            self.get_logger().info(f'{", ".join(self.live_names)}: {format_values(swap.old)} -> '
                                   f'{format_values(swap.new)} at {swap.where}')
        if outcome.instability is not None:
            self.get_logger().warning(f'MuJoCo instability ({outcome.instability}); '
                                      'episode reset')

    def publish_state(self, state: PublishedState) -> None:
        joint_state = JointState(name=list(self.env.joint_names),
                                 position=state.positions.tolist(),
                                 velocity=state.velocities.tolist())
        set_stamp(joint_state.header, state.stamp_ns)
        step = StepInfo(episode=state.episode, step=state.step, reward=state.reward,
                        terminal=state.terminal, truncated=state.truncated,
                        applied_action=[] if state.applied_action is None
                        else state.applied_action.tolist(),
                        family=self.spec.name, param_names=list(self.live_names),
                        param_values=list(state.param_values))
        step.header = joint_state.header
        clock = Clock()
        clock.clock = joint_state.header.stamp
        # The loop's two messages first; /clock is for tools and sim-time users.
        if self.publish_step_info:
            self.step_pub.publish(step)
        self.joint_pub.publish(joint_state)
        self.clock_pub.publish(clock)
        self.pause.record(joint_state, step)

    # -- service ----------------------------------------------------------------
    def reset_callback(self, request: Reset.Request, response: Reset.Response) -> Reset.Response:
        names, values = list(request.param_names), list(request.param_values)
        problem = check_reset_request(request.seed, names, values, self.spec)
        superseded = ()
        if problem is None:
            # The request's value replaces any still waiting: they never take effect.
            superseded = self.swaps.clear() if names else ()
            problem = self._set_for_reset(request.seed, names, values)
        if problem is not None:
            self.warnings.warn('reset', f'reset refused: {problem}')
            response.success, response.message = False, problem
            return response
        restarts = self.stepper.pending_seed is not None
        with self.physics_lock:
            outcome = self.stepper.reset()   # waits for queued values' models (ms each)
        self._report(outcome)
        stepper = self.stepper
        stream = (f'stream restarted at seed {stepper.stream_seed}' if restarts
                  else f'stream of seed {stepper.stream_seed} continued')
        response.success, response.episode = True, stepper.episode
        response.message = (f'episode {stepper.episode}: {stream}, '
                            f'{self._values_text(self.env.param_values)}')
        if superseded:
            response.message += (f' ({", ".join(self.live_names)} '
                                 f'{", ".join(format_values(v) for v in superseded)} set '
                                 'before it and not yet in force: superseded)')
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
        counters, now = self.stepper.counters, time.monotonic()
        recent = self.recent.rises(now, counters)
        sim_s = self.stepper.tick * self.stepper.dt_ns * 1e-9
        values = dict(counters, episode=self.stepper.episode, step=self.env.step_count,
                      mode=self.stepper.mode, paused=self.stepper.paused,
                      real_time_factor_achieved=(
                          f'{self.achieved_rtf.update(now, sim_s):.3f}'),
                      **dict(zip(self.live_names, self.env.param_values, strict=True)),
                      swaps_waiting=len(self.swaps), window_s=self.recent.window_s,
                      recent_steps=recent['steps'], recent_answered=recent['answered'],
                      **self.step_rate.report(), **self.tick_lateness.report())
        self.diagnostics_pub.publish(diagnostic_array(
            self, 'simulation', self.spec.name, values, self._problem(recent)))

    def _problem(self, recent: dict) -> str | None:
        """Return the loop's problems over the window; log more than one controller.

        A paused sim steps nothing: its loop has no problem then, but a second
        controller is still one.
        """
        window_s = self.recent.window_s
        commands = command_problem(publisher_names(self, self.command_sub.topic_name),
                                   recent['stale'], window_s)
        if commands is not None:
            self.warnings.warn('commands', commands)
        loop = None if self.stepper.paused else loop_problem(recent, window_s)
        return '; '.join(p for p in (commands, loop) if p) or None


def main(args: list[str] | None = None) -> int:
    # A bad family, initial parameter value or unknown parameter: say which, exit 1.
    return run_node(SimNode, args, fatal=(ValueError,))


if __name__ == '__main__':
    sys.exit(main())
