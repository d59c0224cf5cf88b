"""`up-osi`: Universal Policy + Online System Identification (Yu et al. 2017), appendix B.2.1.

* UP: actor and critic see the TRUE parameter, min-max normalised (as the
  oracle) in every training update.
* OSI: psi over the last k transitions (s, a, r, s') regressing the
  normalised parameter (MSE), trained on the replay's windows; no policy
  gradient reaches it.
* Collection: the first ``osi_warmup_updates`` updates act on the true
  parameter, later ones on OSI's estimate (the paper's 3-5 of 500 iterations,
  scaled to the number of updates), so OSI also learns on the states the
  policy visits when it acts on its own estimates.
* Deployment ("UP-inferred"): the latent is OSI's estimate, which is also the
  decoded parameter; a deployed UP-OSI needs no true parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch.nn.functional as F

from zeus_ros.core.methods.base import ContextMethod, Dims, MethodConfig, ParamScale
from zeus_ros.core.methods.common import EncoderMethod, EncoderSettings, ModelLoss
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    import torch

    from zeus_ros.core.replay import Batch


@dataclass(frozen=True)
class UpOsiSettings(EncoderSettings):
    """The learned-encoder settings plus how long UP collects before OSI acts."""

    osi_warmup_updates: int = setting(
        800, 'up-osi: updates that collect with the true parameter before OSI acts '
        '(the paper: 3-5 of 500 iterations; 4/500 of 100k updates).')

    def validate(self) -> 'UpOsiSettings':
        super().validate()
        if self.osi_warmup_updates < 0:
            raise ValueError('osi_warmup_updates must be >= 0')
        return self


class UpOsiMethod(EncoderMethod):
    """Context = true parameter in training, OSI's estimate when acting on its own."""

    name = 'up-osi'
    has_decoder = False
    config_defaults = {'context_input': 'delta', 'context_critic_grad': False}
    settings_class = UpOsiSettings
    metric_names = ('osi_loss',)

    def __init__(self, cfg: MethodConfig, dims: Dims, param: ParamScale,
                 training: bool = True):
        super().__init__(cfg, dims, param, training)
        self.updates = 0

    @property
    def encoder_dim(self) -> int:
        return self.param.param_dim

    @property
    def critic_trains_context(self) -> bool:
        return False

    def encode(self, rows: torch.Tensor, mask: torch.Tensor,  # noqa: ARG002 (ContextMethod's signature)
               param: torch.Tensor | None) -> torch.Tensor:
        if param is None:
            raise ValueError('UP is trained on the true parameter: pass it')
        return self.param.normalise(self.param.as_rows(param))

    # In training the latent is the true parameter, not psi's: no codes to share.
    encode_pair = ContextMethod.encode_pair

    def acting_context(self, rows: torch.Tensor, mask: torch.Tensor,
                       param: torch.Tensor | None) -> torch.Tensor:
        if param is not None and self.updates < self.settings.osi_warmup_updates:
            return self.encode(rows, mask, param)
        return self.psi(rows, mask)

    def deployed_context(self, rows: torch.Tensor, mask: torch.Tensor,
                         param: torch.Tensor | None) -> torch.Tensor:  # noqa: ARG002 (ContextMethod's signature)
        return self.psi(rows, mask)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return latent

    def model_loss(self, b: Batch) -> ModelLoss:
        estimate = self.psi(b.ctx_rows, b.ctx_mask)
        loss = F.mse_loss(estimate, self.param.normalise(b.param))
        return loss, estimate, {'osi_loss': loss.detach()}

    def update(self, batch: Batch, z: torch.Tensor, step: int) -> dict[str, torch.Tensor]:
        self.updates = step   # the agent's update count: a resumed run keeps its warm-up done
        return super().update(batch, z, step)
