"""ROS-free bookkeeping of the context and policy nodes: matching messages by stamp.

`TransitionAssembler` (context node) joins each `JointState` with the
`StepInfo` of the same stamp (whose reward is the observation's last entry
for weights that read it), rebuilds the transition `(s, a, r, s')` from
consecutive states of one episode (the action and reward come from StepInfo,
exactly as the simulator applied them), and feeds the `ContextWindow` with the
same semantics as training: cleared at an episode start, one push per step.

`StateContextPairer` (policy node) joins a state with the context of its stamp
and says which state to answer: the newest complete pair, or, once a state has
waited longer than the context timeout, that state with a zero action.

Both follow the simulator's clock with a `StampFollower`, so that a restarted
sim (its clock starts from zero again) gets control back at once, and a stray
message stamped far ahead does not stop control. `observation_from_message`
turns a `JointState`'s fields into an observation or says why it does not fit;
(`zeus_ros.ros.protocol.RecentCounts` keeps the nodes' diagnostic levels to the last few seconds.)
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Callable, Sequence

import numpy as np

from sim_node.layout import ObservationLayout
from zeus_ros.core.window import ContextWindow

# Partial entries kept while their partner message is in flight.
MAX_PENDING = 64

# The largest forward step of the sim clock between two accepted messages that
# is taken at face value. The clock advances one control period (10-25 ms) per
# state; a controller that falls behind in realtime mode skips at most the
# 10-message queue, and even at real_time_factor 100 a 0.1 s stall moves it
# 10 s. A wrong guess costs little either way (see StampFollower).
MAX_FORWARD_JUMP_NS = 10 * 1_000_000_000

# What StampFollower.observe says of a stamp.
NEXT = 'next'              # the clock goes on: accept
DUPLICATE = 'duplicate'    # the newest stamp again: ignore
RESTART = 'restart'        # the clock went back: a new clock, start over
JUMP = 'jump'              # a forward jump that continues a clock seen before: start over
OUTLIER = 'outlier'        # a lone jump far ahead: ignore

# Called with (event, stamp_ns, previous newest stamp_ns) on RESTART, JUMP, OUTLIER.
ClockListener = Callable[[str, int, int], None]


class BadMessage(ValueError):
    """A message that cannot be used (wrong joints, lengths, non-finite values)."""


def observation_from_message(layout: ObservationLayout, names: Sequence[str],
                             positions: Sequence[float],
                             velocities: Sequence[float]) -> np.ndarray:
    """Return a JointState's fields as the policy observation; BadMessage says why not."""
    if not len(names) == len(positions) == len(velocities):
        raise BadMessage(f'{len(names)} names, {len(positions)} positions and '
                         f'{len(velocities)} velocities')
    try:
        obs = layout.observation_from_joint_state(names, positions, velocities)
    except ValueError as error:
        raise BadMessage(str(error)) from None
    if not np.all(np.isfinite(obs)):
        raise BadMessage('non-finite joint positions or velocities')
    return obs


class StampFollower:
    """Follows the sim clock through restarts; a lone stamp far ahead is ignored.

    `observe(stamp)` compares a stamp with the newest one accepted (`high`):

    * high < stamp <= high + max_jump: NEXT, accepted.
    * stamp == high: DUPLICATE, ignored.
    * stamp < high: RESTART, accepted as the new newest stamp. One publisher's
      messages arrive in order (reliable DDS, one topic), so a clock that goes
      back is another clock: a restarted sim starts from zero. The caller
      starts over (window, pending pairs) at once: a lockstep sim waits for
      the answer to its first state, so control comes back with it.
    * stamp > high + max_jump: suspicious. It is accepted (JUMP, the caller
      starts over) only if it continues the OTHER clock, the one remembered
      in `alt`: the newest stamp before the last restart, or the last
      suspicious stamp. Otherwise it is an OUTLIER, ignored, and becomes `alt`.

    So one message stamped 1000 s ahead moves nothing (the sim's next state is
    NEXT), a second one continuing it is taken as a clock that really jumped,
    and if the sim then goes on from its own clock, that is a RESTART: control
    resumes at once. A stray message stamped in the past is a RESTART, and the
    sim's next state, far ahead of it but continuing the old clock, is a JUMP
    back. Any wrong guess costs one start-over, never control.
    """

    def __init__(self, max_jump_ns: int = MAX_FORWARD_JUMP_NS):
        self.max_jump_ns = max_jump_ns
        self.high: int | None = None
        self.alt: int | None = None

    def observe(self, stamp_ns: int) -> str:
        """Classify a stamp (NEXT, DUPLICATE, RESTART, JUMP or OUTLIER); accept it or not."""
        high = self.high
        if high is None or high < stamp_ns <= high + self.max_jump_ns:
            self.high = stamp_ns
            return NEXT
        if stamp_ns == high:
            return DUPLICATE
        if stamp_ns < high:
            self.high, self.alt = stamp_ns, high
            return RESTART
        if self.alt is not None and self.alt < stamp_ns <= self.alt + self.max_jump_ns:
            self.high, self.alt = stamp_ns, high
            return JUMP
        self.alt = stamp_ns
        return OUTLIER


