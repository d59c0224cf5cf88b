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

from zeus_ros.core.methods.common import EncoderMethod, gaussian_nll
from zeus_ros.core.networks import GaussianModel


class CadmMethod(EncoderMethod):
    """Encoder shaped by forward + beta * backward dynamics prediction."""

    name = 'cadm'
    config_defaults = {'context_input': 'delta', 'context_critic_grad': False,
                       'backward_weight': 0.5}

    def build_models(self):
        cfg, o, a = self.cfg, self.dims.obs_dim, self.dims.action_dim
        return {name: GaussianModel(o, a, cfg.context_dim, cfg.dynamics_hidden,
                                    cfg.dynamics_layers) for name in ('T_forward', 'T_backward')}

    def model_loss(self, b):
        x, delta = self.standardised_step(b)
        # s' standardised like s (the row standardiser's statistics of s).
        o, norm = self.dims.obs_dim, self.psi.norm
        x_next = (b.next_obs - norm.mean[:o]) / (norm.var[:o].sqrt() + 1e-4)
        c = self.psi(b.ctx_rows, b.ctx_mask)
        forward = gaussian_nll(*self.models['T_forward'](x, b.action, c), delta)
        backward = gaussian_nll(*self.models['T_backward'](x_next, b.action, c), -delta)
        loss = forward + self.cfg.backward_weight * backward
        return loss, c, {'dynamics_loss': forward.detach(), 'backward_loss': backward.detach()}
