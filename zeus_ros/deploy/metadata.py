"""Typed checkpoint metadata: the schema of metadata.json, checked field by field.

`CheckpointMetadata.parse(raw)` turns the JSON object into frozen dataclasses
or raises `MetadataError` naming the first field that is missing, of the
wrong type, out of range, inconsistent with another field, or not what the
family's robot has (``context.k: must be >= 1, got 0``). It checks, in order:
the type and range of every field (ranges are part of the types:
``Annotated[int, Between(1, 10_000)]``), the training configuration against
`ZeusConfig`'s fields (`CONFIG_LIMITS`), the relations between fields, and
the family (its parameters, the joints, encodings, actuators and control
period of its robot, from MuJoCo-free tables: sim_node.families,
sim_node.structures). Nothing is built before it has passed; the loader then
checks the tensors against the networks the config describes
(zeus_ros.deploy.checkpoint). Every loader goes through it, so a consumer
reads ``meta.context.k``, never a string key.

The same tree is what the trainer builds (zeus_ros.deploy.checkpoint.build_metadata)
and `CheckpointMetadata.to_json()` writes: the schema is written once, here.
Parsing then serialising gives back the file it read (an optional key the
file left out stays out, a key the schema does not know is kept), so a
checkpoint passed on (the ONNX export's copy) is the one trained. (A whole
number where a float belongs is read as a float and comes back as ``1.0``:
the trainer writes floats there.)
"""

from __future__ import annotations

from dataclasses import dataclass, Field, field, fields, is_dataclass, MISSING, replace
import hashlib
import json
import math
import re
import types
import typing
from typing import Annotated, Iterable, Sequence

from sim_node.families import get_sim_family, LiveParam, register_family, SPLITS
from sim_node.family_file import FamilyFileError, parse_family_text
from sim_node.layout import ObservationLayout
from sim_node.structures import DOMAIN_STRUCTURES, DomainStructure
from zeus_ros.core.config import config_types, SHARED_KEYS, ZeusConfig
from zeus_ros.core.methods import METHODS

# The metadata.json format this code reads and writes.
FORMAT_VERSION = 1
# What this code computes; a checkpoint that describes something else is not for it.
ROW_LAYOUT = 'concat(s, a, [r], s_next) float32'
EMPTY_WINDOW = 'zero latent'
NORMALISATION = '(value - offset) / scale'
LOG_NORMALISATION = '(ln(value) - offset) / scale'   # param_space='log'
ACTION_RANGE = (-1.0, 1.0)


class MetadataError(ValueError):
    """metadata.json does not follow the schema; the message names the field."""


def shown(value: object) -> str:   # any value a refusal quotes
    """Return repr(value), cut short: a refusal stays one readable line."""
    text = repr(value)
    return text if len(text) <= 60 else f'{text[:57]}...'


@dataclass(frozen=True)
class Between:
    """A range constraint on a number (bounds included unless open)."""

    lo: float
    hi: float
    lo_open: bool = False

    def why_not(self, value: float) -> str | None:
        """Return why `value` is out of range, or None."""
        low_ok = value > self.lo if self.lo_open else value >= self.lo
        if low_ok and value <= self.hi:
            return None
        return f'must be in {"(" if self.lo_open else "["}{self.lo:g}, {self.hi:g}], ' \
               f'got {shown(value)}'


@dataclass(frozen=True)
class Matches:
    """A string constraint: the whole string matches a regular expression."""

    pattern: str
    meaning: str

    def why_not(self, value: str) -> str | None:
        """Return why `value` does not match, or None."""
        return None if re.fullmatch(self.pattern, value) else \
            f'must be {self.meaning}, got {shown(value)}'


COUNT = 10 ** 11               # bound of a step, update or byte count (years of steps)
COUNTER = Between(0, COUNT)
SEED = Between(0, 2 ** 63 - 1)
WIDTH = Between(1, 65_536)     # a layer's or a vector's size
LAYERS = Between(0, 64)        # hidden layers of an MLP
FRACTION = Between(0.0, 1.0)
Count = Annotated[int, COUNTER]
NonNegative = Annotated[float, Between(0.0, 1e9)]
# A key the trainer writes only when it says something (velocity_encoding only
# when a velocity is dropped); absent, it holds its default.
WRITTEN_IF_SET = {'written': 'if set'}


