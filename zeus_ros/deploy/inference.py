"""Deployment model: the exact functions the ROS nodes and `zeus_ros.learning_tools.evaluate` call.

    model = InferenceModel.load(path)           # checks the checkpoint (CheckpointError)
    latent = model.context(rows, mask)          # np.float32 [context_dim]
    latent = model.context(rows, mask, true_param=v)   # privileged methods (oracle)
    action = model.act(obs, latent)             # np.float64 [action_dim], tanh(mean)
    # the same action in two parts, phi(s) computed before the latent is in:
    action = model.act_on_features(model.features(obs), latent)
    estimate = model.decode(latent)             # physical parameter (float; NaN if none)

Everything runs with batch size 1 and one torch thread (set on load:
``torch.set_num_threads(1)`` is process-wide), in float32, so the in-process
evaluation and the ROS nodes, which pass the latent between them as float32,
compute bit-identical actions for the same observations and windows. (With two
threads the same episode's actions differ in the last bits, so every call
re-asserts one thread if something else in the process changed it.)

`DeployedModel` is that interface over the checkpoint's metadata (`meta`,
the typed tree of zeus_ros.deploy.metadata), with the checks of what goes
in; `InferenceModel` runs it in torch, and
`zeus_ros.deploy.onnx_model.OnnxInferenceModel` runs the same networks,
exported, in ONNX Runtime. `zeus_ros.deploy.backends.load_deployed` picks one.
"""

from __future__ import annotations

import math
from typing import Sequence, TYPE_CHECKING

import numpy as np
import torch

from zeus_ros.deploy.checkpoint import build_metadata, load_model
from zeus_ros.deploy.metadata import CheckpointMetadata

if TYPE_CHECKING:
    from pathlib import Path

    from zeus_ros.core.agent import Agent
    from zeus_ros.core.methods import ContextMethod


def _single_thread() -> None:
    """Keep torch on one intra-op thread: with more, reductions may split differently."""
    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)


