"""The observation and action definitions the nodes share with the simulation, MuJoCo-free.

`ObservationLayout` turns joint positions and velocities (a JointState) into
the policy's observation; `check_action` validates an action; `StepResult`
is what one control step of any env returns. Plain numpy,
so the ROS plumbing and the controller nodes use them without loading
MuJoCo (`sim_node.env.layout_from_model` reads a layout off a model).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence, TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

# Horizontal position is dropped from the observation: the tasks are invariant
# to it, and it grows without bound while the robot moves.
DROPPED_JOINTS = frozenset({'rootx'})


@dataclass(frozen=True)
class ObservationLayout:
    """How the policy's observation is made from joint positions and velocities.

    Per joint, in model order: its position, or (cos, sin) for a hinge without
    limits (a free rotation, which would otherwise wrap), or nothing for the
    dropped horizontal position; then every joint velocity, except where
    `velocity_encoding` says 'drop' (an entry with no velocity of its own,
    such as the Sawyer's commanded hand position; None: keep all). With
    `reward_in_observation` (the appendix's choice for families whose tasks
    differ only in the reward), the reward of the transition INTO the state
    comes last (0 for an episode's first state): on ROS it is the StepInfo
    reward of the state's stamp.
    """

    joint_names: tuple[str, ...]
    position_encoding: tuple[str, ...]  # 'raw', 'angle' (cos, sin) or 'drop'
    reward_in_observation: bool = False
    velocity_encoding: tuple[str, ...] | None = None   # 'raw' or 'drop'; None: all 'raw'

    @property
    def size(self) -> int:
        """Length of the observation vector."""
        width = {'raw': 1, 'angle': 2, 'drop': 0}
        positions = sum(width[e] for e in self.position_encoding)
        return positions + len(self._kept_velocities()) + int(self.reward_in_observation)

    def _kept_velocities(self) -> list[int]:
        if self.velocity_encoding is None:
            return list(range(len(self.joint_names)))
        return [i for i, e in enumerate(self.velocity_encoding) if e == 'raw']

    def observation(self, positions: np.ndarray, velocities: np.ndarray,
                    reward: float = 0.0) -> np.ndarray:
        """Observation from joint positions and velocities in `joint_names` order.

        `reward` (into this state) is read only with `reward_in_observation`.
        """
        parts = []
        for encoding, q in zip(self.position_encoding, positions, strict=True):
            if encoding == 'raw':
                parts.append(q)
            elif encoding == 'angle':
                parts.extend((math.cos(q), math.sin(q)))
        tail = [float(reward)] if self.reward_in_observation else []
        velocities = np.asarray(velocities, dtype=np.float64)
        if self.velocity_encoding is not None:
            velocities = velocities[self._kept_velocities()]
        return np.concatenate([np.asarray(parts, dtype=np.float64), velocities,
                               np.asarray(tail, dtype=np.float64)])

    def with_reward(self, observation: np.ndarray, reward: float) -> np.ndarray:
        """Return a copy of `observation` whose reward entry is `reward` (a copy either way)."""
        out = np.array(observation, dtype=np.float64)
        if self.reward_in_observation:
            out[-1] = float(reward)
        return out

    def observation_from_joint_state(self, names: Sequence[str], positions: Sequence[float],
                                     velocities: Sequence[float],
                                     reward: float = 0.0) -> np.ndarray:
        """Observation from a JointState's fields; the names may be in any order."""
        index = {name: i for i, name in enumerate(names)}
        missing = [n for n in self.joint_names if n not in index]
        if missing:
            raise ValueError(f'joint state lacks joints {missing}')
        order = [index[n] for n in self.joint_names]
        return self.observation(np.asarray(positions, dtype=np.float64)[order],
                                np.asarray(velocities, dtype=np.float64)[order], reward)


def check_action(action: ArrayLike, action_dim: int) -> tuple[np.ndarray | None, str | None]:
    """Validate an action: a finite vector of the right length, clipped to [-1, 1].

    Returns (action, None) when usable, (None, reason) when not.
    """
    try:
        array = np.asarray(action, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None, 'action is not numeric'
    if array.shape != (action_dim,):
        return None, f'action has {array.size} values, expected {action_dim}'
    if not np.all(np.isfinite(array)):
        return None, 'action contains NaN or inf'
    return np.clip(array, -1.0, 1.0), None


@dataclass(frozen=True)
class StepResult:
    """What one control step returns."""

    observation: np.ndarray
    reward: float
    terminal: bool
    truncated: bool
    # The action MuJoCo applied (validated, clipped to [-1, 1]).
    applied_action: np.ndarray | None = None
    # Set when MuJoCo became unstable: the episode was reset, and the
    # observation is the new episode's first one.
    instability: str | None = None