@dataclass(frozen=True)
class Section:
    """What every object of metadata.json keeps besides its schema fields.

    They make a file round-trip through the tree: `extra` holds the keys the
    schema does not know (a newer writer's: read by nothing, written back),
    `omitted` the optional keys the file did not have (files from before the
    key existed), which `to_json` leaves out again while they hold their default.
    """

    extra: dict = field(default_factory=dict, kw_only=True)
    omitted: frozenset[str] = field(default=frozenset(), kw_only=True, compare=False,
                                    repr=False)


@dataclass(frozen=True)
class ObsLayoutMeta(Section):
    """The observation the weights expect (sim_node.env.ObservationLayout)."""

    obs_dim: Annotated[int, Between(1, 100_000)]
    joint_names: tuple[str, ...]
    position_encoding: tuple[str, ...]
    # The reward into the state is the observation's last entry (absent: false).
    reward_in_observation: bool = False
    # Per joint entry, 'raw' or 'drop' (its velocity is not observed); absent: all kept.
    velocity_encoding: tuple[str, ...] | None = field(default=None, metadata=WRITTEN_IF_SET)

    def layout(self) -> ObservationLayout:
        """Return the observation layout these fields describe."""
        return ObservationLayout(self.joint_names, self.position_encoding,
                                 self.reward_in_observation, self.velocity_encoding)


@dataclass(frozen=True)
class ActionLayoutMeta(Section):
    """The action the weights produce, in actuator order."""

    action_dim: Annotated[int, Between(1, 10_000)]
    actuator_names: tuple[str, ...]
    range: tuple[float, ...] = ACTION_RANGE
    # Each actuator's control range and gear (MuJoCo motors: effort = gear * ctrl),
    # so that a robot can be commanded in joint units (#49). Absent in checkpoints
    # from before: such weights command in normalised units only.
    ctrl_low: tuple[float, ...] | None = field(default=None, metadata=WRITTEN_IF_SET)
    ctrl_high: tuple[float, ...] | None = field(default=None, metadata=WRITTEN_IF_SET)
    gear: tuple[float, ...] | None = field(default=None, metadata=WRITTEN_IF_SET)


@dataclass(frozen=True)
class ContextMeta(Section):
    """The context window and latent of the weights' method."""

    k: Annotated[int, Between(1, 10_000)]
    row_dim: Annotated[int, Between(1, 1_000_000)]
    aggregation: str
    context_dim: Annotated[int, Between(0, 65_536)]
    # Absent in checkpoints from before the method plug-ins: they are ZeUS.
    method: str = 'zeus'
    needs_true_param: bool = False
    row_layout: str = ROW_LAYOUT
    empty_window: str = EMPTY_WINDOW


@dataclass(frozen=True)
class ParamNormMeta(Section):
    """Min-max normalisation of the physical parameter(s): (value - offset) / scale.

    A number each for a one-parameter family; a list (one entry per name of
    `param_names`) for a family with several, whose train values are lists too.
    """

    offset: float | tuple[float, ...]
    scale: float | tuple[float, ...]
    train_values: tuple[float | tuple[float, ...], ...] = ()
    formula: str = NORMALISATION

    @property
    def log(self) -> bool:
        """Whether the min-max is of the values' logarithms (`param_space='log'`)."""
        return self.formula == LOG_NORMALISATION

    @property
    def offsets(self) -> tuple[float, ...]:
        """The offsets as a tuple, one per parameter."""
        return self.offset if isinstance(self.offset, tuple) else (self.offset,)

    @property
    def scales(self) -> tuple[float, ...]:
        """The scales as a tuple, one per parameter."""
        return self.scale if isinstance(self.scale, tuple) else (self.scale,)


@dataclass(frozen=True)
class FileMeta(Section):
    """Size and SHA-256 of one safetensors file."""

    sha256: Annotated[str, Matches('[0-9a-f]{64}', '64 lowercase hex digits')]
    bytes: Count


