"""context_node: keeps the last k transitions and publishes the latent context.

Subscribes /joint_states and /zeus/step, rebuilds each transition (s, a, r, s')
by stamp with the training window's semantics, runs psi, and publishes
/zeus/context once per state, stamped with the state it describes, with the
physical parameter decoded from the latent.

By default (`action_source` step_info) it does not subscribe the commands:
StepInfo carries the action MuJoCo actually applied (after clipping, or zeros
after a rejected or late command), which a command on the wire cannot tell,
and one subscription fewer is one executor wake-up fewer per control step.
A robot publishes no StepInfo: with `action_source` commands the window is
built from /joint_states and the commands that answered them
(`command_type`, `command_topic`, `command_units`, `joints` as the policy's;
zeus_ros.ros.commands.CommandTransitionAssembler), with no reward, so only
weights whose context needs neither the reward nor the sim's true values run
that way; others are refused at start-up (one line, exit 1), unless
`missing_reward` training_mean puts psi's training mean of the reward in its
place (an approximation; docs/pages/robot.md says what it costs).

Bad input does not stop it: a joint state or StepInfo that does not fit the
weights is ignored, a restarted sim (its clock starts again) is followed with
an empty window (`zeus_ros.ros.pairing.StampFollower`), and a non-finite latent
from psi is replaced by the empty window's zero latent; each is counted,
warned (throttled) and reported in /diagnostics, whose level reflects the
last 10 s. A sim of another family (StepInfo.family) is refused: the node
exits with code 1 and one line (checked again after the sim clock restarts).
"""

# ruff: noqa: E402
# (The stop guard must come before the heavy imports: torch loads for seconds.)
from __future__ import annotations

from zeus_ros.ros import stop_guard

stop_guard.install('context_node', __name__)

import math
import sys
import time
from typing import TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from rclpy.node import Node
from rclpy.exceptions import ParameterException
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32MultiArray, Float64MultiArray, MultiArrayDimension
from zeus_msgs.msg import Context, StepInfo

from zeus_ros.ros.protocol import RecentCounts
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.inference import DeployedModel
from zeus_ros.core.window import ContextWindow
from zeus_ros.ros.command_params import (CommandPort, declare_command_port,
                                         declare_decimator, units_of)
from zeus_ros.ros.commands import (ACTION_SOURCES, choose, CommandSetupError,
                                   CommandTransitionAssembler, MISSING_REWARD,
                                   reward_free_refusal)
from zeus_ros.ros.controller import (check_family, describe_clock_event, GraphMismatch,
                                     load_weights_parameter)
from zeus_ros.ros.loop_spin import create_loop_subscription
from zeus_ros.ros.pairing import (BadMessage, forget_received, OUTLIER, StateRecord,
                                  TransitionAssembler)
from zeus_ros.ros.util import (describe, diagnostic_array, LOOP_QOS, RateMeter, run_node,
                               set_stamp, stamp_ns, ThrottledWarnings)

if TYPE_CHECKING:
    from std_msgs.msg import Header

# Largest magnitude a float32 field (Context.param_estimates) holds.
FLOAT32_MAX = float(np.finfo(np.float32).max)


class ContextGuard:
    """psi's latent and the decoded estimates (one per parameter), never non-finite.

    A non-finite latent is replaced by the empty window's: the zero latent (as
    defined in zeus_ros.core.window, whatever psi computes of an empty mask)
    and its estimates. A non-finite estimate of a finite latent is replaced by
    that same prior estimate. Where the prior is NaN, the weights carry no
    decoder, and NaN is what Context.param_estimates means by 'no estimate'.
    """

    def __init__(self, model: DeployedModel):
        self.model = model
        self.zero_latent = np.zeros(model.context_dim, dtype=np.float32)
        prior = self._estimates(self.zero_latent)
        self.prior_estimates = np.where(np.isinf(prior), math.nan, prior)
        self.non_finite_latents = self.non_finite_estimates = 0

    def _estimates(self, latent: np.ndarray) -> np.ndarray:
        values = np.asarray(self.model.decode_values(latent), dtype=np.float64)
        # A float32 field would turn a larger float into inf (or refuse it).
        return np.where(np.abs(values) <= FLOAT32_MAX, values,
                        np.where(np.isnan(values), math.nan, math.inf))

    def context(self, rows: np.ndarray, mask: np.ndarray,
                true_param: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, str]:
        """(latent, estimates, problem): problem is '' when nothing was replaced."""
        latent = self.model.context(rows, mask, true_param)
        if not np.all(np.isfinite(latent)):
            self.non_finite_latents += 1
            return self.zero_latent, self.prior_estimates, (
                'psi gave a non-finite latent; published the zero latent instead')
        estimates = self._estimates(latent)
        bad = np.isinf(estimates) | (np.isnan(estimates) & ~np.isnan(self.prior_estimates))
        if bad.any():
            self.non_finite_estimates += 1
            fixed = np.where(bad, self.prior_estimates, estimates)
            return latent, fixed, (
                f'the decoder gave {estimates.tolist()}; published the prior estimate '
                f'{self.prior_estimates[bad].tolist()} in its place')
        return latent, estimates, ''


