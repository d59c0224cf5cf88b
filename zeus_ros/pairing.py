"""ROS-free bookkeeping of the context and policy nodes: matching messages by stamp.

`TransitionAssembler` (context node) joins each `JointState` with the
`StepInfo` of the same stamp, rebuilds the transition `(s, a, r, s')` from
consecutive states of one episode (the action and reward come from StepInfo,
exactly as the simulator applied them), and feeds the `ContextWindow` with the
same semantics as training: cleared at an episode start, one push per step.

`StateContextPairer` (policy node) joins a state with the context of its stamp
and says which state to answer: the newest complete pair, or, once a state has
waited longer than the context timeout, that state with a zero action.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_node.env import ObservationLayout
from zeus_ros.core.window import ContextWindow

# Partial entries kept while their partner message is in flight.
MAX_PENDING = 64


def layout_from_metadata(metadata: dict) -> ObservationLayout:
    """Build the checkpoint's observation layout (joint names and encodings)."""
    obs = metadata['obs_layout']
    layout = ObservationLayout(tuple(obs['joint_names']), tuple(obs['position_encoding']))
    if layout.size != int(obs['obs_dim']):
        raise ValueError(f'checkpoint layout gives {layout.size} observations, '
                         f'metadata says {obs["obs_dim"]}')
    return layout


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

    def __init__(self, window: ContextWindow, layout: ObservationLayout):
        self.window, self.layout = window, layout
        self._observations: dict[int, np.ndarray] = {}
        self._infos: dict[int, tuple] = {}
        self.previous: StateRecord | None = None
        self.dropped = 0   # messages out of order or never completed
        self.gaps = 0      # transitions that could not be rebuilt (missed a state)

    def add_joint_state(self, stamp_ns: int, names, positions, velocities):
        """Record a joint state; return the StateRecord it completes, if any."""
        self._observations[stamp_ns] = self.layout.observation_from_joint_state(
            names, positions, velocities)
        return self._complete(stamp_ns)

    def add_step_info(self, stamp_ns: int, episode: int, step: int, reward: float,
                      applied_action, truncated: bool):
        """Record a StepInfo; return the StateRecord it completes, if any."""
        self._infos[stamp_ns] = (episode, step, reward,
                                 np.asarray(applied_action, dtype=np.float64), truncated)
        return self._complete(stamp_ns)

    def _complete(self, stamp_ns: int) -> StateRecord | None:
        if stamp_ns not in self._observations or stamp_ns not in self._infos:
            self._trim()
            return None
        record = StateRecord(stamp_ns, self._observations.pop(stamp_ns),
                             *self._infos.pop(stamp_ns))
        if self.previous is not None and stamp_ns <= self.previous.stamp_ns:
            self.dropped += 1
            return None
        self._feed_window(record)
        self.previous = record
        return record

    def _feed_window(self, record: StateRecord) -> None:
        prev = self.previous
        follows = (prev is not None and record.step > 0 and prev.episode == record.episode
                   and prev.step + 1 == record.step)
        if follows:
            self.window.push(prev.observation, record.applied_action, record.reward,
                             record.observation)
            return
        if record.step > 0:
            self.gaps += 1
        self.window.clear()

    def _trim(self) -> None:
        for pending in (self._observations, self._infos):
            while len(pending) > MAX_PENDING:
                pending.pop(min(pending))
                self.dropped += 1


class StateContextPairer:
    """Decides which state the policy answers, and when it must answer blind."""

    def __init__(self, context_timeout: float):
        self.context_timeout = context_timeout
        self._states: dict[int, tuple[np.ndarray, float]] = {}
        self._contexts: dict[int, np.ndarray] = {}
        self.last_answered = -1
        self.dropped = 0

    def add_state(self, stamp_ns: int, observation: np.ndarray, now: float):
        """Record a state received at wall time `now`."""
        if stamp_ns > self.last_answered:
            self._states[stamp_ns] = (observation, now)
        self._trim()

    def add_context(self, stamp_ns: int, latent: np.ndarray):
        """Record the latent context published for a state's stamp."""
        if stamp_ns > self.last_answered:
            self._contexts[stamp_ns] = latent
        self._trim()

    def ready(self) -> tuple[int, np.ndarray, np.ndarray] | None:
        """Newest state whose context is in: (stamp, what `add_state` got, latent), or None."""
        complete = [s for s in self._states if s in self._contexts]
        if not complete:
            return None
        stamp = max(complete)
        observation = self._states[stamp][0]
        latent = self._contexts[stamp]
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