@dataclass(frozen=True)
class StepsMeta(Section):
    """How far training had got (absent counters: 0, as an in-memory agent's)."""

    timestep: Count = 0
    env_steps: Count = 0
    update_step: Count = 0
    episodes: Count = 0
    wall_s: NonNegative | None = field(default=None, metadata=WRITTEN_IF_SET)


@dataclass(frozen=True)
class RunMeta(Section):
    """The training command's arguments (learning_tools.train.RunArgs): provenance only.

    Each may be absent; present, it must agree with what the checkpoint says.
    """

    out: str = ''
    family: str | None = None
    family_file: str | None = None
    method: str | None = None
    profile: str | None = None
    steps: Annotated[int, Between(1, COUNT)] | None = None
    seed: Annotated[int, SEED] | None = None
    overrides: dict = field(default_factory=dict)
    eval_every: Count | None = None
    eval_episodes: Count | None = None
    eval_max_steps: Count | None = None
    eval_splits: tuple[str, ...] = ()
    checkpoint_every: Count | None = None
    log_every: Count | None = None
    time_limit: NonNegative | None = None
    save_replay: bool = True
    resume: bool = False
    quiet: bool = False


@dataclass(frozen=True)
class FamilyFileMeta(Section):
    """The family file the weights were trained on, and its model: both texts, whole.

    A checkpoint carries them so that it loads, and its family is known by name,
    without the files (sim_node.family_file). `path` is where the file was: provenance.
    """

    path: str
    sha256: Annotated[str, Matches('[0-9a-f]{64}', '64 lowercase hex digits')]
    text: str
    model_xml: str


@dataclass(frozen=True)
class CheckpointMetadata(Section):
    """Everything metadata.json says about a checkpoint."""

    format_version: int
    family: str
    param_name: str    # several parameters: their names joined by ', ' (param_names lists them)
    obs_layout: ObsLayoutMeta
    action_layout: ActionLayoutMeta
    context: ContextMeta
    param_normalisation: ParamNormMeta
    config: dict       # ZeusConfig.to_dict(), checked against CONFIG_LIMITS
    steps: StepsMeta
    files: dict[str, FileMeta]
    control_timestep: Annotated[float, Between(0.0, 10.0, lo_open=True)] | None = None
    run: RunMeta | None = None
    seed: Annotated[int, SEED] | None = None
    git_commit: str = 'unknown'
    created_unix: Annotated[float, Between(0.0, 1e11)] | None = None
    replay_saved: bool = False
    # Written for a family of several parameters only.
    param_names: tuple[str, ...] = field(default=(), metadata=WRITTEN_IF_SET)
    # Written for a family from a family file only (checkpoints before #48 have none).
    family_file: FamilyFileMeta | None = field(default=None, metadata=WRITTEN_IF_SET)

    @property
    def names(self) -> tuple[str, ...]:
        """The parameters, in the order of values, normalisation and estimates."""
        return self.param_names or (self.param_name,)

    @classmethod
    def parse(cls, raw: dict) -> 'CheckpointMetadata':
        """Check `raw` (the JSON object) against the schema; MetadataError names the field."""
        meta = parse_section(cls, raw)
        _check_config(meta.config)
        _check(_family_file_facts(meta))
        _check(_family_facts(meta))
        _check(_consistency(meta))
        _check([(meta.format_version == FORMAT_VERSION, 'format_version',
                 f'checkpoint format {meta.format_version}, this code reads {FORMAT_VERSION}')])
        return meta

    def to_dict(self) -> dict:
        """Return metadata.json's object: `parse` of it gives back an equal tree."""
        return as_json(self)

    def to_json(self) -> str:
        """Return metadata.json's text as the trainer writes it."""
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    def checked(self) -> 'CheckpointMetadata':
        """Return this tree once it has passed every check a file gets (one built in memory)."""
        return self.parse(self.to_dict())

    def with_files(self, files: dict[str, FileMeta], replay_saved: bool) -> 'CheckpointMetadata':
        """Return the tree with the saved files' sizes and hashes (known once they are written)."""
        return replace(self, files=files, replay_saved=replay_saved)

    def zeus_config(self) -> ZeusConfig:
        """Return the training configuration (validated by `parse`)."""
        try:
            return ZeusConfig.from_dict(self.config)
        except (TypeError, ValueError) as error:
            raise MetadataError(f'config: {error}') from None


