"""The observation and action definitions the nodes share with the simulation, MuJoCo-free.

`ObservationLayout` turns joint positions and velocities (a JointState) into
the policy's observation; `check_action` validates an action. Plain numpy,
so the ROS plumbing and the controller nodes use them without loading
MuJoCo (`sim_node.env.layout_from_model` reads a layout off a model).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

# Horizontal position is dropped from the observation: the tasks are invariant
# to it, and it grows without bound while the robot moves.
DROPPED_JOINTS = frozenset({'rootx'})


@dataclass(frozen=True)
class ObservationLayout:
    """How the policy's observation is made from joint positions and velocities.

    Per joint, in model order: its position, or (cos, sin) for a hinge without
    limits (a free rotation, which would otherwise wrap), or nothing for the
    dropped horizontal position; then every joint velocity.
    """

    joint_names: tuple[str, ...]
    position_encoding: tuple[str, ...]  # 'raw', 'angle' (cos, sin) or 'drop'

    @property
    def size(self) -> int:
        """Length of the observation vector."""
        width = {'raw': 1, 'angle': 2, 'drop': 0}
        return sum(width[e] for e in self.position_encoding) + len(self.joint_names)

    def observation(self, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Observation from joint positions and velocities in `joint_names` order."""
        parts = []
        for encoding, q in zip(self.position_encoding, positions, strict=True):
            if encoding == 'raw':
                parts.append(q)
            elif encoding == 'angle':
                parts.extend((math.cos(q), math.sin(q)))
        return np.concatenate([np.asarray(parts, dtype=np.float64),
                               np.asarray(velocities, dtype=np.float64)])

    def observation_from_joint_state(self, names, positions, velocities) -> np.ndarray:
        """Observation from a JointState's fields; the names may be in any order."""
        index = {name: i for i, name in enumerate(names)}
        missing = [n for n in self.joint_names if n not in index]
        if missing:
            raise ValueError(f'joint state lacks joints {missing}')
        order = [index[n] for n in self.joint_names]
        return self.observation(np.asarray(positions, dtype=np.float64)[order],
                                np.asarray(velocities, dtype=np.float64)[order])


def check_action(action, action_dim: int) -> tuple[np.ndarray | None, str | None]:
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
