"""The plug-in interface: how a method obtains and trains the context the policy sees.

The SAC core (`zeus_ros.core.agent.Agent`) owns phi, the actor, the twin
critic and their targets. Everything about the context belongs to a
`ContextMethod`: its networks (split into those a deployed policy needs and
those only training needs), its optimisers, how a latent is computed from a
window (or from the true parameter, for privileged references), whether the
critic's TD error may shape it, its own losses, and how a physical-parameter
estimate is read from a latent. A new method is a module in this package that
subclasses `ContextMethod` and registers itself in `METHODS`; the trainer,
the checkpoint code and the nodes need no change. Settings only the method
reads go in its own `MethodSettings` subclass (`settings_class`), not in the
shared config; the metrics its `update` returns are named in `metric_names`
(the train log's columns).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Iterable, Protocol, Sequence, TYPE_CHECKING

import numpy as np
import torch
from torch import nn

if TYPE_CHECKING:
    from zeus_ros.core.replay import Batch


@dataclass(frozen=True)
class Dims:
    """Sizes a method builds its networks for."""

    obs_dim: int
    action_dim: int
    row_dim: int


@dataclass(frozen=True)
class ParamScale:
    """Min-max normalisation of the physical parameters over the train values, per parameter.

    One entry per parameter of the family (one for most; goal_x and goal_y
    for Sawyer-Peg-v0). Parameters travel as [B, param_dim] tensors. With
    `log`, the min-max is of the values' logarithms (`param_space='log'`): for
    a scale such as friction over 0.05-4.5, 0.05 -> 0.1 is then as large a
    step as 2 -> 4, where linearly it is 1 % of the span and a regression
    trained by MSE barely tells the low values apart.
    """

    offset: tuple[float, ...] = (0.0,)
    scale: tuple[float, ...] = (1.0,)
    log: bool = False

    def __post_init__(self):
        # Accept plain numbers for a one-parameter family.
        for name in ('offset', 'scale'):
            value = getattr(self, name)
            values = tuple(float(v) for v in (value if isinstance(value, tuple | list)
                                              else (value,)))
            object.__setattr__(self, name, values)
        if len(self.offset) != len(self.scale):
            raise ValueError(f'{len(self.offset)} offsets for {len(self.scale)} scales')

    @property
    def param_dim(self) -> int:
        """How many parameters the family varies."""
        return len(self.offset)

    def as_rows(self, value: torch.Tensor | np.ndarray | float | Sequence[float]
                ) -> torch.Tensor:
        """Parameters as a float32 [B, param_dim] tensor (from [B], [B, P] or one row)."""
        return torch.as_tensor(value, dtype=torch.float32).reshape(-1, self.param_dim)

    def normalise(self, value: torch.Tensor) -> torch.Tensor:
        """Physical values [B, P] -> normalised (train values span [0, 1] per parameter)."""
        if self.log:
            value = torch.log(value)
        return (value - value.new_tensor(self.offset)) / value.new_tensor(self.scale)

    def physical(self, normalised: np.ndarray) -> np.ndarray:
        """Normalised values [..., P] (numpy) -> physical values."""
        value = np.asarray(normalised, dtype=np.float64) * np.asarray(self.scale) \
            + np.asarray(self.offset)
        return np.exp(value) if self.log else value


@dataclass(frozen=True)
class MethodSettings:
    """Settings one method (or one family of methods) reads; the base has none.

    A method declares a frozen subclass in its own module, each field with
    `zeus_ros.core.settings.setting(default, help)`, and names it in
    `ContextMethod.settings_class`; the command line and `--help` pick it up.
    Field names are keys of the checkpoint's flat config dict, so they never
    reuse a shared `ZeusConfig` field's name. A field's default is what a
    checkpoint written before the field existed meant (absent = that value);
    what a new run of the method starts with is its `config_defaults` preset.
    """

    def validate(self) -> 'MethodSettings':
        """Raise ValueError naming the first bad field ('<field> must be ...'); return self."""
        return self


class MethodConfig(Protocol):
    """The fields of the run's config a method reads: a zeus_ros.core.config.ZeusConfig.

    A protocol, not that class: config imports this registry to check a
    config's method, so the methods only read the config they get.
    """

    @property
    def method_settings(self) -> MethodSettings | None: ...

    @property
    def feature_dim(self) -> int: ...

    @property
    def context_dim(self) -> int: ...

    @property
    def context_hidden(self) -> int: ...

    @property
    def context_layers(self) -> int: ...

    @property
    def aggregation(self) -> str: ...

    @property
    def alpha_psi(self) -> float: ...

    @property
    def dynamics_hidden(self) -> int: ...

    @property
    def dynamics_layers(self) -> int: ...

    @property
    def model_lr(self) -> float: ...

    @property
    def decoder_hidden(self) -> int: ...

    @property
    def decoder_lr(self) -> float: ...


def adam(params: Iterable[nn.Parameter], lr: float,
         betas: tuple[float, float] = (0.9, 0.999)) -> torch.optim.Adam:
    """Adam with the fused CPU kernel: one kernel per step instead of ~10 ops a tensor.

    The same algorithm as the default implementation (not bit-identical to it:
    the fused kernel orders the arithmetic differently); measured 13 % off a
    `zeus` update at batch 256 on one thread.
    """
    return torch.optim.Adam(params, lr=lr, betas=betas, fused=True)


def soft_update(net: nn.Module, target: nn.Module, tau: float) -> None:
    """Polyak average: target <- tau * net + (1 - tau) * target."""
    with torch.no_grad():
        for p, tp in zip(net.parameters(), target.parameters(), strict=True):
            tp.lerp_(p, tau)


class ContextMethod:
    """Base of every context method: no context, nothing to train."""

    name: ClassVar[str] = ''
    # The context is the TRUE parameter (privileged reference): callers must pass it.
    needs_true_param: ClassVar[bool] = False
    # The critic's TD loss back-propagates into the context encoder.
    critic_trains_context: ClassVar[bool] = False
    # The method has losses of its own: `update` runs (and phi(s) is computed for it).
    has_own_update: ClassVar[bool] = False
    # Config fields (shared or its own settings) this method presets (a user's --set wins).
    config_defaults: ClassVar[dict] = {}
    # The settings only this method reads (`self.settings`, the config's `method_settings`).
    settings_class: ClassVar[type[MethodSettings]] = MethodSettings
    # The names of the metrics `update` may return (the train log's columns for them).
    metric_names: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        # A method that writes `update` but leaves the flag off would never train.
        if cls.update is not ContextMethod.update and not cls.has_own_update:
            raise TypeError(f'{cls.__name__} defines update(): set has_own_update = True')

    def __init__(self, cfg: MethodConfig, dims: Dims, param: ParamScale,
                 training: bool = True):
        self.cfg, self.dims, self.param = cfg, dims, param
        if not isinstance(cfg.method_settings, self.settings_class):
            raise TypeError(f'{self.name} reads {self.settings_class.__name__}, got '
                            f'{type(cfg.method_settings).__name__}')
        self.settings = cfg.method_settings
        self.training = training

    @property
    def context_dim(self) -> int:
        """Width of the latent the actor and critic see beside phi(s)."""
        return 0

    def inference_modules(self) -> dict[str, nn.Module]:
        """Networks a deployed policy needs (saved in model.safetensors)."""
        return {}

    def training_modules(self) -> dict[str, nn.Module]:
        """Networks only training needs (saved in training_state.safetensors)."""
        return {}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Return the method's own optimisers, by name."""
        return {}

    def encoder_parameters(self) -> list[nn.Parameter]:
        """Parameters the critic's optimiser trains when `critic_trains_context`."""
        return []

    # Base hooks (here and below) ignore arguments their overrides use: hence the noqas.
    def encode(self, rows: torch.Tensor,
               mask: torch.Tensor,  # noqa: ARG002
               param: torch.Tensor | None) -> torch.Tensor:  # noqa: ARG002
        """Latent context [B, context_dim] of windows rows [B, k, D], mask [B, k]."""
        return rows.new_zeros((rows.shape[0], 0))

    def encode_pair(self, batch: Batch, grad: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Latents of the batch's windows before s_t and before s_{t+1} (the critic's).

        The first keeps its graph when `grad` (the critic trains the encoder),
        the second never does. Methods whose latent is a pooled per-row code
        compute both from one pass over the chain (`batch.chain_rows`).
        """
        with torch.no_grad():
            following = self.encode(batch.next_ctx_rows, batch.next_ctx_mask, batch.param)
        with torch.set_grad_enabled(grad):
            current = self.encode(batch.ctx_rows, batch.ctx_mask, batch.param)
        return current, following

    def actor_context(self, batch: Batch, critic_latent: torch.Tensor,  # noqa: ARG002
                      following: bool = False) -> torch.Tensor:  # noqa: ARG002
        """Latent the ACTOR reads in the losses (before s_{t+1} if `following`): the critic's.

        An asymmetric method (rma with `rma_asymmetric`) gives the actor its
        deployed estimate while the critic keeps the privileged latent, so the
        policy learns to act on what it will have when deployed.
        """
        return critic_latent

    def acting_context(self, rows: torch.Tensor, mask: torch.Tensor,
                       param: torch.Tensor | None) -> torch.Tensor:
        """Latent the trainer acts on while collecting (UP-OSI switches to its estimate)."""
        return self.encode(rows, mask, param)

    def deployed_context(self, rows: torch.Tensor, mask: torch.Tensor,
                         param: torch.Tensor | None) -> torch.Tensor:
        """Latent a deployed policy acts on (evaluation, the ROS nodes)."""
        return self.encode(rows, mask, param)

    def encode_target(self, rows: torch.Tensor, mask: torch.Tensor,
                      param: torch.Tensor | None) -> torch.Tensor:
        """Latent for the TD target (a slow copy where the critic trains the encoder)."""
        with torch.no_grad():
            return self.encode(rows, mask, param)

    def update_targets(self, tau: float) -> None:
        """Move the method's target networks (if any) towards the online ones."""

    def update(self, batch: Batch,  # noqa: ARG002
               z: torch.Tensor, step: int) -> dict[str, torch.Tensor]:  # noqa: ARG002
        """Run the method's own losses and optimiser steps; `z` = phi(s), detached."""
        return {}

    def decode(self, latent: torch.Tensor) -> torch.Tensor | None:  # noqa: ARG002
        """Normalised parameter estimates [B, param_dim] from latents, or None (no decoder)."""
        return None
