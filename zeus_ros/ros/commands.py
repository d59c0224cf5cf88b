"""ROS-free logic of commands in ros2_control's form, and of a window built from them (#49).

A ros2_control robot publishes `/joint_states` and nothing else: no StepInfo.
This module holds what the nodes need to work with one:

* `joint_order` / `CommandCodec`: the policy's normalised action (actuator
  order, [-1, 1]) as a `Float64MultiArray`'s values in a declared joint order,
  normalised or in the actuators' units (MuJoCo: effort = gear * ctrl, ctrl
  mapped from [-1, 1] onto the control range), and back.
* `reward_free_refusal`: whether a checkpoint's context can be computed
  without the reward and the sim's true values (what StepInfo alone carries).
* `CommandTransitionAssembler`: the context window fed from joint states and
  the commands that answered them, with the StepInfo path's semantics
  (`zeus_ros.ros.pairing.TransitionAssembler`) wherever a robot can give them.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from sim_node.layout import check_action, ObservationLayout
from zeus_ros.core.window import ContextWindow
from zeus_ros.ros.pairing import (BadMessage, ClockListener, DUPLICATE, NEXT, OUTLIER,
                                  observation_from_message, StampFollower, StateRecord)

ACTION_SOURCES = ('step_info', 'commands')
# What a window built from commands puts in place of the reward a robot does not give:
# nothing (weights whose context reads it are refused) or psi's training mean.
MISSING_REWARD = ('refuse', 'training_mean')
COMMAND_TYPES = ('joint_state', 'float64_array')
COMMAND_UNITS = ('normalised', 'actuator')
# What each command type is published on when `command_topic` is left empty:
# today's topic, and the topic of a forward_command_controller named as
# ros2_control's examples name their effort controller.
DEFAULT_COMMAND_TOPICS = {'joint_state': '/joint_commands',
                          'float64_array': '/forward_effort_controller/commands'}
# States kept while the command answering their predecessor is in flight.
MAX_WAITING_STATES = 8


class CommandSetupError(ValueError):
    """A command interface that cannot work (refused at start-up, one line, exit 1)."""


def choose(value: str, allowed: Sequence[str], name: str) -> str:
    """Return `value` if it is one of `allowed`; CommandSetupError names the parameter."""
    if value not in allowed:
        raise CommandSetupError(f'parameter {name} must be one of {", ".join(allowed)}, '
                                f'got {value!r}')
    return value


def command_topic(command_type: str, topic: str) -> str:
    """Return the topic given, or the command type's default when it is empty."""
    return topic or DEFAULT_COMMAND_TOPICS[choose(command_type, COMMAND_TYPES, 'command_type')]


def joint_order(actuators: Sequence[str], joints: Sequence[str]) -> tuple[int, ...]:
    """For each declared joint, its index in actuator order; an empty list keeps that order.

    CommandSetupError for a mapping that names an unknown joint, names one
    twice or leaves one out: a robot would otherwise drive the wrong joint.
    """
    if not joints:
        return tuple(range(len(actuators)))
    unknown = [j for j in joints if j not in actuators]
    twice = sorted({j for j in joints if list(joints).count(j) > 1})
    missing = [a for a in actuators if a not in joints]
    problems = [f'unknown {unknown}' if unknown else '', f'twice {twice}' if twice else '',
                f'left out {missing}' if missing else '']
    problems = [p for p in problems if p]
    if problems:
        raise CommandSetupError(f'parameter joints {list(joints)} must name each of the '
                                f'actuators {list(actuators)} once: {"; ".join(problems)}')
    return tuple(actuators.index(j) for j in joints)


