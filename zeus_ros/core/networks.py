"""Plain-torch networks of ZeUS: phi, psi, T, R, SAC actor and twin critic, decoder.

Shapes: observations [B, obs_dim]; context windows rows [B, k, row_dim] with
mask [B, k] (see `zeus_ros.core.window`); actions in [-1, 1].
"""

from __future__ import annotations

import math

import torch
from torch import nn
import torch.nn.functional as F


def mlp(in_dim: int, hidden: int, out_dim: int, layers: int) -> nn.Sequential:
    """ReLU MLP with `layers` hidden layers (0 = a single linear map)."""
    mods, d = [], in_dim
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU()]
        d = hidden
    mods.append(nn.Linear(d, out_dim))
    return nn.Sequential(*mods)


def run_mlp(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """Apply an `mlp()` network layer by layer through torch.nn.functional.

    The same kernels on the same parameters as `net(x)`, so bit-identical, but
    without a Module call per layer: at batch size 1 (the ROS nodes) that
    per-call overhead is most of the cost.
    """
    for layer in net:
        x = F.linear(x, layer.weight, layer.bias) if isinstance(layer, nn.Linear) else F.relu(x)
    return x


def weight_init(module: nn.Module) -> None:
    """Orthogonal weights and zero biases for linear layers (SAC-AE convention)."""
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight.data)
        module.bias.data.fill_(0.0)


class ObsEncoder(nn.Module):
    """Phi: observation -> latent state (MLP, LayerNorm, tanh as in SAC-AE's head)."""

    def __init__(self, obs_dim: int, feature_dim: int, hidden: int, layers: int):
        super().__init__()
        self.net = mlp(obs_dim, hidden, feature_dim, layers)
        self.norm = nn.LayerNorm(feature_dim)
        self.feature_dim = feature_dim

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.norm(run_mlp(self.net, obs)))


class ContextEncoder(nn.Module):
    """Psi: window of transitions -> latent context.

    Each transition row is encoded by the same MLP, then the codes of the
    valid rows (mask True) are aggregated with a permutation-invariant
    operator: mean (default), sum or max. An empty window (no valid row)
    gives the zero vector for every operator.
    """

    def __init__(self, row_dim: int, context_dim: int, hidden: int, layers: int,
                 aggregation: str = 'mean'):
        super().__init__()
        if aggregation not in ('mean', 'sum', 'max'):
            raise ValueError(f'unknown aggregation {aggregation!r}')
        self.net = mlp(row_dim, hidden, context_dim, layers)
        self.aggregation = aggregation
        self.context_dim = context_dim

    def forward(self, rows: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.pool(self.codes(rows), mask)

    def codes(self, rows: torch.Tensor) -> torch.Tensor:
        """Per-transition codes [..., context_dim] before aggregation."""
        return run_mlp(self.net, rows)

    def window_pair(self, codes: torch.Tensor, chain_mask: torch.Tensor,
                    grad: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Pool a chain's codes [B, k+1, C] (newest first) into the two windows it holds.

        The window before the oldest transition's successor (rows 1..k, keeping
        the graph when `grad`) and the one ending with the newest (rows 0..k-1,
        detached): the same latents `forward` gives of the two windows, up to
        the order of the floating-point sum.
        """
        with torch.set_grad_enabled(grad):
            current = self.pool(codes[:, 1:], chain_mask[:, 1:])
        with torch.no_grad():
            following = self.pool(codes[:, :-1].detach(), chain_mask[:, :-1])
        return current, following

    def pool(self, codes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Aggregate codes [B, k, C] over the valid rows of `mask` [B, k]."""
        m = mask.to(codes.dtype).unsqueeze(-1)  # [B, k, 1]
        count = m.sum(dim=1)  # [B, 1]
        if self.aggregation == 'max':
            filled = codes.masked_fill(~mask.unsqueeze(-1), -math.inf)
            pooled = filled.max(dim=1).values
            return torch.where(count > 0, pooled, torch.zeros_like(pooled))
        total = (codes * m).sum(dim=1)
        if self.aggregation == 'sum':
            return total
        return total / count.clamp(min=1.0)


class GaussianModel(nn.Module):
    """T: (phi(s), a, psi) -> mean and log-std of phi(s') (diagonal Gaussian)."""

    log_std_min = -5.0
    log_std_max = 2.0

    def __init__(self, feature_dim: int, action_dim: int, context_dim: int, hidden: int,
                 layers: int):
        super().__init__()
        self.net = mlp(feature_dim + action_dim + context_dim, hidden, 2 * feature_dim, layers)

    def forward(self, z: torch.Tensor, a: torch.Tensor,
                c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, log_std = run_mlp(self.net, torch.cat([z, a, c], dim=-1)).chunk(2, dim=-1)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (
            torch.tanh(log_std) + 1.0)
        return mu, log_std


class RewardModel(nn.Module):
    """R: (phi(s), a, psi) -> predicted reward."""

    def __init__(self, feature_dim: int, action_dim: int, context_dim: int, hidden: int,
                 layers: int):
        super().__init__()
        self.net = mlp(feature_dim + action_dim + context_dim, hidden, 1, layers)

    def forward(self, z: torch.Tensor, a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return run_mlp(self.net, torch.cat([z, a, c], dim=-1)).squeeze(-1)


class Actor(nn.Module):
    """Tanh-Gaussian policy on concat(phi(s), psi(H)); log-std squashed into bounds."""

    def __init__(self, in_dim: int, action_dim: int, hidden: int, layers: int,
                 log_std_min: float, log_std_max: float):
        super().__init__()
        self.net = mlp(in_dim, hidden, 2 * action_dim, layers)
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, log_std = run_mlp(self.net, x).chunk(2, dim=-1)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (
            torch.tanh(log_std) + 1.0)
        return mu, log_std

    def mean_action(self, x: torch.Tensor) -> torch.Tensor:
        """Deterministic action tanh(mu)."""
        mu, _ = self(x)
        return torch.tanh(mu)

    def sample(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reparameterised sample: (action, log_prob[B], tanh(mu))."""
        mu, log_std = self(x)
        std = log_std.exp()
        noise = torch.randn_like(mu)
        pre = mu + noise * std
        action = torch.tanh(pre)
        log_prob = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        # Tanh change of variables, in the numerically stable softplus form.
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))).sum(-1)
        return action, log_prob, torch.tanh(mu)


class Critic(nn.Module):
    """Twin Q heads on concat(phi(s), psi(H), a)."""

    def __init__(self, in_dim: int, action_dim: int, hidden: int, layers: int):
        super().__init__()
        self.q1 = mlp(in_dim + action_dim, hidden, 1, layers)
        self.q2 = mlp(in_dim + action_dim, hidden, 1, layers)

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        xa = torch.cat([x, a], dim=-1)
        return self.q1(xa).squeeze(-1), self.q2(xa).squeeze(-1)


class ParamDecoder(nn.Module):
    """Reads the (normalised) physical parameter from a latent context.

    The caller passes a DETACHED latent during training, so the decoder can
    never shape psi; it is a probe and a deployment-time estimate only.
    """

    def __init__(self, context_dim: int, hidden: int, param_dim: int = 1):
        super().__init__()
        self.net = mlp(context_dim, hidden, param_dim, 1)

    def forward(self, c: torch.Tensor) -> torch.Tensor:
        """Normalised estimates [B, param_dim]."""
        return run_mlp(self.net, c)
