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
* ``id_weight=1``: the decoder's regression of the (normalised) training
  parameter back-propagates into psi, the privileged supervision UP-OSI's OSI
  also has in training; a deployed psi still reads transitions only. Measured
  without it (``id_weight=0``, seed 1, 38k timesteps): the decoder stayed at
  chance (loss 0.139 for a variance of 0.14 of the normalised train values)
  and the held-out R^2 was -0.19: the unsupervised losses alone did not put
  friction into the latent.

The loss (one optimiser for psi, T and R): NLL of T's Gaussian over the
standardised s' - s, MSE of R, plus alpha_psi * MSE(||c1 - c2|| / mean,
d / mean) with d = |R(x, a, c1) - R(x, a, c2)| + W2(T(x, a, c1), T(x, a, c2))
at the same (x, a), under no_grad. The decoder reads the DETACHED latent.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from zeus_ros.core.methods.common import (EncoderMethod, EncoderSettings, gaussian_nll,
                                          ModelLoss, safe_norm, transition_features,
                                          w2_diag_gaussians)
from zeus_ros.core.networks import GaussianModel, RewardModel
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch

__all__ = ['ZeusIdMethod', 'ZeusIdSettings', 'transition_features']


@dataclass(frozen=True)
class ZeusIdSettings(EncoderSettings):
    """The learned-encoder settings plus zeus-id's normalised task metric."""

    metric_normalise: bool = setting(
        False, 'zeus-id: divide the task metric and latent distances by their batch means.')


class ZeusIdMethod(EncoderMethod):
    """Long-window, delta-input context shaped by raw-dynamics models and a normalised metric."""

    name = 'zeus-id'
    settings_class = ZeusIdSettings
    metric_names = ('dynamics_loss', 'reward_loss', 'context_loss', 'decoder_loss')
    config_defaults = {'context_length': 25, 'context_input': 'delta',
                       'context_critic_grad': False, 'metric_normalise': True,
                       'context_hidden': 64, 'id_weight': 1.0}

    def build_models(self) -> dict[str, torch.nn.Module]:
        cfg, o, a = self.cfg, self.dims.obs_dim, self.dims.action_dim
        # T and R read the standardised s (the first obs_dim features of a row).
        return {'T': GaussianModel(o, a, cfg.context_dim, cfg.dynamics_hidden,
                                   cfg.dynamics_layers),
                'R': RewardModel(o, a, cfg.context_dim, cfg.dynamics_hidden,
                                 cfg.dynamics_layers)}

    def context_loss(self, x: torch.Tensor, a: torch.Tensor, c: torch.Tensor,
                     perm: torch.Tensor) -> torch.Tensor:
        """MSE between latent distances and the task metric, each over its batch mean."""
        T, R = self.models['T'], self.models['R']
        c2 = c[perm]
        with torch.no_grad():
            c1d, c2d = c.detach(), c2.detach()
            mu1, ls1 = T(x, a, c1d)
            mu2, ls2 = T(x, a, c2d)
            d = (R(x, a, c1d) - R(x, a, c2d)).abs() + w2_diag_gaussians(mu1, ls1, mu2, ls2)
        dist = safe_norm(c - c2)
        if self.settings.metric_normalise:
            d = d / (d.mean() + 1e-6)
            dist = dist / (dist.mean().detach() + 1e-6)
        return F.mse_loss(dist, d)

    def model_loss(self, b: Batch, perm: torch.Tensor | None = None) -> ModelLoss:
        """NLL of standardised s' - s, MSE of r, alpha_psi * context loss; trains psi, T, R."""
        x, delta = self.standardised_step(b)
        c = self.psi(b.ctx_rows, b.ctx_mask)
        mu, log_std = self.models['T'](x, b.action, c)
        dyn = gaussian_nll(mu, log_std, delta)
        rew = F.mse_loss(self.models['R'](x, b.action, c), b.reward)
        metrics = {'dynamics_loss': dyn.detach(), 'reward_loss': rew.detach()}
        loss = dyn + rew
        if self.cfg.alpha_psi > 0:
            perm = torch.randperm(c.shape[0]) if perm is None else perm
            ctx = self.context_loss(x, b.action, c, perm)
            loss = loss + self.cfg.alpha_psi * ctx
            metrics['context_loss'] = ctx.detach()
        return loss, c, metrics
