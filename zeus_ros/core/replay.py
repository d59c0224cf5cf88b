"""Replay buffer of transitions whose context windows are rebuilt at sampling time.

Each stored transition t keeps s_t, a_t, r_t, s_{t+1}, done, its training
task and the true parameter value, plus a link to the transition before it in
the same episode of the same task. The windows are not stored: `sample`
follows the links back k steps and lays the rows out exactly as
`ContextWindow.arrays()` does (oldest first, zero-padded at the end):

* ``ctx``: H_t, the window before s_t (the context for acting at s_t);
* ``next_ctx``: H_{t+1}, the window for s_{t+1} (it ends with transition t);
* ``chain``: transition t and its k predecessors, newest first: H_t is its
  last k rows and H_{t+1} its first k, so per-row codes of both windows can
  be computed once (`ContextMethod.encode_pair`).

Storing links instead of two k-row windows per transition makes memory and
checkpoints independent of k (k = 25 would otherwise cost ~11 KB a
transition). A link whose target has been overwritten by the ring ends the
window there, as an episode start does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

# Arrays saved in checkpoints (the filled part of each, in slot order).
ARRAY_NAMES = ('obs', 'action', 'reward', 'next_obs', 'not_done', 'task', 'param',
               'serial', 'prev_serial')


@dataclass
class Batch:
    """One sampled minibatch as torch tensors (float32, bool, int64)."""

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    not_done: torch.Tensor
    ctx_rows: torch.Tensor
    ctx_mask: torch.Tensor
    next_ctx_rows: torch.Tensor
    next_ctx_mask: torch.Tensor
    task: torch.Tensor
    param: torch.Tensor         # [B, param_dim]: the true values in force
    chain_rows: torch.Tensor    # [B, k + 1, D]: transition t, t-1, ... t-k (zeros where none)
    chain_mask: torch.Tensor    # [B, k + 1]: which of them exist


def oldest_first(rows_newest_first: np.ndarray,
                 valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reorder [B, k, D] rows given newest first (valid rows a prefix) to window layout."""
    b, k = valid.shape
    count = valid.sum(axis=1)
    src = count[:, None] - 1 - np.arange(k)[None, :]
    mask = src >= 0
    out = np.take_along_axis(rows_newest_first, np.clip(src, 0, k - 1)[..., None], axis=1)
    out[~mask] = 0.0
    return out, mask


