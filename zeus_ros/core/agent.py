"""The SAC core every method shares: phi, actor, twin critic, targets and the update.

Who trains what (every target is computed under `torch.no_grad()`):

* critic loss -> twin Q heads and phi, and the method's context encoder when
  the method says the critic trains it (`zeus`: SAC-AE / mtrl convention). The
  TD target uses the target critic with Polyak copies of phi (and of the
  method's encoder where it has one), and the online actor for the next action.
* actor loss -> actor only: phi(s) and the latent are DETACHED and the
  critic's parameters are frozen while the loss is back-propagated.
* alpha loss -> log temperature only (target entropy = -action_dim).
* the method's own update (`ContextMethod.update`): its context/model losses
  and decoder, on phi(s) detached.

Update schedule (Tables 8-9, SAC-AE/mtrl conventions): every call of `update`
does one critic step and, for a method with losses of its own
(`has_own_update`), one method step; the actor and the temperature step
every `actor_update_freq` (2) updates; the targets (critic heads tau=0.01,
encoders tau=0.05) move every `critic_target_update_freq` (2) updates.
Metrics come back as 0-d tensors: converting them is left to whoever logs.
"""

from __future__ import annotations

import copy
import math
import time
from typing import Sequence, TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from zeus_ros.core.config import ZeusConfig
from zeus_ros.core.methods import ContextMethod, Dims, get_method, ParamScale
from zeus_ros.core.methods.base import adam, soft_update
from zeus_ros.core.networks import Actor, Critic, ObsEncoder, weight_init
from zeus_ros.core.replay import Batch
from zeus_ros.core.window import row_dim

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

# The SAC core's own modules and optimisers; a method adds its own to each group.
CORE_INFERENCE_MODULES = ('phi', 'actor')
CORE_TRAINING_MODULES = ('critic', 'critic_target', 'phi_target')
CORE_OPTIMIZERS = ('critic_opt', 'actor_opt', 'alpha_opt')
# The metrics the core's update returns; a method adds its own `metric_names`.
CORE_METRICS = ('critic_loss', 'q1', 'actor_loss', 'alpha_loss', 'alpha', 'entropy')


def param_normaliser(train_values: Sequence[float | Sequence[float]],
                     log: bool = False) -> ParamScale:
    """Min-max normalisation mapping the train values (or their logs) onto [0, 1], per parameter.

    `train_values`: numbers (a one-parameter family) or value tuples.
    """
    values = np.asarray(train_values, dtype=np.float64)
    values = values.reshape(len(values), -1)
    if log:
        if (values <= 0).any():
            raise ValueError("param_space='log' needs positive train values, got "
                             f'{values.min():g}')
        values = np.log(values)
    lo, hi = values.min(axis=0), values.max(axis=0)
    return ParamScale(tuple(lo), tuple(np.where(hi > lo, hi - lo, 1.0)), log)


def build_method(cfg: ZeusConfig, obs_dim: int, action_dim: int, param: ParamScale,
                 training: bool = True) -> ContextMethod:
    """Build the configured context method, sized for the environment."""
    dims = Dims(obs_dim, action_dim, row_dim(obs_dim, action_dim))
    return get_method(cfg.method)(cfg, dims, param, training)


def build_policy_modules(cfg: ZeusConfig, obs_dim: int, context_dim: int,
                         action_dim: int) -> dict:
    """Build phi and the actor (the SAC half of what a deployed policy needs)."""
    return {
        'phi': ObsEncoder(obs_dim, cfg.feature_dim, cfg.encoder_hidden, cfg.encoder_layers),
        'actor': Actor(cfg.feature_dim + context_dim, action_dim, cfg.hidden_dim,
                       cfg.hidden_layers, cfg.actor_log_std_min, cfg.actor_log_std_max),
    }


