"""Building blocks shared by the learned-encoder methods (zeus-id and the baselines).

* `RunningStandardiser`: per-feature mean/std of what psi reads, learned from
  the training batches and saved with the weights, so a deployed psi sees the
  same standardised inputs.
* `StandardisedContextEncoder`: standardise each window row (optionally as
  concat(s, a, r, s' - s)), encode it, pool the valid rows.
* `EncoderMethod`: psi + the method's own models trained by one optimiser on
  the method's loss, and a decoder probe on the DETACHED latent. Subclasses
  write `build_models` and `model_loss`; whether the critic's TD error also
  trains psi is the config's `context_critic_grad`.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from zeus_ros.core.methods.base import adam, ContextMethod
from zeus_ros.core.networks import ContextEncoder, ParamDecoder, weight_init


def safe_norm(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """L2 norm over the last axis with a finite gradient at 0."""
    return (x.pow(2).sum(-1) + eps).sqrt()


def w2_diag_gaussians(mu1, log_std1, mu2, log_std2) -> torch.Tensor:
    """2-Wasserstein distance between diagonal Gaussians (closed form), per row."""
    sq = (mu1 - mu2).pow(2).sum(-1) + (log_std1.exp() - log_std2.exp()).pow(2).sum(-1)
    return sq.sqrt()


def gaussian_nll(mu, log_std, target) -> torch.Tensor:
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


def transition_features(rows: torch.Tensor, obs_dim: int, delta: bool) -> torch.Tensor:
    """Window rows concat(s, a, r, s') -> concat(s, a, r, s' - s) when `delta`."""
    if not delta:
        return rows
    s, s_next = rows[..., :obs_dim], rows[..., -obs_dim:]
    return torch.cat([rows[..., :-obs_dim], s_next - s], dim=-1)


class StandardisedContextEncoder(nn.Module):
    """psi: standardised transition features -> per-row codes -> pooled over valid rows.

    With ``context_encoder='relational'`` each row is encoded together with its
    deviation from the window's mean row (over the valid rows): a code can then
    depend on how a transition differs from the others, so the pooled latent
    can carry how features co-vary within the window (e.g. whether the reward
    rises or falls with the speed), which a mean of independent per-row codes
    cannot. Still invariant to the order of the rows and to the padding.
    """

    def __init__(self, obs_dim: int, row_dim: int, cfg, out_dim: int | None = None):
        super().__init__()
        self.obs_dim = obs_dim
        self.delta = cfg.context_input == 'delta'
        self.relational = cfg.context_encoder == 'relational'
        self.norm = RunningStandardiser(row_dim)
        self.encoder = ContextEncoder(row_dim * (2 if self.relational else 1),
                                      out_dim or cfg.context_dim, cfg.context_hidden,
                                      cfg.context_layers, cfg.aggregation)

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """Return what psi reads of each row, before standardising."""
        return transition_features(rows, self.obs_dim, self.delta)

    def window_pair(self, chain_rows, chain_mask, grad: bool):
        """Both windows' latents from one pass over a chain (see ContextEncoder.window_pair).

        None for the relational encoder: a row's code depends on its window.
        """
        if self.relational:
            return None
        with torch.set_grad_enabled(grad):
            codes = self.encoder.codes(self.norm(self.features(chain_rows)))
        return self.encoder.window_pair(codes, chain_mask, grad)

    def forward(self, rows: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = self.norm(self.features(rows))
        if self.relational:
            valid = mask.unsqueeze(-1).to(x.dtype)
            mean = (x * valid).sum(1, keepdim=True) / valid.sum(1, keepdim=True).clamp(min=1.0)
            x = torch.cat([x, x - mean], dim=-1)
        return self.encoder.pool(self.encoder.codes(x), mask)


class EncoderMethod(ContextMethod):
    """psi over the window, the method's models, one optimiser on its loss, a decoder probe."""

    has_own_update = True
    has_decoder = True

    def __init__(self, cfg, dims, param, training=True):
        super().__init__(cfg, dims, param, training)
        self.psi = StandardisedContextEncoder(dims.obs_dim, dims.row_dim, cfg,
                                              self.encoder_dim)
        self.decoder = ParamDecoder(cfg.context_dim, cfg.decoder_hidden, param.param_dim) \
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

    def model_loss(self, b):
        """Return (loss, latent of the batch's windows, metrics) of the method's objective."""
        raise NotImplementedError

    # -- the plug-in interface -------------------------------------------------
    @property
    def encoder_dim(self) -> int:
        """Width of psi's output."""
        return self.cfg.context_dim

    @property
    def critic_trains_context(self) -> bool:
        return self.cfg.context_critic_grad

    @property
    def context_dim(self) -> int:
        return self.encoder_dim

    def inference_modules(self):
        return {'psi': self.psi, **({'decoder': self.decoder} if self.decoder else {})}

    def training_modules(self):
        return dict(self.models)

    def optimizers(self):
        opts = {'model_opt': self.model_opt}
        if self.decoder is not None:
            opts['decoder_opt'] = self.decoder_opt
        return opts

    def encoder_parameters(self):
        return list(self.psi.parameters())

    def encode(self, rows, mask, param):
        return self.psi(rows, mask)

    def encode_pair(self, batch, grad):
        pair = self.psi.window_pair(batch.chain_rows, batch.chain_mask, grad)
        return pair if pair is not None else super().encode_pair(batch, grad)

    def decode(self, latent):
        return self.decoder(latent)

    def standardised_step(self, b):
        """Standardised s and s' - s of the batch's own transitions (no gradient)."""
        o = self.dims.obs_dim
        row = torch.cat([b.obs, b.action, b.reward[:, None], b.next_obs], dim=-1)
        feats = self.psi.norm(self.psi.features(row))
        if self.psi.delta:
            return feats[:, :o], feats[:, -o:]
        delta = b.next_obs - b.obs   # raw-row ablation: scale the delta by its batch std
        return feats[:, :o], delta / (delta.std(0) + 1e-4)

    def update(self, batch, z, step):
        valid_rows = batch.ctx_rows[batch.ctx_mask]
        if valid_rows.shape[0] > 1:
            self.psi.norm.observe(self.psi.features(valid_rows))
        loss, c, metrics = self.model_loss(batch)
        decoder_loss = None
        if self.decoder is not None:
            # id_weight > 0: the regression also shapes psi (privileged, as UP-OSI's OSI);
            # 0: the decoder is a probe on the detached latent.
            read = c if self.cfg.id_weight > 0 else c.detach()
            decoder_loss = F.mse_loss(self.decoder(read), self.param.normalise(batch.param))
            loss = loss + self.cfg.id_weight * decoder_loss if self.cfg.id_weight > 0 \
                else loss
            metrics['decoder_loss'] = decoder_loss.detach()
        self._step(loss, decoder_loss)
        return metrics

    def _step(self, loss, decoder_loss) -> None:
        self.model_opt.zero_grad(set_to_none=True)
        if decoder_loss is None:
            loss.backward()
            self.model_opt.step()
            return
        self.decoder_opt.zero_grad(set_to_none=True)
        if self.cfg.id_weight > 0:
            loss.backward()            # includes id_weight * decoder loss
            # the decoder learns at its own rate from the unweighted loss's gradient
            for p in self.decoder.parameters():
                if p.grad is not None:
                    p.grad.div_(self.cfg.id_weight)
        else:
            loss.backward()
            decoder_loss.backward()
        self.model_opt.step()
        self.decoder_opt.step()
