"""A family declared in a file: your robot's MJCF and its varied physics, as data.

A family file (YAML) says which model to load, what the task rewards, the
control period and horizon, which joints are observed, and the parameters
that vary: each with its ROS name, unit, what it edits in the model
(`sim_node.family_edits`), its default, live range, train values and held-out
splits. `parse_family_file` reads one into a `FileFamilySpec`, which answers
`SimFamily` like the built-in specs, so the trainer, the evaluator, the
adaptation report and the sim node take it by name once it is registered
(`families.register_family`).

This module checks the file alone (its schema, then the values against each
other); what needs the model (its names, whether it compiles, whether a
length edit inverts a segment) is checked by `sim_node.family_edits`, which
loads MuJoCo. This one does not: the controllers and the checkpoint metadata
read a family file recorded in a checkpoint without MuJoCo.

Every refusal is a `FamilyFileError` whose message is one line:
``<file>: <field path>: <what was expected>``.
"""

from __future__ import annotations

from dataclasses import dataclass
import hashlib
import itertools
import math
from pathlib import Path
from typing import Annotated, Iterator, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
import yaml

from sim_node.families import check_param, LiveParam, SPLITS

# A ROS parameter name: the sim node declares each one (letters, digits, underscores).
ROS_NAME = r'^[A-Za-z][A-Za-z0-9_]*$'
# The sim node's own parameters (and rclpy's): a family's parameter cannot take one of
# these names (test_family_file_sim.py checks the list against what the node declares).
RESERVED_NAMES = frozenset({'family', 'family_file', 'seed', 'mode', 'real_time_factor',
                            'command_timeout', 'camera_rate', 'thread_priority', 'executor',
                            'use_sim_time', 'start_type_description_service',
                            # the command port (#49)
                            'command_type', 'command_topic', 'command_units', 'joints',
                            'publish_step_info'})


# The trainer runs an env per train task and samples a batch from each: beyond this
# many, one timestep is more environment steps than an update can use.
MAX_TRAIN_TASKS = 64


class FamilyFileError(ValueError):
    """A family file that cannot be used: the file, the field path and what was expected.

    Its message is the one line every tool prints: ``<file>: <field>: <reason>``.
    """

    def __init__(self, origin: str, field: str, reason: str):
        super().__init__(f'{origin}: {field}: {reason}')
        self.origin, self.field, self.reason = origin, field, reason


class _Strict(BaseModel):
    # Every level refuses a key it does not know: a misspelt field is named, not ignored.
    model_config = ConfigDict(extra='forbid', frozen=True)


class ModelSource(_Strict):
    """The robot: an MJCF file (relative to the family file) or a dm_control suite domain."""

    mjcf: str | None = None
    suite: str | None = None     # 'cheetah', 'walker', ...: dm_control's MJCF and assets


class ForwardSpeed(_Strict):
    """A body's speed along an axis; with `target`, -|v - target| instead of v."""

    term: Literal['forward_speed']
    body: str
    axis: Literal['x', 'y', 'z'] = 'x'
    target: float | None = None
    weight: float = 1.0


class Healthy(_Strict):
    """A constant reward each step the robot is healthy (see `HealthyRange`)."""

    term: Literal['healthy']
    weight: float = 1.0


class ControlCost(_Strict):
    """-weight * |ctrl|^2 (the actuators' controls, after scaling to their ranges)."""

    term: Literal['control_cost']
    weight: float = 1e-3


class SiteDistance(_Strict):
    """-weight * the distance between two sites (a fingertip and its target, say)."""

    term: Literal['site_distance']
    site: str
    target_site: str
    weight: float = 1.0


RewardTerm = Annotated[ForwardSpeed | Healthy | ControlCost | SiteDistance,
                       Field(discriminator='term')]


class HealthyRange(_Strict):
    """Where the robot counts as healthy: a body's height and, optionally, a joint's angle."""

    body: str
    z_range: tuple[float, float]
    angle_joint: str | None = None
    angle_range: tuple[float, float] | None = None   # radians
    end_episode: bool = True   # leaving the range ends the episode (a terminal step)


class Task(_Strict):
    """What the robot is rewarded for: a dm_control task by name, or a sum of weighted terms."""

    suite_task: str | None = None   # a task of the model's suite domain ('run', 'walk')
    reward: tuple[RewardTerm, ...] = ()
    healthy: HealthyRange | None = None
    reset_noise: float = Field(0.0, ge=0.0)   # uniform +- this on qpos and qvel at reset


