"""What every family's env answers: `FamilyEnv`, the one interface of a simulated family.

Two classes implement it: `sim_node.env.ParamEnv` (the dm_control families:
one parameter, a swap recompiles the model) and `sim_node.sawyer.SawyerPegEnv`
(Sawyer-Peg-v0: the goal's two coordinates, a swap moves the block in place);
`sim_node.env.make_env` returns the one a family needs. The trainer, the
evaluator, the adaptation report, the sim node and its stepper use an env
through these members only, so a new kind of family needs a class that
answers them and nothing else changes (test_family_protocol.py holds both
classes to it).

A family's parameters are a value tuple in `param_names` order, everywhere:
a one-parameter family's is a tuple of one, and there is no scalar form.
A live swap comes in two halves: `prepare_values` (slow, any thread, the env
untouched) and `apply_prepared` (fast, at a step boundary); `set_values`
does both at once.

Types only, no MuJoCo: code that annotates with these loads nothing heavy.
The classes implement the protocols structurally and do not inherit them (a
protocol's read-only property would hide an env's plain attribute).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable, Self, TYPE_CHECKING, TypeVar

import numpy as np

from sim_node.families import SimFamily
from sim_node.layout import ObservationLayout, StepResult

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

Values = tuple[float, ...]   # a family's parameter values, in its param_names order


@runtime_checkable
class PreparedValues(Protocol):
    """A swap's slow half done: values checked (and compiled, where that is needed)."""

    @property
    def values(self) -> Values: ...


@dataclass(frozen=True)
class ModelView:
    """A bare MjModel as dm_control's Physics shows it: `ptr`."""

    ptr: Any   # mujoco.MjModel (not imported here: this module stays MuJoCo-free)


@dataclass(frozen=True)
class PhysicsView:
    """The part of a dm_control Physics the sim node's camera reads, for envs on raw MuJoCo."""

    model: ModelView
    data: Any   # mujoco.MjData


@runtime_checkable
class EnvPhysics(Protocol):
    """The part of an env's physics the sim node's camera reads (`model.ptr`, `data`)."""

    @property
    def model(self) -> Any: ...    # has `ptr`, the mujoco.MjModel

    @property
    def data(self) -> Any: ...     # mujoco.MjData, or dm_control's wrapper of it


# The prepared swap an env answers with and takes back: each env its own kind.
PreparedT = TypeVar('PreparedT', bound=PreparedValues)


@runtime_checkable
class FamilyEnv(Protocol[PreparedT]):
    """A simulated family: episodes, the JointState it publishes, its live parameters."""

    # -- what it is ------------------------------------------------------------
    @property
    def spec(self) -> SimFamily: ...

    @property
    def family(self) -> str: ...

    @property
    def episode_steps(self) -> int: ...      # steps before an episode is truncated

    @property
    def control_timestep(self) -> float: ...   # simulated seconds per step

    @property
    def layout(self) -> ObservationLayout: ...

    @property
    def joint_names(self) -> tuple[str, ...]: ...   # the JointState entries, in order

    @property
    def actuator_names(self) -> tuple[str, ...]: ...   # the command's entries, in order

    @property
    def obs_dim(self) -> int: ...

    @property
    def action_dim(self) -> int: ...

    @property
    def default_camera(self) -> int | None: ...   # what the camera renders from

    # -- where the episode is ----------------------------------------------------
    @property
    def step_count(self) -> int: ...

    @property
    def time(self) -> float: ...

    @property
    def physics(self) -> EnvPhysics: ...

    def joint_positions(self) -> np.ndarray: ...

    def joint_velocities(self) -> np.ndarray: ...

    def observation(self) -> np.ndarray: ...

    def reset(self, seed: int | None = None) -> np.ndarray: ...

    def step(self, action: ArrayLike) -> StepResult: ...

    def copy_state_from(self, other: Self) -> None: ...   # the adaptation report's shadow

    # -- the live parameters -----------------------------------------------------
    @property
    def param_names(self) -> tuple[str, ...]: ...

    @property
    def param_values(self) -> Values: ...

    def set_values(self, values: Values) -> None: ...

    def prepare_values(self, values: Values) -> PreparedT: ...

    def apply_prepared(self, prepared: PreparedT) -> None: ...
