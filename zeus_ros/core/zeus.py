"""ZeUS agent: SAC on concat(phi(s), psi(H)) plus the context/dynamics/reward losses.

Who trains what (every target is computed under `torch.no_grad()`):

* critic loss -> twin Q heads, phi AND psi (SAC-AE / mtrl convention: the
  encoders are shaped by the critic's TD error). The TD target uses the target
  critic with its own Polyak-averaged phi/psi copies, and the online actor for
  the next action.
* actor loss -> actor only: phi(s) and psi(H) are DETACHED and the critic's
  parameters are frozen while the loss is back-propagated.
* alpha loss -> log temperature only (target entropy = -action_dim).
* model update (Algorithm 2; Equation 2) -> psi, T and R only:
  alpha_psi * MSE(||psi(H1) - psi(H2)||_2, d(c1, c2))
  + dynamics loss of T against stop-gradient phi(s')
  + MSE of R against r.
  phi(s) is DETACHED here (Algorithm 2 updates psi, T, R), so phi is trained by
  the critic only. H2 is the batch permuted, so the "same for H2" terms of
  Equation 2 are the same average over the batch and are counted once.
  d(c1, c2) = |R(phi(s), a, psi1) - R(phi(s), a, psi2)|
              + W2(N(mu1, sigma1), N(mu2, sigma2)),
  with T and R evaluated at the SAME (s, a) (that of H1's sample) under the two
  contexts, all under no_grad; W2 of diagonal Gaussians in closed form:
  sqrt(||mu1 - mu2||^2 + ||sigma1 - sigma2||^2). With alpha_psi = 0 (ablation
  ZeUS-no-context-loss) the context term is not computed at all.
* decoder loss -> parameter decoder only, on the DETACHED latent psi(H),
  against the true parameter of the transition's training task, min-max
  normalised over the family's train values.

Update schedule (Tables 8-9, SAC-AE/mtrl conventions): every call of `update`
does one critic step and one model (context) step and one decoder step; the
actor and the temperature step every `actor_update_freq` (2) updates; the
target networks (critic heads tau=0.01, phi/psi tau=0.05) move every
`critic_target_update_freq` (2) updates.
"""

from __future__ import annotations

import copy
import math
import time

import numpy as np
import torch
import torch.nn.functional as F

from zeus_ros.core.config import ZeusConfig
from zeus_ros.core.networks import (Actor, ContextEncoder, Critic, GaussianModel,
                                    ObsEncoder, ParamDecoder, RewardModel, weight_init)
from zeus_ros.core.replay import Batch
from zeus_ros.core.window import row_dim

# Modules the deployed policy needs (model.safetensors) and the rest (training state).
INFERENCE_MODULES = ('phi', 'psi', 'actor', 'decoder')
TRAINING_MODULES = ('critic', 'critic_target', 'phi_target', 'psi_target', 'T', 'R')
OPTIMIZERS = ('critic_opt', 'actor_opt', 'alpha_opt', 'model_opt', 'decoder_opt')


def soft_update(net: torch.nn.Module, target: torch.nn.Module, tau: float) -> None:
    """Polyak average: target <- tau * net + (1 - tau) * target."""
    with torch.no_grad():
        for p, tp in zip(net.parameters(), target.parameters(), strict=True):
            tp.lerp_(p, tau)


def param_normaliser(train_values) -> tuple[float, float]:
    """(offset, scale) mapping the train values min-max onto [0, 1]."""
    lo, hi = float(min(train_values)), float(max(train_values))
    return lo, (hi - lo) if hi > lo else 1.0


def w2_diag_gaussians(mu1, log_std1, mu2, log_std2) -> torch.Tensor:
    """2-Wasserstein distance between diagonal Gaussians (closed form), per row."""
    sq = (mu1 - mu2).pow(2).sum(-1) + (log_std1.exp() - log_std2.exp()).pow(2).sum(-1)
    return sq.sqrt()


