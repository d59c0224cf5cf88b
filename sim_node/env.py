"""One parameter-varied MuJoCo environment, shared by the trainer and sim_node.

`ParamEnv` runs a dm_control task (walker walk, cheetah run, finger spin) on a
model built for one value of the family's parameter, steps it at the task's
control rate for episodes of the family's horizon (`FamilySpec.episode_steps`,
1000 steps), and can swap the parameter mid-episode: the model is rebuilt
and the whole simulator state (positions, velocities, actuator state, warm
start, time) carried over, so motion continues. Its parameter is a value
tuple of one, as every family's (`sim_node.family_env.FamilyEnv`): `set_values`
puts a tuple into force. A swap also comes in two halves, for a caller that
must not wait for MuJoCo's compiler (the sim node): `prepare_values` on any
thread, `apply_prepared` at a step boundary (the same trajectory as `set_values`).

The observation is a function of joint positions and velocities only (see
`ObservationLayout`), so the sim node's `sensor_msgs/JointState` carries
everything the policy needs, and the vector rebuilt from it is bit-identical.
With ``reward_in_obs`` the reward of the transition into the state is
appended (the appendix's choice for reward-varying families); the nodes read
it from the StepInfo of the state's stamp.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import functools
import math
from typing import TYPE_CHECKING
import xml.etree.ElementTree as ElementTree

from dm_control.rl import control
from dm_control import mujoco as dm_mujoco
from dm_control.suite import base, cartpole, cheetah, finger, walker
from dm_control.utils import rewards
import mujoco
import numpy as np

from sim_node.families import (domain_model, FamilySpec, get_family, get_sim_family,
                               GOAL_FAMILIES, TARGET_ORBIT_RATE)
from sim_node.family_env import FamilyEnv
from sim_node.family_file import FileFamilySpec
from sim_node.model_copy import ModelWriter as _ModelWriter, structure_of
from sim_node.layout import check_action, DROPPED_JOINTS, ObservationLayout, StepResult

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = ['check_action', 'ObservationLayout', 'ParamEnv', 'StepResult', 'layout_from_model']

# Control period of each domain, as dm_control's walk/run/spin tasks use it.
CONTROL_TIMESTEP = {'walker': 0.025, 'cheetah': 0.01, 'finger': 0.02, 'cartpole': 0.01,
                    'reacher': 0.02}

_PHYSICS = {'walker': walker.Physics, 'cheetah': cheetah.Physics, 'finger': finger.Physics,
            'cartpole': cartpole.Physics, 'reacher': dm_mujoco.Physics}



class CheetahTargetVelocity(cheetah.Cheetah):
    """Cheetah with MELD's cheetah-vel reward: -|v - v_target| - 0.05 |a|^2."""

    def __init__(self, target_velocity: float,
                 random: np.random.RandomState | int | None = None):
        super().__init__(random=random)
        self.target_velocity = float(target_velocity)

    def get_reward(self, physics: cheetah.Physics):  # noqa: D102
        speed_error = abs(physics.speed() - self.target_velocity)
        control_cost = 0.05 * float(np.sum(np.square(physics.data.ctrl)))
        return -speed_error - control_cost


class ReachTargetInSpace(base.Task):
    """Reacher whose target is a joint-state position and whose fingertip is not observed.

    The target is put at a uniform angle and a radius of 0.10-0.17 m, reachable
    by every forearm length of `reacher-length`'s core range. The reward is
    1 within 1 cm and falls with a long tail (0.24 at 6 cm): dense enough to
    learn from, sharp enough that a tip placed for the wrong length loses it.
    """

    TARGET_RADII = (0.10, 0.17)

    def initialize_episode(self, physics: dm_mujoco.Physics):  # noqa: D102
        qpos = physics.named.data.qpos
        qpos['shoulder'] = self.random.uniform(-np.pi, np.pi)
        qpos['wrist'] = self.random.uniform(*np.radians((-160.0, 160.0)))
        angle = self.random.uniform(0, 2 * np.pi)
        radius = self.random.uniform(*self.TARGET_RADII)
        qpos['target_x'] = radius * np.sin(angle)
        qpos['target_y'] = radius * np.cos(angle)
        super().initialize_episode(physics)

    # ARG002: the env builds its own observation.
    def get_observation(self, physics: dm_mujoco.Physics):  # noqa: D102, ARG002
        return {}

    def get_reward(self, physics: dm_mujoco.Physics):  # noqa: D102
        xpos = physics.named.data.geom_xpos
        distance = float(np.linalg.norm(xpos['target', :2] - xpos['finger', :2]))
        return rewards.tolerance(distance, bounds=(0.0, 0.01), margin=0.05,
                                 sigmoid='long_tail', value_at_margin=0.1)


