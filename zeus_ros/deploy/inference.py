"""Deployment model: the exact functions the ROS nodes and `zeus_ros.evaluate` call.

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
"""

from __future__ import annotations

import math

import numpy as np
import torch

from zeus_ros.deploy.checkpoint import build_metadata, load_model
from zeus_ros.deploy.metadata import CheckpointMetadata


def _single_thread() -> None:
    """Keep torch on one intra-op thread: with more, reductions may split differently."""
    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)


class InferenceModel:
    """phi, psi, actor and decoder of a checkpoint, with numpy in and out."""

    def __init__(self, metadata: dict, method, modules: dict):
        self.metadata = metadata
        self.meta = CheckpointMetadata.parse(dict(metadata, files=metadata.get('files', {})))
        self.method = method
        self.phi = modules['phi']
        self.actor = modules['actor']
        self.family = self.meta.family
        self.method_name = self.meta.context.method
        self.needs_true_param = method.needs_true_param
        self.obs_dim = self.meta.obs_layout.obs_dim
        # The observation ends with the reward into the state (ParamEnv reward_in_obs).
        self.reward_in_observation = self.meta.obs_layout.reward_in_observation
        self.action_dim = self.meta.action_layout.action_dim
        self.k = self.meta.context.k
        self.row_dim = self.meta.context.row_dim
        self.context_dim = method.context_dim
        self.param_names = self.meta.names
        self.param_offset = np.asarray(self.meta.param_normalisation.offsets)
        self.param_scale = np.asarray(self.meta.param_normalisation.scales)

    @classmethod
    def from_agent(cls, agent, env_info: dict) -> 'InferenceModel':
        """Wrap an agent in memory in the deployed functions (the trainer's evaluation)."""
        meta = build_metadata(agent, env_info, {})
        return cls(meta, agent.method, agent.inference_modules())

    @classmethod
    def load(cls, path, expected_family: str | None = None, obs_dim: int | None = None,
             action_dim: int | None = None) -> 'InferenceModel':
        """Load a checkpoint directory (or a run directory holding `checkpoint/`)."""
        torch.set_num_threads(1)
        meta, method, modules = load_model(path, expected_family, obs_dim, action_dim)
        return cls(meta, method, modules)

    @torch.no_grad()
    def context(self, rows: np.ndarray, mask: np.ndarray,
                true_param=None) -> np.ndarray:
        """Latent context of one window (rows [k, row_dim], mask [k]) as float32.

        `true_param` (a number, or one per parameter) is read only by privileged
        methods (`needs_true_param`).
        """
        _single_thread()
        rows = np.asarray(rows, dtype=np.float32)
        mask = np.asarray(mask, dtype=bool)
        if rows.shape != (self.k, self.row_dim) or mask.shape != (self.k,):
            raise ValueError(f'window must be rows {(self.k, self.row_dim)} and mask '
                             f'({self.k},), got {rows.shape} and {mask.shape}')
        param = None if true_param is None else torch.from_numpy(
            np.asarray(true_param, dtype=np.float32).reshape(1, -1))
        latent = self.method.deployed_context(torch.from_numpy(rows)[None],
                                              torch.from_numpy(mask)[None], param)[0]
        return latent.numpy().astype(np.float32)

    def act(self, obs: np.ndarray, latent: np.ndarray) -> np.ndarray:
        """Deterministic action tanh(mu) in [-1, 1] as float64."""
        return self.act_on_features(self.features(obs), latent)

    @torch.no_grad()
    def features(self, obs: np.ndarray) -> np.ndarray:
        """phi(s) as float32: the half of `act` that needs no context.

        The policy node computes it when a state arrives, while the context
        node is still computing that state's latent.
        """
        _single_thread()
        obs = np.asarray(obs, dtype=np.float32).reshape(-1)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f'obs must have {self.obs_dim} values, got {obs.size}')
        return self.phi(torch.from_numpy(obs)[None])[0].numpy()

    @torch.no_grad()
    def act_on_features(self, features: np.ndarray, latent: np.ndarray) -> np.ndarray:
        """Deterministic action tanh(mu) from phi(s) (`features`) and the latent, as float64."""
        _single_thread()
        latent = np.asarray(latent, dtype=np.float32).reshape(-1)
        if latent.shape != (self.context_dim,):
            raise ValueError(f'latent must have {self.context_dim} values, got {latent.size}')
        x = torch.cat([torch.from_numpy(features)[None], torch.from_numpy(latent)[None]], dim=-1)
        return self.actor.mean_action(x)[0].numpy().astype(np.float64)

    @torch.no_grad()
    def decode_values(self, latent: np.ndarray) -> np.ndarray:
        """Physical-parameter estimates read from a latent, one per name (NaN: no decoder)."""
        _single_thread()
        latent = np.asarray(latent, dtype=np.float32).reshape(1, -1)
        normalised = self.method.decode(torch.from_numpy(latent))
        if normalised is None:
            return np.full(len(self.param_names), math.nan)
        return normalised[0].numpy().astype(np.float64) * self.param_scale + self.param_offset

    def decode(self, latent: np.ndarray) -> float:
        """Return the estimate of a one-parameter family's parameter (NaN without a decoder)."""
        if len(self.param_names) != 1:
            raise ValueError(f'{self.family} has {len(self.param_names)} parameters: '
                             'use decode_values')
        return float(self.decode_values(latent)[0])
