"""Replay buffer of transitions with their context windows, in preallocated numpy arrays.

Each stored transition t keeps: s_t, a_t, r_t, s_{t+1}, the window (rows+mask)
that preceded s_t (history H_t, the context for acting at s_t) and the window
for s_{t+1} (H_{t+1}, which ends with transition t itself), the training-task
index and the true parameter value. Sampling is uniform over all stored
transitions of all tasks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

ARRAY_NAMES = ('obs', 'action', 'reward', 'next_obs', 'not_done', 'ctx_rows', 'ctx_mask',
               'next_ctx_rows', 'next_ctx_mask', 'task', 'param')


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
    param: torch.Tensor


class ReplayBuffer:
    """Fixed-capacity FIFO buffer; `add` overwrites the oldest when full."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, k: int, row_dim: int,
                 seed: int = 0):
        self.capacity = int(capacity)
        c = self.capacity
        self.obs = np.zeros((c, obs_dim), np.float32)
        self.action = np.zeros((c, action_dim), np.float32)
        self.reward = np.zeros((c,), np.float32)
        self.next_obs = np.zeros((c, obs_dim), np.float32)
        self.not_done = np.zeros((c,), np.float32)
        self.ctx_rows = np.zeros((c, k, row_dim), np.float32)
        self.ctx_mask = np.zeros((c, k), bool)
        self.next_ctx_rows = np.zeros((c, k, row_dim), np.float32)
        self.next_ctx_mask = np.zeros((c, k), bool)
        self.task = np.zeros((c,), np.int64)
        self.param = np.zeros((c,), np.float32)
        self.idx = 0
        self.size = 0
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, obs, action, reward, next_obs, done, ctx, next_ctx, task, param) -> None:
        """Store one transition; `ctx`/`next_ctx` are (rows, mask) from ContextWindow."""
        i = self.idx
        self.obs[i] = obs
        self.action[i] = action
        self.reward[i] = reward
        self.next_obs[i] = next_obs
        self.not_done[i] = 0.0 if done else 1.0
        self.ctx_rows[i], self.ctx_mask[i] = ctx
        self.next_ctx_rows[i], self.next_ctx_mask[i] = next_ctx
        self.task[i] = task
        self.param[i] = param
        self.idx = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        """Uniform minibatch (with replacement) as torch tensors."""
        if self.size == 0:
            raise ValueError('cannot sample from an empty replay buffer')
        idx = self.rng.integers(0, self.size, size=batch_size)
        return Batch(**{n: torch.from_numpy(getattr(self, n)[idx]) for n in ARRAY_NAMES})

    # -- persistence (arrays only; used by zeus_ros.checkpoint) ------------
    def state_arrays(self) -> dict[str, np.ndarray]:
        """Return the filled part of every array plus the write index and size."""
        n = self.size
        out = {f'replay.{name}': np.ascontiguousarray(getattr(self, name)[:n])
               for name in ARRAY_NAMES}
        out['replay.meta'] = np.array([self.idx, self.size, self.capacity], np.int64)
        return out

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore from `state_arrays()` output (capacities must agree)."""
        idx, size, capacity = (int(v) for v in arrays['replay.meta'])
        if capacity != self.capacity:
            raise ValueError(f'replay capacity {capacity} in checkpoint, {self.capacity} now')
        for name in ARRAY_NAMES:
            src = arrays[f'replay.{name}']
            getattr(self, name)[:size] = src
        self.idx, self.size = idx, size
