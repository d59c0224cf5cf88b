"""Registry of parameter-varied environment families (paper appendix, Tables 2-6).

Most families (`FamilySpec`) name one physical (or reward) parameter, the
values of the paper's train / interpolation / extrapolation splits exactly as
printed, and a wider, physically sane range that live swaps may use. The model
edits that put a value into force live here too, so the trainer and the sim
node build the same MuJoCo model for the same value. Sawyer-Peg-v0
(`GoalFamilySpec`, Table 7) varies two, the goal's x and y: its tasks are
value tuples.

Every family describes its live parameters the same way (`live_params`, a
tuple of `LiveParam`), and the sim node reads only that: a family's values
are a tuple in `param_names` order, through the sim node, the trainer, the
controllers and the adaptation report (`get_sim_family`, `sim_node.env.make_env`).
Both kinds of spec answer `SimFamily` (the parameters, the splits, the
horizon `episode_steps`), and code that takes either reads it through that.
`get_family` is for what needs a dm_control family (`ParamEnv`, the research/analysis scripts).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Iterable, Mapping, Protocol, runtime_checkable, Sequence
import xml.etree.ElementTree as ElementTree

import numpy as np


SPLITS = ('train', 'interpolation', 'extrapolation')
# Control steps per episode of the dm_control families (their tasks' 1000); a family
# with a horizon of its own says so in its spec (Sawyer-Peg-v0: Table 9's 40).
EPISODE_STEPS = 1000


def _fmt(values: Iterable[float]) -> str:
    return ' '.join(f'{float(v):.10g}' for v in values)


def _walker_friction(xml: str, friction: float) -> str:
    # MuJoCo combines two geoms' friction by taking the maximum, so changing
    # only the floor would leave every contact at the walker's default 0.7
    # for any value below it. Set the default class that the floor and all
    # walker geoms share: every foot-ground contact then has this friction.
    root = ElementTree.fromstring(xml)
    geom_default = root.find('./default/geom')
    geom_default.set('friction', _sliding(geom_default.get('friction'), friction))
    return ElementTree.tostring(root, encoding='unicode')


def _sliding(friction_attribute: str, sliding: float) -> str:
    """Return an MJCF friction triple with its sliding part replaced."""
    _, torsional, rolling = friction_attribute.split()
    return f'{sliding:.10g} {torsional} {rolling}'


def _walker_foot_length(xml: str, half_length: float) -> str:
    # Both feet (public variants change only one). The value is the capsule's
    # half-length, MJCF `size[1]` (dm_control's default is 0.1).
    root = ElementTree.fromstring(xml)
    for name in ('right_foot', 'left_foot'):
        geom = root.find(f".//geom[@name='{name}']")
        radius = geom.get('size').split()[0]
        geom.set('size', f'{radius} {half_length:.10g}')
    return ElementTree.tostring(root, encoding='unicode')


def _cheetah_torso_length(xml: str, length: float) -> str:
    # The torso capsule spans [-L/2, L/2]; the thighs hang from its ends and
    # the head sits 0.1 beyond the front end. `settotalmass` in the model makes
    # MuJoCo rescale all masses so the total stays 14 kg: a longer torso takes
    # mass from the legs.
    half = length / 2.0
    root = ElementTree.fromstring(xml)
    root.find(".//geom[@name='torso']").set('fromto', _fmt((-half, 0, 0, half, 0, 0)))
    root.find(".//body[@name='bthigh']").set('pos', _fmt((-half, 0, 0)))
    root.find(".//body[@name='fthigh']").set('pos', _fmt((half, 0, 0)))
    root.find(".//geom[@name='head']").set('pos', _fmt((half + 0.1, 0, 0.1)))
    return ElementTree.tostring(root, encoding='unicode')


def _cheetah_friction(xml: str, friction: float) -> str:
    # The cheetah's geoms default to 0.4 and the ground to MuJoCo's 1.0, and a
    # contact takes the larger: set both, so every foot-ground contact has it.
    root = ElementTree.fromstring(xml)
    cheetah_geoms = root.find("./default/default[@class='cheetah']/geom")
    setting = _sliding(cheetah_geoms.get('friction'), friction)
    cheetah_geoms.set('friction', setting)
    root.find(".//geom[@name='ground']").set('friction', setting)
    return ElementTree.tostring(root, encoding='unicode')


def _finger_distal_length(xml: str, length: float) -> str:
    # "Finger size" is the length of the distal segment, the one whose
    # fingertip strikes the spinner (dm_control's default is 0.16). A shorter
    # finger reaches the spinner less or not at all, a longer one sweeps
    # farther with more inertia: the dynamics really change. (Public variants
    # moved only the touch-sensor sites, which changes nothing.)
    root = ElementTree.fromstring(xml)
    root.find(".//geom[@name='distal']").set('fromto', _fmt((0, 0, 0, 0, 0, -length)))
    tip_start = max(length - 0.03, 0.0)
    root.find(".//geom[@name='fingertip']").set(
        'fromto', _fmt((0, 0, -tip_start, 0, 0, -(length + 0.001))))
    for site, x in (('touchtop', 0.01), ('touchbottom', -0.01)):
        root.find(f".//site[@name='{site}']").set('pos', _fmt((x, 0, -(length + 0.01))))
    return ElementTree.tostring(root, encoding='unicode')


def _cartpole_pole_length(xml: str, length: float) -> str:
    # The pole capsule spans 0..L along the hinge's z; its mass stays 0.1 kg
    # (set on the class), so a longer pole swings slower with more inertia, as
    # CaDM's pole-length CartPole. Contacts are off in this model, so a pole
    # longer than the cart's height passes through the floor harmlessly.
    root = ElementTree.fromstring(xml)
    root.find(".//geom[@name='pole_1']").set('fromto', _fmt((0, 0, 0, 0, 0, length)))
    return ElementTree.tostring(root, encoding='unicode')


def _reacher_forearm_length(xml: str, length: float) -> str:
    # The forearm (wrist to fingertip) of dm_control's two-link reacher
    # (default 0.12). The target becomes a body on two unactuated slide
    # joints, so its position is part of the joint state (observed), while
    # the fingertip is not: where the tip is depends on the length, which
    # a policy can learn only from the context (or be told, as the oracle).
    root = ElementTree.fromstring(xml)
    root.find(".//geom[@name='hand']").set('fromto', _fmt((0, 0, 0, length - 0.02, 0, 0)))
    finger = root.find(".//body[@name='finger']")
    finger.set('pos', _fmt((length, 0, 0)))
    # The fingertip's tracking camera would be the one renderings pick (the first
    # that moves); the fixed top view shows the arm, the target and the reach.
    finger.remove(finger.find("camera[@name='hand']"))
    worldbody = root.find('worldbody')
    old_target = worldbody.find("geom[@name='target']")
    worldbody.remove(old_target)
    target = ElementTree.SubElement(worldbody, 'body', name='target', pos='0 0 .01')
    for name, axis in (('target_x', '1 0 0'), ('target_y', '0 1 0')):
        ElementTree.SubElement(target, 'joint', name=name, type='slide', axis=axis,
                               damping='0', limited='false')
    ElementTree.SubElement(target, 'geom', name='target', type='sphere', size='.015',
                           material='target', contype='0', conaffinity='0')
    return ElementTree.tostring(root, encoding='unicode')


# reacher-length-orbit's target: a point mass on an isotropic spring about the
# arm's base, started on a circle with the speed of a circular orbit, so it
# goes round at this rate for the whole episode (and across a length swap,
# which carries the state over) without a scripted trajectory.
TARGET_ORBIT_RATE = 1.0    # rad/s: a lap in 6.3 s, about 314 control steps
TARGET_MASS = 0.01         # kg


def _reacher_forearm_length_orbit(xml: str, length: float) -> str:
    # As reacher-length, the target moving: an arm at rest holds no sign of
    # its length error (research/results/length_sign_ambiguity_*.md), an arm
    # that follows a moving target keeps showing its dynamics.
    root = ElementTree.fromstring(_reacher_forearm_length(xml, length))
    for name in ('target_x', 'target_y'):
        root.find(f".//joint[@name='{name}']").set(
            'stiffness', _fmt((TARGET_MASS * TARGET_ORBIT_RATE ** 2,)))
    root.find(".//body[@name='target']/geom[@name='target']").set('mass', _fmt((TARGET_MASS,)))
    return ElementTree.tostring(root, encoding='unicode')


def _unchanged(xml: str, _value: float) -> str:
    return xml


@dataclass(frozen=True)
class LiveParam:
    """One parameter a family varies: its ROS name, unit, default and live-swap range."""

    name: str
    unit: str
    default: float
    live_range: tuple[float, float]
    description: str

    def check(self, value: object) -> str | None:   # any value: checking it is the point
        """Return why a value cannot be put into force, or None when it can."""
        lo, hi = self.live_range
        try:
            value = float(value)
        except (TypeError, ValueError):
            return f'{self.name} must be a number, got {value!r}'
        if value != value:
            return f'{self.name} must not be NaN'
        if not lo <= value <= hi:
            # repr: the shortest text that is exactly this float, so a value just
            # past a bound (3.000001 against 3) never reads as the bound itself.
            return f'{self.name}={value!r} is outside the allowed range [{lo!r}, {hi!r}]'
        return None


def check_param(live_params: tuple[LiveParam, ...], family: str, name: str,
                value: object) -> str | None:
    """Why `name=value` cannot be put into force in `family`, or None when it can."""
    for param in live_params:
        if param.name == name:
            return param.check(value)
    names = ', '.join(repr(p.name) for p in live_params)
    return f'unknown parameter {name!r}; {family} has {names}'


# A family's task: a number for a one-parameter family (its splits are numbers, as
# printed in the paper), a value tuple in `param_names` order for one with several.
Task = float | tuple[float, ...]


@runtime_checkable
class SimFamily(Protocol):
    """What every family's spec answers (`FamilySpec`, `GoalFamilySpec`).

    Code that takes a family of either kind (the sim node, the trainer, the
    evaluator, the adaptation report, the reset check) reads it through this.
    Read-only properties: the specs are frozen dataclasses.
    """

    @property
    def name(self) -> str: ...            # the family's name, e.g. 'walker-walk-v0'

    @property
    def domain(self) -> str: ...          # the robot: 'walker', 'cheetah', ..., 'sawyer'

    @property
    def description(self) -> str: ...

    @property
    def live_params(self) -> tuple[LiveParam, ...]: ...   # in value-tuple order

    @property
    def param_names(self) -> tuple[str, ...]: ...

    @property
    def train(self) -> tuple[Task, ...]: ...

    @property
    def interpolation(self) -> tuple[Task, ...]: ...

    @property
    def extrapolation(self) -> tuple[Task, ...]: ...

    @property
    def alpha_psi(self) -> float: ...     # Table 11

    @property
    def reward_varies_only(self) -> bool: ...   # tasks differ only in the reward

    @property
    def episode_steps(self) -> int: ...   # the family's horizon, in control steps

    def split(self, name: str) -> tuple[Task, ...]: ...

    def check_param(self, name: str, value: object) -> str | None: ...


@dataclass(frozen=True)
class FamilySpec:
    """One environment family: a dm_control task and one varied parameter."""

    name: str
    domain: str
    param_name: str
    param_unit: str
    default: float
    train: tuple[float, ...]
    interpolation: tuple[float, ...]
    extrapolation: tuple[float, ...]
    live_range: tuple[float, float]
    alpha_psi: float
    description: str
    edit_xml: Callable[[str, float], str]
    reward_varies_only: bool = False
    episode_steps: int = EPISODE_STEPS
    task: str = ''   # a variant of the domain's task ('orbit': reacher's moving target)

    def split(self, name: str) -> tuple[float, ...]:
        """Parameter values of a split: train, interpolation or extrapolation."""
        if name not in SPLITS:
            raise ValueError(f'unknown split {name!r}; expected one of {SPLITS}')
        return getattr(self, name)

    @property
    def live_params(self) -> tuple[LiveParam, ...]:
        """The one parameter, as every family describes its parameters."""
        return (LiveParam(self.param_name, self.param_unit, self.default, self.live_range,
                          self.description),)

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of the live parameters, in the order of a value tuple."""
        return (self.param_name,)

    def check_value(self, value: float) -> str | None:
        """Return why a value cannot be put into force, or None when it can."""
        return self.live_params[0].check(value)

    def check_param(self, name: str, value: object) -> str | None:
        """Return why `name=value` cannot be put into force, or None when it can."""
        return check_param(self.live_params, self.name, name, value)


