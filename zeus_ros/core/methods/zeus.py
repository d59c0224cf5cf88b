"""`zeus`: the paper's method (Equation 2, Algorithm 2), kept as published for reproduction.

* psi: per-transition MLP over concat(s, a, r, s'), aggregated (mean / sum /
  max); trained by the critic's TD loss (SAC-AE convention) AND by the
  model update below. A Polyak copy `psi_target` feeds the TD target.
* model update -> psi, T and R only:
  alpha_psi * MSE(||psi(H1) - psi(H2)||_2, d(c1, c2)) + dynamics + reward,
  T: (phi(s), a, psi) -> Gaussian over phi(s') (stop-gradient target),
  R: (phi(s), a, psi) -> r; phi(s) detached (phi is trained by the critic).
  d(c1, c2) = |R(z, a, c1) - R(z, a, c2)| + W2(T(z, a, c1), T(z, a, c2)) at
  the SAME (z, a) under the two contexts, under no_grad. H2 is the batch
  permuted, so Equation 2's "same for H2" terms are the same batch average.
* decoder -> reads the normalised parameter from the DETACHED latent (a
  probe and the deployed estimate; it never shapes psi).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from zeus_ros.core.methods.base import (adam, ContextMethod, Dims, MethodConfig, MethodSettings,
                                        ParamScale, soft_update)
from zeus_ros.core.methods.common import gaussian_nll, ModelLoss, safe_norm, w2_diag_gaussians
from zeus_ros.core.networks import (ContextEncoder, GaussianModel, ParamDecoder, RewardModel,
                                    weight_init)
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch

DYNAMICS_LOSSES = ('nll', 'mse')


@dataclass(frozen=True)
class ZeusSettings(MethodSettings):
    """What only the paper's method (and its no-context-loss ablation) reads."""

    dynamics_loss: str = setting(
        'nll', "Loss of T in phi-space: 'nll' = Gaussian NLL (trains mean and log-std); "
        "'mse' = mean only.", choices=DYNAMICS_LOSSES)

    def validate(self) -> 'ZeusSettings':
        if self.dynamics_loss not in DYNAMICS_LOSSES:
            raise ValueError("dynamics_loss must be 'nll' or 'mse'")
        return self