class Agent:
    """SAC on concat(phi(s), latent) with a pluggable context method."""

    def __init__(self, config: ZeusConfig, obs_dim: int, action_dim: int,
                 param: ParamScale | None = None):
        self.config = cfg = config
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.row_dim = row_dim(obs_dim, action_dim)
        self.param = param or ParamScale()
        self.method = build_method(cfg, obs_dim, action_dim, self.param)
        nets = build_policy_modules(cfg, obs_dim, self.method.context_dim, action_dim)
        self.phi, self.actor = nets['phi'], nets['actor']
        self.critic = Critic(cfg.feature_dim + self.method.context_dim, action_dim,
                             cfg.hidden_dim, cfg.hidden_layers)
        for m in (self.phi, self.actor, self.critic):
            m.apply(weight_init)
        self.method.phi = self.phi
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.phi_target = copy.deepcopy(self.phi).requires_grad_(False)
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(cfg.init_temperature)))
        self.target_entropy = -float(action_dim)
        betas = (cfg.adam_beta1, 0.999)
        shaped_by_critic = self.method.encoder_parameters() \
            if self.method.critic_trains_context else []
        self.critic_opt = adam(
            [*self.critic.parameters(), *self.phi.parameters(), *shaped_by_critic],
            lr=cfg.critic_lr, betas=betas)
        self.actor_opt = adam(self.actor.parameters(), lr=cfg.actor_lr, betas=betas)
        self.alpha_opt = adam([self.log_alpha], lr=cfg.alpha_lr, betas=betas)
        self.update_step = 0
        self.timers: dict[str, float] | None = None  # set to {} to profile update()

    @property
    def alpha(self) -> torch.Tensor:
        """Current temperature."""
        return self.log_alpha.exp()

    def inference_modules(self) -> dict[str, torch.nn.Module]:
        """Networks a deployed policy needs, by checkpoint prefix."""
        return {'phi': self.phi, 'actor': self.actor, **self.method.inference_modules()}

    def training_modules(self) -> dict[str, torch.nn.Module]:
        """Networks only training needs, by checkpoint prefix."""
        return {'critic': self.critic, 'critic_target': self.critic_target,
                'phi_target': self.phi_target, **self.method.training_modules()}

    def modules(self) -> dict[str, torch.nn.Module]:
        """Every network by name (inference and training ones)."""
        return {**self.inference_modules(), **self.training_modules()}

    def metric_names(self) -> tuple[str, ...]:
        """Every metric `update` may return: the core's, then the method's."""
        return (*CORE_METRICS, *(m for m in self.method.metric_names if m not in CORE_METRICS))

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Every optimiser by checkpoint name."""
        return {'critic_opt': self.critic_opt, 'actor_opt': self.actor_opt,
                'alpha_opt': self.alpha_opt, **self.method.optimizers()}

    # -- acting ----------------------------------------------------------------
    @torch.no_grad()
    def act(self, obs: np.ndarray, window_rows: np.ndarray, window_mask: np.ndarray,
            param: ArrayLike | None = None, deterministic: bool = False) -> np.ndarray:
        """Action(s) in [-1, 1] for one observation [obs_dim] or a batch [B, obs_dim].

        `param`: the true parameter per row, needed only by privileged methods.
        """
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32))
        single = obs_t.dim() == 1
        rows = torch.as_tensor(np.asarray(window_rows, dtype=np.float32))
        mask = torch.as_tensor(np.asarray(window_mask, dtype=bool))
        p = None if param is None else self.param.as_rows(np.asarray(param, dtype=np.float32))
        if single:
            obs_t, rows, mask = obs_t[None], rows[None], mask[None]
        x = torch.cat([self.phi(obs_t), self.method.acting_context(rows, mask, p)], dim=-1)
        if deterministic:
            action = self.actor.mean_action(x)
        else:
            action, _, _ = self.actor.sample(x)
        out = action.numpy().astype(np.float64)
        return out[0] if single else out

    # -- losses ----------------------------------------------------------------
    def critic_loss(self, b: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                             dict[str, torch.Tensor]]:
        """TD loss of both Q heads; returns (loss, z, c, metrics), z/c carrying the graph."""
        c, cn = self.method.encode_pair(b, grad=self.method.critic_trains_context)
        with torch.no_grad():
            zn = self.phi(b.next_obs)
            actor_next = self.method.actor_context(b, cn, following=True)
            next_action, next_logp, _ = self.actor.sample(torch.cat([zn, actor_next], -1))
            ct = self.method.encode_target(b.next_ctx_rows, b.next_ctx_mask, b.param) \
                if self.method.critic_trains_context else cn
            tq1, tq2 = self.critic_target(torch.cat([self.phi_target(b.next_obs), ct], -1),
                                          next_action)
            target_v = torch.min(tq1, tq2) - self.alpha.detach() * next_logp
            target_q = b.reward + b.not_done * self.config.discount * target_v
        z = self.phi(b.obs)
        q1, q2 = self.critic(torch.cat([z, c], -1), b.action)
        loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        return loss, z, c, {'critic_loss': loss.detach(), 'q1': q1.detach().mean()}

    def actor_and_alpha_loss(self, z: torch.Tensor, c: torch.Tensor,
                             c_actor: torch.Tensor | None = None,
                             ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Actor loss on DETACHED phi/latent (critic frozen by the caller) and alpha loss.

        `c_actor`: the latent the actor reads when it is not the critic's `c`
        (an asymmetric method); the critic judges the action with `c`.
        """
        x = torch.cat([z.detach(), c.detach()], -1)
        x_actor = x if c_actor is None else torch.cat([z.detach(), c_actor.detach()], -1)
        action, logp, _ = self.actor.sample(x_actor)
        q1, q2 = self.critic(x, action)
        actor_loss = (self.alpha.detach() * logp - torch.min(q1, q2)).mean()
        alpha_loss = (self.alpha * (-logp - self.target_entropy).detach()).mean()
        return actor_loss, alpha_loss, {'actor_loss': actor_loss.detach(),
                                        'alpha_loss': alpha_loss.detach(),
                                        'entropy': -logp.detach().mean()}

    # -- update ----------------------------------------------------------------
    def _tick(self, name: str, start: float) -> float:
        """Accumulate section time into `self.timers` when profiling; return now."""
        now = time.perf_counter()
        if self.timers is not None:
            self.timers[name] = self.timers.get(name, 0.0) + now - start
        return now

    def _actor_step(self, z: torch.Tensor, c: torch.Tensor, c_actor: torch.Tensor) -> dict:
        self.critic.requires_grad_(False)
        actor_loss, alpha_loss, metrics = self.actor_and_alpha_loss(z, c, c_actor)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        self.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_opt.step()
        self.critic.requires_grad_(True)
        metrics['alpha'] = self.alpha.detach()
        return metrics

    def update(self, b: Batch) -> dict[str, torch.Tensor]:
        """One update of every component on a batch; returns 0-d metric tensors."""
        cfg = self.config
        self.update_step += 1
        n = self.update_step
        t = time.perf_counter()
        loss, z, c, metrics = self.critic_loss(b)
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_opt.step()
        t = self._tick('critic', t)
        if n % cfg.actor_update_freq == 0:
            with torch.no_grad():
                c_actor = self.method.actor_context(b, c)
            metrics.update(self._actor_step(z, c, c_actor))
            t = self._tick('actor_alpha', t)
        if n % cfg.critic_target_update_freq == 0:
            soft_update_all(self, cfg)
            t = self._tick('target', t)
        if self.method.has_own_update:
            with torch.no_grad():  # the method's models read phi as the critic step left it
                z_now = self.phi(b.obs)
            metrics.update(self.method.update(b, z_now, n))
            self._tick('method', t)
        return metrics


def soft_update_all(agent: Agent, cfg: ZeusConfig) -> None:
    """Move every target network: critic heads, phi, and the method's own."""
    soft_update(agent.critic, agent.critic_target, cfg.critic_tau)
    soft_update(agent.phi, agent.phi_target, cfg.encoder_tau)
    agent.method.update_targets(cfg.encoder_tau)
