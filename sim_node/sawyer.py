"""Sawyer-Peg-v0 (appendix Table 7, from MELD, Zhao et al. 2020): a Sawyer arm inserts a peg.

The family (`families.GOAL_FAMILIES`) has two live parameters, `goal_x` and
`goal_y`, the position of the hole the peg must go into; the sim node runs
it (`sim_node -p family:=sawyer-peg-v0`), the trainer not yet.

Model source. The scene is metaworld 3.1.1's `sawyer_peg_insertion_side.xml`
(MIT licence): the Sawyer arm with its two-finger gripper, driven through a
mocap body welded to the hand, a table, a free peg and a block with a square
channel through it. metaworld's metadata pins mujoco==3.3.0 while dm-control
1.0.50 needs mujoco==3.17.0, so `scripts/setup.sh` installs the wheel with
`--no-deps` from `requirements-assets.lock` (version and hash pinned) and only
its asset files are read: metaworld's Python code (which would need gymnasium
and its own MuJoCo) is never imported. Vendoring the files instead would put
the scene's 19 meshes and textures (9.6 MB) in the repository for the same
bytes; downloading a model at run time (mujoco-menagerie, robot-descriptions)
does not work offline.

One edit is made when the scene is compiled, none to the files: the
hand-mocap weld gets an identity relative pose (the compiler would otherwise
keep the hand 1.2 m away from the mocap body, their offset in the file's
default pose; metaworld makes the same change at run time). At run time the
block is moved to the goal (`set_values`, in the live model).

Task, as MELD's (the peg is already held; the horizon is Table 9's 40 steps,
too short to pick it up first): the episode starts with the peg grasped
horizontally above the table; the goal is the point `INSERT_DEPTH` inside the
block's channel, behind the hole the policy never observes. It has to infer
it from the reward, which is concatenated to the observation (appendix B.2.1,
as MELD does for its reward-varying tasks).

What the sim publishes and the policy observes are the same named entries
(`ENTRIES`), so a controller node builds the observation from a JointState
without MuJoCo, as for the other families: the arm's and the fingers' joints,
then, as entries of their own, the hand (the endEffector site), the
commanded hand position, the peg's position and the vector part of its
orientation (w >= 0), each position with its velocity (the command has none).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
import functools
import importlib.metadata
import importlib.util
import math
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from sim_node.families import GOAL_FAMILIES, SAWYER_PEG
from sim_node.family_env import ModelView, PhysicsView
from sim_node.layout import check_action, ObservationLayout, StepResult

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

SPEC = GOAL_FAMILIES[SAWYER_PEG]
FAMILY_NAME = SPEC.name
PARAM_NAMES = SPEC.param_names       # ('goal_x', 'goal_y'): Table 7's frame, m
METAWORLD_VERSION = '3.1.1'
SCENE_FILE = 'assets/sawyer_xyz/sawyer_peg_insertion_side.xml'

EPISODE_STEPS = SPEC.episode_steps  # Table 9's horizon, 40
CONTROL_TIMESTEP = 0.05             # s; 20 MuJoCo steps of 2.5 ms
MAX_HAND_STEP = 0.02                # m per control step and axis at |action| = 1
MAX_LEAD = 0.05                     # m the commanded hand position may run ahead of the hand
WORKSPACE_LOW = np.array([-0.45, 0.30, 0.10])  # the held peg stays above the table
WORKSPACE_HIGH = np.array([0.45, 0.85, 0.40])
HOME_HAND = np.array([0.30, 0.525, 0.28])   # world frame; the peg's tip points to -x
START_NOISE = 0.01                  # m, uniform per axis, on the start hand position
INSERT_DEPTH = 0.04                 # m behind the hole, along the channel
SUCCESS_DISTANCE = 0.02             # m between peg tip and goal: inside the channel
REWARD_DISTANCE_SCALE = 5.0         # MELD's d is 5x the distance in metres
REWARD_EPS = 1e-5

_HAND_QUAT = np.array([1.0, 0.0, 1.0, 0.0]) / math.sqrt(2.0)   # fingers pointing down
_GRASP_BELOW_PADS = 0.015           # m: the peg sits inside the pads' height
_SETTLE_STEPS = 100                 # MuJoCo steps after placing the hand at reset


Goal = tuple[float, float]   # (goal_x, goal_y), Table 7's frame


@dataclass(frozen=True)
class PreparedGoal:
    """A checked goal, not yet in force (`SawyerPegEnv.prepare_values`; `FamilyEnv`'s)."""

    values: Goal


@dataclass(frozen=True)
class SawyerStepResult(StepResult):
    """A step's result, with the task's success (peg tip within SUCCESS_DISTANCE of the goal)."""

    success: bool = False
    distance: float = math.inf


def meld_reward(distance: float) -> float:
    """MELD's dense peg-insertion reward, without the offset of their implementation.

    With d = REWARD_DISTANCE_SCALE x the peg-tip-to-goal distance (m), the
    reward is -(d^2 + log10(d^2 + 1e-5)): the squared term pulls from far
    away, the log term sharpens it near the goal; it falls monotonically with
    the distance and peaks at 5 when the tip is at the goal. MELD's code adds
    a constant "offset" (the same expression at d = 0.15), which their paper
    does not have; ZeUS (appendix B.2) leaves it out, and so does this. A
    constant does not change the optimal policy, but it changes the reward a
    context encoder reads from the observation. The scale 5, the base-10 log
    and the 1e-5 are MELD's code's (the form d^2 + log(d^2 + eps) is their
    paper's); if a reading of the paper gives others, only the constants move.
    """
    scaled_sq = (REWARD_DISTANCE_SCALE * float(distance)) ** 2
    return -(scaled_sq + math.log10(scaled_sq + REWARD_EPS))


def check_goal(values: object) -> str | None:   # any value: checking it is the point
    """Why a goal (goal_x, goal_y) cannot be put into force, or None when it can."""
    try:
        values = tuple(values)
    except TypeError:
        return f'a goal is ({", ".join(PARAM_NAMES)}), got {values!r}'
    if len(values) != len(PARAM_NAMES):
        return f'a goal is ({", ".join(PARAM_NAMES)}), got {len(values)} values'
    for name, value in zip(PARAM_NAMES, values, strict=True):
        reason = SPEC.check_param(name, value)
        if reason is not None:
            return reason
    return None


def scene_path() -> Path:
    """Return the metaworld scene file, found without importing metaworld (needs gymnasium)."""
    spec = importlib.util.find_spec('metaworld')
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError('metaworld (for the Sawyer assets) is not installed: run '
                                '`make setup` (it installs requirements-assets.lock)')
    version = importlib.metadata.version('metaworld')
    if version != METAWORLD_VERSION:
        # The grasp, the block geometry and the start pose were measured on this release.
        raise RuntimeError(f'metaworld {version} is installed; the Sawyer scene needs '
                           f'{METAWORLD_VERSION} (requirements-assets.lock)')
    return Path(spec.submodule_search_locations[0]) / SCENE_FILE


def build_model() -> mujoco.MjModel:
    """Compile the Sawyer peg scene with the hand welded to the mocap body at zero offset."""
    spec = mujoco.MjSpec.from_file(str(scene_path()))
    (weld,) = [e for e in spec.equalities if e.type == mujoco.mjtEq.mjEQ_WELD]
    # data = anchor (3), relative pose (3 + 4), torque scale: identity pose, so the
    # hand goes where the mocap body is put.
    weld.data[3:10] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    return spec.compile()


@functools.cache
def _compiled_model() -> mujoco.MjModel:
    """Compile the scene once per process (~0.5 s; a copy takes ~0.03 s)."""
    return build_model()


def fresh_model() -> mujoco.MjModel:
    """Return a copy of the compiled scene, the env's own to change (every array copied)."""
    return copy.deepcopy(_compiled_model())


ARM_JOINTS = tuple(f'right_j{i}' for i in range(7))
FINGER_JOINTS = ('r_close', 'l_close')
_XYZ = ('x', 'y', 'z')
# The JointState entries the sim publishes, which are the observation: positions
# of all, velocities of all but the command's, then the reward into the state.
# The goal is not in it: the policy has to infer it, from the reward above all.
ENTRIES = (ARM_JOINTS + FINGER_JOINTS
           + tuple(f'hand_{a}' for a in _XYZ)           # endEffector site, world (m, m/s)
           + tuple(f'hand_target_{a}' for a in _XYZ)    # the commanded (mocap) position:
                                                        # it persists between steps: state
           + tuple(f'peg_{a}' for a in _XYZ)            # peg body, world (m, m/s)
           + tuple(f'peg_q{a}' for a in _XYZ))          # orientation's vector part (w >= 0);
                                                        # velocity: the angular one (rad/s)
NO_VELOCITY = frozenset(f'hand_target_{a}' for a in _XYZ)
LAYOUT = ObservationLayout(ENTRIES, ('raw',) * len(ENTRIES), reward_in_observation=True,
                           velocity_encoding=tuple('drop' if e in NO_VELOCITY else 'raw'
                                                   for e in ENTRIES))
OBS_DIM = LAYOUT.size
HAND = slice(ENTRIES.index('hand_x'), ENTRIES.index('hand_x') + 3)   # in the observation
# Action: hand displacement (x, y, z in the world frame, x MAX_HAND_STEP) and gripper
# (+1 closes, -1 opens), all in [-1, 1].
ACTION_NAMES = ('hand_dx', 'hand_dy', 'hand_dz', 'gripper')


def table7_to_world(goal: Goal) -> np.ndarray:
    """Table 7's (x forward, y left) as the scene's world xy (y forward, x to the right)."""
    return np.array([-goal[1], goal[0]])


@dataclass(frozen=True)
class _Ids:
    """Indices into the model of what the task reads."""

    hand_site: int
    fingertips: tuple[int, int]
    pads: tuple[int, int]
    peg_tip: int
    peg_grasp: int
    hole: int
    hand_body: int
    box_body: int
    joint_qpos: np.ndarray      # arm, then fingers
    joint_qvel: np.ndarray
    peg_qpos: int
    peg_qvel: int

    @classmethod
    def of(cls, model: mujoco.MjModel) -> '_Ids':
        def site(name: str):
            return model.site(name).id

        def geom(name: str):
            return model.geom(name).id

        peg_joint = model.body('peg').jntadr[0]
        return cls(
            hand_site=site('endEffector'),
            fingertips=(site('rightEndEffector'), site('leftEndEffector')),
            pads=(geom('rightpad_geom'), geom('leftpad_geom')),
            peg_tip=site('pegHead'), peg_grasp=site('pegGrasp'), hole=site('hole'),
            hand_body=model.body('hand').id, box_body=model.body('box').id,
            joint_qpos=np.array([model.joint(j).qposadr[0] for j in ARM_JOINTS + FINGER_JOINTS]),
            joint_qvel=np.array([model.joint(j).dofadr[0] for j in ARM_JOINTS + FINGER_JOINTS]),
            peg_qpos=int(model.jnt_qposadr[peg_joint]),
            peg_qvel=int(model.jnt_dofadr[peg_joint]))


@dataclass(frozen=True)
class _SimState:
    """The dynamic state a reset restores."""

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    qacc_warmstart: np.ndarray

    @classmethod
    def capture(cls, data: mujoco.MjData) -> '_SimState':
        return cls(*(getattr(data, f).copy() for f in cls.__dataclass_fields__))

    def restore(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        mujoco.mj_resetData(model, data)   # also clears warnings and time
        for name in self.__dataclass_fields__:
            getattr(data, name)[...] = getattr(self, name)
        mujoco.mj_forward(model, data)


def _grasp_peg(model: mujoco.MjModel, data: mujoco.MjData, ids: _Ids) -> _SimState:
    """Bring the hand to HOME_HAND and close the gripper on the peg; return that state.

    Deterministic (no randomness), so it is computed once per env. The peg is
    held in place while the fingers close (else it falls before they reach
    it), then released and left to settle in the grasp.
    """
    mujoco.mj_resetData(model, data)
    data.mocap_pos[0] = HOME_HAND
    data.mocap_quat[0] = _HAND_QUAT
    data.ctrl[:] = (-1.0, 1.0)                     # open
    mujoco.mj_step(model, data, nstep=1000)        # 2.5 s: the arm swings from qpos0
    pads = 0.5 * (data.geom_xpos[ids.pads[0]] + data.geom_xpos[ids.pads[1]])
    grasp_x = model.site_pos[ids.peg_grasp][0]
    peg_pos = pads - np.array([grasp_x, 0.0, _GRASP_BELOW_PADS])
    adr = ids.peg_qpos
    data.ctrl[:] = (1.0, -1.0)                     # close
    for _ in range(200):
        data.qpos[adr:adr + 3] = peg_pos
        data.qpos[adr + 3:adr + 7] = (1.0, 0.0, 0.0, 0.0)
        data.qvel[ids.peg_qvel:ids.peg_qvel + 6] = 0.0
        mujoco.mj_step(model, data)
    mujoco.mj_step(model, data, nstep=400)
    data.time = 0.0
    return _SimState.capture(data)


class SawyerPegEnv:
    """Sawyer-Peg-v0 with a live goal: reset(seed) and step(action) as `ParamEnv`'s.

    Action: a hand displacement (3) and a gripper command (1), in [-1, 1],
    applied through the mocap body: the commanded hand position moves by
    `action[:3] * MAX_HAND_STEP`, at most MAX_LEAD ahead of the hand and inside
    the workspace, and the weld pulls the hand after it. End-effector deltas
    rather than joint targets, because the task is defined in Cartesian space
    (the hole's position is what changes between tasks), because the scene is
    built for it (metaworld drives its Sawyer only this way; its arm joints
    have no actuators), and because in a 4-D action each dimension moves the
    peg one way, where in a redundant 7-D joint space the same tip motion
    needs coordinated joints (easier to explore; not measured here).
    (MELD itself used joint-position deltas on its own arm model.) The
    gripper is kept, as the issue asks, so a policy can also drop the peg.

    Each control step holds the command for CONTROL_TIMESTEP (20 MuJoCo
    steps); an episode is EPISODE_STEPS control steps.
    """

    def __init__(self, values: Goal | None = None, seed: int | None = 0,
                 episode_steps: int | None = None):
        """`values` None: the default goal; `episode_steps` None: EPISODE_STEPS."""
        self.spec = SPEC
        self._model = fresh_model()
        self._data = mujoco.MjData(self._model)
        self._ids = _Ids.of(self._model)
        self._n_substeps = int(round(CONTROL_TIMESTEP / self._model.opt.timestep))
        self.episode_steps = EPISODE_STEPS if episode_steps is None else episode_steps
        self.control_timestep = CONTROL_TIMESTEP
        self.layout = LAYOUT
        self.actuator_names = ACTION_NAMES
        # MuJoCo's free camera over the whole scene: metaworld's own cameras come
        # out upside down through the sim's renderer (they are set up for theirs).
        self.default_camera = -1
        self._random = np.random.RandomState(seed)
        self._hole_in_box = self._measure_hole_in_box()
        # Computed with the block at the scene's own place, far from the hand: the
        # start state is the same whatever goal is set later.
        self._home = _grasp_peg(self._model, self._data, self._ids)
        self._goal = SPEC.defaults
        self.set_values(SPEC.defaults if values is None else values)
        self.step_count = 0
        self._previous_reward = 0.0
        self._velocity = np.zeros(6)   # mj_objectVelocity's output, reused
        self.reset()

    # -- properties -------------------------------------------------------
    @property
    def family(self) -> str:
        """The family's name."""
        return FAMILY_NAME

    @property
    def param_names(self) -> tuple[str, ...]:
        """The live parameters, in the order of `param_values`."""
        return PARAM_NAMES

    @property
    def param_values(self) -> Goal:
        """The live parameters in force: (goal_x, goal_y)."""
        return self._goal

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The JointState entries the sim publishes (ENTRIES)."""
        return ENTRIES

    @property
    def obs_dim(self) -> int:
        """Length of the observation vector."""
        return OBS_DIM

    @property
    def action_dim(self) -> int:
        """Hand dx, dy, dz and the gripper."""
        return len(ACTION_NAMES)

    @property
    def time(self) -> float:
        """Simulated time within the episode, in seconds."""
        return float(self._data.time)

    @property
    def model(self) -> mujoco.MjModel:
        """The live MuJoCo model (a goal swap edits it in place)."""
        return self._model

    @property
    def data(self) -> mujoco.MjData:
        """The live MuJoCo data."""
        return self._data

    @property
    def physics(self) -> PhysicsView:
        """The live model and data as the camera reads a Physics (the block moves in place)."""
        return PhysicsView(ModelView(self._model), self._data)

    # -- episode control --------------------------------------------------
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start a new episode; a seed restarts the random stream, None continues it."""
        if seed is not None:
            self._random.seed(seed)
        offset = self._random.uniform(-START_NOISE, START_NOISE, size=3)
        self._home.restore(self._model, self._data)
        self._data.mocap_pos[0] = HOME_HAND + offset
        mujoco.mj_step(self._model, self._data, nstep=_SETTLE_STEPS)
        self._data.time = 0.0
        self.step_count = 0
        self._previous_reward = 0.0
        return self.observation()

    def step(self, action: ArrayLike) -> SawyerStepResult:
        """Apply a normalised action for one control period.

        Raises ValueError for an action that `check_action` rejects, as ParamEnv.
        """
        clean, reason = check_action(action, self.action_dim)
        if reason is not None:
            raise ValueError(reason)
        bad_before = self._data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
        self._command(clean)
        mujoco.mj_step(self._model, self._data, nstep=self._n_substeps)
        distance = self.peg_goal_distance()
        reward = meld_reward(distance)
        self._previous_reward = reward
        observation = self.observation()
        unstable = self._data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > bad_before
        if unstable or not (np.all(np.isfinite(observation)) and math.isfinite(reward)):
            # MuJoCo reset the data itself on a bad acceleration; start a proper episode.
            first = self.reset()
            return SawyerStepResult(first, 0.0, False, True, applied_action=clean,
                                    instability='MuJoCo became unstable (bad or non-finite '
                                                'state); the episode was reset')
        self.step_count += 1
        return SawyerStepResult(observation, reward, False, self.step_count >= self.episode_steps,
                                applied_action=clean, success=distance < SUCCESS_DISTANCE,
                                distance=distance)

    def _command(self, action: np.ndarray) -> None:
        # The command accumulates (a hand that sags under gravity or is blocked
        # keeps its target), bounded to MAX_LEAD ahead of the hand so that it
        # cannot wind up while the peg is pressed against the block.
        hand = self._data.xpos[self._ids.hand_body]
        target = self._data.mocap_pos[0] + action[:3] * MAX_HAND_STEP
        target = np.clip(target, hand - MAX_LEAD, hand + MAX_LEAD)
        self._data.mocap_pos[0] = np.clip(target, WORKSPACE_LOW, WORKSPACE_HIGH)
        self._data.ctrl[:] = (action[3], -action[3])

    # -- the goal (live parameters) ---------------------------------------
    def set_values(self, values: Goal) -> None:
        """Put the goal `values` into force: move the block, in the live model, keeping the state.

        The block is a static body, so this is a write of its position and
        a forward pass (microseconds): no recompile, and positions, velocities
        and the command are untouched; the arm does not jump.
        """
        reason = check_goal(values)
        if reason is not None:
            raise ValueError(reason)
        goal = tuple(float(v) for v in values)
        rotation = self._data.xmat[self._ids.box_body].reshape(3, 3)
        hole_offset = rotation @ self._hole_in_box
        self._model.body_pos[self._ids.box_body][:2] = table7_to_world(goal) - hole_offset[:2]
        mujoco.mj_forward(self._model, self._data)
        self._goal = goal

    def prepare_values(self, values: Goal) -> PreparedGoal:
        """Check a goal for a live swap: nothing to compile, unlike ParamEnv's."""
        reason = check_goal(values)
        if reason is not None:
            raise ValueError(reason)
        return PreparedGoal(tuple(float(v) for v in values))

    def apply_prepared(self, prepared: PreparedGoal) -> None:
        """Put a prepared goal into force at a step boundary, keeping the state."""
        self.set_values(prepared.values)

    def hole_position(self) -> np.ndarray:
        """Return the hole's position in the world (the channel's opening), m."""
        return self._data.site_xpos[self._ids.hole].copy()

    def goal_position(self) -> np.ndarray:
        """Return the insertion goal in the world: INSERT_DEPTH behind the hole, in the channel."""
        box = self._ids.box_body
        rotation = self._data.xmat[box].reshape(3, 3)
        # The channel runs along the block's local y, from the hole (at -0.096) inwards.
        inside = self._hole_in_box + np.array([0.0, INSERT_DEPTH, 0.0])
        return self._data.xpos[box] + rotation @ inside

    def peg_goal_distance(self) -> float:
        """Distance from the peg's tip to the insertion goal, m."""
        tip = self._data.site_xpos[self._ids.peg_tip]
        return float(np.linalg.norm(tip - self.goal_position()))

    def copy_state_from(self, other: 'SawyerPegEnv') -> None:
        """Take another env's state, command and step count (any goal): as ParamEnv's.

        Gives "the same state and action under another goal": the
        counterfactual transitions of the adaptation report.
        """
        _SimState.capture(other.data).restore(self._model, self._data)
        self._data.time = other.data.time
        mujoco.mj_forward(self._model, self._data)
        self.step_count = other.step_count
        self._previous_reward = other._previous_reward

    def joint_positions(self) -> np.ndarray:
        """Positions of the ENTRIES, in their order (what /joint_states carries)."""
        data, ids = self._data, self._ids
        peg = data.qpos[ids.peg_qpos:ids.peg_qpos + 7]
        quat = peg[3:] if peg[3] >= 0 else -peg[3:]
        return np.concatenate([data.qpos[ids.joint_qpos], data.site_xpos[ids.hand_site],
                               data.mocap_pos[0], peg[:3], quat[1:]])

    def joint_velocities(self) -> np.ndarray:
        """Velocities of the ENTRIES (0 for the commanded position, which has none)."""
        data, ids = self._data, self._ids
        mujoco.mj_objectVelocity(self._model, data, mujoco.mjtObj.mjOBJ_SITE, ids.hand_site,
                                 self._velocity, 0)   # world frame: (angular, linear)
        peg = data.qvel[ids.peg_qvel:ids.peg_qvel + 6]
        return np.concatenate([data.qvel[ids.joint_qvel], self._velocity[3:], np.zeros(3),
                               peg[:3], peg[3:]])

    def observation(self) -> np.ndarray:
        """Return the policy's observation: LAYOUT over the entries, the reward last."""
        return self.layout.observation(self.joint_positions(), self.joint_velocities(),
                                       self._previous_reward)

    def _measure_hole_in_box(self) -> np.ndarray:
        """Return the hole's position in the block's frame (the block moves, this does not)."""
        mujoco.mj_forward(self._model, self._data)
        box = self._ids.box_body
        rotation = self._data.xmat[box].reshape(3, 3)
        return rotation.T @ (self._data.site_xpos[self._ids.hole] - self._data.xpos[box])