class Control(_Strict):
    """Control period (s, a multiple of the model's timestep) and episode length (steps)."""

    period: float = Field(gt=0.0)
    horizon: int = Field(gt=0)


class Observation(_Strict):
    """The joints whose positions and velocities are observed ('all': every joint)."""

    joints: Literal['all'] | tuple[str, ...] = 'all'


class FrictionEdit(_Strict):
    """Sliding friction of named geoms, of every geom of a default class, or of all geoms."""

    kind: Literal['friction']
    geoms: tuple[str, ...] = ()
    geom_class: str | None = None
    all_geoms: bool = False


class LengthEdit(_Strict):
    """A link segment's length: its capsule/cylinder geom and what hangs from its end."""

    kind: Literal['length']
    geom: str
    mass_rule: Literal['keep_density', 'keep_mass']


class MassEdit(_Strict):
    """A body's mass (its inertia scaled with it)."""

    kind: Literal['mass']
    body: str


class DampingEdit(_Strict):
    """Damping of named joints."""

    kind: Literal['damping']
    joints: tuple[str, ...] = Field(min_length=1)


class GearEdit(_Strict):
    """Gear (torque per unit control) of named actuators."""

    kind: Literal['gear']
    actuators: tuple[str, ...] = Field(min_length=1)


Edit = Annotated[FrictionEdit | LengthEdit | MassEdit | DampingEdit | GearEdit,
                 Field(discriminator='kind')]


class TrainRange(_Strict):
    """`count` train values spread over a range by quantiles of a distribution."""

    range: tuple[float, float]
    distribution: Literal['uniform', 'log_uniform'] = 'uniform'
    count: int = Field(ge=1, le=64)


class Parameter(_Strict):
    """One varied parameter, a ROS parameter of the sim node."""

    name: str = Field(pattern=ROS_NAME)
    unit: str = ''
    description: str = ''
    edit: Edit
    default: float
    live_range: tuple[float, float]
    train: tuple[float, ...] | TrainRange
    interpolation: tuple[float, ...] = ()
    extrapolation: tuple[float, ...] = ()


class Training(_Strict):
    """How the trainer uses the family."""

    # Per step, the chance a training task jumps to another train value mid-episode
    # (the trainer's `train_swap_prob`; it swaps a whole task, so the rate is the family's).
    resample_rate: float = Field(0.0, ge=0.0, le=1.0)
    alpha_psi: float = Field(1.0, ge=0.0)   # the context loss weight (Table 11's role)


class FamilyFile(_Strict):
    """The whole file."""

    name: str = Field(pattern=r'^[a-z][a-z0-9_.-]*$')
    description: str = ''
    model: ModelSource
    task: Task
    control: Control
    observation: Observation = Observation()
    parameters: tuple[Parameter, ...] = Field(min_length=1)
    training: Training = Training()


# Discriminated unions put the chosen kind into an error's location ('edit', 'length',
# 'geom'); a path in a message names fields only.
_UNION_FIELDS = {'edit', 'reward'}
_TAGS = {'friction', 'length', 'mass', 'damping', 'gear', 'forward_speed', 'healthy',
         'control_cost', 'site_distance'}


def field_path(loc: tuple) -> str:
    """'parameters[1].edit.geom' from pydantic's location tuple."""
    text, previous = '', None
    for part in loc:
        in_union = previous in _UNION_FIELDS or isinstance(previous, int)
        if isinstance(part, str) and part in _TAGS and in_union and previous != 'parameters':
            previous = part
            continue
        text += f'[{part}]' if isinstance(part, int) else f'.{part}' if text else str(part)
        previous = part
    return text or '(top level)'


def _schema_problem(error: ValidationError) -> tuple[str, str]:
    """Return the first problem pydantic found: (field path, reason)."""
    first = error.errors()[0]
    reason = 'unknown field' if first['type'] == 'extra_forbidden' else first['msg']
    more = error.error_count() - 1
    return field_path(first['loc']), reason + (f' (and {more} more)' if more else '')


def parse_document(text: str, origin: str) -> FamilyFile:
    """Parse and schema-check a family file's text; `origin` names it in errors."""
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, 'problem_mark', None)
        where = f'line {mark.line + 1}' if mark is not None else 'YAML'
        problem = getattr(error, 'problem', None) or str(error).splitlines()[0]
        raise FamilyFileError(origin, where, f'malformed YAML ({problem})') from None
    if not isinstance(raw, dict):
        raise FamilyFileError(origin, '(top level)',
                              f'must be a mapping of fields, got {type(raw).__name__}')
    try:
        return FamilyFile.model_validate(raw)
    except ValidationError as error:
        raise FamilyFileError(origin, *_schema_problem(error)) from None


