"""Context methods, by the name `--method` and the checkpoint's config use.

Add a method: write a module here with a `ContextMethod` subclass and list it
below; nothing else changes (trainer, checkpoint, evaluator, nodes).
"""

from __future__ import annotations

from zeus_ros.core.methods.base import ContextMethod, Dims, ParamScale
from zeus_ros.core.methods.cadm import CadmMethod
from zeus_ros.core.methods.hyperdynamics import HyperDynamicsMethod
from zeus_ros.core.methods.oracle import OracleMethod
from zeus_ros.core.methods.rma import RmaMethod
from zeus_ros.core.methods.sac import SacMethod
from zeus_ros.core.methods.zeus import ZeusMethod, ZeusNoContextLoss
from zeus_ros.core.methods.up_osi import UpOsiMethod
from zeus_ros.core.methods.zeus_id import ZeusIdMethod
from zeus_ros.core.methods.zeus_osi import ZeusOsiMethod

METHODS: dict[str, type[ContextMethod]] = {
    m.name: m for m in (ZeusMethod, ZeusNoContextLoss, SacMethod, OracleMethod, ZeusIdMethod,
                        CadmMethod, UpOsiMethod, HyperDynamicsMethod, ZeusOsiMethod,
                        RmaMethod)}


def get_method(name: str) -> type[ContextMethod]:
    """Return the method class registered under `name` (ValueError names the known)."""
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f'unknown method {name!r}; known: {sorted(METHODS)}') from None


__all__ = ['ContextMethod', 'Dims', 'METHODS', 'ParamScale', 'get_method']