# A two-link arm reaching a target given in space, with the fingertip
# not observed: the joint angles that put the tip on the target
# depend on the forearm's length. Every target lies within reach of
# every length in the live range's core (radius 0.10-0.17).
_REACHER_LENGTH = FamilySpec(
    name='reacher-length', domain='reacher', param_name='forearm_length',
    param_unit='m', default=0.12,
    train=(0.08, 0.09, 0.1, 0.11, 0.14, 0.15, 0.16, 0.17),
    interpolation=(0.12, 0.125, 0.13, 0.135),
    extrapolation=(0.06, 0.065, 0.07, 0.075, 0.18, 0.19, 0.2, 0.21),
    live_range=(0.05, 0.25), alpha_psi=1.0,
    description='Two-link reacher, target observed, fingertip not; length of the '
                'forearm, wrist to fingertip (this project, not the paper).',
    edit_xml=_reacher_forearm_length)

FAMILIES: dict[str, FamilySpec] = {
    spec.name: spec
    for spec in (
        FamilySpec(
            name='walker-walk-v0', domain='walker', param_name='friction', param_unit='',
            default=0.7,
            train=(0.8, 0.85, 0.9, 0.95, 1.2, 1.25, 1.3, 1.35),
            interpolation=(1.0, 1.05, 1.1, 1.15),
            extrapolation=(0.3, 0.5, 0.7, 0.75, 1.4, 1.45, 1.7, 1.9),
            live_range=(0.05, 3.0), alpha_psi=2.0,
            description='Walker walk; sliding friction of every foot-ground contact (Table 4).',
            edit_xml=_walker_friction),
        # Not in the paper. In walker-walk-v0's range (0.8-1.35) a walking walker's
        # feet do not slip, and friction cannot be learned from k=5 transitions
        # (research/analysis/friction_identifiability.py). Here they do slip, so a live
        # friction swap changes the dynamics the context encoder sees. Splits
        # shaped like Table 4: two training clusters, the gap between them for
        # interpolation, values on both sides for extrapolation.
        FamilySpec(
            name='walker-walk-slippery', domain='walker', param_name='friction', param_unit='',
            default=0.25,
            train=(0.1, 0.125, 0.15, 0.175, 0.3, 0.325, 0.35, 0.375),
            interpolation=(0.2, 0.225, 0.25, 0.275),
            extrapolation=(0.06, 0.07, 0.08, 0.09, 0.4, 0.45, 0.5, 0.6),
            live_range=(0.05, 3.0), alpha_psi=2.0,
            description='Walker walk on a slippery floor; sliding friction of every foot-ground '
                        'contact, in a range where the feet slip (this project, not the paper).',
            edit_xml=_walker_friction),
        FamilySpec(
            name='walker-walk-v1', domain='walker', param_name='foot_length', param_unit='m',
            default=0.1,
            train=(0.09, 0.095, 0.1, 0.105, 0.13, 0.135, 0.14, 0.145),
            interpolation=(0.11, 0.115, 0.12, 0.125),
            extrapolation=(0.03, 0.06, 0.08, 0.085, 0.15, 0.155, 0.18, 0.21),
            live_range=(0.02, 0.3), alpha_psi=0.1,
            description='Walker walk; half-length of both foot capsules (Table 5).',
            edit_xml=_walker_foot_length),
        FamilySpec(
            name='cheetah-run-v0', domain='cheetah', param_name='torso_length', param_unit='m',
            default=1.0,
            train=(0.6, 0.65, 0.7, 0.75, 1.0, 1.05, 1.1, 1.15, 1.25, 1.4, 1.5),
            interpolation=(0.8, 0.85, 0.9, 0.95),
            # As printed: 1.25, 1.4 and 1.5 are in both train and extrapolation.
            extrapolation=(0.3, 0.4, 0.5, 0.55, 1.2, 1.25, 1.4, 1.5),
            live_range=(0.2, 2.0), alpha_psi=1.0,
            description='Cheetah run; torso length, total mass kept at 14 kg (Table 3).',
            edit_xml=_cheetah_torso_length),
        # Not in the paper: a candidate friction family where adaptation matters.
        # The walker's feet slip at 0.1-0.375 and yet its oracle was no better
        # than sac there. A running cheetah loses most of its return below 0.2
        # (a policy trained at 1.0: 524 at 1.0, 432 at 0.2, 211 at 0.05, 101 at
        # 0.02), so its gait has to change with friction. Splits shaped like
        # Table 4; extrapolation below and above the training clusters. Whether
        # the oracle beats sac here: research/results/cheetah_slippery_100k/.
        FamilySpec(
            name='cheetah-run-slippery', domain='cheetah', param_name='friction',
            param_unit='', default=0.15,
            train=(0.05, 0.06, 0.07, 0.08, 0.25, 0.3, 0.35, 0.4),
            interpolation=(0.12, 0.15, 0.18, 0.2),
            extrapolation=(0.02, 0.03, 0.035, 0.04, 0.5, 0.6, 0.8, 1.0),
            live_range=(0.01, 3.0), alpha_psi=1.0,
            description='Cheetah run on a slippery floor; sliding friction of every '
                        'foot-ground contact (this project, not the paper).',
            edit_xml=_cheetah_friction),
        FamilySpec(
            name='finger-spin-v0', domain='finger', param_name='finger_length', param_unit='m',
            default=0.16,
            train=(0.05, 0.0625, 0.075, 0.0875, 0.15, 0.1625, 0.175, 0.1875),
            interpolation=(0.1, 0.1125, 0.125, 0.1375),
            extrapolation=(0.01, 0.0125, 0.025, 0.0375, 0.2, 0.2125, 0.35, 0.5),
            live_range=(0.005, 0.6), alpha_psi=0.5,
            description='Finger spin; length of the distal finger segment (Table 2).',
            edit_xml=_finger_distal_length),
        # Not in the paper: issue #36's pilots, families where the parameter may
        # decide the return. Friction over RMA's width (trained 0.05-4.5,
        # tested below and above), meant to be trained with swaps inside
        # episodes (`train_swap_prob`).
        FamilySpec(
            name='cheetah-run-wide-friction', domain='cheetah', param_name='friction',
            param_unit='', default=0.4,
            train=(0.05, 0.1, 0.2, 0.4, 0.8, 1.5, 2.5, 4.5),
            interpolation=(0.07, 0.3, 1.1, 3.5),
            extrapolation=(0.02, 0.025, 0.03, 0.04, 5.0, 5.25, 5.5, 6.0),
            live_range=(0.01, 8.0), alpha_psi=1.0,
            description='Cheetah run; sliding friction of every foot-ground contact over '
                        "RMA's width (this project, not the paper).",
            edit_xml=_cheetah_friction),
        # CaDM's pole-length CartPole ranges (train 0.8-1.2 of the default,
        # tested at 0.3-0.4 and 1.6-1.7) on dm_control's swing-up.
        FamilySpec(
            name='cartpole-swingup-length', domain='cartpole', param_name='pole_length',
            param_unit='m', default=1.0,
            train=(0.8, 0.85, 0.9, 0.95, 1.05, 1.1, 1.15, 1.2),
            interpolation=(0.875, 0.975, 1.0, 1.125),
            extrapolation=(0.3, 0.33, 0.36, 0.4, 1.6, 1.63, 1.66, 1.7),
            live_range=(0.2, 2.0), alpha_psi=1.0,
            description="Cartpole swing-up; length of the pole, mass kept at 0.1 kg "
                        "(CaDM's ranges; this project, not the paper).",
            edit_xml=_cartpole_pole_length),
        _REACHER_LENGTH,
        # The same arm and splits, the target going round the base on a circle
        # (TARGET_ORBIT_RATE): the arm keeps moving, so its windows keep
        # showing how the forearm's length shapes its dynamics.
        replace(_REACHER_LENGTH, name='reacher-length-orbit',
                description='Two-link reacher following a target that orbits its base '
                            '(1 rad/s), target observed, fingertip not; length of the '
                            'forearm (this project, not the paper).',
                edit_xml=_reacher_forearm_length_orbit, task='orbit'),
        FamilySpec(
            name='cheetah-run-v1', domain='cheetah', param_name='target_velocity',
            param_unit='m/s', default=1.5,
            train=(0.0, 0.43, 0.86, 1.29, 1.71, 2.14, 2.57, 3.0),
            # Table 6 has one evaluation split; it lies inside the train range.
            interpolation=(0.4, 0.78, 1.11, 1.47, 1.83, 2.18, 2.55, 2.9),
            extrapolation=(),
            live_range=(-1.0, 6.0), alpha_psi=1.0,
            description="Cheetah; reward -|v - v_target| - 0.05|a|^2 as MELD's cheetah-vel "
                        '(Table 6); dynamics unchanged.',
            edit_xml=_unchanged, reward_varies_only=True),
    )
}


