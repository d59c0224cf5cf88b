"""Sawyer-Peg-v0's simulation (sim_node/sawyer.py): model source, episodes, live goal, reward."""

import ast
import importlib.metadata
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

from sim_node import sawyer
from sim_node.families import table7_goals, TABLE7_X_RANGES, TABLE7_Y_RANGES, values_with
from sim_node.sawyer import (ENTRIES, HAND, LAYOUT, MAX_HAND_STEP, meld_reward, OBS_DIM,
                             SawyerPegEnv, SUCCESS_DISTANCE)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def env():
    # One compile (~0.5 s) for the module; every test starts with its own reset.
    return SawyerPegEnv(table7_goals('train')[0])


def _scripted_insertion(env: SawyerPegEnv) -> list:
    """Steer the peg's tip to 3 cm in front of the hole, then along the channel to the goal."""
    results = []
    for _ in range(env.episode_steps):
        tip = env.data.site_xpos[env._ids.peg_tip]
        hole, goal = env.hole_position(), env.goal_position()
        in_front = hole + np.array([0.03, 0.0, 0.0])    # the hole faces +x (world)
        aligned = np.linalg.norm((tip - in_front)[1:]) < 0.006 or tip[0] < hole[0] + 0.01
        target = goal if aligned else in_front
        action = np.append(np.clip((target - tip) / MAX_HAND_STEP, -1, 1), 1.0)
        results.append(env.step(action))
    return results


def test_model_loads_from_metaworld_assets_under_the_pinned_mujoco():
    assert mujoco.__version__ == '3.17.0'
    assert importlib.metadata.version('metaworld') == sawyer.METAWORLD_VERSION
    assert 'site-packages' in str(sawyer.scene_path())
    model = sawyer.build_model()
    assert (model.nu, model.nmocap, model.opt.timestep) == (2, 1, 0.0025)
    # The weld's relative pose is the identity: the hand goes where the mocap body is.
    np.testing.assert_array_equal(model.eq_data[0, 3:10], [0, 0, 0, 1, 0, 0, 0])


def test_envs_share_one_compilation_but_not_its_model():
    """Each env gets a copy of the scene compiled once.

    The copy simulates as a fresh compilation does, and one env's goal does not
    move another's block.
    """
    copied, compiled = sawyer.fresh_model(), sawyer.build_model()
    trajectories = []
    for model in (copied, compiled):
        data = mujoco.MjData(model)
        data.ctrl[:] = (1.0, -1.0)
        mujoco.mj_step(model, data, nstep=300)
        trajectories.append(data.qpos.copy())
    np.testing.assert_array_equal(*trajectories)
    first = SawyerPegEnv((0.45, -0.08), seed=0)
    second = SawyerPegEnv((0.60, 0.08), seed=0)
    assert first._model is not second._model
    assert not np.array_equal(first.hole_position(), second.hole_position())
    first.set_values((0.60, 0.08))
    np.testing.assert_array_equal(first.hole_position(), second.hole_position())


def test_reset_is_deterministic_per_seed(env):
    def rollout(target, seed):
        first = target.reset(seed)
        rng = np.random.default_rng(1)
        return [first] + [target.step(rng.uniform(-1, 1, 4)).observation for _ in range(10)]

    env.set_values(table7_goals('train')[0])   # as the fresh env's
    a, b = rollout(env, 5), rollout(env, 5)
    fresh = rollout(SawyerPegEnv(table7_goals('train')[0], seed=None), 5)
    for x, y, z in zip(a, b, fresh, strict=True):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(x, z)
    assert not np.array_equal(env.reset(6), a[0])
    assert env.time == 0.0 and env.step_count == 0


@pytest.mark.parametrize('axis', [0, 1, 2])
@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_an_action_moves_the_hand_in_its_direction(env, axis, sign):
    start = env.reset(0)[HAND]
    action = np.zeros(4)
    action[axis], action[3] = sign, 1.0
    for _ in range(3):
        result = env.step(action)
    moved = result.observation[HAND] - start
    assert sign * moved[axis] > 0.04       # 3 steps of 0.02 m, less the weld's lag
    assert np.all(np.abs(np.delete(moved, axis)) < 0.01)


def test_the_gripper_action_opens_and_closes(env):
    fingers = [ENTRIES.index('r_close'), ENTRIES.index('l_close')]

    def opening(observation):   # r_close closes at +q, l_close at -q
        return observation[fingers[1]] - observation[fingers[0]]
    closed = opening(env.reset(0))
    for _ in range(3):
        opened = opening(env.step([0, 0, 0, -1]).observation)
    assert opened > closed + 0.03


