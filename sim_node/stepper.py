"""The sim node's stepping logic without ROS: lockstep and realtime, commands, swaps, episodes.

`SimStepper` owns one env (a `FamilyEnv`) and decides when it steps and on which
action. It is driven by explicit calls, each given the time it happened at:

* `on_command(stamp_ns, action, now)`: a command answering the state stamped
  `stamp_ns` (action None: it was malformed, a zero action stands in);
* `deadline()` / `due(now)` / `on_deadline(now)`: the one moment the sim must
  act without a message (the realtime tick, the lockstep command timeout, or
  a lockstep step waiting for a swap's physics);
* `request_swap(values)`, `reset()`, `configure(...)` for parameters and the
  reset service.

Every state it enters goes to the injected `publish(PublishedState)`; the
injected `clock()` stamps when a state went out (the command latency and the
lockstep timeout count from there). Each call returns a `StepOutcome` saying
what happened, for the caller's log and meters. No rclpy here: the node
(zeus_ros/nodes/sim_node.py) converts messages and parameters and calls these methods.

Modes. lockstep: publish a state, wait for the command answering its stamp
(a command for any other stamp is stale, counted, ignored), step; with no
answer within `command_timeout`, step on a zero action. realtime: tick n at
start + n x period (period = control period / real_time_factor, so the
schedule does not drift); each tick steps on the latest command, or a zero
action once that is older than `command_timeout`. A tick more than a period
late is counted and restarts the schedule from then; a tick at which the
command answering the previous state has not arrived is counted unanswered
(the controller's missed deadline). `configure` (a mode switch) restarts it.

Swaps. A value is the family's value tuple (sim_node.swaps; `with_changes`
makes one from the names a parameter set changes). A requested value is
queued (its physics is built by a worker thread) and takes effect at a step
boundary, at most one value per boundary, so every accepted value is in
force for at least one step, in order. realtime never waits for a build: a
tick steps on the physics in force and the value takes effect at the first
tick after its build. lockstep keeps its determinism: a step after a swap was
requested waits for the build (the loop keeps serving messages and services
meanwhile; `deadline` polls). A reset puts every queued value into force
before the episode's first state.

Pause. `pause(now)` stops the stepping (no tick, no timeout: nothing is
published and the sim clock stands still); `resume(now)` runs freely again and
`step(n, now)` runs exactly n steps, then pauses again (`budget` counts them
down). While paused a lockstep command answering the state in force is held,
and the first step after the pause is taken on it (none: the state waits for
its command as ever, the timeout counted from the resume); realtime takes the
first step at once, on the latest command. Time spent paused does not age a
command or count towards the timeout. A value set while paused is in force at
the first step after it (realtime waits for its build there, a few ms).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time
from typing import Callable, TYPE_CHECKING

import numpy as np

from sim_node.families import values_with
from sim_node.family_env import FamilyEnv, PreparedValues, Values

if TYPE_CHECKING:
    from sim_node.swaps import SwapQueue

MODES = ('lockstep', 'realtime')
# lockstep: how often a step waiting for a swap's build looks again (a build
# takes a few ms; the worker cannot wake the loop, so the loop polls).
SWAP_POLL_S = 0.001


@dataclass(frozen=True)
class PublishedState:
    """One state the sim entered: what /joint_states, /zeus/step and /clock carry."""

    stamp_ns: int             # simulated clock: states since start x control period
    episode: int
    step: int
    reward: float             # of the step that led here (0 at an episode start)
    terminal: bool
    truncated: bool
    applied_action: np.ndarray | None   # what MuJoCo applied; None at an episode start
    param_values: Values      # the parameter values in force (the family's param_names)
    positions: np.ndarray
    velocities: np.ndarray


@dataclass(frozen=True)
class SwapApplied:
    """A parameter value put into force."""

    old: Values
    new: Values
    where: str                # 'episode 3 step 41', 'the start of episode 4'


@dataclass
class StepOutcome:
    """What one call to the stepper did."""

    stepped: bool = False
    stale: bool = False               # lockstep: a command for a state not awaited
    timed_out: bool = False           # lockstep: no command within the timeout
    waiting_for_swap: bool = False    # lockstep: the step waits for a swap's build
    # lockstep: state published -> command in; realtime: age of the command used.
    latency_s: float | None = None
    tick_late_s: float | None = None  # realtime: tick start - scheduled time
    answered: bool = True             # realtime: the previous state's command had come
    swaps: list[SwapApplied] = field(default_factory=list)
    instability: str | None = None    # MuJoCo went unstable: the episode was restarted


class SimStepper:
    """Lockstep/realtime stepping of a `FamilyEnv`, with live swaps (see the module docstring)."""

    def __init__(self, env: FamilyEnv, publish: Callable[[PublishedState], None],
                 swaps: SwapQueue, clock: Callable[[], float] = time.monotonic,
                 seed: int = 0):
        """Step `env`; `swaps` is a sim_node.swaps.SwapQueue (or has its methods)."""
        self.env, self.publish, self.swaps, self.clock = env, publish, swaps, clock
        self.dt_ns = int(round(env.control_timestep * 1e9))
        self.tick = 0               # states published since start; the sim clock is tick * dt
        self.episode = 0
        self.stream_seed = seed     # where the current stream of initial states started
        self.pending_seed: int | None = None   # restarts the stream at the next episode start
        self.awaited_ns: int | None = None     # the published state not yet answered
        self.awaited_since = 0.0
        self.latest_action = self._zero()      # realtime: the latest command...
        self.latest_action_time = -math.inf
        self.latest_action_stamp = -1          # ...and the state it answers
        self._deferred: tuple[np.ndarray, int] | None = None  # lockstep step waiting for a swap
        self._poll_at = 0.0
        self.budget: int | None = None   # steps still allowed: None runs freely, 0 is paused
        self._paused_at: float | None = None
        self._swap_first = False   # realtime: the first tick after a pause takes the swap
        # Totals since start (the node's diagnostics report them).
        self.counters = {'rejected': 0, 'stale': 0, 'timeouts': 0, 'instabilities': 0,
                         'steps': 0, 'answered': 0, 'late_ticks': 0, 'swaps': 0}
        self.mode = 'lockstep'
        self.configure('lockstep', 0.5, 1.0, clock())

    def start(self) -> None:
        """Begin the first episode of the stream: publish its first state."""
        self.env.reset(seed=self.stream_seed)
        self._publish(0.0, False)

    # -- configuration ------------------------------------------------------------
    def configure(self, mode: str, command_timeout: float, real_time_factor: float,
                  now: float) -> None:
        """Set the mode and its timing; the realtime schedule restarts from `now`."""
        if mode not in MODES:
            raise ValueError(f'mode must be one of {MODES}, got {mode!r}')
        self.mode, self.command_timeout = mode, command_timeout
        self.tick_period = self.env.control_timestep / real_time_factor
        self.next_tick = now + self.tick_period
        if mode == 'realtime' and self._deferred is not None:
            # The command a lockstep step held for a swap: realtime steps on it next tick.
            (self.latest_action, self.latest_action_stamp), self._deferred = self._deferred, None
            self.latest_action_time = now

    @property
    def wanted_values(self) -> Values:
        """The values the sim will end up with: the last queued, or those in force."""
        waiting = self.swaps.values
        return waiting[-1] if waiting else tuple(self.env.param_values)

    def with_changes(self, changes: dict[str, float]) -> Values:
        """Return the wanted values with `changes` (name: value) made: what a set asks for.

        ValueError for a name the family lacks or a value out of its live range.
        """
        return values_with(self.env.spec, self.wanted_values, changes)

    def swap_refusal(self, values: Values) -> str | None:
        """Why `values` cannot be queued now (the queue is full), or None."""
        return None if tuple(values) == self.wanted_values else self.swaps.full_reason()

    def request_swap(self, values: Values) -> bool:
        """Queue `values` (checked by `swap_refusal`); False if the sim will have them anyway."""
        values = tuple(float(v) for v in values)
        if values == self.wanted_values:
            return False
        self.swaps.push(values)
        return True

    # -- pause, resume, step -----------------------------------------------------------
    @property
    def paused(self) -> bool:
        """Whether stepping is stopped (by `pause`, or at the end of a `step`)."""
        return self.budget == 0

    def pause(self, now: float) -> bool:
        """Stop stepping (a `step` under way ends here); False if it was paused already."""
        if self.paused:
            return False
        self.budget, self._paused_at = 0, now
        return True

    def resume(self, now: float) -> bool:
        """Run freely again; False if it was running already."""
        if self.budget is None:
            return False
        self.budget = None
        self._unpause(now)
        return True

    def step(self, steps: int, now: float) -> None:
        """Run exactly `steps` (>= 1) steps from a pause, then pause again."""
        if not self.paused or steps < 1:
            raise ValueError(f'step({steps}) needs a paused stepper and steps >= 1')
        self.budget = steps
        self._unpause(now)

    def _unpause(self, now: float) -> None:
        if self._paused_at is not None:
            idle = now - self._paused_at   # not counted: the timeout and a command's age
            self.awaited_since += idle
            self.latest_action_time += idle
        self._paused_at = None
        self.next_tick = now    # realtime: the first step at once
        self._poll_at = now     # lockstep: a command held while paused steps now
        self._swap_first = len(self.swaps) > 0

    # -- inputs ---------------------------------------------------------------------
    def on_command(self, stamp_ns: int, action: np.ndarray | None, now: float) -> StepOutcome:
        """Take a command answering the state stamped `stamp_ns` (`action` None: malformed)."""
        outcome = StepOutcome()
        if action is None:
            self.counters['rejected'] += 1
            action = self._zero()
        if self.mode == 'realtime':
            self.latest_action, self.latest_action_time = action, now
            self.latest_action_stamp = stamp_ns
            return outcome
        if stamp_ns != self.awaited_ns:
            self.counters['stale'] += 1
            outcome.stale = True
            return outcome
        outcome.latency_s = now - self.awaited_since
        self.counters['answered'] += 1
        self._lockstep_step(action, stamp_ns, now, outcome)
        return outcome

    def deadline(self) -> float | None:
        """When the stepper must act without a command (clock seconds), or None."""
        if self.paused:
            return None
        if self.mode == 'realtime':
            return self.next_tick
        if self._deferred is not None:
            return self._poll_at
        if self.awaited_ns is not None:
            return self.awaited_since + self.command_timeout
        return None

    def due(self, now: float) -> bool:
        """Whether the deadline has come."""
        deadline = self.deadline()
        return deadline is not None and now >= deadline

    def on_deadline(self, now: float) -> StepOutcome:
        """Act on the deadline (call it once `due(now)`): tick, time out, or retry a held step."""
        outcome = StepOutcome()
        if self.mode == 'realtime':
            self._tick(now, outcome)
        elif self._deferred is not None:
            action, stamp = self._deferred
            self._lockstep_step(action, stamp, now, outcome)
        elif self.awaited_ns is not None:
            self.counters['timeouts'] += 1
            outcome.timed_out = True
            self._lockstep_step(self._zero(), self.awaited_ns, now, outcome)
        return outcome

    def reset(self) -> StepOutcome:
        """Start a new episode now; every queued value is put into force first (waiting for it)."""
        outcome = StepOutcome()
        self._start_episode(outcome, take_swaps=True)
        return outcome

    # -- stepping -------------------------------------------------------------------
    def _tick(self, now: float, outcome: StepOutcome) -> None:
        late = now - self.next_tick
        answered = self.awaited_ns is None or self.latest_action_stamp == self.awaited_ns
        outcome.tick_late_s, outcome.answered = late, answered
        self.counters['answered'] += int(answered)
        self.counters['late_ticks'] += int(late > self.tick_period)
        # Absolute schedule (no drift); after a missed deadline it restarts from now.
        self.next_tick += self.tick_period
        if self.next_tick <= now:
            self.next_tick = now + self.tick_period
        age = now - self.latest_action_time
        fresh = age <= self.command_timeout
        outcome.latency_s = age if fresh else 0.0
        # Never waits (the tick keeps its time), but for a value set while paused.
        prepared = self.swaps.take_waiting() if self._swap_first else self.swaps.take_ready()
        self._swap_first = False
        if prepared is not None:
            self._apply(prepared, self._here(), outcome)
        self._step(self.latest_action if fresh else self._zero(), outcome)

    def _lockstep_step(self, action: np.ndarray, stamp: int, now: float,
                       outcome: StepOutcome) -> None:
        self.awaited_ns = None   # answered (or timed out): another command for it is stale
        if self.paused:   # held for the first step after the pause
            self._deferred = (action, stamp)
            return
        if len(self.swaps):
            prepared = self.swaps.take_ready()
            if prepared is None:   # hold the step until the swap's physics is built
                self._deferred, self._poll_at = (action, stamp), now + SWAP_POLL_S
                outcome.waiting_for_swap = True
                return
            self._apply(prepared, self._here(), outcome)
        self._deferred = None
        self._step(action, outcome)

    def _step(self, action: np.ndarray, outcome: StepOutcome) -> None:
        self.counters['steps'] += 1
        if self.budget is not None:
            self.budget -= 1
            if self.budget == 0:
                self._paused_at = self.clock()
        outcome.stepped = True
        result = self.env.step(action)
        if result.instability is not None:
            self.counters['instabilities'] += 1
            outcome.instability = result.instability
            self._start_episode(outcome, take_swaps=False)
            return
        self._publish(result.reward, result.truncated, result.terminal, result.applied_action)
        if result.truncated or result.terminal:
            self._start_episode(outcome, take_swaps=False)

    def _start_episode(self, outcome: StepOutcome, take_swaps: bool) -> None:
        """Next episode: queued swaps (a reset), pending seed (else the stream goes on), step 0."""
        self.episode += 1
        self._deferred = None
        while take_swaps and (prepared := self.swaps.take_waiting()) is not None:
            self._apply(prepared, f'the start of episode {self.episode}', outcome)
        seed, self.pending_seed = self.pending_seed, None
        if seed is not None:
            self.stream_seed = seed
        self.env.reset(seed=seed)
        self._publish(0.0, False)

    def _apply(self, prepared: PreparedValues, where: str, outcome: StepOutcome) -> None:
        old = tuple(self.env.param_values)
        self.env.apply_prepared(prepared)
        self.swaps.retire(prepared)   # the worker frees its compiled model, off the loop
        self.counters['swaps'] += 1
        outcome.swaps.append(SwapApplied(old, tuple(prepared.values), where))

    def _publish(self, reward: float, truncated: bool, terminal: bool = False,
                 applied_action: np.ndarray | None = None) -> None:
        self.tick += 1
        stamp = self.tick * self.dt_ns
        env = self.env
        self.publish(PublishedState(
            stamp, self.episode, env.step_count, float(reward), bool(terminal), bool(truncated),
            applied_action, tuple(env.param_values), env.joint_positions(),
            env.joint_velocities()))
        self.awaited_ns = None if truncated or terminal else stamp
        self.awaited_since = self.clock()

    def _here(self) -> str:
        return f'episode {self.episode} step {self.env.step_count}'

    def _zero(self) -> np.ndarray:
        return np.zeros(self.env.action_dim)