# `raw` is whatever the JSON holds there: checking that it is an object is part of the job.
def parse_section(cls: type[Section], raw: object, where: str = '') -> Section:
    """Build section `cls` from its JSON object, checking each field's type and range.

    `where` is the section's path in the file ('run.'), for the refusals.
    """
    if not isinstance(raw, dict):
        raise MetadataError(f'{where.rstrip(".") or "metadata"}: must be an object, '
                            f'got {type(raw).__name__}')
    hints = typing.get_type_hints(cls, include_extras=True)
    schema = _schema_fields(cls)
    values = {}
    for f in schema:
        path = f'{where}{f.name}'
        if f.name in raw:
            values[f.name] = _value(hints[f.name], raw[f.name], path)
        elif f.default is MISSING and f.default_factory is MISSING:
            raise MetadataError(f'{path}: missing')
    known = {f.name for f in schema}
    return cls(**values, extra={k: v for k, v in raw.items() if k not in known},
               omitted=frozenset(known - raw.keys()))


def _schema_fields(section: Section | type[Section]) -> list:
    """Return the fields of a section (class or instance) that metadata.json holds by name."""
    bookkeeping = {f.name for f in fields(Section)}
    return [f for f in fields(section) if f.name not in bookkeeping]


def as_json(value: object) -> typing.Any:
    """Return the JSON value of a part of the tree: a section, a tuple, a number..."""
    if is_dataclass(value):
        return _section_json(value)
    if isinstance(value, tuple | list):
        return [as_json(v) for v in value]
    if isinstance(value, dict):
        return {k: as_json(v) for k, v in value.items()}
    return value


def _section_json(section: Section) -> dict:
    """Return a section's JSON object, its keys sorted as metadata.json has them."""
    out = dict(section.extra)
    for f in _schema_fields(section):
        value = getattr(section, f.name)
        optional = f.name in section.omitted or f.metadata.get('written') == 'if set'
        if not (optional and value == _default(f)):
            out[f.name] = as_json(value)
    return dict(sorted(out.items()))


def _default(f: Field):
    """Return a field's default (MISSING for a required one: equal to no value)."""
    return f.default_factory() if f.default_factory is not MISSING else f.default


