"""Typed checkpoint metadata: the schema of metadata.json, checked field by field.

`CheckpointMetadata.parse(raw)` turns the JSON object into frozen dataclasses
or raises `MetadataError` naming the first field that is missing, of the
wrong type, or out of range (``context.k: must be >= 1, got 0``). Every
loader goes through it, so a consumer reads ``meta.context.k``, never a
string key.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass, MISSING
import math
import types
import typing

from zeus_ros.core.config import ZeusConfig


class MetadataError(ValueError):
    """metadata.json does not follow the schema; the message names the field."""


@dataclass(frozen=True)
class ObsLayoutMeta:
    """The observation the weights expect (sim_node.env.ObservationLayout)."""

    obs_dim: int
    joint_names: tuple[str, ...]
    position_encoding: tuple[str, ...]
    # The reward into the state is the observation's last entry (absent: false).
    reward_in_observation: bool = False
    # Per joint entry, 'raw' or 'drop' (its velocity is not observed); absent: all kept.
    velocity_encoding: tuple[str, ...] | None = None


@dataclass(frozen=True)
class ActionLayoutMeta:
    """The action the weights produce, in actuator order."""

    action_dim: int
    actuator_names: tuple[str, ...]
    range: tuple[float, ...] = (-1.0, 1.0)


@dataclass(frozen=True)
class ContextMeta:
    """The context window and latent of the weights' method."""

    k: int
    row_dim: int
    aggregation: str
    context_dim: int
    method: str = 'zeus'
    needs_true_param: bool = False
    row_layout: str = 'concat(s, a, [r], s_next) float32'
    empty_window: str = 'zero latent'


@dataclass(frozen=True)
class ParamNormMeta:
    """Min-max normalisation of the physical parameter(s): (value - offset) / scale.

    A number each for a one-parameter family; a list (one entry per name of
    `param_names`) for a family with several, whose train values are lists too.
    """

    offset: float | tuple[float, ...]
    scale: float | tuple[float, ...]
    train_values: tuple[float | tuple[float, ...], ...] = ()
    formula: str = '(value - offset) / scale'

    @property
    def offsets(self) -> tuple[float, ...]:
        """The offsets as a tuple, one per parameter."""
        return self.offset if isinstance(self.offset, tuple) else (self.offset,)

    @property
    def scales(self) -> tuple[float, ...]:
        """The scales as a tuple, one per parameter."""
        return self.scale if isinstance(self.scale, tuple) else (self.scale,)


@dataclass(frozen=True)
class FileMeta:
    """Size and SHA-256 of one safetensors file."""

    sha256: str
    bytes: int


@dataclass(frozen=True)
class CheckpointMetadata:
    """Everything metadata.json says about a checkpoint."""

    format_version: int
    family: str
    param_name: str    # several parameters: their names joined by ', ' (param_names lists them)
    obs_layout: ObsLayoutMeta
    action_layout: ActionLayoutMeta
    context: ContextMeta
    param_normalisation: ParamNormMeta
    config: dict
    steps: dict
    files: dict[str, FileMeta]
    control_timestep: float | None = None
    run: dict | None = None
    seed: int | None = None
    git_commit: str = 'unknown'
    created_unix: float | None = None
    replay_saved: bool = False
    extra: dict = field(default_factory=dict)
    param_names: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        """The parameters, in the order of values, normalisation and estimates."""
        return self.param_names or (self.param_name,)

    @classmethod
    def parse(cls, raw) -> 'CheckpointMetadata':
        """Check `raw` (the JSON object) against the schema; MetadataError names the field."""
        meta = _build(cls, raw, '')
        _check_consistency(meta)
        return meta

    def zeus_config(self) -> ZeusConfig:
        """Return the training configuration (validated)."""
        try:
            return ZeusConfig.from_dict(self.config)
        except (TypeError, ValueError) as error:
            raise MetadataError(f'config: {error}') from None