@dataclass(frozen=True)
class ActuatorUnits:
    """Control range and gear of each actuator (actuator order): MuJoCo's motor semantics."""

    low: np.ndarray
    high: np.ndarray
    gear: np.ndarray

    @classmethod
    def of(cls, low: Sequence[float], high: Sequence[float],
           gear: Sequence[float]) -> 'ActuatorUnits':
        """Build from three equal-length sequences; CommandSetupError if unusable."""
        arrays = [np.asarray(v, dtype=np.float64).reshape(-1) for v in (low, high, gear)]
        if len({a.size for a in arrays}) != 1 or not all(np.all(np.isfinite(a)) for a in arrays) \
                or np.any(arrays[1] <= arrays[0]) or np.any(arrays[2] == 0.0):
            raise CommandSetupError(f'actuator units need finite low < high and a non-zero '
                                    f'gear per actuator, got {[a.tolist() for a in arrays]}')
        return cls(*arrays)

    def to_effort(self, action: np.ndarray) -> np.ndarray:
        """Normalised action -> joint effort (gear * ctrl)."""
        ctrl = self.low + (action + 1.0) * 0.5 * (self.high - self.low)
        return self.gear * ctrl

    def to_normalised(self, effort: np.ndarray) -> np.ndarray:
        """Joint effort -> normalised action (unclipped)."""
        ctrl = effort / self.gear
        return (ctrl - self.low) * 2.0 / (self.high - self.low) - 1.0


@dataclass(frozen=True)
class CommandCodec:
    """A normalised action (actuator order) <-> a command's values (declared joint order)."""

    actuator_names: tuple[str, ...]
    order: tuple[int, ...]            # declared joint i is actuator order[i]
    units: ActuatorUnits | None       # None: normalised values

    @property
    def joint_names(self) -> list[str]:
        """The declared joint order (a JointState command's names)."""
        return [self.actuator_names[i] for i in self.order]

    def encode(self, action: np.ndarray) -> list[float]:
        """Return the values to publish for a normalised action."""
        values = action if self.units is None else self.units.to_effort(action)
        return [float(values[i]) for i in self.order]

    def decode(self, values: Sequence[float]) -> tuple[np.ndarray | None, str | None]:
        """Return a command's values as (normalised action in [-1, 1], None), or (None, why)."""
        if len(values) != len(self.order):
            return None, f'{len(values)} values for the {len(self.order)} joints'
        array = np.empty(len(self.order))
        array[list(self.order)] = np.asarray(values, dtype=np.float64)
        if self.units is not None:
            array = self.units.to_normalised(array)
        return check_action(array, len(self.order))


def make_codec(actuator_names: Sequence[str], joints: Sequence[str], units_mode: str,
               units: ActuatorUnits | None) -> CommandCodec:
    """Return the codec for a `joints` mapping and a `command_units` mode (CommandSetupError)."""
    actuators = tuple(actuator_names)
    order = joint_order(actuators, list(joints))
    if choose(units_mode, COMMAND_UNITS, 'command_units') == 'normalised':
        return CommandCodec(actuators, order, None)
    if units is None:
        raise CommandSetupError('command_units actuator: the checkpoint records no control '
                                'range and gear (written since #49); use command_units '
                                'normalised')
    return CommandCodec(actuators, order, units)


def reward_free_refusal(method: str, context_dim: int, needs_true_param: bool,
                        reward_in_observation: bool, reward_prior: float | None = None,
                        reads_reward: bool = True) -> str | None:
    """Why a checkpoint cannot run on a window built without StepInfo, or None.

    Such a window lacks the reward and the sim's true values. Every context
    encoder of this project reads the reward in its rows (concat(s, a, r, s')),
    unless trained not to (`context_reward` false: `reads_reward` False here),
    so only such a checkpoint or one without a context (context_dim 0) runs
    reward-free, unless a stand-in reward is given (`reward_prior`, psi's training mean:
    `missing_reward` training_mean, an approximation).
    """
    if needs_true_param:
        return f'{method} reads the true parameter values, which only StepInfo carries'
    if reward_in_observation:
        return f'{method} observes the reward, which only StepInfo carries'
    if context_dim > 0 and reads_reward and reward_prior is None:
        return (f"{method} reads the reward in its window rows (concat(s, a, r, s')), "
                'which only StepInfo carries')
    return None