def test_a_goal_swap_moves_the_hole_in_place_and_keeps_the_state(env):
    env.set_values((0.45, -0.075))
    env.reset(0)
    for _ in range(5):
        env.step([0.3, -0.2, -0.5, 1.0])
    before = {f: getattr(env.data, f).copy() for f in ('qpos', 'qvel', 'mocap_pos', 'ctrl')}
    time, hole = env.time, env.hole_position()
    model_id = id(env.model)
    env.set_values(values_with(env.spec, env.param_values, {'goal_x': 0.60}))
    env.set_values(values_with(env.spec, env.param_values, {'goal_y': 0.078}))
    assert env.param_values == (0.60, 0.078)
    # Table 7's x is the world's y, its y the world's -x.
    np.testing.assert_allclose(env.hole_position() - hole, [-0.153, 0.15, 0.0], atol=1e-6)
    np.testing.assert_allclose(env.hole_position()[:2], [-0.078, 0.60], atol=1e-6)
    for field, value in before.items():
        np.testing.assert_array_equal(getattr(env.data, field), value, err_msg=field)
    assert env.time == time and id(env.model) == model_id
    assert np.all(np.isfinite(env.step([0, 0, 0, 1]).observation))


@pytest.mark.parametrize('name, value', [('goal_x', 0.2), ('goal_y', 0.5), ('goal_x', math.nan),
                                         ('goal_z', 0.5), ('goal_x', 'far')])
def test_a_bad_goal_is_refused_and_nothing_changes(env, name, value):
    before = env.param_values
    with pytest.raises(ValueError):
        env.set_values(values_with(env.spec, env.param_values, {name: value}))
    assert env.param_values == before


def _place_tip(env: SawyerPegEnv, offset) -> None:
    """Construct a state: the peg (level, as held) with its tip at goal + offset."""
    tip_local = env.model.site_pos[env._ids.peg_tip]
    adr = env._ids.peg_qpos
    env.data.qpos[adr:adr + 3] = env.goal_position() + np.asarray(offset) - tip_local
    env.data.qpos[adr + 3:adr + 7] = (1.0, 0.0, 0.0, 0.0)
    mujoco.mj_forward(env.model, env.data)


def test_the_reward_is_the_written_formula_and_peaks_when_inserted(env):
    env.reset(0)
    _place_tip(env, (0.1, 0.0, 0.0))
    assert env.peg_goal_distance() == pytest.approx(0.1, abs=1e-9)
    # d = 5 x 0.1 m: -(d^2 + log10(d^2 + 1e-5)), no offset term.
    assert meld_reward(env.peg_goal_distance()) == pytest.approx(
        -(0.25 + math.log10(0.25 + 1e-5)), rel=1e-9)
    rewards = []
    for offset in (0.0, 0.005, 0.02, 0.05, 0.1, 0.3):
        _place_tip(env, (offset, 0.0, 0.0))
        rewards.append(meld_reward(env.peg_goal_distance()))
    assert rewards[0] == pytest.approx(5.0, abs=1e-6)     # -log10(1e-5): tip at the goal
    assert all(a > b for a, b in zip(rewards, rewards[1:], strict=False))
    # MELD's offset would make the reward 0 at d = 0.15 (3 cm); without it, it is not.
    assert meld_reward(0.03) == pytest.approx(-(0.0225 + math.log10(0.0225 + 1e-5)))
    assert meld_reward(0.03) > 1.0


def test_a_scripted_insertion_succeeds_for_goals_of_both_splits(env):
    for goal in (table7_goals('train')[0], table7_goals('interpolation')[3]):
        env.set_values(goal)
        env.reset(2)
        assert env.peg_goal_distance() > 0.1
        results = _scripted_insertion(env)
        assert not results[0].success
        assert results[-1].success and results[-1].distance < SUCCESS_DISTANCE
        best = max(results, key=lambda r: r.reward)
        assert best.reward == max(r.reward for r in results) > 4.0
        for r in results:
            assert r.reward == pytest.approx(meld_reward(r.distance))


