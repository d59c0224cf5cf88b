"""`cadm`: Context-aware Dynamics Model (Lee et al. 2020), as the paper's appendix B.2.1 runs it.

A context encoder over the last k transitions (the same window, per-row MLP
and aggregation as every method here), trained by forward AND backward
one-step dynamics prediction: T_f(s, a, c) -> s' - s and T_b(s', a, c) ->
s - s', both diagonal Gaussians over standardised deltas, loss NLL_f +
beta * NLL_b with beta = ``backward_weight`` (0.5, Table 10). The context is
passed to the policy and to both models. As in CaDM's model-free variant no
policy gradient reaches the encoder (``context_critic_grad`` False; set it
True to ablate). Public code (younggyoseo/CaDM) predicts several steps
ahead over a concatenated, order-dependent history; here one step and a
permutation-invariant window, the aggregation choices shared by all methods.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from zeus_ros.core.methods.common import (EncoderMethod, EncoderSettings, gaussian_nll,
                                          ModelLoss)
from zeus_ros.core.networks import GaussianModel
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch


@dataclass(frozen=True)
class CadmSettings(EncoderSettings):
    """The learned-encoder settings plus the weight of CaDM's backward model."""

    backward_weight: float = setting(
        0.5, 'cadm: weight beta of the backward dynamics loss (Table 10).')

    def validate(self) -> 'CadmSettings':
        super().validate()
        if self.backward_weight < 0:
            raise ValueError('backward_weight must be >= 0')
        return self


class CadmMethod(EncoderMethod):
    """Encoder shaped by forward + beta * backward dynamics prediction."""

    name = 'cadm'
    settings_class = CadmSettings
    metric_names = ('dynamics_loss', 'backward_loss', 'decoder_loss')
    config_defaults = {'context_input': 'delta', 'context_critic_grad': False,
                       'backward_weight': 0.5}

    def build_models(self) -> dict[str, GaussianModel]:
        cfg, o, a = self.cfg, self.dims.obs_dim, self.dims.action_dim
        return {name: GaussianModel(o, a, cfg.context_dim, cfg.dynamics_hidden,
                                    cfg.dynamics_layers) for name in ('T_forward', 'T_backward')}

    def model_loss(self, b: Batch) -> ModelLoss:
        x, delta = self.standardised_step(b)
        # s' standardised like s (the row standardiser's statistics of s).
        o, norm = self.dims.obs_dim, self.psi.norm
        x_next = (b.next_obs - norm.mean[:o]) / (norm.var[:o].sqrt() + 1e-4)
        c = self.psi(b.ctx_rows, b.ctx_mask)
        forward = gaussian_nll(*self.models['T_forward'](x, b.action, c), delta)
        backward = gaussian_nll(*self.models['T_backward'](x_next, b.action, c), -delta)
        loss = forward + self.settings.backward_weight * backward
        return loss, c, {'dynamics_loss': forward.detach(), 'backward_loss': backward.detach()}