def _build(cls, raw, where: str):
    if not isinstance(raw, dict):
        raise MetadataError(f'{where or "metadata"}: must be an object, got {type(raw).__name__}')
    hints = typing.get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    values = {}
    for f in fields(cls):
        path = f'{where}{f.name}'
        if f.name == 'extra':
            values['extra'] = {k: v for k, v in raw.items() if k not in known}
        elif f.name in raw:
            values[f.name] = _value(hints[f.name], raw[f.name], path)
        elif f.default is MISSING and f.default_factory is MISSING:
            raise MetadataError(f'{path}: missing')
    return cls(**values)


def _value(kind, value, path: str):
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        # `float | tuple[...]`: a list is read as the tuple, anything else as the first.
        listed = [a for a in args if typing.get_origin(a) is tuple]
        others = [a for a in args if a is not type(None) and a not in listed]
        kind = listed[0] if listed and (isinstance(value, list | tuple) or not others) \
            else others[0]
        return _value(kind, value, path)
    if is_dataclass(kind):
        return _build(kind, value, f'{path}.')
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise MetadataError(f'{path}: must be a list, got {type(value).__name__}')
        return tuple(_value(args[0], v, f'{path}[{i}]') for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise MetadataError(f'{path}: must be an object, got {type(value).__name__}')
        return {k: _value(args[1], v, f'{path}.{k}') for k, v in value.items()}
    return _scalar(kind, value, path)


def _scalar(kind, value, path: str):
    if kind is dict:
        if not isinstance(value, dict):
            raise MetadataError(f'{path}: must be an object, got {type(value).__name__}')
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise MetadataError(f'{path}: must be true or false, got {value!r}')
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise MetadataError(f'{path}: must be an integer, got {value!r}')
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(value):
            raise MetadataError(f'{path}: must be a finite number, got {value!r}')
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise MetadataError(f'{path}: must be a string, got {value!r}')
        return value
    raise MetadataError(f'{path}: unsupported schema type {kind}')  # pragma: no cover


def _check_consistency(meta: CheckpointMetadata) -> None:
    """Ranges and the relations between fields that the types alone do not say."""
    obs, act, ctx = meta.obs_layout, meta.action_layout, meta.context
    checks = (
        (obs.obs_dim >= 1, 'obs_layout.obs_dim', f'must be >= 1, got {obs.obs_dim}'),
        (act.action_dim >= 1, 'action_layout.action_dim',
         f'must be >= 1, got {act.action_dim}'),
        (len(act.actuator_names) == act.action_dim, 'action_layout.actuator_names',
         f'has {len(act.actuator_names)} names for action_dim {act.action_dim}'),
        (len(obs.position_encoding) == len(obs.joint_names), 'obs_layout.position_encoding',
         f'has {len(obs.position_encoding)} entries for {len(obs.joint_names)} joints'),
        (obs.velocity_encoding is None or len(obs.velocity_encoding) == len(obs.joint_names),
         'obs_layout.velocity_encoding',
         f'has {len(obs.velocity_encoding or ())} entries for {len(obs.joint_names)} joints'),
        (set(obs.velocity_encoding or ()) <= {'raw', 'drop'}, 'obs_layout.velocity_encoding',
         f"entries must be 'raw' or 'drop', got {sorted(set(obs.velocity_encoding or ()))}"),
        (ctx.k >= 1, 'context.k', f'must be >= 1, got {ctx.k}'),
        (ctx.context_dim >= 0, 'context.context_dim', f'must be >= 0, got {ctx.context_dim}'),
        (ctx.row_dim == 2 * obs.obs_dim + act.action_dim + 1, 'context.row_dim',
         f'must be 2 * obs_dim + action_dim + 1 = {2 * obs.obs_dim + act.action_dim + 1}, '
         f'got {ctx.row_dim}'),
        (all(s > 0 for s in meta.param_normalisation.scales), 'param_normalisation.scale',
         f'must be > 0, got {meta.param_normalisation.scale}'),
        (len(meta.param_normalisation.offsets) == len(meta.param_normalisation.scales)
         == len(meta.names), 'param_normalisation',
         f'needs one offset and one scale per parameter {meta.names}'),
    )
    for ok, name, reason in checks:
        if not ok:
            raise MetadataError(f'{name}: {reason}')
