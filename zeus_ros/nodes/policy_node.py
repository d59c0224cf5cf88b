"""policy_node: publishes the trained policy's action for each state and its context.

Subscribes /joint_states and /zeus/context; when the state and the context of
one stamp are both in, publishes the deterministic (mean) action on
/joint_commands with that stamp and the actuator names, or, by `command_type`
float64_array, as ros2_control's forward_command_controller takes it
(zeus_ros.ros.command_params: topic, joint order, units). phi(s) is computed
as soon as the state arrives, while the context node works on its latent
(for weights whose observation ends with the reward into the state, once the
context brings that reward: Context.reward). It
answers the newest complete pair (in realtime mode older states are skipped);
a state whose context has not come within `context_timeout` gets a zero action
and a warning (before the first context ever came, no answer: the sim's own
command timeout applies the zero action).

It acts only once the sim's first StepInfo has shown the weights' family (a
sim of another family ends the node with code 1 and one line); with
`require_step_info` false (a robot publishes none) it acts at once, unchecked. A joint state
that does not fit the weights is ignored, a restarted sim (its clock starts
again) is followed (`zeus_ros.ros.pairing.StampFollower`), and a non-finite
action becomes the zero action; each is counted, warned (throttled) and
reported in /diagnostics.
"""

# ruff: noqa: E402
# (The stop guard must come before the heavy imports: torch loads for seconds.)
from __future__ import annotations

from zeus_ros.ros import stop_guard

stop_guard.install('policy_node', __name__)

import math
import sys
import time
from typing import TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from rcl_interfaces.msg import FloatingPointRange
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from sensor_msgs.msg import JointState
from zeus_msgs.msg import Context, StepInfo

from zeus_ros.ros.protocol import RecentCounts
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.ros.command_params import declare_command_port, declare_decimator, units_of
from zeus_ros.ros.timing import LatencyWindow
from zeus_ros.ros.commands import CommandSetupError
from zeus_ros.ros.controller import (check_family, describe_clock_event, GraphMismatch,
                                     load_weights_parameter)
from zeus_ros.ros.loop_spin import create_loop_subscription, LoopDeadline
from zeus_ros.ros.pairing import (BadMessage, forget_received, observation_from_message, OUTLIER,
                              StateContextPairer)
from zeus_ros.ros.util import (declare_double, describe, diagnostic_array, FirstContact,
                               LOOP_QOS, RateMeter, run_node,
                               stamp_ns, ThrottledWarnings)

if TYPE_CHECKING:
    from rclpy.parameter import Parameter