class CommandTransitionAssembler:
    """Feeds the window from joint states and the commands that answered them.

    A state completes (gets its context) once the command answering the state
    before it is in: the transition (s, a, r, s') is pushed then, with r the
    assembler's `reward` (NaN: unknown without StepInfo; or a stand-in). A
    stamped command (JointState) answers the state of its stamp; an unstamped
    one (Float64MultiArray) answers the state a waiting state follows, else
    the newest state. A state whose predecessor got no command starts an
    empty window, as the StepInfo path does at a gap. Without step numbers a
    state this node never received goes unnoticed: the next transition then
    spans two periods. There are no episodes: a robot's clock restarting is
    the only boundary.
    """

    def __init__(self, window: ContextWindow, layout: ObservationLayout,
                 on_clock: ClockListener | None = None, reward: float = math.nan):
        self.window, self.layout, self.on_clock = window, layout, on_clock
        self.reward = reward    # put in every row: NaN (unknown) or a stand-in
        self.clock = StampFollower()
        self.previous: StateRecord | None = None     # the last completed state
        self._waiting: list[StateRecord] = []         # states after it, oldest first
        self._commands: dict[int, np.ndarray] = {}    # stamp -> action that answered it
        self.dropped = 0       # duplicated or stray states
        self.gaps = 0          # transitions without their command (window emptied)
        self.restarts = 0      # clocks that went back or jumped
        self.outliers = 0      # states ignored for a stamp far ahead

    @property
    def newest_stamp(self) -> int | None:
        """The newest accepted state's stamp."""
        if self._waiting:
            return self._waiting[-1].stamp_ns
        return None if self.previous is None else self.previous.stamp_ns

    def add_joint_state(self, stamp_ns: int, names: Sequence[str], positions: Sequence[float],
                        velocities: Sequence[float]) -> list[StateRecord]:
        """Record a state; return the states it completes (BadMessage if it does not fit)."""
        obs = observation_from_message(self.layout, names, positions, velocities)
        if not self._accept(stamp_ns):
            return []
        record = StateRecord(stamp_ns, obs, episode=0, step=0, reward=self.reward,
                             applied_action=np.zeros(self.window.action_dim), truncated=False)
        if self.previous is None:
            return [self._complete(record, None)]
        self._waiting.append(record)
        # A further state came: the command answering the one before the first never will.
        return self._flush(give_up_first=len(self._waiting) > 1)

    def add_command(self, action: np.ndarray, stamp_ns: int | None = None) -> list[StateRecord]:
        """Record the action that answered a state (its stamp, or None: unstamped)."""
        target = stamp_ns if stamp_ns is not None else self._unstamped_target()
        if target is None:
            return []
        self._commands[target] = np.asarray(action, dtype=np.float64)
        self._trim_commands()
        return self._flush(give_up_first=False)

    def _unstamped_target(self) -> int | None:
        if self._waiting and self.previous is not None:
            return self.previous.stamp_ns      # a waiting state awaits exactly this
        return self.newest_stamp

    def _accept(self, stamp_ns: int) -> bool:
        high = self.clock.high
        event = self.clock.observe(stamp_ns)
        if event == NEXT:
            return True
        if event == DUPLICATE:
            self.dropped += 1
            return False
        if self.on_clock is not None:
            self.on_clock(event, stamp_ns, high)
        if event == OUTLIER:
            self.outliers += 1
            return False
        self.restarts += 1                 # RESTART or JUMP: a new clock
        self.previous, self._waiting, self._commands = None, [], {}
        return True

    def _flush(self, give_up_first: bool) -> list[StateRecord]:
        done = []
        while self._waiting:
            action = self._commands.get(self.previous.stamp_ns)
            if action is None and not give_up_first:
                break
            done.append(self._complete(self._waiting.pop(0), action))
            give_up_first = False
        return done

    def _complete(self, record: StateRecord, action: np.ndarray | None) -> StateRecord:
        prev = self.previous
        if prev is not None and action is not None:
            self.window.push(prev.observation, action, record.reward, record.observation)
            record.applied_action = action
        else:
            if prev is not None:
                self.gaps += 1
            self.window.clear()
        for stamp in [s for s in self._commands if s < record.stamp_ns]:
            del self._commands[stamp]   # answered states older than this one: used or late
        self.previous = record
        return record

    def _trim_commands(self) -> None:
        while len(self._commands) > MAX_WAITING_STATES:
            self._commands.pop(min(self._commands))


__all__ = ['ACTION_SOURCES', 'ActuatorUnits', 'BadMessage', 'choose', 'command_topic',
           'COMMAND_TYPES', 'COMMAND_UNITS', 'CommandCodec', 'CommandSetupError',
           'CommandTransitionAssembler', 'DEFAULT_COMMAND_TOPICS', 'joint_order', 'make_codec',
           'MISSING_REWARD', 'reward_free_refusal']