class ReachOrbitingTarget(ReachTargetInSpace):
    """ReachTargetInSpace with the target started on a circular orbit about the base.

    The target's spring (families.TARGET_ORBIT_RATE) keeps it on the circle;
    the direction of travel is drawn per episode.
    """

    def initialize_episode(self, physics: dm_mujoco.Physics):  # noqa: D102
        super().initialize_episode(physics)
        qpos, qvel = physics.named.data.qpos, physics.named.data.qvel
        direction = self.random.choice((-1.0, 1.0))
        x, y = qpos['target_x'], qpos['target_y']
        qvel['target_x'] = -direction * TARGET_ORBIT_RATE * y
        qvel['target_y'] = direction * TARGET_ORBIT_RATE * x


def _make_task(spec: FamilySpec, value: float, random: np.random.RandomState):
    if spec.domain == 'reacher':
        return (ReachOrbitingTarget if spec.task == 'orbit' else ReachTargetInSpace)(random=random)
    if spec.domain == 'cartpole':
        return cartpole.Balance(swing_up=True, sparse=False, random=random)
    if spec.domain == 'walker':
        return walker.PlanarWalker(move_speed=walker._WALK_SPEED, random=random)
    if spec.domain == 'finger':
        return finger.Spin(random=random)
    if spec.reward_varies_only:
        return CheetahTargetVelocity(value, random=random)
    return cheetah.Cheetah(random=random)


def _edited_model(spec: FamilySpec, value: float) -> tuple[str, dict, float | None]:
    """Return the family's MJCF with `value` put in (families.py's edit), assets, total mass."""
    xml, assets = domain_model(spec.domain)
    xml = xml.decode() if isinstance(xml, bytes) else xml
    root = ElementTree.fromstring(spec.edit_xml(xml, value))
    # The compiler's `settotalmass` is deprecated in MuJoCo 3.x; do the same
    # rescaling (masses and inertias to a fixed total) on the compiled model.
    compiler = root.find('compiler')
    total_mass = None
    if compiler is not None and compiler.get('settotalmass') is not None:
        total_mass = float(compiler.attrib.pop('settotalmass'))
    return ElementTree.tostring(root, encoding='unicode'), assets, total_mass


def build_physics(spec: FamilySpec, value: float):
    """Compile the family's MuJoCo model with the parameter set to `value`."""
    xml, assets, total_mass = _edited_model(spec, value)
    physics = _PHYSICS[spec.domain].from_xml_string(xml, assets)
    if total_mass is not None:
        mujoco.mj_setTotalmass(physics.model.ptr, total_mass)
        mujoco.mj_setConst(physics.model.ptr, physics.data.ptr)
    return physics


def build_model(spec: FamilySpec, value: float) -> mujoco.MjModel:
    """Compile the model `build_physics` compiles, for a swap: no Physics, low-res textures.

    Every field but the textures is the one `build_physics` gives (test_swap_physics.py).
    The builtin textures (dm_control's 800x800 skybox, 11.8 MB) are made 2x2:
    they only colour renderings, a swap keeps the live model's (`_ModelWriter`),
    and generating them was 98 % of the compile (~100 ms against ~2 ms).
    """
    xml, _, total_mass = _edited_model(spec, value)
    model = mujoco.MjModel.from_xml_string(xml, dict(_low_res_assets(spec.domain)))
    if total_mass is not None:
        mujoco.mj_setTotalmass(model, total_mass)
        mujoco.mj_setConst(model, mujoco.MjData(model))
    return model


@functools.lru_cache(maxsize=None)
def _low_res_assets(domain: str) -> dict:
    """Return the domain's assets with every builtin texture at 2x2 pixels.

    (The main MJCF of these domains has no texture; one there would only compile slower.)
    """
    _, assets = domain_model(domain)
    low_res = {}
    for name, content in assets.items():
        if name.endswith('.xml'):
            root = ElementTree.fromstring(content)
            for texture in root.iter('texture'):
                if texture.get('builtin') is not None:
                    texture.set('width', '2')
                    texture.set('height', '2')
            content = ElementTree.tostring(root)
        low_res[name] = content
    return low_res


def layout_from_model(model: mujoco.MjModel) -> ObservationLayout:
    """Read the observation layout off a model whose joints are all hinges or slides."""
    names, encodings = [], []
    for j in range(model.njnt):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
        jtype = int(model.jnt_type[j])
        if jtype not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            raise ValueError(f'joint {name!r} is not a hinge or slide joint')
        names.append(name)
        if name in DROPPED_JOINTS:
            encodings.append('drop')
        elif jtype == mujoco.mjtJoint.mjJNT_HINGE and not model.jnt_limited[j]:
            encodings.append('angle')
        else:
            encodings.append('raw')
    return ObservationLayout(tuple(names), tuple(encodings))