# Sawyer-Peg-v0 (Table 7, from MELD). Its goal is the hole's position in MELD's
# frame: x forward from the robot's base, y to its left (m).
SAWYER_PEG = 'sawyer-peg-v0'
TABLE7_X_RANGES = ((0.44, 0.45), (0.6, 0.61))
TABLE7_Y_RANGES = ((-0.08, -0.07), (0.07, 0.08))
# MELD drew its evaluation tasks from seed 0 and its training tasks from seed 1.
TABLE7_SEEDS = {'train': 1, 'interpolation': 0}
GOALS_PER_SPLIT = 8        # two per (x range, y range) cluster, as the other families' 8


def table7_goals(split: str) -> tuple[tuple[float, float], ...]:
    """Return the split's (x, y) hole positions, drawn per Table 7 from a fixed seed.

    Each draw takes the four (x range, y range) clusters in turn and a uniform
    point in it, as MELD placed its four boxes. The paper has one evaluation
    split, stored as `interpolation` (as cheetah-run-v1's Table 6);
    `extrapolation` is empty.
    """
    if split not in SPLITS:
        raise ValueError(f'unknown split {split!r}; expected one of {SPLITS}')
    if split not in TABLE7_SEEDS:
        return ()
    rng = np.random.default_rng(TABLE7_SEEDS[split])
    clusters = [(xr, yr) for xr in TABLE7_X_RANGES for yr in TABLE7_Y_RANGES]
    goals = []
    for i in range(GOALS_PER_SPLIT):
        x_range, y_range = clusters[i % len(clusters)]
        goals.append((float(rng.uniform(*x_range)), float(rng.uniform(*y_range))))
    return tuple(goals)


