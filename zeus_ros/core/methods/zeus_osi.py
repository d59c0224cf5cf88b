"""`zeus-osi`: zeus-id with UP-OSI's read-out of the parameter (this project, beyond the paper).

Measured on cheetah-run-v0 (`research/results/cross_reader.md`, three seeds of
each): the up-osi baseline's OSI network reads the held-out torso lengths
from zeus-id's OWN episodes at R^2 0.88-0.96, while zeus-id's decoder reads
them at 0.81-0.88. zeus-id's windows carry the length; its read-out loses
part of it. OSI's read-out is the mean over the window of per-transition
estimates (psi's last layer is linear and its output IS the normalised
parameter); zeus-id's is an MLP decoder of the pooled 16-d latent, which
saturates outside the training range.

So this variant keeps everything of zeus-id (k = 25, delta inputs, no critic
gradient into psi, raw-dynamics models, the normalised task metric) and
changes only the read-out: the first P coordinates of psi's latent are the
estimate of the P normalised parameters, regressed by MSE through psi with
``id_weight``; there is no decoder. The policy and the models read the whole
latent, estimate included. Ablations: ``--method zeus-id`` is the same
method with the decoder read-out; ``--set context_length=5`` OSI's window.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch.nn.functional as F

from zeus_ros.core.methods.common import ModelLoss
from zeus_ros.core.methods.zeus_id import ZeusIdMethod

if TYPE_CHECKING:
    import torch

    from zeus_ros.core.methods.base import Dims, MethodConfig, ParamScale
    from zeus_ros.core.replay import Batch


class ZeusOsiMethod(ZeusIdMethod):
    """zeus-id whose latent's first P coordinates are the parameter estimate itself."""

    name = 'zeus-osi'
    has_decoder = False

    def __init__(self, cfg: MethodConfig, dims: Dims, param: ParamScale,
                 training: bool = True):
        if cfg.method_settings.id_weight <= 0:
            raise ValueError('zeus-osi reads its estimate from the latent: it needs '
                             'id_weight > 0 (the regression that makes those coordinates '
                             'the parameter)')
        if cfg.context_dim <= param.param_dim:
            raise ValueError(f'zeus-osi needs context_dim > {param.param_dim} (the estimate '
                             'plus at least one free coordinate)')
        super().__init__(cfg, dims, param, training)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return latent[..., :self.param.param_dim]

    def model_loss(self, b: Batch, perm: torch.Tensor | None = None) -> ModelLoss:
        """zeus-id's loss plus id_weight * MSE(first P latent coordinates, parameter)."""
        loss, c, metrics = super().model_loss(b, perm)
        id_loss = F.mse_loss(self.decode(c), self.param.normalise(b.param))
        # The read-out's regression loss, under the name zeus-id's decoder logs it: the two
        # read-outs compare in one column (read by
        # research/analysis/target_velocity_identifiability.py).
        metrics['decoder_loss'] = id_loss.detach()
        return loss + self.settings.id_weight * id_loss, c, metrics