def safe_norm(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """L2 norm over the last axis with a finite gradient at 0."""
    return (x.pow(2).sum(-1) + eps).sqrt()


def build_inference_modules(cfg: ZeusConfig, obs_dim: int, action_dim: int) -> dict:
    """Build the networks a deployed policy needs: phi, psi, actor, decoder."""
    in_dim = cfg.feature_dim + cfg.context_dim
    return {
        'phi': ObsEncoder(obs_dim, cfg.feature_dim, cfg.encoder_hidden, cfg.encoder_layers),
        'psi': ContextEncoder(row_dim(obs_dim, action_dim), cfg.context_dim,
                              cfg.context_hidden, cfg.context_layers, cfg.aggregation),
        'actor': Actor(in_dim, action_dim, cfg.hidden_dim, cfg.hidden_layers,
                       cfg.actor_log_std_min, cfg.actor_log_std_max),
        'decoder': ParamDecoder(cfg.context_dim, cfg.decoder_hidden),
    }


class ZeusAgent:
    """All ZeUS networks, their optimisers, and the update step."""

    def __init__(self, config: ZeusConfig, obs_dim: int, action_dim: int,
                 param_offset: float = 0.0, param_scale: float = 1.0):
        self.config = cfg = config
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.row_dim = row_dim(obs_dim, action_dim)
        self.param_offset, self.param_scale = float(param_offset), float(param_scale)
        nets = build_inference_modules(cfg, obs_dim, action_dim)
        self.phi, self.psi = nets['phi'], nets['psi']
        self.actor, self.decoder = nets['actor'], nets['decoder']
        in_dim = cfg.feature_dim + cfg.context_dim
        self.critic = Critic(in_dim, action_dim, cfg.hidden_dim, cfg.hidden_layers)
        self.T = GaussianModel(cfg.feature_dim, action_dim, cfg.context_dim,
                               cfg.dynamics_hidden, cfg.dynamics_layers)
        self.R = RewardModel(cfg.feature_dim, action_dim, cfg.context_dim,
                             cfg.dynamics_hidden, cfg.dynamics_layers)
        for m in (self.phi, self.psi, self.actor, self.critic, self.T, self.R, self.decoder):
            m.apply(weight_init)
        self.critic_target = copy.deepcopy(self.critic)
        self.phi_target = copy.deepcopy(self.phi)
        self.psi_target = copy.deepcopy(self.psi)
        for m in (self.critic_target, self.phi_target, self.psi_target):
            m.requires_grad_(False)
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(cfg.init_temperature)))
        self.target_entropy = -float(action_dim)
        betas = (cfg.adam_beta1, 0.999)
        self.critic_opt = torch.optim.Adam(
            [*self.critic.parameters(), *self.phi.parameters(), *self.psi.parameters()],
            lr=cfg.critic_lr, betas=betas)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr, betas=betas)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=cfg.alpha_lr, betas=betas)
        self.model_opt = torch.optim.Adam(
            [*self.psi.parameters(), *self.T.parameters(), *self.R.parameters()],
            lr=cfg.model_lr)
        self.decoder_opt = torch.optim.Adam(self.decoder.parameters(), lr=cfg.decoder_lr)
        self.update_step = 0
        self.timers: dict[str, float] | None = None  # set to {} to profile update()

    @property
    def alpha(self) -> torch.Tensor:
        """Current temperature."""
        return self.log_alpha.exp()

    def modules(self) -> dict[str, torch.nn.Module]:
        """Every network by name (inference and training ones)."""
        return {n: getattr(self, n) for n in (*INFERENCE_MODULES, *TRAINING_MODULES)}

    def normalise_param(self, value):
        """Physical parameter -> decoder target."""
        return (value - self.param_offset) / self.param_scale

    # -- acting ----------------------------------------------------------------
    @torch.no_grad()
    def act(self, obs, window_rows, window_mask, deterministic: bool = False) -> np.ndarray:
        """Action(s) in [-1, 1] for one observation [obs_dim] or a batch [B, obs_dim]."""
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32))
        single = obs_t.dim() == 1
        rows = torch.as_tensor(np.asarray(window_rows, dtype=np.float32))
        mask = torch.as_tensor(np.asarray(window_mask, dtype=bool))
        if single:
            obs_t, rows, mask = obs_t[None], rows[None], mask[None]
        x = torch.cat([self.phi(obs_t), self.psi(rows, mask)], dim=-1)
        if deterministic:
            action = self.actor.mean_action(x)
        else:
            action, _, _ = self.actor.sample(x)
        out = action.numpy().astype(np.float64)
        return out[0] if single else out

    # -- losses ----------------------------------------------------------------
    def critic_loss(self, b: Batch):
        """TD loss of both Q heads; gradients reach critic, phi and psi.

        Returns (loss, z, c, metrics) where z = phi(s), c = psi(H) carry the
        graph (the actor update reuses them detached).
        """
        with torch.no_grad():
            zn = self.phi(b.next_obs)
            cn = self.psi(b.next_ctx_rows, b.next_ctx_mask)
            next_action, next_logp, _ = self.actor.sample(torch.cat([zn, cn], -1))
            xt = torch.cat([self.phi_target(b.next_obs),
                            self.psi_target(b.next_ctx_rows, b.next_ctx_mask)], -1)
            tq1, tq2 = self.critic_target(xt, next_action)
            target_v = torch.min(tq1, tq2) - self.alpha.detach() * next_logp
            target_q = b.reward + b.not_done * self.config.discount * target_v
        z = self.phi(b.obs)
        c = self.psi(b.ctx_rows, b.ctx_mask)
        q1, q2 = self.critic(torch.cat([z, c], -1), b.action)
        loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        return loss, z, c, {'critic_loss': loss.item(), 'q1': q1.mean().item()}

    def actor_and_alpha_loss(self, z: torch.Tensor, c: torch.Tensor):
        """Actor loss on DETACHED phi/psi (critic frozen by the caller) and alpha loss."""
        x = torch.cat([z.detach(), c.detach()], -1)
        action, logp, _ = self.actor.sample(x)
        q1, q2 = self.critic(x, action)
        actor_loss = (self.alpha.detach() * logp - torch.min(q1, q2)).mean()
        alpha_loss = (self.alpha * (-logp - self.target_entropy).detach()).mean()
        entropy = -logp.mean().item()
        return actor_loss, alpha_loss, {'actor_loss': actor_loss.item(),
                                        'alpha_loss': alpha_loss.item(),
                                        'entropy': entropy}

    def context_target(self, z, a, c1, c2) -> torch.Tensor:
        """d(c1, c2) from the learned R and T at the same (z, a); no gradient."""
        with torch.no_grad():
            r1, r2 = self.R(z, a, c1), self.R(z, a, c2)
            mu1, ls1 = self.T(z, a, c1)
            mu2, ls2 = self.T(z, a, c2)
            return (r1 - r2).abs() + w2_diag_gaussians(mu1, ls1, mu2, ls2)

    def context_loss(self, z, a, c, perm) -> torch.Tensor:
        """alpha_psi-free Equation-2 context term: MSE(||c - c[perm]||, d).

        `z` must be detached (phi is not trained here). Only psi (through
        `c`) receives gradients; the target d has none.
        """
        c2 = c[perm]
        target = self.context_target(z, a, c.detach(), c2.detach())
        return F.mse_loss(safe_norm(c - c2), target)

    def model_loss(self, b: Batch, perm: torch.Tensor | None = None):
        """Equation 2: alpha_psi * context loss + dynamics + reward; trains psi, T, R."""
        with torch.no_grad():
            z = self.phi(b.obs)            # phi is trained by the critic only
            zn = self.phi(b.next_obs)      # stop-gradient dynamics target
        c = self.psi(b.ctx_rows, b.ctx_mask)
        mu, log_std = self.T(z, b.action, c)
        if self.config.dynamics_loss == 'nll':
            diff = (mu - zn) / log_std.exp()
            dyn = (0.5 * diff.pow(2) + log_std).sum(-1).mean()
        else:
            dyn = F.mse_loss(mu, zn)
        rew = F.mse_loss(self.R(z, b.action, c), b.reward)
        metrics = {'dynamics_loss': dyn.item(), 'dynamics_mse': F.mse_loss(mu, zn).item(),
                   'reward_loss': rew.item()}
        loss = dyn + rew
        if self.config.alpha_psi > 0:
            if perm is None:
                perm = torch.randperm(c.shape[0])
            ctx = self.context_loss(z, b.action, c, perm)
            loss = loss + self.config.alpha_psi * ctx
            metrics['context_loss'] = ctx.item()
        return loss, c, metrics

    def decoder_loss(self, c: torch.Tensor, param: torch.Tensor) -> torch.Tensor:
        """MSE of the decoder on the DETACHED latent against the normalised parameter."""
        return F.mse_loss(self.decoder(c.detach()), self.normalise_param(param))

    # -- update ----------------------------------------------------------------
    def _tick(self, name: str, start: float) -> float:
        """Accumulate section time into `self.timers` when profiling; return now."""
        now = time.perf_counter()
        if self.timers is not None:
            self.timers[name] = self.timers.get(name, 0.0) + now - start
        return now

    def update(self, b: Batch, step: int | None = None) -> dict:
        """One update of every component on a batch; returns scalar metrics."""
        cfg = self.config
        self.update_step += 1
        n = self.update_step
        metrics = {}
        t = time.perf_counter()

        loss, z, c, m = self.critic_loss(b)
        metrics.update(m)
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_opt.step()
        t = self._tick('critic', t)

        if n % cfg.actor_update_freq == 0:
            self.critic.requires_grad_(False)
            actor_loss, alpha_loss, m = self.actor_and_alpha_loss(z, c)
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_opt.step()
            self.critic.requires_grad_(True)
            metrics.update(m)
            metrics['alpha'] = self.alpha.item()
            t = self._tick('actor_alpha', t)

        if n % cfg.critic_target_update_freq == 0:
            soft_update(self.critic, self.critic_target, cfg.critic_tau)
            soft_update(self.phi, self.phi_target, cfg.encoder_tau)
            soft_update(self.psi, self.psi_target, cfg.encoder_tau)
            t = self._tick('target', t)

        loss, c, m = self.model_loss(b)
        metrics.update(m)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.model_opt.step()
        t = self._tick('model_context', t)

        dec = self.decoder_loss(c, b.param)
        self.decoder_opt.zero_grad(set_to_none=True)
        dec.backward()
        self.decoder_opt.step()
        metrics['decoder_loss'] = dec.item()
        self._tick('decoder', t)
        return metrics