class PolicyNode(Node):
    """Thin ROS shell around `StateContextPairer` and the checkpoint's actor."""

    def __init__(self):
        super().__init__('policy_node')
        self.model = load_weights_parameter(self)
        timeout = declare_double(self, 'context_timeout', 0.5, describe(
            'Seconds a state waits for its context before a zero action is sent.',
            floating_point_range=[FloatingPointRange(from_value=0.001, to_value=60.0)]))
        self.layout = self.model.meta.obs_layout.layout()
        self.actuator_names = list(self.model.meta.action_layout.actuator_names)
        self.zero_action = np.zeros(self.model.action_dim)
        self.pairer = StateContextPairer(timeout, on_clock=self.clock_event,
                                         max_context_age_ns=self._max_context_age_ns())
        self.received_at: dict[int, float] = {}
        self.counters = {'zero_actions': 0, 'non_finite_actions': 0, 'bad_contexts': 0,
                         'bad_joint_states': 0}
        self.action_rate = RateMeter()   # latency: state received -> command published
        self.recent = RecentCounts()
        self.warnings = ThrottledWarnings(self.get_logger())
        # At start-up a state may come before the sim's first StepInfo or its
        # context (readers still matching): said once, not warned (issue #38.5).
        self.first_step = FirstContact(self.get_logger(), self.warnings,
                                       "waiting for the sim's first StepInfo: not answering")
        self.first_context = FirstContact(self.get_logger(), self.warnings,
                                          'waiting for the first context: not answering')
        # The family is checked once, on the first StepInfo, by the executor
        # thread; the subscription then goes, so it costs nothing per step.
        self.family_checked = not self._require_step_info()
        if not self.family_checked:
            self.family_sub = self.create_subscription(StepInfo, '/zeus/step',
                                                       self.family_callback, LOOP_QOS)
        action = self.model.meta.action_layout
        self.port = declare_command_port(self, self.actuator_names, units_of(
            action.ctrl_low, action.ctrl_high, action.gear))
        self.command_pub = self.create_publisher(self.port.message_type, self.port.topic,
                                                 LOOP_QOS)
        # A robot's states may come faster than the trained period: act on one per period.
        self.decimator = declare_decimator(self, self.model.meta.control_timestep)
        self.latencies = LatencyWindow()
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        create_loop_subscription(self, JointState, '/joint_states', self.joint_state_callback,
                                 LOOP_QOS)
        create_loop_subscription(self, Context, '/zeus/context', self.context_callback, LOOP_QOS)
        self.create_timer(1.0, self.diagnostics_callback)
        self.add_post_set_parameters_callback(self.parameters_callback)

    def _max_context_age_ns(self) -> int:
        age = declare_double(self, 'context_max_age', 0.0, describe(
            '0: a state waits for its own context; > 0 (s): it is answered at once with the '
            'newest context at most this much older (asynchronous adaptation); read-only.',
            read_only=True,
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=60.0)]))
        if age > 0 and self.model.reward_in_observation:
            raise ParameterException('must be 0 for weights that observe the reward '
                                     "(the context brings the state's own reward)",
                                     'context_max_age')
        return round(age * 1e9)

    def _require_step_info(self) -> bool:
        value = self.declare_parameter('require_step_info', True, describe(
            "true: act once the sim's first StepInfo has shown the weights' family; "
            'false: act at once, for a robot that publishes no StepInfo (read-only).',
            read_only=True)).value
        if not isinstance(value, bool):
            raise ParameterException('must be true or false', 'require_step_info')
        return value

    def parameters_callback(self, params: list[Parameter]) -> None:
        for param in params:
            if param.name == 'context_timeout':
                self.pairer.context_timeout = float(param.value)

    def family_callback(self, msg: StepInfo) -> None:
        if self.family_checked:
            return  # taken before the subscription went
        check_family(msg.family, self.model)
        self.family_checked = True
        self.first_step.seen()
        self.destroy_subscription(self.family_sub)
        self.get_logger().info(f'the sim runs {msg.family}: controlling')
        self.act_on_ready()

    def joint_state_callback(self, msg: JointState) -> None:
        try:
            obs = observation_from_message(self.layout, msg.name, msg.position, msg.velocity)
        except BadMessage as error:
            # A stray publisher must not stop the controller (the sim's own
            # states are vouched for by the family check).
            self.counters['bad_joint_states'] += 1
            self.warnings.warn('joint_state', f'ignored a joint state that does not fit the '
                                              f'{self.model.family} weights: {error}')
            return
        stamp = stamp_ns(msg.header)
        if not self.decimator.accept(stamp):
            return
        now = time.monotonic()
        self.received_at[stamp] = now
        # phi(s) now, unless the observation still lacks its reward (the context brings it).
        state = obs if self.layout.reward_in_observation else self.model.features(obs)
        self.pairer.add_state(stamp, state, now)
        self.act_on_ready()

    def context_callback(self, msg: Context) -> None:
        latent = np.asarray(msg.latent, dtype=np.float32)
        reward_ok = math.isfinite(msg.reward) or not self.layout.reward_in_observation
        if latent.shape != (self.model.context_dim,) or not np.all(np.isfinite(latent)) \
                or not reward_ok:
            self.counters['bad_contexts'] += 1
            self.warnings.warn('context', f'ignored a context of {latent.size} values '
                                          f'(expected {self.model.context_dim}, finite) '
                                          f'with reward {msg.reward}')
            return
        self.pairer.add_context(stamp_ns(msg.header), (latent, float(msg.reward)))
        self.first_context.seen()
        self.act_on_ready()

    def clock_event(self, event: str, stamp: int, previous: int | None) -> None:
        """Warn of a restart, jump or ignored stamp of a clock (the pairer calls it)."""
        self.warnings.warn(event, describe_clock_event(event, stamp, previous))
        if event.startswith('state') and not event.endswith(OUTLIER):
            self.received_at = {s: t for s, t in self.received_at.items() if s == stamp}

    def act_on_ready(self) -> None:
        if not self.family_checked:
            return  # nothing goes to a sim of unknown family; states wait, then expire
        ready = self.pairer.ready()
        if ready is None:
            return
        stamp, state, (latent, reward) = ready
        action = self.model.act_on_features(self.state_features(state, reward), latent)
        if not np.all(np.isfinite(action)):
            self.counters['non_finite_actions'] += 1
            self.warnings.warn('nonfinite', 'the policy produced a non-finite action; '
                                            'sending zeros')
            action = self.zero_action
        self.publish_command(stamp, np.clip(action, -1.0, 1.0))

    def state_features(self, state: np.ndarray, reward: float) -> np.ndarray:
        """phi(s) of a paired state (computed on arrival, or now with its reward put in)."""
        if not self.layout.reward_in_observation:
            return state
        return self.model.features(self.layout.with_reward(state, reward))

    def loop_deadline(self) -> LoopDeadline | None:
        """Return when the oldest waiting state's context times out (see ros.loop_spin)."""
        expiry = self.pairer.next_expiry()
        return None if expiry is None else LoopDeadline(expiry, self.timeout_callback)

    def timeout_callback(self) -> None:
        stamp = self.pairer.expired(time.monotonic())
        if stamp is None:
            return
        if not self.family_checked:
            self.first_step.timed_out('family', 'no StepInfo from the sim yet: not answering')
            return
        if not self.first_context.timed_out(
                'timeout', f'no context within {self.pairer.context_timeout} s; '
                'sending a zero action'):
            # Before the first context the context node's readers are still
            # matching: a blind answer would race the sim's own command timeout
            # (which applies the same zero action), a warning on every start.
            return
        self.counters['zero_actions'] += 1
        self.publish_command(stamp, self.zero_action)

    def publish_command(self, stamp: int, action: np.ndarray) -> None:
        self.command_pub.publish(self.port.message(action, stamp))
        received = self.received_at.get(stamp, time.monotonic())
        self.action_rate.record(time.monotonic() - received)
        self.latencies.record(time.monotonic() - received)
        forget_received(self.received_at, stamp)

    def diagnostics_callback(self) -> None:
        # Skipped states are not a problem (realtime mode answers the newest).
        counts = dict(self.counters, clock_restarts=self.pairer.restarts,
                      stamp_outliers=self.pairer.outliers)
        values = dict(self.action_rate.report(), **self.latencies.report(),
                      decimated_states=self.decimator.skipped,
                      older_contexts=self.pairer.older_contexts,
                      dropped_states=self.pairer.dropped,
                      family_checked=self.family_checked, **counts)
        # The level says what happened lately, the values count since start.
        problem = self.recent.problem(time.monotonic(), counts)
        self.diagnostics_pub.publish(diagnostic_array(self, 'policy', self.model.family,
                                                      values, problem))


def main(args: list[str] | None = None) -> int:
    return run_node(PolicyNode, args, fatal=(CheckpointError, GraphMismatch, CommandSetupError))


if __name__ == '__main__':
    sys.exit(main())
