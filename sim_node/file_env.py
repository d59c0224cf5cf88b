"""`FileEnv`: the env of a family declared in a family file (`sim_node.family_file`).

It answers `FamilyEnv` as `ParamEnv` does, so `make_env` returns it for a
registered file family and the trainer, evaluator, adaptation report and sim
node use it unchanged. The task is the file's: a weighted sum of reward
terms and, where declared, a healthy range whose exit ends the episode (a
terminal step, as Gymnasium's `terminate_when_unhealthy`).

A live swap follows MuJoCo's rules for model changes: values that differ
only in friction are written straight into `geom_friction` (a real-valued
field MuJoCo allows to change between steps; no compile); any other change
compiles the new model off the loop (`prepare_values`, `family_edits`) and
copies it into the live model at a step boundary, MjData (the state) kept.
"""

from __future__ import annotations

from dataclasses import dataclass
import importlib
import math
from typing import TYPE_CHECKING

from dm_control import mujoco as dm_mujoco
from dm_control.rl.control import PhysicsError
import mujoco
import numpy as np

from sim_node.family_edits import family_model
from sim_node.family_file import (ControlCost, FileFamilySpec, ForwardSpeed, FrictionEdit,
                                  Healthy, SiteDistance)
from sim_node.family_env import ModelView, PhysicsView
from sim_node.layout import check_action, StepResult
from sim_node.model_copy import ModelWriter, structure_of

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

_AXES = {'x': 0, 'y': 1, 'z': 2}


@dataclass(frozen=True)
class PreparedFileValues:
    """Values checked, and their model compiled unless only friction changed."""

    values: tuple[float, ...]
    model: mujoco.MjModel | None   # None: a friction-only swap, written directly
    assumes: tuple[float, ...]     # the non-friction values the direct write presumes


class SuiteTask:
    """A dm_control suite task on this env's model: its Physics wraps the same MjModel.

    Stepping, resetting and the reward are dm_control's own calls, in the order
    `sim_node.env.ParamEnv` makes them, so a family file naming a suite task
    runs as the built-in family of that task does.
    """

    def __init__(self, domain: str, name: str, model: mujoco.MjModel,
                 random: np.random.RandomState):
        from dm_control import suite
        from dm_control.mujoco import wrapper
        self.task = suite.load(domain, name, task_kwargs={'random': random}).task
        self.physics = _physics_class(domain).from_model(wrapper.MjModel(model))

    def reset(self) -> None:  # noqa: D102
        with self.physics.reset_context():
            self.task.initialize_episode(self.physics)

    def step(self, ctrl: np.ndarray, n_sub_steps: int) -> tuple[float, bool]:
        """One control period; the reward and whether the task ended the episode."""
        self.task.before_step(ctrl, self.physics)
        self.physics.step(n_sub_steps)
        self.task.after_step(self.physics)
        ended = self.task.get_termination(self.physics) is not None
        return float(self.task.get_reward(self.physics)), ended


def _physics_class(domain: str) -> type:
    # The domain's own Physics (cheetah's has speed()), which its tasks call.
    return getattr(importlib.import_module(f'dm_control.suite.{domain}'), 'Physics',
                   dm_mujoco.Physics)


