"""`oracle`: the TRUE parameter, min-max normalised over the train values, is the context.

The upper bound of what knowing the physics is worth: with `sac` it says
whether a family needs adaptation at all (the oracle-vs-sac gap). It is
privileged: callers pass the true parameter (the replay buffer, the
evaluator, and on ROS the parameter the sim publishes in StepInfo).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from zeus_ros.core.methods.base import ContextMethod

if TYPE_CHECKING:
    import torch


class OracleMethod(ContextMethod):
    """Latent = [normalised true parameter]; the decoded estimate is exact by construction."""

    name = 'oracle'
    needs_true_param = True

    @property
    def context_dim(self) -> int:
        return self.param.param_dim

    def encode(self, rows: torch.Tensor, mask: torch.Tensor,  # noqa: ARG002 (ContextMethod's signature)
               param: torch.Tensor | None) -> torch.Tensor:
        if param is None:
            raise ValueError('the oracle method needs the true parameter')
        return self.param.normalise(self.param.as_rows(param))

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return latent