class DeployedModel:
    """The deployed functions of a checkpoint, numpy in and out, whatever runs them.

    Subclasses write `_context`, `_features`, `_act` and `_decode`, each given
    checked float32 arrays with a batch axis of 1.
    """

    backend_note = 'torch'    # what runs the networks, for the nodes' start-up line

    def __init__(self, meta: CheckpointMetadata, context_dim: int, needs_true_param: bool):
        self.meta = meta
        self.family = self.meta.family
        self.method_name = self.meta.context.method
        self.needs_true_param = needs_true_param
        self.obs_dim = self.meta.obs_layout.obs_dim
        # The observation ends with the reward into the state (ParamEnv reward_in_obs).
        self.reward_in_observation = self.meta.obs_layout.reward_in_observation
        self.action_dim = self.meta.action_layout.action_dim
        self.k = self.meta.context.k
        self.row_dim = self.meta.context.row_dim
        self.context_dim = context_dim
        self.param_names = self.meta.names
        self.param_offset = np.asarray(self.meta.param_normalisation.offsets)
        self.param_scale = np.asarray(self.meta.param_normalisation.scales)

    def context(self, rows: np.ndarray, mask: np.ndarray,
                true_param: float | Sequence[float] | np.ndarray | None = None) -> np.ndarray:
        """Latent context of one window (rows [k, row_dim], mask [k]) as float32.

        `true_param` (a number, or one per parameter) is read only by privileged
        methods (`needs_true_param`).
        """
        rows = np.asarray(rows, dtype=np.float32)
        mask = np.asarray(mask, dtype=bool)
        if rows.shape != (self.k, self.row_dim) or mask.shape != (self.k,):
            raise ValueError(f'window must be rows {(self.k, self.row_dim)} and mask '
                             f'({self.k},), got {rows.shape} and {mask.shape}')
        param = None if true_param is None else \
            np.asarray(true_param, dtype=np.float32).reshape(1, -1)
        return self._context(rows[None], mask[None], param)[0].astype(np.float32)

    def act(self, obs: np.ndarray, latent: np.ndarray) -> np.ndarray:
        """Deterministic action tanh(mu) in [-1, 1] as float64."""
        return self.act_on_features(self.features(obs), latent)

    def features(self, obs: np.ndarray) -> np.ndarray:
        """phi(s) as float32: the half of `act` that needs no context.

        The policy node computes it when a state arrives, while the context
        node is still computing that state's latent.
        """
        obs = np.asarray(obs, dtype=np.float32).reshape(-1)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f'obs must have {self.obs_dim} values, got {obs.size}')
        return self._features(obs[None])[0]

    def act_on_features(self, features: np.ndarray, latent: np.ndarray) -> np.ndarray:
        """Deterministic action tanh(mu) from phi(s) (`features`) and the latent, as float64."""
        latent = np.asarray(latent, dtype=np.float32).reshape(-1)
        if latent.shape != (self.context_dim,):
            raise ValueError(f'latent must have {self.context_dim} values, got {latent.size}')
        features = np.asarray(features, dtype=np.float32).reshape(1, -1)
        return self._act(features, latent[None])[0].astype(np.float64)

    def decode_values(self, latent: np.ndarray) -> np.ndarray:
        """Physical-parameter estimates read from a latent, one per name (NaN: no decoder)."""
        normalised = self._decode(np.asarray(latent, dtype=np.float32).reshape(1, -1))
        if normalised is None:
            return np.full(len(self.param_names), math.nan)
        value = normalised[0].astype(np.float64) * self.param_scale + self.param_offset
        return np.exp(value) if self.meta.param_normalisation.log else value

    def decode(self, latent: np.ndarray) -> float:
        """Return the estimate of a one-parameter family's parameter (NaN without a decoder)."""
        if len(self.param_names) != 1:
            raise ValueError(f'{self.family} has {len(self.param_names)} parameters: '
                             'use decode_values')
        return float(self.decode_values(latent)[0])

    def reward_prior(self) -> float | None:
        """Return the reward psi's standardiser saw on average in training (None: unknown).

        Filled in for a reward a robot cannot give (zeus_ros.ros.commands): its
        standardised value is 0, the feature's training mean. None where the
        backend cannot read it (ONNX) or psi has no standardiser.
        """
        return None

    # -- what a backend writes (arrays [1, ...], float32 in and out) -------------------
    def _context(self, rows: np.ndarray, mask: np.ndarray,
                 param: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def _features(self, obs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _act(self, features: np.ndarray, latent: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _decode(self, latent: np.ndarray) -> np.ndarray | None:
        raise NotImplementedError


class InferenceModel(DeployedModel):
    """phi, psi, actor and decoder of a checkpoint, run in torch."""

    def __init__(self, meta: CheckpointMetadata, method: ContextMethod,
                 modules: dict[str, torch.nn.Module]):
        super().__init__(meta, method.context_dim, method.needs_true_param)
        self.method = method
        self.phi = modules['phi']
        self.actor = modules['actor']

    @classmethod
    def from_agent(cls, agent: Agent, env_info: dict) -> 'InferenceModel':
        """Wrap an agent in memory in the deployed functions (the trainer's evaluation)."""
        # Checked as a file would be: what the trainer evaluates is what a loader accepts.
        meta = build_metadata(agent, env_info, {}).checked()
        return cls(meta, agent.method, agent.inference_modules())

    @classmethod
    def load(cls, path: str | Path, expected_family: str | None = None,
             obs_dim: int | None = None, action_dim: int | None = None) -> 'InferenceModel':
        """Load a checkpoint directory (or a run directory holding `checkpoint/`)."""
        torch.set_num_threads(1)
        meta, method, modules = load_model(path, expected_family, obs_dim, action_dim)
        return cls(meta, method, modules)

    def reward_prior(self) -> float | None:
        norm = getattr(getattr(self.method, 'psi', None), 'norm', None)
        if norm is None or self.method.context_dim == 0:
            return None
        # The reward's column of a row concat(s, a, r, s') (or of its delta features).
        return float(norm.mean[self.obs_dim + self.action_dim])

    @torch.no_grad()
    def _context(self, rows: np.ndarray, mask: np.ndarray,
                 param: np.ndarray | None) -> np.ndarray:
        _single_thread()
        param = None if param is None else torch.from_numpy(param)
        latent = self.method.deployed_context(torch.from_numpy(rows),
                                              torch.from_numpy(mask), param)
        return latent.numpy()

    @torch.no_grad()
    def _features(self, obs: np.ndarray) -> np.ndarray:
        _single_thread()
        return self.phi(torch.from_numpy(obs)).numpy()

    @torch.no_grad()
    def _act(self, features: np.ndarray, latent: np.ndarray) -> np.ndarray:
        _single_thread()
        x = torch.cat([torch.from_numpy(features), torch.from_numpy(latent)], dim=-1)
        return self.actor.mean_action(x).numpy()

    @torch.no_grad()
    def _decode(self, latent: np.ndarray) -> np.ndarray | None:
        _single_thread()
        normalised = self.method.decode(torch.from_numpy(latent))
        return None if normalised is None else normalised.numpy()
