"""`rma`: Rapid Motor Adaptation (Kumar et al., RSS 2021), its two phases in one run.

* Phase 1, the teacher: the actor and critic see privileged extrinsics
  z = mu(e), e the normalised true parameter, and mu is trained end to end by
  the critic's TD loss (as the paper trains it with the policy's loss); the
  actor reads z detached, as every method's latent here.
* Phase 2, the adaptation module: psi over the last k transitions, by
  default a 1-D temporal convolution (`context_encoder='temporal'`, RMA's
  shape), regresses z (detached: it never moves the teacher) by MSE on the
  replay's windows.
* Its own rollouts: the first ``rma_student_after_updates`` updates collect
  with the teacher's z; later ones act on psi's estimate, so the replay
  fills with the states the policy reaches when it acts on its own
  estimates, the data RMA trains its adaptation module on.
* Deployment: the latent is psi's estimate; the decoder (a probe trained on
  that estimate, detached) gives the parameter the context node publishes.
* `rma_asymmetric=True` (this project's, not RMA's): after the switch the
  actor's losses read psi's estimate, the critic the teacher's z, so the
  policy learns what to do with the estimate it will deploy with (hedging,
  or moving to learn more) rather than with a perfect one.
* `rma_latent=False` is the raw-parameter ablation: z = e, no mu, nothing
  for the critic to shape (UP-OSI's target with RMA's switch and encoder).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from zeus_ros.core.methods.base import ContextMethod, Dims, MethodConfig, ParamScale
from zeus_ros.core.methods.common import EncoderMethod, EncoderSettings, ModelLoss
from zeus_ros.core.networks import mlp, run_mlp, weight_init
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch


@dataclass(frozen=True)
class RmaSettings(EncoderSettings):
    """The learned-encoder settings plus RMA's teacher and when its student acts."""

    rma_student_after_updates: int = setting(
        10_000, 'rma: updates that collect with the teacher (the privileged extrinsics); '
        "later ones act on the adaptation module's estimate, so it learns on the states its "
        'own estimates lead to (RMA phase 2 on its own rollouts).')
    rma_latent: bool = setting(
        True, 'rma: the teacher sees extrinsics z = mu(parameter) learned by the critic '
        '(RMA); false = the normalised parameter itself (the raw-parameter ablation).')

    rma_asymmetric: bool = setting(
        False, "rma: once the student acts, the actor reads the adaptation module's estimate "
        'in its losses too, while the critic keeps the teacher latent (an asymmetric '
        'actor-critic; not in RMA): the policy learns to act on what it has when deployed.')

    def validate(self) -> 'RmaSettings':
        super().validate()
        if self.rma_student_after_updates < 0:
            raise ValueError('rma_student_after_updates must be >= 0')
        return self


class RmaMethod(EncoderMethod):
    """Teacher latent mu(parameter) in training; the adaptation module's estimate deployed."""

    name = 'rma'
    # RMA's sizes: 50 past steps, 8 extrinsics, 32 channels in its adaptation module
    # (128 made an update over 50-step windows ten times slower than sac's on a CPU).
    config_defaults = {'context_input': 'delta', 'context_critic_grad': False,
                       'context_encoder': 'temporal', 'context_length': 50,
                       'context_dim': 8, 'context_hidden': 32}
    settings_class = RmaSettings
    metric_names = ('adaptation_loss', 'decoder_loss')

    def __init__(self, cfg: MethodConfig, dims: Dims, param: ParamScale,
                 training: bool = True):
        super().__init__(cfg, dims, param, training)
        # Built in both modes: deployed weights carry mu, so a report can act as the teacher.
        self.mu = mlp(param.param_dim, cfg.decoder_hidden, cfg.context_dim, 1) \
            if self.settings.rma_latent else None
        if self.mu is not None and training:
            self.mu.apply(weight_init)
        self.updates = 0

    @property
    def encoder_dim(self) -> int:
        return self.cfg.context_dim if self.settings.rma_latent else self.param.param_dim

    @property
    def critic_trains_context(self) -> bool:
        return self.mu is not None

    def encoder_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.mu is None else list(self.mu.parameters())

    def inference_modules(self) -> dict[str, torch.nn.Module]:
        return {**super().inference_modules(), **({'mu': self.mu} if self.mu else {})}

    def teacher(self, param: torch.Tensor) -> torch.Tensor:
        """Return the privileged extrinsics z of true parameters [B, P] (physical units)."""
        e = self.param.normalise(self.param.as_rows(param))
        return e if self.mu is None else run_mlp(self.mu, e)

    def encode(self, rows: torch.Tensor, mask: torch.Tensor,  # noqa: ARG002 (ContextMethod's signature)
               param: torch.Tensor | None) -> torch.Tensor:
        if param is None:
            raise ValueError('the rma teacher is trained on the true parameter: pass it')
        return self.teacher(param)

    # In training the latent is the teacher's, not psi's: no codes to share.
    encode_pair = ContextMethod.encode_pair

    def acting_context(self, rows: torch.Tensor, mask: torch.Tensor,
                       param: torch.Tensor | None) -> torch.Tensor:
        if param is not None and self.updates < self.settings.rma_student_after_updates:
            return self.encode(rows, mask, param)
        return self.psi(rows, mask)

    def deployed_context(self, rows: torch.Tensor, mask: torch.Tensor,
                         param: torch.Tensor | None) -> torch.Tensor:  # noqa: ARG002 (ContextMethod's signature)
        return self.psi(rows, mask)

    def actor_context(self, batch: Batch, critic_latent: torch.Tensor,
                      following: bool = False) -> torch.Tensor:
        if not (self.settings.rma_asymmetric
                and self.updates >= self.settings.rma_student_after_updates):
            return critic_latent
        with torch.no_grad():   # the actor's loss never trains psi
            if following:
                return self.psi(batch.next_ctx_rows, batch.next_ctx_mask)
            return self.psi(batch.ctx_rows, batch.ctx_mask)

    def model_loss(self, b: Batch) -> ModelLoss:
        estimate = self.psi(b.ctx_rows, b.ctx_mask)
        loss = F.mse_loss(estimate, self.teacher(b.param).detach())
        return loss, estimate, {'adaptation_loss': loss.detach()}

    def update(self, batch: Batch, z: torch.Tensor, step: int) -> dict[str, torch.Tensor]:
        self.updates = step   # the agent's update count: a resumed run stays in its phase
        return super().update(batch, z, step)