def train_values(train: tuple[float, ...] | TrainRange) -> tuple[float, ...]:
    """Return the train values: as listed, or `count` quantiles of the range's distribution."""
    if not isinstance(train, TrainRange):
        return tuple(float(v) for v in train)
    lo, hi = train.range
    # Quantiles at the middles of `count` equal slices: deterministic, inside the range.
    q = (np.arange(train.count) + 0.5) / train.count
    if train.distribution == 'log_uniform':
        return tuple(float(v) for v in np.exp(np.log(lo) + q * (np.log(hi) - np.log(lo))))
    return tuple(float(v) for v in lo + q * (hi - lo))


def _range_problems(p: Parameter, where: str) -> Iterator[tuple[str, str]]:
    lo, hi = p.live_range
    if not lo < hi:
        yield f'{where}.live_range', f'must be [low, high] with low < high, got {[lo, hi]}'
        return
    if not lo <= p.default <= hi:
        yield f'{where}.default', f'{p.default:g} is outside live_range [{lo:g}, {hi:g}]'
    if isinstance(p.train, TrainRange):
        tlo, thi = p.train.range
        if not (lo <= tlo < thi <= hi):
            yield f'{where}.train.range', (f'must be [low, high] inside live_range '
                                           f'[{lo:g}, {hi:g}] with low < high, got {[tlo, thi]}')
        if p.train.distribution == 'log_uniform' and tlo <= 0:
            yield f'{where}.train.range', 'log_uniform needs a range above 0'
    for split in ('train', 'interpolation', 'extrapolation'):
        if split == 'train' and isinstance(p.train, TrainRange):
            continue
        outside = [v for v in getattr(p, split) if not lo <= v <= hi]
        if outside:
            yield f'{where}.{split}', (f'{outside[0]:g} is outside live_range '
                                       f'[{lo:g}, {hi:g}]')


def _split_problems(p: Parameter, where: str) -> Iterator[tuple[str, str]]:
    train = train_values(p.train)
    if not train:
        yield f'{where}.train', 'needs at least one value'
    for split in ('interpolation', 'extrapolation'):
        shared = [v for v in getattr(p, split) if any(math.isclose(v, t) for t in train)]
        if shared:
            yield f'{where}.{split}', (f'{shared[0]:g} is a train value: a held-out split '
                                       f'holds none')


def _source_problems(doc: FamilyFile) -> Iterator[tuple[str, str]]:
    model, task = doc.model, doc.task
    if (model.mjcf is None) == (model.suite is None):
        yield 'model', 'needs exactly one of mjcf (a file) and suite (a dm_control domain)'
    if (task.suite_task is None) == (not task.reward):
        yield 'task', 'needs exactly one of suite_task and reward (a list of terms)'
    if task.suite_task is not None and model.suite is None:
        yield 'task.suite_task', 'needs model.suite: a dm_control task runs on its own domain'
    if task.suite_task is not None and task.healthy is not None:
        yield 'task.healthy', 'goes with reward terms: a dm_control task ends its own episodes'
    if task.suite_task is not None and task.reset_noise:
        yield 'task.reset_noise', 'goes with reward terms: a dm_control task draws its own starts'


def _document_problems(doc: FamilyFile) -> Iterator[tuple[str, str]]:
    yield from _source_problems(doc)
    names = [p.name for p in doc.parameters]
    for i, p in enumerate(doc.parameters):
        where = f'parameters[{i}]'
        if names.index(p.name) != i:
            yield f'{where}.name', f'{p.name!r} is declared twice'
        if p.name in RESERVED_NAMES:
            yield f'{where}.name', f'{p.name!r} is a parameter of the sim node itself'
        yield from _range_problems(p, where)
        yield from _split_problems(p, where)
        if isinstance(p.edit, FrictionEdit):
            chosen = bool(p.edit.geoms) + (p.edit.geom_class is not None) + p.edit.all_geoms
            if chosen != 1:
                yield f'{where}.edit', 'friction needs exactly one of geoms, geom_class, all_geoms'
        if isinstance(p.edit, LengthEdit) and p.live_range[0] <= 0:
            yield f'{where}.live_range', (f'a length must stay above 0 (a segment of length '
                                          f'<= 0 is inverted), got low {p.live_range[0]:g}')
    tasks = math.prod(len(train_values(p.train)) for p in doc.parameters)
    if tasks > MAX_TRAIN_TASKS:
        yield 'parameters', (f'{tasks} train tasks (every combination of the train values); '
                             f'the trainer steps each every timestep: at most {MAX_TRAIN_TASKS}')
    healthy = doc.task.healthy
    if healthy is not None and (healthy.angle_joint is None) != (healthy.angle_range is None):
        yield 'task.healthy', 'angle_joint and angle_range go together'