@dataclass(frozen=True)
class PreparedParam:
    """Values and the model compiled for them, not yet in force (`ParamEnv.prepare_values`)."""

    values: tuple[float]   # the family's value tuple (one value), as the swaps carry it
    model: mujoco.MjModel


class ParamEnv:
    """A dm_control task whose physical parameter can change at a step boundary."""

    def __init__(self, family: str, value: float | None = None, seed: int | None = 0,
                 episode_steps: int | None = None, reward_in_obs: bool = False):
        """`episode_steps` None: the family's horizon (`FamilySpec.episode_steps`)."""
        self.spec = get_family(family)
        self.episode_steps = self.spec.episode_steps if episode_steps is None else episode_steps
        self.control_timestep = CONTROL_TIMESTEP[self.spec.domain]
        self._random = np.random.RandomState(seed)
        self._value = float(self.spec.default if value is None else value)
        self._require_valid(self._value)
        self._physics = build_physics(self.spec, self._value)
        self._task = _make_task(self.spec, self._value, self._random)
        self._n_sub_steps = int(round(self.control_timestep / self._physics.model.opt.timestep))
        model = self._physics.model
        self.layout = replace(layout_from_model(model.ptr), reward_in_observation=reward_in_obs)
        self._last_reward = 0.0    # into the current state (the observation's last entry)
        self.actuator_names = tuple(model.id2name(i, 'actuator') for i in range(model.nu))
        self._writer = _ModelWriter(model.ptr)   # apply_prepared's (binding it takes ~1 ms)
        self.default_camera = None               # the camera's choice (camera.pick_camera)
        self._structure = structure_of(model.ptr)
        self.step_count = 0
        self._reset_physics()

    # -- properties -------------------------------------------------------
    @property
    def family(self) -> str:
        """The family's name."""
        return self.spec.name

    @property
    def param_names(self) -> tuple[str, ...]:
        """The live parameter's name, as a tuple (what the sim node reads for any family)."""
        return self.spec.param_names

    @property
    def param_values(self) -> tuple[float, ...]:
        """The parameter value in force, as a tuple in `param_names` order."""
        return (self._value,)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """All joints, root degrees of freedom included, in model order."""
        return self.layout.joint_names

    @property
    def actuator_units(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """(ctrl low, ctrl high, gear) per actuator: a motor's effort is gear * ctrl."""
        model = self._physics.model
        ranges = model.actuator_ctrlrange
        return (tuple(float(v) for v in ranges[:, 0]), tuple(float(v) for v in ranges[:, 1]),
                tuple(float(v) for v in model.actuator_gear[:, 0]))

    @property
    def obs_dim(self) -> int:
        """Length of the observation vector."""
        return self.layout.size

    @property
    def action_dim(self) -> int:
        """Number of actuators."""
        return len(self.actuator_names)

    @property
    def time(self) -> float:
        """Simulated time within the episode, in seconds."""
        return float(self._physics.data.time)

    @property
    def physics(self) -> dm_mujoco.Physics:
        """The dm_control Physics in force (`set_values` makes a new one, `apply_prepared` not)."""
        return self._physics

    def joint_positions(self) -> np.ndarray:
        """Joint positions in `joint_names` order (a copy)."""
        return self._physics.data.qpos.copy()

    def joint_velocities(self) -> np.ndarray:
        """Joint velocities in `joint_names` order (a copy)."""
        return self._physics.data.qvel.copy()

    def observation(self) -> np.ndarray:
        """Return the policy's observation of the current state."""
        data = self._physics.data
        return self.layout.observation(data.qpos, data.qvel, self._last_reward)

    # -- episode control --------------------------------------------------
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start a new episode; a seed restarts the random stream, None continues it."""
        if seed is not None:
            self._random.seed(seed)
        self._reset_physics()
        return self.observation()

    def step(self, action: ArrayLike) -> StepResult:
        """Apply a normalised action for one control period.

        Raises ValueError for an action that `check_action` rejects: callers
        decide what to apply instead, nothing invalid reaches MuJoCo.
        """
        clean, reason = check_action(action, self.action_dim)
        if reason is not None:
            raise ValueError(reason)
        try:
            self._task.before_step(clean, self._physics)
            self._physics.step(self._n_sub_steps)
            self._task.after_step(self._physics)
            reward = float(self._task.get_reward(self._physics))
            self._last_reward = reward
            observation = self.observation()
            if not (np.all(np.isfinite(observation)) and math.isfinite(reward)):
                raise control.PhysicsError('non-finite state or reward')
        except control.PhysicsError as error:
            self._reset_physics()
            return StepResult(self.observation(), 0.0, False, True, applied_action=clean,
                              instability=str(error))
        self.step_count += 1
        truncated = self.step_count >= self.episode_steps
        return StepResult(observation, reward, False, truncated, applied_action=clean)

    def set_values(self, values: tuple[float, ...]) -> None:
        """Put new parameter values into force, keeping the simulator state (a new Physics)."""
        value = self._one_value(values)
        physics = build_physics(self.spec, value)
        _copy_state(self._physics.data, physics)
        self._physics = physics
        self._writer = _ModelWriter(physics.model.ptr)
        self._task = _make_task(self.spec, value, self._random)
        self._value = value

    def prepare_values(self, values: tuple[float, ...]) -> PreparedParam:
        """Compile the model of `values` without touching this env (safe on another thread).

        The slow half of a live swap (2-5 ms, see `build_model`); the sim node
        runs it on a worker thread, so that its control loop never waits for it.
        """
        value = self._one_value(values)
        model = build_model(self.spec, value)
        if structure_of(model) != self._structure:   # the edit changed more than values
            raise ValueError(f'{self.spec.param_name}={value:g} changes the structure of the '
                             f'{self.spec.domain} model: it cannot be swapped in place')
        return PreparedParam((value,), model)

    def apply_prepared(self, prepared: PreparedParam) -> None:
        """Put prepared values into force at a step boundary, keeping the simulator state.

        The fast half (~0.2 ms): the new model is written into the live one
        in place and the derived quantities recomputed; the physics, its data
        and the state stay. The trajectory is bit-identical to `set_values`'
        (test_swap_physics.py checks every family).
        """
        (value,) = prepared.values
        self._writer.write(prepared.model)
        self._physics.forward()
        self._task = _make_task(self.spec, value, self._random)
        self._value = value

    def copy_state_from(self, other: 'ParamEnv') -> None:
        """Take another env's simulator state and step count (same family, any value).

        Gives "the same state and action under other physics": the
        counterfactual transitions of the adaptation report.
        """
        if other.family != self.family:
            raise ValueError(f'cannot copy a {other.family} state into {self.family}')
        _copy_state(other.physics.data, self._physics)
        self.step_count = other.step_count
        self._last_reward = other._last_reward

    def _one_value(self, values: tuple[float, ...]) -> float:
        """Return the one value of a value tuple, checked against the live range."""
        values = tuple(values)
        if len(values) != 1:
            raise ValueError(f'{self.family} has one parameter, got {len(values)} values')
        self._require_valid(values[0])
        return float(values[0])

    def _require_valid(self, value: float) -> None:
        reason = self.spec.check_value(value)
        if reason is not None:
            raise ValueError(reason)

    def _reset_physics(self) -> None:
        self.step_count = 0
        self._last_reward = 0.0
        with self._physics.reset_context():
            self._task.initialize_episode(self._physics)


def _copy_state(source: dm_mujoco.wrapper.MjData, physics: dm_mujoco.Physics) -> None:
    """Copy the dynamic state of MjData `source` into `physics` and recompute derived terms."""
    # Same joints, actuators and activations: only sizes/friction/masses differ.
    new = physics.data
    for field in ('qpos', 'qvel', 'act', 'ctrl', 'qacc_warmstart'):
        getattr(new, field)[:] = getattr(source, field)
    new.time = source.time
    physics.forward()


def make_env(family: str, values: tuple[float, ...] | None = None, seed: int | None = 0,
             **options) -> FamilyEnv:
    """Return the env of any family the sim node runs: `ParamEnv`, Sawyer-Peg-v0's, `FileEnv`.

    Both are a `FamilyEnv` (sim_node.family_env): what the trainer, the
    evaluator, the adaptation report and the sim node use of an env.
    `values` None: the family's defaults. `options`: `episode_steps` (None
    or left out: the family's horizon), `reward_in_obs` (Sawyer-Peg-v0 always
    observes the reward).
    """
    spec = get_sim_family(family)
    if isinstance(spec, FileFamilySpec):
        from sim_node.file_env import FileEnv   # MuJoCo only: no dm_control task
        return FileEnv(spec, values, seed=seed, **options)
    if spec.name in GOAL_FAMILIES:
        from sim_node.sawyer import SawyerPegEnv   # the Sawyer scene loads for its family only
        if not options.pop('reward_in_obs', True):
            raise ValueError(f'{family} observes the reward: reward_in_obs cannot be off')
        return SawyerPegEnv(values, seed=seed, **options)
    if values is not None and len(values) != 1:
        raise ValueError(f'{family} has one parameter, got {len(values)} values')
    return ParamEnv(family, None if values is None else values[0], seed=seed, **options)