def test_the_observation_has_a_constant_size_is_finite_and_carries_the_reward(env):
    first = env.reset(1)
    assert first.shape == (OBS_DIM,) and first[-1] == 0.0
    rng = np.random.default_rng(0)
    for step in range(env.episode_steps):
        result = env.step(rng.uniform(-1, 1, 4))
        assert result.observation.shape == (OBS_DIM,)
        assert np.all(np.isfinite(result.observation)) and result.instability is None
        assert result.observation[-1] == result.reward
        assert result.truncated == (step == env.episode_steps - 1)
    assert env.reset()[-1] == 0.0


def test_a_bad_action_is_refused(env):
    env.reset(0)
    for bad in ([0, 0, 1], [0, 0, math.nan, 0]):
        with pytest.raises(ValueError):
            env.step(bad)


def test_table7_goals_are_fixed_and_in_the_tables_ranges():
    for split in ('train', 'interpolation'):
        goals = table7_goals(split)
        assert goals == table7_goals(split) and len(goals) == 8
        clusters = [(next(i for i, (lo, hi) in enumerate(TABLE7_X_RANGES) if lo <= x <= hi),
                     next(i for i, (lo, hi) in enumerate(TABLE7_Y_RANGES) if lo <= y <= hi))
                    for x, y in goals]
        assert sorted(clusters) == sorted([(i, j) for i in (0, 1) for j in (0, 1)] * 2)
    assert set(table7_goals('train')).isdisjoint(table7_goals('interpolation'))
    assert table7_goals('extrapolation') == ()
    with pytest.raises(ValueError):
        table7_goals('test')


def test_the_sawyer_module_stays_in_the_simulation_layer():
    tree = ast.parse((REPO / 'sim_node' / 'sawyer.py').read_text())
    roots = {alias.name.split('.')[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
             for alias in node.names}
    roots |= {node.module.split('.')[0] for node in ast.walk(tree)
              if isinstance(node, ast.ImportFrom) and node.module}
    assert roots.isdisjoint({'rclpy', 'torch', 'zeus_msgs', 'zeus_ros', 'metaworld', 'gymnasium'})


def test_a_joint_state_of_the_entries_gives_the_controllers_the_same_observation(env):
    """What sim_node publishes (names, positions, velocities, reward) is the observation."""
    env.reset(3)
    rng = np.random.default_rng(2)
    for _ in range(6):
        result = env.step(rng.uniform(-1, 1, 4))
    positions, velocities = env.joint_positions(), env.joint_velocities()
    assert len(positions) == len(velocities) == len(env.joint_names) == len(ENTRIES)
    shuffled = rng.permutation(len(ENTRIES))   # a JointState may list them in any order
    rebuilt = LAYOUT.observation_from_joint_state(
        [ENTRIES[i] for i in shuffled], positions[shuffled], velocities[shuffled],
        result.reward)
    np.testing.assert_array_equal(rebuilt, result.observation)
    # The peg's orientation: the vector part of a unit quaternion with w >= 0.
    quat_xyz = positions[ENTRIES.index('peg_qx'):ENTRIES.index('peg_qz') + 1]
    assert np.linalg.norm(quat_xyz) <= 1.0
    # The command has no velocity of its own: it is not in the observation.
    assert OBS_DIM == 2 * len(ENTRIES) - 3 + 1


def test_a_prepared_goal_applies_as_set_values_and_a_bad_one_is_refused(env):
    env.reset(0)
    prepared = env.prepare_values((0.6, 0.07))
    assert env.param_values != (0.6, 0.07)     # preparing changes nothing
    env.apply_prepared(prepared)
    assert env.param_values == (0.6, 0.07)
    for bad in ((0.6,), (0.9, 0.0), (0.6, math.nan), 'xy'):
        with pytest.raises(ValueError):
            env.prepare_values(bad)


def test_the_camera_draws_the_block_where_the_goal_puts_it(env):
    """The free camera (metaworld's own render upside down here); a goal swap moves the block."""
    from sim_node.camera import geometry_of, SimCamera
    camera = SimCamera(160, 120, camera=env.default_camera)
    try:
        frames = []
        for goal in ((0.45, -0.075), (0.6, 0.075)):
            env.set_values(goal)
            physics = env.physics
            frames.append(camera.render_state(physics.model.ptr, physics.data.qpos.copy(),
                                              None, geometry_of(physics.model.ptr)))
    finally:
        camera.close()
    sky, floor = frames[0][:10].mean(), frames[0][-10:].mean()
    assert sky > 0 and floor > 0                        # drawn, not a blank buffer
    changed = (np.abs(frames[0].astype(int) - frames[1]).sum(axis=-1) > 30).sum()
    assert changed > 20, changed          # the block moved (the same state otherwise)