@dataclass
class StateRecord:
    """A state with the StepInfo of its stamp."""

    stamp_ns: int
    observation: np.ndarray
    episode: int
    step: int
    reward: float
    applied_action: np.ndarray
    truncated: bool


class TransitionAssembler:
    """Turns the sim's state stream into context-window pushes."""

    def __init__(self, window: ContextWindow, layout: ObservationLayout,
                 on_clock: ClockListener | None = None):
        self.window, self.layout = window, layout
        self.on_clock = on_clock
        self.clock = StampFollower()
        self._observations: dict[int, np.ndarray] = {}
        self._infos: dict[int, tuple] = {}
        self.previous: StateRecord | None = None
        self.dropped = 0    # messages duplicated or never completed
        self.gaps = 0       # transitions that could not be rebuilt (missed a state)
        self.restarts = 0   # clocks that went back or jumped (RESTART, JUMP)
        self.outliers = 0   # states ignored for a stamp far ahead (OUTLIER)

    def add_joint_state(self, stamp_ns: int, names: Sequence[str], positions: Sequence[float],
                        velocities: Sequence[float]) -> StateRecord | None:
        """Record a joint state; return the StateRecord it completes, if any.

        Raises BadMessage, before touching anything, for a state that does not fit.
        """
        self._observations[stamp_ns] = observation_from_message(
            self.layout, names, positions, velocities)
        return self._complete(stamp_ns)

    def add_step_info(self, stamp_ns: int, episode: int, step: int, reward: float,
                      applied_action: Sequence[float], truncated: bool) -> StateRecord | None:
        """Record a StepInfo; return the StateRecord it completes, if any.

        Raises BadMessage, before touching anything, for a transition that
        does not fit the window (the action's length, a non-finite value).
        """
        action = np.asarray(applied_action, dtype=np.float64)
        if step > 0 and (action.shape != (self.window.action_dim,)
                         or not np.all(np.isfinite(action)) or not math.isfinite(reward)):
            raise BadMessage(f'step {step}: reward {reward} and {action.size} applied action '
                             f'values (expected {self.window.action_dim}, finite)')
        self._infos[stamp_ns] = (episode, step, reward, action, truncated)
        return self._complete(stamp_ns)

    def _complete(self, stamp_ns: int) -> StateRecord | None:
        if stamp_ns not in self._observations or stamp_ns not in self._infos:
            self._trim()
            return None
        observation, info = self._observations.pop(stamp_ns), self._infos.pop(stamp_ns)
        if self.layout.reward_in_observation:   # the reward into the state, as in training
            observation = self.layout.with_reward(observation, info[2])
        record = StateRecord(stamp_ns, observation, *info)
        previous_high = self.clock.high
        event = self.clock.observe(stamp_ns)
        if event == DUPLICATE:
            self.dropped += 1
            return None
        if event != NEXT:
            self._notify(event, stamp_ns, previous_high)
        if event == OUTLIER:
            self.outliers += 1
            return None
        if event == NEXT:
            self._feed_window(record)
        else:
            self._start_over()
        self.previous = record
        self._forget_pending(stamp_ns)
        return record

    def _feed_window(self, record: StateRecord) -> None:
        prev = self.previous
        follows = (prev is not None and record.step > 0 and prev.episode == record.episode
                   and prev.step + 1 == record.step)
        if follows:
            self.window.push(prev.observation, record.applied_action, record.reward,
                             record.observation)
            return
        if record.step > 0 and prev is not None:
            self.gaps += 1
        self.window.clear()

    def _start_over(self) -> None:
        # A new clock: nothing pending belongs to it (a half of its own that
        # came early is lost: one missed transition, in realtime mode only).
        self.restarts += 1
        self.window.clear()
        self._observations.clear()
        self._infos.clear()

    def _forget_pending(self, stamp_ns: int) -> None:
        # A topic delivers in order, so once a stamp completes, a half still
        # pending below it lost its partner; one far ahead is a stray message.
        for pending in (self._observations, self._infos):
            for stale in [s for s in pending
                          if s < stamp_ns or s > stamp_ns + self.clock.max_jump_ns]:
                del pending[stale]
                self.dropped += 1

    def _notify(self, event: str, stamp_ns: int, previous_high: int | None) -> None:
        if self.on_clock is not None:
            self.on_clock(event, stamp_ns, previous_high)

    def _trim(self) -> None:
        for pending in (self._observations, self._infos):
            while len(pending) > MAX_PENDING:
                pending.pop(min(pending))
                self.dropped += 1