class ContextNode(Node):
    """Thin ROS shell around `TransitionAssembler` and the checkpoint's psi."""

    def __init__(self):
        super().__init__('context_node')
        self.model = load_weights_parameter(self)
        self.window = ContextWindow(self.model.k, self.model.obs_dim, self.model.action_dim)
        self.port, reward = self._command_port()   # None: actions come from StepInfo
        layout = self.model.meta.obs_layout.layout()
        self.assembler = TransitionAssembler(self.window, layout, on_clock=self.clock_event) \
            if self.port is None else CommandTransitionAssembler(
                self.window, layout, on_clock=self.clock_event, reward=reward)
        self.guard = ContextGuard(self.model)
        self.param_names = list(self.model.param_names)
        # The sim's TRUE values (StepInfo.param_values): read only by privileged
        # weights (oracle), which are defined as knowing them.
        self.true_param = np.full(len(self.param_names), math.nan)
        self.family_checked = False
        self.bad_messages = {'joint_state': 0, 'step_info': 0, 'command': 0}
        self.received_at: dict[int, float] = {}
        self.context_rate = RateMeter()    # latency: first message of a stamp -> context out
        self.recent = RecentCounts()
        self.warnings = ThrottledWarnings(self.get_logger())

        self.context_pub = self.create_publisher(Context, '/zeus/context', LOOP_QOS)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        create_loop_subscription(self, JointState, '/joint_states', self.joint_state_callback,
                                 LOOP_QOS)
        if self.port is None:
            create_loop_subscription(self, StepInfo, '/zeus/step', self.step_callback,
                                     LOOP_QOS)
        else:
            create_loop_subscription(self, self.port.message_type, self.port.topic,
                                     self.command_callback, LOOP_QOS)
        self.window_pub = self._window_publisher()
        # As the policy's: the same stamps kept, one per trained period (commands only:
        # the sim's StepInfo path sees one state per period by construction).
        self.decimator = declare_decimator(self, self.model.meta.control_timestep)
        self.create_timer(1.0, self.diagnostics_callback)

    def _command_port(self) -> tuple[CommandPort | None, float]:
        """Declare `action_source` and the command interface; return the port and the reward.

        The port is None for step_info; the reward is what a window built from
        commands holds in its place (NaN: none). Misfits are refused.
        """
        source = self.declare_parameter('action_source', 'step_info', describe(
            "Where a transition's action comes from: step_info (the sim's StepInfo: the "
            'applied action and the reward) or commands (the commands answering each '
            'state: a robot without StepInfo; no reward); read-only.', read_only=True)).value
        port = declare_command_port(self, self.model.meta.action_layout.actuator_names,
                                    units_of(*self._units()))
        missing = choose(self.declare_parameter('missing_reward', 'refuse', describe(
            'action_source commands, weights whose context reads the reward: refuse (exit 1) '
            "or training_mean (psi's training mean in its place, an approximation); "
            'read-only.', read_only=True)).value, MISSING_REWARD, 'missing_reward')
        if choose(source, ACTION_SOURCES, 'action_source') == 'step_info':
            return None, math.nan
        prior = self.model.reward_prior() if missing == 'training_mean' else None
        refusal = reward_free_refusal(self.model.method_name, self.model.context_dim,
                                      self.model.needs_true_param,
                                      self.model.reward_in_observation, prior,
                                      self.model.meta.config.get('context_reward', True))
        if refusal is not None:
            # The stand-in reward helps only a context whose one lack is the reward.
            only_reward = not (self.model.needs_true_param or self.model.reward_in_observation)
            hint = ', or missing_reward training_mean (torch backend)' if only_reward else ''
            raise CommandSetupError(f'action_source commands: {refusal}; use step_info{hint}')
        reward = math.nan if prior is None or self.model.context_dim == 0 else prior
        self.get_logger().info(f'window from /joint_states and {port.command_type} '
                               f'commands on {port.topic}; reward in its rows: {reward:g}')
        return port, reward

    def _units(self) -> tuple:
        action = self.model.meta.action_layout
        return action.ctrl_low, action.ctrl_high, action.gear

    def _window_publisher(self):
        publish = self.declare_parameter('publish_window', False, describe(
            "Publish each context's window rows on ~/window (Float32MultiArray, rows "
            "oldest first, the state's stamp in the first dimension's label): for "
            'tests and debugging; read-only.', read_only=True)).value
        if not isinstance(publish, bool):
            raise ParameterException('must be true or false', 'publish_window')
        return self.create_publisher(Float32MultiArray, '~/window', LOOP_QOS) \
            if publish else None

    def joint_state_callback(self, msg: JointState) -> None:
        if self.port is not None and not self.decimator.accept(stamp_ns(msg.header)):
            return
        try:
            record = self.assembler.add_joint_state(stamp_ns(msg.header), msg.name,
                                                    msg.position, msg.velocity)
        except BadMessage as error:
            # A stray publisher must not stop the controller: the sim's own
            # states are checked by the family of its StepInfo.
            self.bad_messages['joint_state'] += 1
            self.warnings.warn('joint_state', f'ignored a joint state that does not fit the '
                                              f'{self.model.family} weights: {error}')
            return
        self._note(msg.header)
        for each in record if isinstance(record, list) else [record]:
            self._publish_for(each)

    def command_callback(self, msg: JointState | Float64MultiArray) -> None:
        action, reason, stamp = self.port.action(msg)
        if action is None:
            self.bad_messages['command'] += 1
            self.warnings.warn('command', f'ignored a command: {reason}')
            return
        for record in self.assembler.add_command(action, stamp):
            self._publish_for(record)

    def step_callback(self, msg: StepInfo) -> None:
        if not self.family_checked:
            check_family(msg.family, self.model)
            self.family_checked = True
        if len(msg.param_values) == len(self.param_names):
            self.true_param = np.asarray(msg.param_values, dtype=np.float64)
        try:
            record = self.assembler.add_step_info(stamp_ns(msg.header), msg.episode, msg.step,
                                                  msg.reward, msg.applied_action,
                                                  msg.truncated)
        except BadMessage as error:
            self.bad_messages['step_info'] += 1
            self.warnings.warn('step_info', f'ignored a StepInfo: {error}')
            return
        self._note(msg.header)
        self._publish_for(record)

    def clock_event(self, event: str, stamp: int, previous: int | None) -> None:
        """Warn of a restart, jump or ignored stamp of the sim clock (the assembler calls it)."""
        self.warnings.warn(event, describe_clock_event(event, stamp, previous))
        if event != OUTLIER:
            # Another clock may be another sim: check its family again.
            self.family_checked = False
            self.received_at = {s: t for s, t in self.received_at.items() if s == stamp}

    def _note(self, header: Header) -> None:
        self.received_at.setdefault(stamp_ns(header), time.monotonic())

    def _publish_for(self, record: StateRecord | None) -> None:
        if record is None:
            return
        true_param = self.true_param if self.model.needs_true_param else None
        latent, estimates, problem = self.guard.context(*self.window.arrays(), true_param)
        if problem:
            self.warnings.warn('non_finite', problem)
        msg = Context(latent=latent.tolist(), window_fill=self.window.fill,
                      param_names=self.param_names, param_estimates=estimates.tolist(),
                      # A window built from commands has no reward of its own to tell.
                      reward=float(record.reward) if self.port is None else math.nan)
        set_stamp(msg.header, record.stamp_ns)
        self.context_pub.publish(msg)
        if self.window_pub is not None:
            self._publish_window(record.stamp_ns)
        first_seen = self.received_at.get(record.stamp_ns, time.monotonic())
        self.context_rate.record(time.monotonic() - first_seen)
        forget_received(self.received_at, record.stamp_ns)

    def _publish_window(self, stamp: int) -> None:
        rows, _ = self.window.arrays()
        msg = Float32MultiArray(data=rows.reshape(-1).tolist())
        msg.layout.dim = [MultiArrayDimension(label=f'stamp_ns={stamp}', size=rows.shape[0],
                                              stride=rows.size),
                          MultiArrayDimension(label='row', size=rows.shape[1],
                                              stride=rows.shape[1])]
        self.window_pub.publish(msg)

    def diagnostics_callback(self) -> None:
        counts = dict(dropped=self.assembler.dropped, gaps=self.assembler.gaps,
                      clock_restarts=self.assembler.restarts,
                      stamp_outliers=self.assembler.outliers,
                      bad_joint_states=self.bad_messages['joint_state'],
                      bad_step_infos=self.bad_messages['step_info'],
                      bad_commands=self.bad_messages['command'],
                      non_finite_latents=self.guard.non_finite_latents,
                      non_finite_estimates=self.guard.non_finite_estimates)
        values = dict(self.context_rate.report(), window_fill=self.window.fill,
                      window_k=self.window.k, decimated_states=self.decimator.skipped,
                      **counts)
        # The level says what happened lately, the values count since start.
        problem = self.recent.problem(time.monotonic(), counts)
        self.diagnostics_pub.publish(diagnostic_array(self, 'context', self.model.family,
                                                      values, problem))


def main(args: list[str] | None = None) -> int:
    return run_node(ContextNode, args, fatal=(CheckpointError, GraphMismatch, CommandSetupError))


if __name__ == '__main__':
    sys.exit(main())