@dataclass(frozen=True)
class GoalFamilySpec:
    """A family whose tasks are goal positions: several named parameters, values as tuples.

    Sawyer-Peg-v0 is the one such family. Its goal moves the hole the peg goes
    into: only the reward changes, and a swap writes the block's position into
    the live model (no recompile).
    """

    name: str
    domain: str
    live_params: tuple[LiveParam, ...]
    train: tuple[tuple[float, ...], ...]
    interpolation: tuple[tuple[float, ...], ...]
    extrapolation: tuple[tuple[float, ...], ...]
    description: str
    alpha_psi: float = 1.0        # Table 11
    episode_steps: int = 40       # Table 9's horizon
    reward_varies_only: bool = True

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of the live parameters, in the order of a value tuple."""
        return tuple(p.name for p in self.live_params)

    @property
    def defaults(self) -> tuple[float, ...]:
        """What a sim starts with before any task is set."""
        return tuple(p.default for p in self.live_params)

    def split(self, name: str) -> tuple[tuple[float, ...], ...]:
        """Goal positions of a split: train, interpolation or extrapolation."""
        if name not in SPLITS:
            raise ValueError(f'unknown split {name!r}; expected one of {SPLITS}')
        return getattr(self, name)

    def check_param(self, name: str, value: object) -> str | None:
        """Return why `name=value` cannot be put into force, or None when it can."""
        return check_param(self.live_params, self.name, name, value)


# The live ranges keep the block on the table, within the arm's reach and clear of
# the peg at the start pose; the default lies between Table 7's four clusters.
GOAL_FAMILIES: dict[str, GoalFamilySpec] = {
    SAWYER_PEG: GoalFamilySpec(
        name=SAWYER_PEG, domain='sawyer',
        live_params=(
            LiveParam('goal_x', 'm', 0.525, (0.40, 0.65),
                      'Sawyer peg insertion; x of the hole, forward from the robot base '
                      '(Table 7).'),
            LiveParam('goal_y', 'm', 0.0, (-0.15, 0.15),
                      "Sawyer peg insertion; y of the hole, to the robot's left (Table 7).")),
        train=table7_goals('train'), interpolation=table7_goals('interpolation'),
        extrapolation=(),
        description='Sawyer arm inserting a held peg into a hole whose position varies '
                    "(Table 7, MELD's reward without its offset); the reward is observed."),
}
# Every family the sim node runs, by name.
SIM_FAMILIES: dict[str, SimFamily] = {**FAMILIES, **GOAL_FAMILIES}


def domain_model(domain: str) -> tuple[str, dict]:
    """Return the dm_control model XML and assets of a domain (walker, cheetah, finger).

    dm_control is imported here, not at module level: the family tables are
    read by processes that must not load MuJoCo (the controller nodes).
    """
    from dm_control.suite import cartpole, cheetah, finger, reacher, walker
    loaders = {'walker': walker.get_model_and_assets,
               'cheetah': cheetah.get_model_and_assets,
               'finger': finger.get_model_and_assets,
               'cartpole': cartpole.get_model_and_assets,
               'reacher': reacher.get_model_and_assets}
    return loaders[domain]()


def values_with(spec: SimFamily, values: Sequence[float],
                changes: Mapping[str, float]) -> tuple[float, ...]:
    """Return `values` (in `spec.param_names` order) with `changes` (name: value) made.

    The one way from names to a value tuple: a ROS parameter set names the
    parameters it changes, an env takes the whole tuple (`set_values`,
    `prepare_values`). Each change is checked as a live set is
    (`check_param`: a known name, a number in its live range); ValueError says why not.
    """
    for name, value in changes.items():
        reason = spec.check_param(name, value)
        if reason is not None:
            raise ValueError(reason)
    merged = dict(zip(spec.param_names, values, strict=True))
    merged.update({name: float(value) for name, value in changes.items()})
    return tuple(merged[name] for name in spec.param_names)


def as_values(value: float | Sequence[float] | np.ndarray) -> tuple[float, ...]:
    """Return a task's value as a value tuple: (v,) for a one-parameter family's number."""
    if isinstance(value, tuple | list | np.ndarray):
        return tuple(float(v) for v in value)
    return (float(value),)


def format_task(value: float | Sequence[float] | np.ndarray) -> str:
    """Return a task's value as text: '0.4', or '0.445 -0.0705' for several parameters."""
    return ' '.join(f'{v:.6g}' for v in as_values(value))