class StateContextPairer:
    """Decides which state the policy answers, and when it must answer blind.

    States and contexts each follow their own clock (`StampFollower`): the
    context node sees a restarted sim at about the time this node does, and
    either stream may show the new clock first. A stream that restarts drops
    what it holds (the old clock's); a context is kept whatever was answered
    before, so the first context of a new clock waits for its state.

    With `max_context_age_ns` > 0 (a robot, RMA's asynchronous adaptation) a
    state need not wait for its own context: the newest state is answered at
    once with the newest context stamped at most that much before it.
    """

    def __init__(self, context_timeout: float, on_clock: ClockListener | None = None,
                 max_context_age_ns: int = 0):
        self.context_timeout = context_timeout
        self.max_context_age_ns = max_context_age_ns
        self._newest_context: tuple[int, object] | None = None
        self.older_contexts = 0   # states answered with an older state's context
        self.on_clock = on_clock
        self.state_clock, self.context_clock = StampFollower(), StampFollower()
        self._states: dict[int, tuple[np.ndarray, float]] = {}
        self._contexts: dict[int, np.ndarray] = {}
        self.last_answered = -1
        self.dropped = 0     # states skipped, duplicated or never answered
        self.restarts = 0    # state clocks that went back or jumped
        self.outliers = 0    # states and contexts ignored for a stamp far ahead

    def add_state(self, stamp_ns: int, observation: np.ndarray, now: float) -> str:
        """Record a state received at wall time `now`; return what its stamp was."""
        event = self._observe(self.state_clock, stamp_ns, 'state')
        if event == RESTART:
            self.restarts += 1
            self._states.clear()
            self.last_answered = -1
        elif event == JUMP:
            self.restarts += 1
        if event == DUPLICATE:
            self.dropped += 1
        if event in (DUPLICATE, OUTLIER):
            return event
        self._states[stamp_ns] = (observation, now)
        self._trim()
        return event

    def add_context(self, stamp_ns: int, latent: np.ndarray) -> str:
        """Record the latent context published for a state's stamp; return what its stamp was."""
        event = self._observe(self.context_clock, stamp_ns, 'context')
        if event == RESTART:
            self._contexts.clear()
            self._newest_context = None
        if event not in (DUPLICATE, OUTLIER):
            self._contexts[stamp_ns] = latent
            self._newest_context = (stamp_ns, latent)
            self._trim()
        return event

    def _observe(self, clock: StampFollower, stamp_ns: int, stream: str) -> str:
        previous_high = clock.high
        event = clock.observe(stamp_ns)
        if event == OUTLIER:
            self.outliers += 1
        if event in (RESTART, JUMP, OUTLIER) and self.on_clock is not None:
            self.on_clock(f'{stream} {event}', stamp_ns, previous_high)
        return event

    def ready(self) -> tuple[int, np.ndarray, np.ndarray] | None:
        """Newest state whose context is in: (stamp, what `add_state` got, latent), or None."""
        complete = [s for s in self._states if s in self._contexts]
        if not complete:
            return self._ready_with_older_context()
        stamp = max(complete)
        observation = self._states[stamp][0]
        latent = self._contexts[stamp]
        self._answered(stamp)
        return stamp, observation, latent

    def _ready_with_older_context(self) -> tuple[int, np.ndarray, np.ndarray] | None:
        if self.max_context_age_ns <= 0 or not self._states or self._newest_context is None:
            return None
        stamp = max(self._states)
        context_stamp, latent = self._newest_context
        if not 0 <= stamp - context_stamp <= self.max_context_age_ns:
            return None   # none yet, or too old: the state waits (then times out)
        observation = self._states[stamp][0]
        self.older_contexts += 1
        self._answered(stamp)
        return stamp, observation, latent

    def next_expiry(self) -> float | None:
        """When the oldest waiting state runs out of time for its context (or None)."""
        if not self._states:
            return None
        return min(t for _, t in self._states.values()) + self.context_timeout

    def expired(self, now: float) -> int | None:
        """Newest state that waited past the timeout for its context, or None."""
        # >= so that a check at exactly `next_expiry()` finds the state expired.
        late = [s for s, (_, t) in self._states.items() if now - t >= self.context_timeout]
        if not late:
            return None
        stamp = max(late)
        self._answered(stamp)
        return stamp

    def _answered(self, stamp: int) -> None:
        self.last_answered = stamp
        skipped = [s for s in self._states if s < stamp]
        self.dropped += len(skipped)
        for pending in (self._states, self._contexts):
            for old in [s for s in pending if s <= stamp]:
                del pending[old]

    def _trim(self) -> None:
        for pending in (self._states, self._contexts):
            while len(pending) > MAX_PENDING:
                pending.pop(min(pending))
                self.dropped += 1


def forget_received(received_at: dict[int, float], stamp_ns: int) -> None:
    """Drop the arrival times of `stamp_ns` and older (a node's latency bookkeeping).

    More than MAX_PENDING newer ones cannot be a backlog (the queues keep 10):
    they are strays or another clock's, and are dropped too.
    """
    for old in [s for s in received_at if s <= stamp_ns]:
        del received_at[old]
    if len(received_at) > MAX_PENDING:
        received_at.clear()