@dataclass(frozen=True)
class FileFamilySpec:
    """A family from a family file: answers `SimFamily`, built envs are `FileEnv`s.

    `text` is the file as read and `model_xml` the MJCF it names, so a
    checkpoint that records both can rebuild the family without either path
    (empty for a suite domain: dm_control ships that model).
    """

    document: FamilyFile
    text: str
    model_xml: str
    origin: str          # the file's path, or where its text came from (a checkpoint)

    @property
    def name(self) -> str:  # noqa: D102
        return self.document.name

    @property
    def domain(self) -> str:
        """The robot: a file family's own (its structure is registered under its name)."""
        return self.document.name

    @property
    def description(self) -> str:  # noqa: D102
        return self.document.description

    @property
    def sha256(self) -> str:
        """Hash of the family file's text (what a checkpoint records)."""
        return hashlib.sha256(self.text.encode()).hexdigest()

    @property
    def live_params(self) -> tuple[LiveParam, ...]:  # noqa: D102
        return tuple(LiveParam(p.name, p.unit, p.default, tuple(p.live_range), p.description)
                     for p in self.document.parameters)

    @property
    def param_names(self) -> tuple[str, ...]:  # noqa: D102
        return tuple(p.name for p in self.document.parameters)

    @property
    def defaults(self) -> tuple[float, ...]:
        """The values a sim starts with."""
        return tuple(p.default for p in self.document.parameters)

    @property
    def train(self) -> tuple[tuple[float, ...], ...]:
        """Every combination of the parameters' train values."""
        return tuple(itertools.product(*(train_values(p.train) for p in self.document.parameters)))

    @property
    def interpolation(self) -> tuple[tuple[float, ...], ...]:  # noqa: D102
        return self._held_out('interpolation')

    @property
    def extrapolation(self) -> tuple[tuple[float, ...], ...]:  # noqa: D102
        return self._held_out('extrapolation')

    def _held_out(self, split: str) -> tuple[tuple[float, ...], ...]:
        # Each parameter at its held-out values, the others at their defaults: a task
        # varies one parameter away from training at a time. None declared: no tasks.
        params = self.document.parameters
        tasks = []
        for i, p in enumerate(params):
            for value in getattr(p, split):
                tasks.append(tuple(value if j == i else q.default for j, q in enumerate(params)))
        return tuple(tasks)

    @property
    def alpha_psi(self) -> float:  # noqa: D102
        return self.document.training.alpha_psi

    @property
    def reward_varies_only(self) -> bool:
        """Every edit kind changes the dynamics."""
        return False

    @property
    def episode_steps(self) -> int:  # noqa: D102
        return self.document.control.horizon

    def split(self, name: str) -> tuple[tuple[float, ...], ...]:  # noqa: D102
        if name not in SPLITS:
            raise ValueError(f'unknown split {name!r}; expected one of {SPLITS}')
        return getattr(self, name)

    def check_param(self, name: str, value: object) -> str | None:  # noqa: D102
        return check_param(self.live_params, self.name, name, value)


def parse_family_text(text: str, model_xml: str, origin: str) -> FileFamilySpec:
    """Check a family file's text (and keep the model's) without reading anything else."""
    doc = parse_document(text, origin)
    for path, reason in _document_problems(doc):
        raise FamilyFileError(origin, path, reason)
    return FileFamilySpec(doc, text, model_xml, origin)


def read_family_file(path: str | Path) -> FileFamilySpec:
    """Read a family file and the MJCF it names (relative to it); checks without MuJoCo."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise FamilyFileError(str(path), '(file)', f'cannot be read ({error.strerror})') \
            from None
    doc = parse_document(text, str(path))
    for field, reason in _source_problems(doc):   # before reading a file it may not name
        raise FamilyFileError(str(path), field, reason)
    if doc.model.mjcf is None:
        return parse_family_text(text, '', str(path))
    model_path = path.parent / doc.model.mjcf
    try:
        model_xml = model_path.read_text()
    except OSError as error:
        raise FamilyFileError(str(path), 'model.mjcf', f'{model_path} cannot be read '
                              f'({error.strerror})') from None
    return parse_family_text(text, model_xml, str(path))