class FileEnv:
    """A family file's robot and task, its parameters swappable at a step boundary."""

    def __init__(self, spec: FileFamilySpec, values: tuple[float, ...] | None = None,
                 seed: int | None = 0, episode_steps: int | None = None,
                 reward_in_obs: bool = False):
        self.spec = spec
        self._builder = family_model(spec)
        doc = spec.document
        self.episode_steps = doc.control.horizon if episode_steps is None else episode_steps
        self.control_timestep = doc.control.period
        self._values = self._checked(spec.defaults if values is None else values)
        self._random = np.random.RandomState(seed)
        self.model = self._builder.compile(self._values)
        self._suite = None if doc.task.suite_task is None else \
            SuiteTask(doc.model.suite, doc.task.suite_task, self.model, self._random)
        self.data = mujoco.MjData(self.model) if self._suite is None else \
            self._suite.physics.data.ptr
        self._structure = structure_of(self.model)
        self._writer = ModelWriter(self.model)
        self._n_sub_steps = round(self.control_timestep / self.model.opt.timestep)
        layout = self._builder.layout()
        self.layout = layout if not reward_in_obs else \
            type(layout)(layout.joint_names, layout.position_encoding, True)
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, n)
               for n in layout.joint_names]
        self._qpos = self.model.jnt_qposadr[ids]
        self._qvel = self.model.jnt_dofadr[ids]
        self.actuator_names = self._builder.structure().actuator_names
        self.default_camera = None
        self._friction_only = [isinstance(p.edit, FrictionEdit) for p in doc.parameters]
        self._reset_physics()

    # -- what it is ----------------------------------------------------------------
    @property
    def family(self) -> str:  # noqa: D102
        return self.spec.name

    @property
    def param_names(self) -> tuple[str, ...]:  # noqa: D102
        return self.spec.param_names

    @property
    def param_values(self) -> tuple[float, ...]:  # noqa: D102
        return self._values

    @property
    def joint_names(self) -> tuple[str, ...]:  # noqa: D102
        return self.layout.joint_names

    @property
    def obs_dim(self) -> int:  # noqa: D102
        return self.layout.size

    @property
    def action_dim(self) -> int:  # noqa: D102
        return len(self.actuator_names)

    @property
    def time(self) -> float:  # noqa: D102
        return float(self.data.time)

    @property
    def physics(self) -> PhysicsView:  # noqa: D102
        if self._suite is not None:
            return self._suite.physics
        return PhysicsView(ModelView(self.model), self.data)

    def joint_positions(self) -> np.ndarray:  # noqa: D102
        return self.data.qpos[self._qpos].copy()

    def joint_velocities(self) -> np.ndarray:  # noqa: D102
        return self.data.qvel[self._qvel].copy()

    def observation(self) -> np.ndarray:  # noqa: D102
        return self.layout.observation(self.joint_positions(), self.joint_velocities(),
                                       self._last_reward)

    # -- episodes --------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> np.ndarray:  # noqa: D102
        if seed is not None:
            self._random.seed(seed)
        self._reset_physics()
        return self.observation()

    def _reset_physics(self) -> None:
        self.step_count = 0
        self._last_reward = 0.0
        if self._suite is not None:
            self._suite.reset()
            return
        mujoco.mj_resetData(self.model, self.data)
        noise = self.spec.document.task.reset_noise
        self.data.qpos[:] += self._random.uniform(-noise, noise, self.model.nq)
        self.data.qvel[:] += self._random.uniform(-noise, noise, self.model.nv)
        mujoco.mj_forward(self.model, self.data)

    def step(self, action: ArrayLike) -> StepResult:
        """One control period; ValueError for an action `check_action` refuses."""
        clean, reason = check_action(action, self.action_dim)
        if reason is not None:
            raise ValueError(reason)
        try:
            reward, terminal = self._advance(self._scaled(clean))
            observation = self.observation()
            if not (np.all(np.isfinite(observation)) and math.isfinite(reward)):
                raise PhysicsError('non-finite state or reward')
        except PhysicsError as error:
            self._reset_physics()
            return StepResult(self.observation(), 0.0, False, True, applied_action=clean,
                              instability=str(error))
        self._last_reward = reward
        observation = self.observation()
        self.step_count += 1
        truncated = not terminal and self.step_count >= self.episode_steps
        return StepResult(observation, reward, terminal, truncated, applied_action=clean)

    def _advance(self, ctrl: np.ndarray) -> tuple[float, bool]:
        """Step one control period; return the reward and whether the episode ended."""
        if self._suite is not None:
            return self._suite.step(ctrl, self._n_sub_steps)
        self.data.ctrl[:] = ctrl
        before = self.data.xpos.copy()
        mujoco.mj_step(self.model, self.data, self._n_sub_steps)
        # mj_step leaves positions (xpos, site_xpos) one substep behind qpos; the reward
        # reads them at the state it is for. Kinematics only: the dynamics are untouched.
        mujoco.mj_kinematics(self.model, self.data)
        healthy = self.spec.document.task.healthy
        return (self._reward(before),
                healthy is not None and healthy.end_episode and not self._healthy())

    def _scaled(self, action: np.ndarray) -> np.ndarray:
        # [-1, 1] onto each limited actuator's control range; an unlimited one takes it as is.
        lo, hi = self.model.actuator_ctrlrange[:, 0], self.model.actuator_ctrlrange[:, 1]
        limited = self.model.actuator_ctrllimited.astype(bool)
        return np.where(limited, lo + (action + 1.0) / 2.0 * (hi - lo), action)

    def _reward(self, xpos_before: np.ndarray) -> float:
        total = 0.0
        for term in self.spec.document.task.reward:
            if isinstance(term, ForwardSpeed):
                b = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, term.body)
                axis = _AXES[term.axis]
                speed = (self.data.xpos[b, axis] - xpos_before[b, axis]) / self.control_timestep
                total += term.weight * (speed if term.target is None
                                        else -abs(speed - term.target))
            elif isinstance(term, Healthy):
                total += term.weight * float(self._healthy())
            elif isinstance(term, ControlCost):
                total -= term.weight * float(np.sum(np.square(self.data.ctrl)))
            elif isinstance(term, SiteDistance):
                a, b = (mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, name)
                        for name in (term.site, term.target_site))
                total -= term.weight * float(np.linalg.norm(self.data.site_xpos[a]
                                                            - self.data.site_xpos[b]))
        return float(total)

    def _healthy(self) -> bool:
        healthy = self.spec.document.task.healthy
        if healthy is None:
            return True
        b = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, healthy.body)
        lo, hi = healthy.z_range
        ok = lo <= self.data.xpos[b, 2] <= hi
        if healthy.angle_joint is not None:
            j = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, healthy.angle_joint)
            alo, ahi = healthy.angle_range
            ok = ok and alo <= self.data.qpos[self.model.jnt_qposadr[j]] <= ahi
        return bool(ok)

    def copy_state_from(self, other: FileEnv) -> None:
        """Take another env's state and step count (same family, any values)."""
        if other.family != self.family:
            raise ValueError(f'cannot copy a {other.family} state into {self.family}')
        for field in ('qpos', 'qvel', 'act', 'ctrl', 'qacc_warmstart'):
            getattr(self.data, field)[:] = getattr(other.data, field)
        self.data.time = other.data.time
        mujoco.mj_forward(self.model, self.data)
        self.step_count = other.step_count
        self._last_reward = other._last_reward

    # -- the live parameters -----------------------------------------------------------
    def _checked(self, values: tuple[float, ...]) -> tuple[float, ...]:
        values = tuple(float(v) for v in values)
        if len(values) != len(self.spec.param_names):
            raise ValueError(f'{self.family} has {len(self.spec.param_names)} parameters, '
                             f'got {len(values)} values')
        for name, value in zip(self.spec.param_names, values, strict=True):
            reason = self.spec.check_param(name, value)
            if reason is not None:
                raise ValueError(reason)
        return values

    def _geometry(self, values: tuple[float, ...]) -> tuple[float, ...]:
        return tuple(v for v, f in zip(values, self._friction_only, strict=True) if not f)

    def set_values(self, values: tuple[float, ...]) -> None:  # noqa: D102
        self.apply_prepared(self.prepare_values(values))

    def prepare_values(self, values: tuple[float, ...]) -> PreparedFileValues:
        """Check `values` and compile their model unless only friction changes (any thread)."""
        values = self._checked(values)
        assumes = self._geometry(self._values)
        if self._geometry(values) == assumes:
            return PreparedFileValues(values, None, assumes)
        model = self._builder.compile(values, low_res=True)
        if structure_of(model) != self._structure:
            raise ValueError(f"{values} change the structure of {self.family}'s model: "
                             f'it cannot be swapped in place')
        return PreparedFileValues(values, model, assumes)

    def apply_prepared(self, prepared: PreparedFileValues) -> None:
        """Put prepared values into force at a step boundary; the state stays."""
        if prepared.model is None and self._geometry(self._values) != prepared.assumes:
            # Prepared against other geometry than is now in force: compile after all.
            prepared = PreparedFileValues(
                prepared.values, self._builder.compile(prepared.values, low_res=True), ())
        if prepared.model is None:
            for param, value in zip(self.spec.document.parameters, prepared.values, strict=True):
                if isinstance(param.edit, FrictionEdit):
                    self.model.geom_friction[self._builder.friction_geoms[param.name], 0] = value
        else:
            self._writer.write(prepared.model)
        mujoco.mj_forward(self.model, self.data)
        self._values = prepared.values
