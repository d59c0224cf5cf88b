"""`zeus-id`: a ZeUS variant that identifies the physics (this project, beyond the paper).

Measured on the paper-faithful `zeus` (issue #14): k = 5 transitions carry
too little of friction; the critic's TD gradient turns psi into a
state-history encoder; Equation 2's target, computed in phi-space, is smaller
than psi's spread within one task, so collapse is a fixed point. Each choice
below answers one of these, and each can be switched back with `--set` to
ablate it:

* ``context_length`` 25 (preset): long enough to read friction on the
  slippery walker (a psi-shaped regressor reaches R^2 0.92 at k = 25, 0.53 at 5).
* ``context_input='delta'``: psi reads concat(s, a, r, s' - s), standardised
  by running statistics stored with the weights (the change a friction alters
  is s' - s, not s', which is dominated by s).
* ``context_critic_grad=False``: the TD loss does not reach psi; it is shaped
  by the model losses only, and the actor and critic read it as an input.
* models of the RAW standardised s' - s and r (not of phi(s')): the task
  metric d is then measured in physical units the parameter changes.
* ``metric_normalise=True``: d and the latent distances are divided by their
  batch means, so the cross-task signal is not lost in the absolute scale.

The loss (one optimiser for psi, T and R): NLL of T's Gaussian over the
standardised s' - s, MSE of R, plus alpha_psi * MSE(||c1 - c2|| / mean,
d / mean) with d = |R(x, a, c1) - R(x, a, c2)| + W2(T(x, a, c1), T(x, a, c2))
at the same (x, a), under no_grad. The decoder reads the DETACHED latent.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from zeus_ros.core.methods.base import ContextMethod
from zeus_ros.core.methods.zeus import gaussian_nll, safe_norm, w2_diag_gaussians
from zeus_ros.core.networks import (ContextEncoder, GaussianModel, ParamDecoder, RewardModel,
                                    weight_init)


class RunningStandardiser(nn.Module):
    """Per-feature mean / std from every batch seen in training (buffers, saved with psi)."""

    def __init__(self, dim: int, min_momentum: float = 1e-3):
        super().__init__()
        self.register_buffer('mean', torch.zeros(dim))
        self.register_buffer('var', torch.ones(dim))
        self.register_buffer('count', torch.zeros(()))
        self.min_momentum = min_momentum

    @torch.no_grad()
    def observe(self, x: torch.Tensor) -> None:
        """Fold a batch [N, dim] into the statistics (a cumulative mean, then an EMA)."""
        self.count += 1
        m = max(1.0 / float(self.count), self.min_momentum)
        self.mean.lerp_(x.mean(0), m)
        self.var.lerp_(x.var(0, unbiased=False), m)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / (self.var.sqrt() + 1e-4)


def transition_features(rows: torch.Tensor, obs_dim: int, delta: bool) -> torch.Tensor:
    """Window rows concat(s, a, r, s') -> concat(s, a, r, s' - s) when `delta`."""
    if not delta:
        return rows
    s, s_next = rows[..., :obs_dim], rows[..., -obs_dim:]
    return torch.cat([rows[..., :-obs_dim], s_next - s], dim=-1)


class DeltaContextEncoder(nn.Module):
    """psi of zeus-id: standardised transition features -> per-row codes -> pooled."""

    def __init__(self, obs_dim: int, row_dim: int, cfg):
        super().__init__()
        self.obs_dim = obs_dim
        self.delta = cfg.context_input == 'delta'
        self.norm = RunningStandardiser(row_dim)
        self.encoder = ContextEncoder(row_dim, cfg.context_dim, cfg.context_hidden,
                                      cfg.context_layers, cfg.aggregation)

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        return transition_features(rows, self.obs_dim, self.delta)

    def codes(self, rows: torch.Tensor) -> torch.Tensor:
        return self.encoder.codes(self.norm(self.features(rows)))

    def forward(self, rows: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.encoder.pool(self.codes(rows), mask)


class ZeusIdMethod(ContextMethod):
    """Long-window, delta-input context shaped by raw-dynamics models and a normalised metric."""

    name = 'zeus-id'
    config_defaults = {'context_length': 25, 'context_input': 'delta',
                       'context_critic_grad': False, 'metric_normalise': True,
                       'context_hidden': 64}

    def __init__(self, cfg, dims, param, training=True):
        super().__init__(cfg, dims, param, training)
        o, a = dims.obs_dim, dims.action_dim
        self.psi = DeltaContextEncoder(o, dims.row_dim, cfg)
        self.decoder = ParamDecoder(cfg.context_dim, cfg.decoder_hidden)
        if not training:
            return
        # T and R read the standardised s (first obs_dim features of a row).
        self.T = GaussianModel(o, a, cfg.context_dim, cfg.dynamics_hidden, cfg.dynamics_layers)
        self.R = RewardModel(o, a, cfg.context_dim, cfg.dynamics_hidden, cfg.dynamics_layers)
        for m in (self.psi, self.T, self.R, self.decoder):
            m.apply(weight_init)
        self.model_opt = torch.optim.Adam(
            [*self.psi.parameters(), *self.T.parameters(), *self.R.parameters()],
            lr=cfg.model_lr)
        self.decoder_opt = torch.optim.Adam(self.decoder.parameters(), lr=cfg.decoder_lr)

    @property
    def critic_trains_context(self) -> bool:
        return self.cfg.context_critic_grad

    @property
    def context_dim(self) -> int:
        return self.cfg.context_dim

    def inference_modules(self):
        return {'psi': self.psi, 'decoder': self.decoder}

    def training_modules(self):
        return {'T': self.T, 'R': self.R}

    def optimizers(self):
        return {'model_opt': self.model_opt, 'decoder_opt': self.decoder_opt}

    def encoder_parameters(self):
        return list(self.psi.parameters())

    def encode(self, rows, mask, param):
        return self.psi(rows, mask)

    def decode(self, latent):
        return self.decoder(latent)

    # -- losses ------------------------------------------------------------------
    def _targets(self, b):
        """Standardised s and s' - s of the batch's own transitions (no gradient)."""
        row = torch.cat([b.obs, b.action, b.reward[:, None], b.next_obs], dim=-1)
        feats = self.psi.norm(transition_features(row, self.dims.obs_dim, True))
        o = self.dims.obs_dim
        return feats[:, :o], feats[:, -o:]

    def context_loss(self, x, a, c, perm) -> torch.Tensor:
        """MSE between latent distances and the task metric, each over its batch mean."""
        c2 = c[perm]
        with torch.no_grad():
            c1d, c2d = c.detach(), c2.detach()
            mu1, ls1 = self.T(x, a, c1d)
            mu2, ls2 = self.T(x, a, c2d)
            d = (self.R(x, a, c1d) - self.R(x, a, c2d)).abs() + w2_diag_gaussians(
                mu1, ls1, mu2, ls2)
        dist = safe_norm(c - c2)
        if self.cfg.metric_normalise:
            d = d / (d.mean() + 1e-6)
            dist = dist / (dist.mean().detach() + 1e-6)
        return F.mse_loss(dist, d)

    def model_loss(self, b, perm=None):
        """NLL of standardised s' - s, MSE of r, alpha_psi * context loss; trains psi, T, R."""
        valid_rows = b.ctx_rows[b.ctx_mask]
        if valid_rows.shape[0] > 1:
            self.psi.norm.observe(self.psi.features(valid_rows))
        x, delta = self._targets(b)
        c = self.psi(b.ctx_rows, b.ctx_mask)
        mu, log_std = self.T(x, b.action, c)
        dyn = gaussian_nll(mu, log_std, delta)
        rew = F.mse_loss(self.R(x, b.action, c), b.reward)
        metrics = {'dynamics_loss': dyn.detach(), 'reward_loss': rew.detach()}
        loss = dyn + rew
        if self.cfg.alpha_psi > 0:
            perm = torch.randperm(c.shape[0]) if perm is None else perm
            ctx = self.context_loss(x, b.action, c, perm)
            loss = loss + self.cfg.alpha_psi * ctx
            metrics['context_loss'] = ctx.detach()
        return loss, c, metrics

    def update(self, batch, z, step):
        loss, c, metrics = self.model_loss(batch)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.model_opt.step()
        dec = F.mse_loss(self.decoder(c.detach()), self.param.normalise(batch.param))
        self.decoder_opt.zero_grad(set_to_none=True)
        dec.backward()
        self.decoder_opt.step()
        metrics['decoder_loss'] = dec.detach()
        return metrics