class ReplayBuffer:
    """Fixed-capacity FIFO buffer; `add` overwrites the oldest when full."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, k: int, row_dim: int,
                 seed: int = 0, param_dim: int = 1):
        self.capacity = c = int(capacity)
        self.k = int(k)
        self.row_dim = int(row_dim)
        self.obs = np.zeros((c, obs_dim), np.float32)
        self.action = np.zeros((c, action_dim), np.float32)
        self.reward = np.zeros((c,), np.float32)
        self.next_obs = np.zeros((c, obs_dim), np.float32)
        self.not_done = np.zeros((c,), np.float32)
        self.task = np.zeros((c,), np.int64)
        self.param = np.zeros((c, param_dim), np.float32)   # the true values, per parameter
        self.serial = np.full((c,), -1, np.int64)       # add count of the slot's transition
        self.prev_serial = np.full((c,), -1, np.int64)  # its predecessor's, -1 = none
        self.added = 0
        self.size = 0
        self._last_of_task: dict[int, int] = {}
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, next_obs: np.ndarray,
            done: bool, task: int, param: float | Sequence[float], continues: bool) -> None:
        """Store one transition.

        `param`: the true value(s) in force (a number, or a tuple for a family
        with several); `continues`: the task's previous add is its predecessor.
        """
        serial = self.added
        i = serial % self.capacity
        self.obs[i] = obs
        self.action[i] = action
        self.reward[i] = reward
        self.next_obs[i] = next_obs
        self.not_done[i] = 0.0 if done else 1.0
        self.task[i] = task
        self.param[i] = param
        self.serial[i] = serial
        self.prev_serial[i] = self._last_of_task.get(int(task), -1) if continues else -1
        self._last_of_task[int(task)] = serial
        self.added += 1
        self.size = min(self.size + 1, self.capacity)

    def _chain(self, idx: np.ndarray) -> np.ndarray:
        """Slots of each sampled transition and its k predecessors, newest first (-1 = none)."""
        chain = np.full((idx.size, self.k + 1), -1, np.int64)
        chain[:, 0] = idx
        link = self.prev_serial[idx]
        for j in range(1, self.k + 1):
            slot = np.where(link >= 0, link % self.capacity, 0)
            alive = (link >= 0) & (self.serial[slot] == link)
            chain[:, j] = np.where(alive, slot, -1)
            link = np.where(alive, self.prev_serial[slot], -1)
        return chain

    def _rows(self, slots: np.ndarray) -> np.ndarray:
        """Window rows concat(s, a, r, s') for slots [B, n] (zeros where -1)."""
        safe = np.maximum(slots, 0)
        rows = np.concatenate([self.obs[safe], self.action[safe], self.reward[safe][..., None],
                               self.next_obs[safe]], axis=-1)
        rows[slots < 0] = 0.0
        return rows

    def windows(self, idx: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray],
                                                tuple[np.ndarray, np.ndarray]]:
        """((ctx_rows, ctx_mask), (next_ctx_rows, next_ctx_mask)) of slots `idx`."""
        return self._windows_and_chain(idx)[:2]

    def _windows_and_chain(self, idx: np.ndarray):
        chain = self._chain(idx)
        rows = self._rows(chain)
        valid = chain >= 0
        ctx = oldest_first(rows[:, 1:], valid[:, 1:])
        nxt = oldest_first(rows[:, :-1], valid[:, :-1])
        return ctx, nxt, (rows, valid)

    def sample(self, batch_size: int) -> Batch:
        """Uniform minibatch (with replacement) as torch tensors."""
        if self.size == 0:
            raise ValueError('cannot sample from an empty replay buffer')
        idx = self.rng.integers(0, self.size, size=batch_size)
        (ctx_rows, ctx_mask), (next_rows, next_mask), (chain_rows, chain_mask) = \
            self._windows_and_chain(idx)
        arrays = {n: getattr(self, n)[idx] for n in
                  ('obs', 'action', 'reward', 'next_obs', 'not_done', 'task', 'param')}
        arrays.update(ctx_rows=ctx_rows, ctx_mask=ctx_mask, next_ctx_rows=next_rows,
                      next_ctx_mask=next_mask, chain_rows=chain_rows, chain_mask=chain_mask)
        return Batch(**{n: torch.from_numpy(np.ascontiguousarray(v)) for n, v in arrays.items()})

    # -- persistence (arrays only; used by zeus_ros.deploy.checkpoint) ------------
    def state_arrays(self) -> dict[str, np.ndarray]:
        """Return the filled part of every array plus the add count, size and capacity."""
        n = self.size
        out = {f'replay.{name}': np.ascontiguousarray(getattr(self, name)[:n])
               for name in ARRAY_NAMES}
        out['replay.meta'] = np.array([self.added, self.size, self.capacity], np.int64)
        return out

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore from `state_arrays()` output (capacities must agree).

        A resumed run starts new episodes, so no link continues past the restore.
        """
        missing = [n for n in ARRAY_NAMES if f'replay.{n}' not in arrays]
        if missing:
            raise ValueError(f'replay arrays {missing} missing (an older buffer layout)')
        added, size, capacity = (int(v) for v in arrays['replay.meta'])
        if capacity != self.capacity:
            raise ValueError(f'replay capacity {capacity} in checkpoint, {self.capacity} now')
        for name in ARRAY_NAMES:
            target = getattr(self, name)
            # Buffers saved before parameters were vectors hold param as [n]: one column.
            target[:size] = arrays[f'replay.{name}'].reshape((size, *target.shape[1:]))
        self.added, self.size = added, size
        self._last_of_task = {}