class ZeusMethod(ContextMethod):
    """Equation 2 on phi-space models; the critic also trains psi."""

    name = 'zeus'
    has_own_update = True
    critic_trains_context = True
    settings_class = ZeusSettings
    metric_names = ('dynamics_loss', 'reward_loss', 'context_loss', 'decoder_loss')

    def __init__(self, cfg: MethodConfig, dims: Dims, param: ParamScale,
                 training: bool = True):
        super().__init__(cfg, dims, param, training)
        self.psi = ContextEncoder(dims.row_dim, cfg.context_dim, cfg.context_hidden,
                                  cfg.context_layers, cfg.aggregation)
        self.decoder = ParamDecoder(cfg.context_dim, cfg.decoder_hidden, param.param_dim)
        if not training:
            return
        self.T = GaussianModel(cfg.feature_dim, dims.action_dim, cfg.context_dim,
                               cfg.dynamics_hidden, cfg.dynamics_layers)
        self.R = RewardModel(cfg.feature_dim, dims.action_dim, cfg.context_dim,
                             cfg.dynamics_hidden, cfg.dynamics_layers)
        for m in (self.psi, self.T, self.R, self.decoder):
            m.apply(weight_init)
        self.psi_target = copy.deepcopy(self.psi).requires_grad_(False)
        self.model_opt = adam(
            [*self.psi.parameters(), *self.T.parameters(), *self.R.parameters()],
            lr=cfg.model_lr)
        self.decoder_opt = adam(self.decoder.parameters(), lr=cfg.decoder_lr)
        self.phi = None  # set by the agent: the model update needs phi(s') targets

    @property
    def context_dim(self) -> int:
        return self.cfg.context_dim

    def inference_modules(self) -> dict[str, torch.nn.Module]:
        return {'psi': self.psi, 'decoder': self.decoder}

    def training_modules(self) -> dict[str, torch.nn.Module]:
        return {'psi_target': self.psi_target, 'T': self.T, 'R': self.R}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {'model_opt': self.model_opt, 'decoder_opt': self.decoder_opt}

    def encoder_parameters(self) -> list[torch.nn.Parameter]:
        return list(self.psi.parameters())

    def encode(self, rows: torch.Tensor, mask: torch.Tensor,
               param: torch.Tensor | None) -> torch.Tensor:  # noqa: ARG002 (ContextMethod's signature)
        return self.psi(rows, mask)

    def encode_pair(self, batch: Batch, grad: bool) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.set_grad_enabled(grad):   # one pass over the k + 1 rows of both windows
            codes = self.psi.codes(batch.chain_rows)
        return self.psi.window_pair(codes, batch.chain_mask, grad)

    def encode_target(self, rows: torch.Tensor, mask: torch.Tensor,
                      param: torch.Tensor | None) -> torch.Tensor:  # noqa: ARG002 (ContextMethod's signature)
        with torch.no_grad():
            return self.psi_target(rows, mask)

    def update_targets(self, tau: float) -> None:
        soft_update(self.psi, self.psi_target, tau)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return self.decoder(latent)

    # -- Equation 2 ------------------------------------------------------------
    def context_target(self, z: torch.Tensor, a: torch.Tensor, c1: torch.Tensor,
                       c2: torch.Tensor) -> torch.Tensor:
        """d(c1, c2) from the learned R and T at the same (z, a); no gradient."""
        with torch.no_grad():
            r1, r2 = self.R(z, a, c1), self.R(z, a, c2)
            mu1, ls1 = self.T(z, a, c1)
            mu2, ls2 = self.T(z, a, c2)
            return (r1 - r2).abs() + w2_diag_gaussians(mu1, ls1, mu2, ls2)

    def context_loss(self, z: torch.Tensor, a: torch.Tensor, c: torch.Tensor,
                     perm: torch.Tensor) -> torch.Tensor:
        """MSE(||c - c[perm]||, d): only psi (through `c`) receives gradients."""
        c2 = c[perm]
        target = self.context_target(z, a, c.detach(), c2.detach())
        return F.mse_loss(safe_norm(c - c2), target)

    def model_loss(self, b: Batch, z: torch.Tensor,
                   perm: torch.Tensor | None = None) -> ModelLoss:
        """Equation 2: alpha_psi * context loss + dynamics + reward; trains psi, T, R."""
        with torch.no_grad():
            zn = self.phi(b.next_obs)      # stop-gradient dynamics target
        c = self.psi(b.ctx_rows, b.ctx_mask)
        mu, log_std = self.T(z, b.action, c)
        dyn = gaussian_nll(mu, log_std, zn) if self.settings.dynamics_loss == 'nll' \
            else F.mse_loss(mu, zn)
        rew = F.mse_loss(self.R(z, b.action, c), b.reward)
        metrics = {'dynamics_loss': dyn.detach(), 'reward_loss': rew.detach()}
        loss = dyn + rew
        if self.cfg.alpha_psi > 0:
            if perm is None:
                perm = torch.randperm(c.shape[0])
            ctx = self.context_loss(z, b.action, c, perm)
            loss = loss + self.cfg.alpha_psi * ctx
            metrics['context_loss'] = ctx.detach()
        return loss, c, metrics

    def decoder_loss(self, c: torch.Tensor, param: torch.Tensor) -> torch.Tensor:
        """MSE of the decoder on the DETACHED latent against the normalised parameter."""
        return F.mse_loss(self.decoder(c.detach()), self.param.normalise(param))

    def update(self, batch: Batch, z: torch.Tensor, step: int,  # noqa: ARG002 (ContextMethod's signature)
               ) -> dict[str, torch.Tensor]:
        loss, c, metrics = self.model_loss(batch, z)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.model_opt.step()
        dec = self.decoder_loss(c, batch.param)
        self.decoder_opt.zero_grad(set_to_none=True)
        dec.backward()
        self.decoder_opt.step()
        metrics['decoder_loss'] = dec.detach()
        return metrics


class ZeusNoContextLoss(ZeusMethod):
    """`zeus-no-context-loss`: the paper's ablation (alpha_psi = 0 whatever the config says)."""

    name = 'zeus-no-context-loss'
    config_defaults = {'alpha_psi': 0.0}

    def model_loss(self, b: Batch, z: torch.Tensor,
                   perm: torch.Tensor | None = None) -> ModelLoss:
        if self.cfg.alpha_psi != 0:
            raise ValueError('zeus-no-context-loss trains with alpha_psi = 0')
        return super().model_loss(b, z, perm)
