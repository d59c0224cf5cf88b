"""The context window: THE single definition of the history H that psi encodes.

Used by the trainer (to build the replay buffer's histories and to act), by
`zeus_ros.learning_tools.evaluate.run_episode` and by the ROS context node, so all three feed
psi exactly the same array for the same trajectory.

Definition
----------
* A transition row is ``concat(s, a, [r], s')`` as float32, of width
  ``row_dim = 2 * obs_dim + action_dim + 1`` (s and s' are the policy
  observations of `sim_node.env.ObservationLayout`, a is the clipped action in
  [-1, 1] that was applied, r the reward it earned).
* The window holds the last ``k`` transitions of the CURRENT episode only; it
  is cleared at every episode boundary (reset, time limit, simulator
  instability). ``fill`` counts the transitions held, 0..k.
* ``arrays()`` returns ``(rows[k, row_dim] float32, mask[k] bool)``: the last
  ``min(fill, k)`` transitions, OLDEST FIRST, in rows ``0..fill-1`` with mask
  True; the remaining rows are zeros with mask False.
* The context used to act at ``s_t`` is psi of the window BEFORE pushing the
  transition ``(s_t, a_t, r_t, s_{t+1})``; after the push the window is the
  history for ``s_{t+1}``.
* At episode start (``fill == 0``) the context is psi over an empty set, which
  is defined as the zero latent vector: psi aggregates per-transition codes
  with the mask, and an empty mask gives zeros (see
  `zeus_ros.core.networks.ContextEncoder`).
"""

from __future__ import annotations

import numpy as np


def row_dim(obs_dim: int, action_dim: int) -> int:
    """Width of one transition row, concat(s, a, [r], s')."""
    return 2 * obs_dim + action_dim + 1


class ContextWindow:
    """Ring of the last `k` transitions of the current episode."""

    def __init__(self, k: int, obs_dim: int, action_dim: int):
        if k < 1:
            raise ValueError('k must be >= 1')
        self.k = int(k)
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.row_dim = row_dim(obs_dim, action_dim)
        self._rows = np.zeros((self.k, self.row_dim), dtype=np.float32)
        self._next = 0  # slot the next push writes (ring index)
        self.fill = 0

    def clear(self) -> None:
        """Forget everything: call at every episode boundary."""
        self._rows[:] = 0.0
        self._next = 0
        self.fill = 0

    def push(self, s: np.ndarray, a: np.ndarray, r: float, s_next: np.ndarray) -> None:
        """Append the transition (s, a, r, s') of the current episode."""
        s = np.asarray(s, dtype=np.float64).reshape(-1)
        a = np.asarray(a, dtype=np.float64).reshape(-1)
        s_next = np.asarray(s_next, dtype=np.float64).reshape(-1)
        if s.shape != (self.obs_dim,) or s_next.shape != (self.obs_dim,):
            raise ValueError(f'observations must have {self.obs_dim} values')
        if a.shape != (self.action_dim,):
            raise ValueError(f'action must have {self.action_dim} values')
        row = self._rows[self._next]
        o, d = self.obs_dim, self.action_dim
        row[:o] = s
        row[o:o + d] = a
        row[o + d] = float(r)
        row[o + d + 1:] = s_next
        self._next = (self._next + 1) % self.k
        self.fill = min(self.fill + 1, self.k)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows[k, row_dim] float32, mask[k] bool): oldest first, zero-padded at the end."""
        rows = np.zeros((self.k, self.row_dim), dtype=np.float32)
        mask = np.zeros(self.k, dtype=bool)
        n = self.fill
        if n:
            start = (self._next - n) % self.k
            order = [(start + i) % self.k for i in range(n)]
            rows[:n] = self._rows[order]
            mask[:n] = True
        return rows, mask