def get_family(name: str) -> FamilySpec:
    """Look a one-parameter dm_control family up by name (`ParamEnv`'s; research/analysis)."""
    try:
        return FAMILIES[name]
    except KeyError:
        if name in GOAL_FAMILIES:
            raise ValueError(f'{name} has {len(GOAL_FAMILIES[name].live_params)} parameters '
                             f'and its own env; this needs one of {", ".join(FAMILIES)}') \
                from None
        raise ValueError(f'unknown family {name!r}; known: {", ".join(SIM_FAMILIES)}') from None


def get_sim_family(name: str) -> SimFamily:
    """Look any family up by name, with the known names in the error."""
    try:
        return SIM_FAMILIES[name]
    except KeyError:
        raise ValueError(f'unknown family {name!r}; known: {", ".join(SIM_FAMILIES)}') from None


def register_family(spec: SimFamily, fingerprint: str) -> None:
    """Make a family from a family file known by name to every tool in this process.

    `fingerprint` (the file's hash) tells a repeated registration of the same
    file, which is harmless, from a second file claiming the same name, which
    would make the name mean two robots: ValueError. A built-in's name cannot be taken.
    """
    if spec.name in FAMILIES or spec.name in GOAL_FAMILIES:
        raise ValueError(f'{spec.name!r} is a built-in family; give the file another name')
    known = _REGISTERED.get(spec.name)
    if known is not None and known != fingerprint:
        raise ValueError(f'a different family file named {spec.name!r} is already loaded')
    _REGISTERED[spec.name] = fingerprint
    SIM_FAMILIES[spec.name] = spec


_REGISTERED: dict[str, str] = {}   # family-file families by name: their files' hashes
