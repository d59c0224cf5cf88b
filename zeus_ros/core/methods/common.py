"""Building blocks shared by the learned-encoder methods (zeus-id and the baselines).

* `RunningStandardiser`: per-feature mean/std of what psi reads, learned from
  the training batches and saved with the weights, so a deployed psi sees the
  same standardised inputs.
* `StandardisedContextEncoder`: standardise each window row (optionally as
  concat(s, a, r, s' - s)), encode it, pool the valid rows.
* `EncoderMethod`: psi + the method's own models trained by one optimiser on
  the method's loss, and a decoder probe on the DETACHED latent. Subclasses
  write `build_models` and `model_loss`; whether the critic's TD error also
  trains psi is their settings' `context_critic_grad`.
* `EncoderSettings`: what every learned-encoder method reads and the paper's
  `zeus` does not; each method's own settings extend it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn
import torch.nn.functional as F

from zeus_ros.core.methods.base import (adam, ContextMethod, Dims, MethodConfig, MethodSettings,
                                        ParamScale)
from zeus_ros.core.networks import ContextEncoder, ParamDecoder, weight_init
from zeus_ros.core.settings import setting

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch

CONTEXT_INPUTS = ('transition', 'delta')
CONTEXT_ENCODERS = ('deepset', 'relational', 'temporal')
# What a method's model_loss returns: (loss, latent of the batch's windows, metrics).
ModelLoss = tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]


@dataclass(frozen=True)
class EncoderSettings(MethodSettings):
    """What every learned-encoder method reads (zeus-id, zeus-osi, cadm, up-osi, ...)."""

    context_input: str = setting(
        'transition', "What psi reads per row: 'transition' = concat(s, a, r, s'), "
        "'delta' = concat(s, a, r, s' - s); both standardised by running statistics.",
        choices=CONTEXT_INPUTS)
    context_encoder: str = setting(
        'deepset', "psi's shape: 'deepset' = pooled per-row codes; 'relational' = each row "
        'also reads its deviation from the window mean (codes can depend on how transitions '
        "co-vary); 'temporal' = 1-D convolutions over the window in order (RMA's adaptation "
        'module).', choices=CONTEXT_ENCODERS)
    context_critic_grad: bool = setting(
        True, "Let the critic's TD loss train psi (zeus, not one of these, always does).")
    context_reward: bool = setting(
        True, 'Let psi read the reward column of its rows; false = it never does, so the '
        'context can be computed on a robot that reports no reward (a ros2_control robot, '
        'context_node action_source commands): the same context, bit for bit (#49).')
    id_weight: float = setting(
        0.0, 'Weight of the parameter-regression loss THROUGH psi (privileged supervision in '
        'training, as UP-OSI; 0 = the decoder reads a detached latent, a pure probe).')

    def validate(self) -> 'EncoderSettings':
        if self.context_input not in CONTEXT_INPUTS:
            raise ValueError("context_input must be 'transition' or 'delta'")
        if self.context_encoder not in CONTEXT_ENCODERS:
            raise ValueError("context_encoder must be 'deepset', 'relational' or 'temporal'")
        if self.id_weight < 0:
            raise ValueError('id_weight must be >= 0')
        return self


def safe_norm(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """L2 norm over the last axis with a finite gradient at 0."""
    return (x.pow(2).sum(-1) + eps).sqrt()


def w2_diag_gaussians(mu1: torch.Tensor, log_std1: torch.Tensor, mu2: torch.Tensor,
                      log_std2: torch.Tensor) -> torch.Tensor:
    """2-Wasserstein distance between diagonal Gaussians (closed form), per row."""
    sq = (mu1 - mu2).pow(2).sum(-1) + (log_std1.exp() - log_std2.exp()).pow(2).sum(-1)
    return sq.sqrt()


def gaussian_nll(mu: torch.Tensor, log_std: torch.Tensor,
                 target: torch.Tensor) -> torch.Tensor:
    """Mean over the batch of the diagonal-Gaussian negative log-likelihood (no constant)."""
    diff = (target - mu) / log_std.exp()
    return (0.5 * diff.pow(2) + log_std).sum(-1).mean()


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


def transition_features(rows: torch.Tensor, obs_dim: int, delta: bool,
                        reward: bool = True) -> torch.Tensor:
    """Window rows concat(s, a, r, s') -> concat(s, a, r, s' - s) when `delta`.

    Without `reward` the r column is left out: never read, so an unknown reward
    (NaN) changes nothing.
    """
    head = rows[..., :-obs_dim] if reward else rows[..., :-obs_dim - 1]
    s, s_next = rows[..., :obs_dim], rows[..., -obs_dim:]
    return torch.cat([head, s_next - s if delta else s_next], dim=-1)


class StandardisedContextEncoder(nn.Module):
    """psi: standardised transition features -> per-row codes -> pooled over valid rows.

    With ``context_encoder='relational'`` each row is encoded together with its
    deviation from the window's mean row (over the valid rows): a code can then
    depend on how a transition differs from the others, so the pooled latent
    can carry how features co-vary within the window (e.g. whether the reward
    rises or falls with the speed), which a mean of independent per-row codes
    cannot. Still invariant to the order of the rows and to the padding.
    """

    def __init__(self, obs_dim: int, row_dim: int, cfg: MethodConfig, settings: EncoderSettings,
                 out_dim: int | None = None):
        super().__init__()
        self.obs_dim = obs_dim
        self.delta = settings.context_input == 'delta'
        self.reward = settings.context_reward
        self.relational = settings.context_encoder == 'relational'
        row_dim = row_dim if self.reward else row_dim - 1   # the features psi reads
        self.norm = RunningStandardiser(row_dim)
        if settings.context_encoder == 'temporal':
            self.encoder = TemporalConvEncoder(row_dim, out_dim or cfg.context_dim,
                                               cfg.context_hidden, cfg.context_layers)
            return
        self.encoder = ContextEncoder(row_dim * (2 if self.relational else 1),
                                      out_dim or cfg.context_dim, cfg.context_hidden,
                                      cfg.context_layers, cfg.aggregation)

    @property
    def temporal(self) -> bool:
        """True when psi reads the window in order (a temporal convolution)."""
        return isinstance(self.encoder, TemporalConvEncoder)

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """Return what psi reads of each row, before standardising."""
        return transition_features(rows, self.obs_dim, self.delta, self.reward)

    def window_pair(self, chain_rows: torch.Tensor, chain_mask: torch.Tensor,
                    grad: bool) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Both windows' latents from one pass over a chain (see ContextEncoder.window_pair).

        None for the relational and temporal encoders: a row's code depends on its window.
        """
        if self.relational or self.temporal:
            return None
        with torch.set_grad_enabled(grad):
            codes = self.encoder.codes(self.norm(self.features(chain_rows)))
        return self.encoder.window_pair(codes, chain_mask, grad)

    def forward(self, rows: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = self.norm(self.features(rows))
        if self.temporal:
            return self.encoder(x, mask)
        if self.relational:
            valid = mask.unsqueeze(-1).to(x.dtype)
            mean = (x * valid).sum(1, keepdim=True) / valid.sum(1, keepdim=True).clamp(min=1.0)
            x = torch.cat([x, x - mean], dim=-1)
        return self.encoder.pool(self.encoder.codes(x), mask)


class TemporalConvEncoder(nn.Module):
    """RMA's adaptation-module shape: per-step embedding, 1-D convolutions over time, pooling.

    Unlike the deep sets it reads the window in order, so it can use how the
    state evolves from one transition to the next. Padding rows (mask False)
    are zeroed before and after every convolution and left out of the mean
    over time, so the latent does not depend on what the padding holds.
    An empty window gives the head's bias (the latent of "no evidence").
    """

    KERNEL = 5

    def __init__(self, row_dim: int, out_dim: int, hidden: int, layers: int):
        super().__init__()
        self.embed = nn.Linear(row_dim, hidden)
        self.convs = nn.ModuleList(
            nn.Conv1d(hidden, hidden, self.KERNEL, padding=self.KERNEL // 2)
            for _ in range(max(layers, 1)))
        self.head = nn.Linear(hidden, out_dim)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.to(x.dtype).unsqueeze(1)                        # [B, 1, k]
        h = F.relu(self.embed(x)).transpose(1, 2) * m            # [B, hidden, k]
        for conv in self.convs:
            h = F.relu(conv(h)) * m
        pooled = h.sum(-1) / m.sum(-1).clamp(min=1.0)
        return self.head(pooled)


class EncoderMethod(ContextMethod):
    """psi over the window, the method's models, one optimiser on its loss, a decoder probe."""

    has_own_update = True
    has_decoder = True
    settings_class = EncoderSettings

    def __init__(self, cfg: MethodConfig, dims: Dims, param: ParamScale,
                 training: bool = True):
        super().__init__(cfg, dims, param, training)
        self.psi = StandardisedContextEncoder(dims.obs_dim, dims.row_dim, cfg, self.settings,
                                              self.encoder_dim)
        self.decoder = ParamDecoder(self.encoder_dim, cfg.decoder_hidden, param.param_dim) \
            if self.has_decoder else None
        if not training:
            return
        self.models = self.build_models()
        for m in (self.psi, *self.models.values(), *([self.decoder] if self.decoder else [])):
            m.apply(weight_init)
        self.model_opt = adam(
            [*self.psi.parameters(), *(p for m in self.models.values() for p in m.parameters())],
            lr=cfg.model_lr)
        if self.decoder is not None:
            self.decoder_opt = adam(self.decoder.parameters(), lr=cfg.decoder_lr)

    # -- what subclasses write ---------------------------------------------------
    def build_models(self) -> dict[str, nn.Module]:
        """Build the method's training-only networks, by checkpoint prefix."""
        return {}

    def model_loss(self, b: Batch) -> ModelLoss:
        """Return (loss, latent of the batch's windows, metrics) of the method's objective."""
        raise NotImplementedError

    # -- the plug-in interface -------------------------------------------------
    @property
    def encoder_dim(self) -> int:
        """Width of psi's output."""
        return self.cfg.context_dim

    @property
    def critic_trains_context(self) -> bool:
        return self.settings.context_critic_grad

    @property
    def context_dim(self) -> int:
        return self.encoder_dim

    def inference_modules(self) -> dict[str, nn.Module]:
        return {'psi': self.psi, **({'decoder': self.decoder} if self.decoder else {})}

    def training_modules(self) -> dict[str, nn.Module]:
        return dict(self.models)

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        opts = {'model_opt': self.model_opt}
        if self.decoder is not None:
            opts['decoder_opt'] = self.decoder_opt
        return opts

    def encoder_parameters(self) -> list[nn.Parameter]:
        return list(self.psi.parameters())

    def encode(self, rows: torch.Tensor, mask: torch.Tensor,
               param: torch.Tensor | None) -> torch.Tensor:  # noqa: ARG002 (ContextMethod's signature)
        return self.psi(rows, mask)

    def encode_pair(self, batch: Batch, grad: bool) -> tuple[torch.Tensor, torch.Tensor]:
        pair = self.psi.window_pair(batch.chain_rows, batch.chain_mask, grad)
        return pair if pair is not None else super().encode_pair(batch, grad)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return self.decoder(latent)

    def standardised_step(self, b: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """Standardised s and s' - s of the batch's own transitions (no gradient)."""
        o = self.dims.obs_dim
        row = torch.cat([b.obs, b.action, b.reward[:, None], b.next_obs], dim=-1)
        feats = self.psi.norm(self.psi.features(row))
        if self.psi.delta:
            return feats[:, :o], feats[:, -o:]
        delta = b.next_obs - b.obs   # raw-row ablation: scale the delta by its batch std
        return feats[:, :o], delta / (delta.std(0) + 1e-4)

    def update(self, batch: Batch, z: torch.Tensor, step: int,  # noqa: ARG002 (ContextMethod's signature)
               ) -> dict[str, torch.Tensor]:
        valid_rows = batch.ctx_rows[batch.ctx_mask]
        if valid_rows.shape[0] > 1:
            self.psi.norm.observe(self.psi.features(valid_rows))
        loss, c, metrics = self.model_loss(batch)
        decoder_loss = None
        if self.decoder is not None:
            # id_weight > 0: the regression also shapes psi (privileged, as UP-OSI's OSI);
            # 0: the decoder is a probe on the detached latent.
            weight = self.settings.id_weight
            read = c if weight > 0 else c.detach()
            decoder_loss = F.mse_loss(self.decoder(read), self.param.normalise(batch.param))
            if weight > 0:
                loss = loss + weight * decoder_loss
            metrics['decoder_loss'] = decoder_loss.detach()
        self._step(loss, decoder_loss)
        return metrics

    def _step(self, loss: torch.Tensor, decoder_loss: torch.Tensor | None) -> None:
        self.model_opt.zero_grad(set_to_none=True)
        if decoder_loss is None:
            loss.backward()
            self.model_opt.step()
            return
        self.decoder_opt.zero_grad(set_to_none=True)
        if self.settings.id_weight > 0:
            loss.backward()            # includes id_weight * decoder loss
            # the decoder learns at its own rate from the unweighted loss's gradient
            for p in self.decoder.parameters():
                if p.grad is not None:
                    p.grad.div_(self.settings.id_weight)
        else:
            loss.backward()
            decoder_loss.backward()
        self.model_opt.step()
        self.decoder_opt.step()
