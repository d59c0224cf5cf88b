"""`hyperdynamics`: HyperDynamics (Xian et al. 2021), as appendix B.2.1 runs it.

An interaction encoder (psi over the last k transitions) feeds a hypernetwork
that GENERATES the weights of a one-hidden-layer dynamics model per sample;
that model predicts the standardised s' - s from (standardised s, a) as a
diagonal Gaussian (NLL). Encoder, hypernetwork and (through its generated
weights) the dynamics model train jointly with the policy: by default the
critic's TD error also shapes the encoder (``context_critic_grad`` True, the
SAC-AE convention every method here shares; set it False to ablate). No
public code was found; this follows the paper's description.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn

from zeus_ros.core.methods.common import (EncoderMethod, EncoderSettings, gaussian_nll,
                                          ModelLoss)
from zeus_ros.core.networks import mlp
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch


@dataclass(frozen=True)
class HyperDynamicsSettings(EncoderSettings):
    """The learned-encoder settings plus the size of the generated dynamics model."""

    hyper_model_hidden: int = setting(
        64, 'hyperdynamics: hidden width of the generated dynamics model.')


class HyperNetwork(nn.Module):
    """Context -> the weights and biases of a (in -> hidden -> 2 * out) ReLU MLP, per sample."""

    log_std_min, log_std_max = -5.0, 2.0

    def __init__(self, context_dim: int, in_dim: int, hidden: int, out_dim: int,
                 hyper_hidden: int):
        super().__init__()
        self.shapes = [(in_dim, hidden), (hidden,), (hidden, 2 * out_dim), (2 * out_dim,)]
        self.sizes = [int(torch.tensor(s).prod()) for s in self.shapes]
        self.net = mlp(context_dim, hyper_hidden, sum(self.sizes), 1)

    def forward(self, c: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the generated model at inputs x [B, in_dim]."""
        w1, b1, w2, b2 = torch.split(self.net(c), self.sizes, dim=-1)
        n = c.shape[0]
        h = torch.relu(torch.bmm(x[:, None], w1.view(n, *self.shapes[0]))[:, 0] + b1)
        out = torch.bmm(h[:, None], w2.view(n, *self.shapes[2]))[:, 0] + b2
        mu, log_std = out.chunk(2, dim=-1)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (
            torch.tanh(log_std) + 1.0)
        return mu, log_std


class HyperDynamicsMethod(EncoderMethod):
    """Encoder -> hypernetwork -> per-context dynamics model of s' - s."""

    name = 'hyperdynamics'
    config_defaults = {'context_input': 'delta', 'context_critic_grad': True}
    settings_class = HyperDynamicsSettings
    metric_names = ('dynamics_loss', 'decoder_loss')

    def build_models(self) -> dict[str, HyperNetwork]:
        cfg, o, a = self.cfg, self.dims.obs_dim, self.dims.action_dim
        return {'hyper': HyperNetwork(cfg.context_dim, o + a, self.settings.hyper_model_hidden, o,
                                      cfg.dynamics_hidden)}

    def model_loss(self, b: Batch) -> ModelLoss:
        x, delta = self.standardised_step(b)
        c = self.psi(b.ctx_rows, b.ctx_mask)
        mu, log_std = self.models['hyper'](c, torch.cat([x, b.action], dim=-1))
        loss = gaussian_nll(mu, log_std, delta)
        return loss, c, {'dynamics_loss': loss.detach()}