# `kind`: a field's type hint (a class, a union, Annotated, a generic alias); `value`:
# whatever the JSON holds there (checking it is the job).
def _value(kind: object, value: object, path: str):
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is Annotated:
        checked = _value(args[0], value, path)
        for constraint in kind.__metadata__:
            reason = constraint.why_not(checked)
            if reason is not None:
                raise MetadataError(f'{path}: {reason}')
        return checked
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
        return parse_section(kind, value, f'{path}.')
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise MetadataError(f'{path}: must be a list, got {shown(value)}')
        return tuple(_value(args[0], v, f'{path}[{i}]') for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise MetadataError(f'{path}: must be an object, got {shown(value)}')
        return {k: _value(args[1], v, f'{path}.{k}') for k, v in value.items()}
    return _scalar(kind, value, path)


def _scalar(kind: type, value: object, path: str):
    if kind is dict:
        if not isinstance(value, dict):
            raise MetadataError(f'{path}: must be an object, got {shown(value)}')
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise MetadataError(f'{path}: must be true or false, got {shown(value)}')
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise MetadataError(f'{path}: must be an integer, got {shown(value)}')
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(value):
            raise MetadataError(f'{path}: must be a finite number, got {shown(value)}')
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise MetadataError(f'{path}: must be a string, got {shown(value)}')
        return value
    raise MetadataError(f'{path}: unsupported schema type {kind}')  # pragma: no cover


# The range of every numeric config key, shared or a method's own setting (None:
# a string or flag, whose values ZeusConfig.validate checks). Loose enough for
# any sane training run, tight enough that nothing absurd reaches a network's
# constructor.
CONFIG_LIMITS: dict[str, Between | None] = {
    **dict.fromkeys(('family', 'method', 'profile', 'aggregation', 'context_input',
                     'context_encoder', 'dynamics_loss', 'train_swap_direction',
                     'context_critic_grad', 'metric_normalise', 'reward_in_observation',
                     'train_sampling', 'train_span', 'param_space', 'rma_latent', 'context_reward',
                     'rma_asymmetric')),
    'context_length': Between(1, 10_000),
    **dict.fromkeys(('context_dim', 'context_hidden', 'feature_dim', 'encoder_hidden',
                     'hidden_dim', 'dynamics_hidden', 'decoder_hidden', 'hyper_model_hidden'),
                    WIDTH),
    **dict.fromkeys(('context_layers', 'encoder_layers', 'hidden_layers', 'dynamics_layers'),
                    LAYERS),
    **dict.fromkeys(('actor_log_std_min', 'actor_log_std_max'), Between(-100.0, 100.0)),
    **dict.fromkeys(('discount', 'critic_tau', 'encoder_tau', 'train_swap_prob'), FRACTION),
    'adam_beta1': Between(0.0, 0.999999),
    'init_temperature': Between(0.0, 1e6, lo_open=True),
    **dict.fromkeys(('actor_lr', 'critic_lr', 'alpha_lr', 'model_lr', 'decoder_lr'), FRACTION),
    **dict.fromkeys(('alpha_psi', 'id_weight', 'backward_weight'), Between(0.0, 1e6)),
    **dict.fromkeys(('actor_update_freq', 'critic_target_update_freq'), Between(1, 1_000_000)),
    **dict.fromkeys(('osi_warmup_updates', 'rma_student_after_updates', 'init_steps'), COUNTER),
    'batch_size_per_task': Between(1, 1_000_000),
    **dict.fromkeys(('replay_capacity', 'episode_steps'), Between(1, COUNT)),
    'num_threads': Between(1, 1024),
}
# Added to the config after the first checkpoints were written: absent, they
# take their default, which is what the code did before they existed. Every
# other shared field must be there (a missing width would be guessed, not
# read); a method's own settings all came later (and a checkpoint written
# since each method owns them holds only its own method's).
LATER_CONFIG_KEYS = frozenset({
    'method', 'context_input', 'context_encoder', 'context_critic_grad', 'metric_normalise',
    'id_weight', 'backward_weight', 'osi_warmup_updates', 'hyper_model_hidden',
    'reward_in_observation', 'train_swap_prob', 'train_swap_direction', 'train_sampling',
    'train_span', 'param_space', 'context_reward',
    'rma_student_after_updates', 'rma_latent', 'rma_asymmetric'})


def _check_config(config: dict) -> None:
    """Every config key of `config`: known, present (or a later one), typed, in range.

    Another method's settings (old checkpoints hold every method's) are
    checked too: a bad value is refused wherever it sits.
    """
    kinds = config_types()
    for name in config:
        if name not in kinds:
            raise MetadataError(f'config.{name}: not a configuration field')
    for name, kind in kinds.items():
        if name not in config:
            if name in LATER_CONFIG_KEYS or name not in SHARED_KEYS:
                continue
            raise MetadataError(f'config.{name}: missing')
        value = _scalar(kind, config[name], f'config.{name}')
        limit = CONFIG_LIMITS.get(name)
        reason = None if limit is None else limit.why_not(value)
        if reason is not None:
            raise MetadataError(f'config.{name}: {reason}')
    try:
        cfg = ZeusConfig.from_dict(config)
    except ValueError as error:
        # ZeusConfig words its refusals '<field> must be ...': name the field first.
        name, _, reason = str(error).partition(' ')
        raise MetadataError(f'config.{name}: {reason}' if name in kinds
                            else f'config: {error}') from None
    if not cfg.actor_log_std_min < cfg.actor_log_std_max:
        raise MetadataError(f'config.actor_log_std_min: must be below config.actor_log_std_max '
                            f'({cfg.actor_log_std_max:g}), got {cfg.actor_log_std_min:g}')


def _check(checks: Iterable[tuple[bool, str, str]]) -> None:
    """Raise MetadataError for the first failed (ok, field, reason) of `checks`.

    `checks` is a generator, so a check runs only once those before it have
    passed (later ones may rely on them).
    """
    for ok, name, reason in checks:
        if not ok:
            raise MetadataError(f'{name}: {reason}')


def _family_file_facts(meta: CheckpointMetadata):
    """Check a recorded family file (hash, schema, name), then make it known by that name."""
    recorded = meta.family_file
    if recorded is None:
        return
    digest = hashlib.sha256(recorded.text.encode()).hexdigest()
    yield (digest == recorded.sha256, 'family_file.sha256',
           f'must be the sha256 of family_file.text ({digest}), got {recorded.sha256}')
    try:
        family = parse_family_text(recorded.text, recorded.model_xml, 'family_file.text')
    except FamilyFileError as error:
        yield False, 'family_file', str(error)
        return
    yield (family.name == meta.family, 'family_file.text',
           f'declares family {family.name!r}, the checkpoint is of {meta.family!r}')
    try:
        register_family(family, family.sha256)
    except ValueError as error:   # another file of that name is already loaded here
        yield False, 'family_file', str(error)
        return
    if family.domain not in DOMAIN_STRUCTURES:
        # In a process that never compiled the model (a controller), the robot is the one
        # the checkpoint describes; a sim node checks the real model (family_edits).
        DOMAIN_STRUCTURES[family.domain] = DomainStructure(
            meta.obs_layout.joint_names, meta.obs_layout.position_encoding,
            meta.obs_layout.velocity_encoding, meta.action_layout.actuator_names,
            meta.control_timestep or family.document.control.period)


def _family_facts(meta: CheckpointMetadata):
    """Check the family's parameters and robot: the ground truth, so first."""
    try:
        spec = get_sim_family(meta.family)
    except ValueError as error:
        yield False, 'family', str(error)
        return
    yield (meta.config.get('family') == meta.family, 'config.family',
           f'must be the family, {shown(meta.family)}, got {shown(meta.config.get("family"))}')
    wanted = ', '.join(spec.param_names)
    several = len(spec.param_names) > 1
    yield (meta.names == spec.param_names, 'param_names' if several else 'param_name',
           f'must be {list(spec.param_names) if several else wanted!r} for {spec.name}, '
           f'got {list(meta.param_names) if several else meta.param_name!r}')
    yield (meta.param_name == wanted, 'param_name',
           f'must be {wanted!r} for {spec.name}, got {shown(meta.param_name)}')
    robot = DOMAIN_STRUCTURES[spec.domain]
    obs, act = meta.obs_layout, meta.action_layout
    every_velocity = ('raw',) * len(robot.joint_names)
    for name, have, want in (
            ('obs_layout.joint_names', obs.joint_names, robot.joint_names),
            ('obs_layout.position_encoding', obs.position_encoding, robot.position_encoding),
            ('obs_layout.velocity_encoding', obs.velocity_encoding or every_velocity,
             robot.velocity_encoding or every_velocity),
            ('action_layout.actuator_names', act.actuator_names, robot.actuator_names)):
        yield have == want, name, f'{_first_difference(have, want)} for {spec.name}'
    step = meta.control_timestep
    yield (step is None or math.isclose(step, robot.control_timestep, rel_tol=1e-9),
           'control_timestep', f'must be {robot.control_timestep:g} s for {spec.name}, '
                               f'got {shown(step)}')


def _consistency(meta: CheckpointMetadata):
    """Check the relations between fields, once each agrees with the family."""
    yield from _layout_consistency(meta.obs_layout, meta.action_layout, meta.config)
    yield from _context_consistency(meta.context, meta.obs_layout, meta.action_layout,
                                    meta.config)
    norm = meta.param_normalisation
    yield from _normalisation_shape(norm, meta.names)
    yield from _values_in_range(norm, get_sim_family(meta.family).live_params)
    yield from _derived_normalisation(norm)
    if meta.run is not None:
        yield from _run_consistency(meta.run, meta)


def _run_consistency(run: RunMeta, meta: CheckpointMetadata):
    config = meta.config
    for name, have, want in (('family', run.family, meta.family),
                             ('method', run.method, config.get('method', 'zeus')),
                             ('profile', run.profile, config['profile']),
                             ('seed', run.seed, meta.seed)):
        yield (have is None or have == want, f'run.{name}',
               f'must be {shown(want)} (as the checkpoint says), got {shown(have)}')
    yield (set(run.eval_splits) <= set(SPLITS), 'run.eval_splits',
           f'entries must be among {SPLITS}, got {shown(list(run.eval_splits))}')
    for name, value in run.overrides.items():
        # The user's overrides win over every preset (zeus_ros.core.config.make_config).
        yield (config.get(name) == value, f'run.overrides.{name}',
               f'must be config.{name} ({shown(config.get(name))}), got {shown(value)}')


def _units_consistency(act: ActionLayoutMeta):
    """Control range and gear: all three or none, one finite value per actuator, low < high."""
    units = {'ctrl_low': act.ctrl_low, 'ctrl_high': act.ctrl_high, 'gear': act.gear}
    given = [name for name, values in units.items() if values is not None]
    yield (len(given) in (0, 3), 'action_layout.gear',
           f'ctrl_low, ctrl_high and gear come together, got only {", ".join(given)}')
    for name in given:
        values = units[name]
        yield (len(values) == act.action_dim and all(math.isfinite(v) for v in values),
               f'action_layout.{name}', f'must be {act.action_dim} finite numbers, got {values}')
    if len(given) == 3 and len(act.ctrl_low) == len(act.ctrl_high):
        yield (all(lo < hi for lo, hi in zip(act.ctrl_low, act.ctrl_high, strict=True)),
               'action_layout.ctrl_high', 'must exceed ctrl_low for every actuator')


def _layout_consistency(obs: ObsLayoutMeta, act: ActionLayoutMeta, config: dict):
    names = len(act.actuator_names)
    yield (act.action_dim == names, 'action_layout.action_dim',
           f'must be {names} (action_layout.actuator_names), got {act.action_dim}')
    yield (act.range == ACTION_RANGE, 'action_layout.range',
           f'must be {list(ACTION_RANGE)} (the tanh actor and the sim), got {list(act.range)}')
    yield from _units_consistency(act)
    wanted = config.get('reward_in_observation', False)
    yield (obs.reward_in_observation == wanted, 'obs_layout.reward_in_observation',
           f'must be config.reward_in_observation ({wanted}), got {obs.reward_in_observation}')
    size = obs.layout().size
    yield (obs.obs_dim == size, 'obs_layout.obs_dim',
           f"must be {size} (what obs_layout's joints, encodings and reward give), "
           f'got {obs.obs_dim}')


def _context_consistency(ctx: ContextMeta, obs: ObsLayoutMeta, act: ActionLayoutMeta,
                         config: dict):
    row = 2 * obs.obs_dim + act.action_dim + 1
    yield (ctx.row_dim == row, 'context.row_dim',
           f'must be 2 * obs_dim + action_dim + 1 = {row}, got {ctx.row_dim}')
    yield (ctx.k == config['context_length'], 'context.k',
           f'must be config.context_length ({config["context_length"]}), got {ctx.k}')
    yield (ctx.aggregation == config['aggregation'], 'context.aggregation',
           f'must be config.aggregation ({config["aggregation"]!r}), '
           f'got {shown(ctx.aggregation)}')
    method = config.get('method', 'zeus')
    yield (ctx.method == method, 'context.method',
           f'must be config.method ({method!r}), got {shown(ctx.method)}')
    privileged = METHODS[method].needs_true_param
    yield (ctx.needs_true_param == privileged, 'context.needs_true_param',
           f'must be {privileged} for method {method!r}, got {ctx.needs_true_param}')
    yield (ctx.row_layout == ROW_LAYOUT, 'context.row_layout',
           f'must be {ROW_LAYOUT!r}, got {shown(ctx.row_layout)}')
    yield (ctx.empty_window == EMPTY_WINDOW, 'context.empty_window',
           f'must be {EMPTY_WINDOW!r}, got {shown(ctx.empty_window)}')


def _rows(norm: ParamNormMeta) -> list[tuple[float, ...]]:
    return [v if isinstance(v, tuple) else (v,) for v in norm.train_values]


def _normalisation_shape(norm: ParamNormMeta, names: tuple[str, ...]):
    path = 'param_normalisation'
    yield (norm.formula in (NORMALISATION, LOG_NORMALISATION), f'{path}.formula',
           f'must be {NORMALISATION!r} or {LOG_NORMALISATION!r}, got {shown(norm.formula)}')
    for label, values in (('offset', norm.offsets), ('scale', norm.scales)):
        yield (len(values) == len(names), f'{path}.{label}',
               f'needs one entry per parameter {list(names)}, got {len(values)}')
    yield (all(s > 0 for s in norm.scales), f'{path}.scale',
           f'must be > 0, got {shown(norm.scale)}')
    yield (all(len(r) == len(names) for r in _rows(norm)), f'{path}.train_values',
           f'each needs one value per parameter {list(names)}')


def _values_in_range(norm: ParamNormMeta, live_params: tuple[LiveParam, ...]):
    """Train values inside the family's ranges; without them, a normalisation that fits them."""
    path = 'param_normalisation'
    rows = _rows(norm)
    for i, param in enumerate(live_params):
        lo, hi = param.live_range
        column = [r[i] for r in rows]
        yield (all(lo <= v <= hi for v in column), f'{path}.train_values',
               f'{param.name} values must lie in its range [{lo:g}, {hi:g}], '
               f'got {shown(column)}')
        if norm.log:
            yield (lo > 0, f'{path}.formula', f'{param.name} has values <= 0 in its range '
                                              f'[{lo:g}, {hi:g}]: no logarithm of them')
            if lo <= 0:
                return
            lo, hi = math.log(lo), math.log(hi)   # offset and scale are of the logs
        if rows:
            continue
        yield (lo <= norm.offsets[i] <= hi, f'{path}.offset',
               f'{param.name} offset must lie in its range [{lo:g}, {hi:g}], '
               f'got {shown(norm.offsets[i])}')
        yield (norm.scales[i] <= max(hi - lo, 1.0), f'{path}.scale',
               f'{param.name} scale must be at most {max(hi - lo, 1.0):g}, '
               f'got {shown(norm.scales[i])}')


def _derived_normalisation(norm: ParamNormMeta):
    """Offset and scale: the trainer's min-max (core.agent.param_normaliser) of the values."""
    path = 'param_normalisation'
    columns = list(zip(*_rows(norm), strict=True))
    if not columns:
        return   # nothing to derive them from: the family's ranges bound them
    if norm.log:
        if min(min(column) for column in columns) <= 0:
            return   # _values_in_range refuses them
        columns = [[math.log(v) for v in column] for column in columns]
    lows = [min(column) for column in columns]
    spans = [max(column) - min(column) if max(column) > min(column) else 1.0
             for column in columns]
    for label, have, want in (('offset', norm.offsets, lows), ('scale', norm.scales, spans)):
        yield (all(math.isclose(h, w, rel_tol=1e-9, abs_tol=1e-12)
                   for h, w in zip(have, want, strict=True)),
               f'{path}.{label}', f'must be {shown(_one_or_list(want))}, the min-max '
                                  f'normalisation of {path}.train_values, got '
                                  f'{shown(_one_or_list(have))}')


def _one_or_list(values: Sequence[float]) -> float | list[float]:
    return values[0] if len(values) == 1 else list(values)


def _first_difference(have: tuple, want: tuple) -> str:
    """Say where two lists first differ, in a few words."""
    if len(have) != len(want):
        return f'has {len(have)} entries, must have {len(want)}: {shown(list(want))}'
    for i, (h, w) in enumerate(zip(have, want, strict=True)):
        if h != w:
            return f'entry {i} must be {shown(w)}, got {shown(h)}'
    return 'is as it must be'   # (worded for every check, shown only for a failed one)
