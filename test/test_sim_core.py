"""Simulation core without ROS: families really differ, swaps keep the state."""

import numpy as np
import pytest
from sim_node.env import check_action, ParamEnv
from sim_node.families import FAMILIES, get_family, TARGET_ORBIT_RATE
from zeus_ros.ros.protocol import parse_command


def rollout(family, value, seed=4, steps=150):
    env = ParamEnv(family, value, seed=seed)
    env.reset(seed=seed)
    actions = np.random.RandomState(0).uniform(-1, 1, (steps, env.action_dim))
    observations, rewards = [], []
    for action in actions:
        result = env.step(action)
        observations.append(result.observation)
        rewards.append(result.reward)
    return np.array(observations), np.array(rewards)


@pytest.mark.parametrize('family', list(FAMILIES))
def test_parameter_values_give_different_tasks(family):
    spec = get_family(family)
    low, high = min(spec.train), max(spec.train)
    obs_low, rew_low = rollout(family, low)
    obs_high, rew_high = rollout(family, high)
    if spec.reward_varies_only:
        np.testing.assert_array_equal(obs_low, obs_high)  # same dynamics...
        assert np.abs(rew_low - rew_high).max() > 0.1     # ...different reward
    else:
        assert np.abs(obs_low - obs_high).max() > 1e-3


@pytest.mark.parametrize('family', list(FAMILIES))
def test_same_seed_same_trajectory(family):
    obs_a, rew_a = rollout(family, None)
    obs_b, rew_b = rollout(family, None)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(rew_a, rew_b)


def test_tables_as_printed():
    assert get_family('cheetah-run-v0').train[-3:] == (1.25, 1.4, 1.5)
    assert set(get_family('cheetah-run-v0').extrapolation) & {1.25, 1.4, 1.5}
    assert get_family('walker-walk-v0').interpolation == (1.0, 1.05, 1.1, 1.15)
    for spec in FAMILIES.values():
        lo, hi = spec.live_range
        values = spec.train + spec.interpolation + spec.extrapolation
        assert lo < min(values) and max(values) < hi


@pytest.mark.parametrize('family', ['walker-walk-v0', 'cheetah-run-slippery'])
def test_friction_reaches_every_contact(family):
    model = ParamEnv(family, 0.06).physics.model
    np.testing.assert_allclose(model.geom_friction[:, 0], 0.06)   # ground and robot alike


def test_foot_length_changes_both_feet():
    model = ParamEnv('walker-walk-v1', 0.15).physics.model
    for foot in ('right_foot', 'left_foot'):
        assert model.geom(foot).size[1] == pytest.approx(0.15)


def test_cheetah_torso_keeps_total_mass():
    short = ParamEnv('cheetah-run-v0', 0.6).physics.model
    long = ParamEnv('cheetah-run-v0', 1.5).physics.model
    assert short.body_mass.sum() == pytest.approx(14.0)
    assert long.body_mass.sum() == pytest.approx(14.0)
    assert long.body('torso').mass > short.body('torso').mass


def test_live_swap_keeps_state_and_changes_physics():
    env = ParamEnv('walker-walk-v0', 1.0, seed=2)
    env.reset(seed=2)
    for _ in range(40):
        env.step(np.full(6, 0.3))
    qpos, qvel, t = env.joint_positions(), env.joint_velocities(), env.time
    env.set_values((0.4,))
    np.testing.assert_array_equal(env.joint_positions(), qpos)
    np.testing.assert_array_equal(env.joint_velocities(), qvel)
    assert env.time == t and env.param_values == (0.4,)
    assert env.physics.model.geom_friction[0, 0] == pytest.approx(0.4)


def test_bad_values_and_actions_are_refused():
    with pytest.raises(ValueError, match='outside the allowed range'):
        ParamEnv('walker-walk-v0', 10.0)
    env = ParamEnv('walker-walk-v0')
    for value in (float('nan'), -1.0):
        with pytest.raises(ValueError):
            env.set_values((value,))
    assert env.param_values == (get_family('walker-walk-v0').default,)
    assert check_action([np.nan] * 6, 6)[0] is None
    assert check_action([1.0] * 5, 6)[1] == 'action has 5 values, expected 6'
    assert check_action([3.0, -3.0, 0, 0, 0, 0], 6)[0].tolist() == [1, -1, 0, 0, 0, 0]
    with pytest.raises(ValueError, match='NaN'):
        env.step([np.inf] * 6)


def test_parse_command_reorders_and_rejects():
    names = ('a', 'b')
    action, reason = parse_command(['b', 'a'], [0.5, -0.5], names)
    assert reason is None and action.tolist() == [-0.5, 0.5]
    assert parse_command(['a', 'c'], [0, 0], names)[0] is None
    assert parse_command(['a', 'b'], [0], names)[0] is None
    assert parse_command(['a', 'a'], [0, 0], names)[0] is None
    assert parse_command(['a', 'b'], [0, float('nan')], names)[0] is None


def test_instability_resets_the_episode_instead_of_crashing():
    env = ParamEnv('walker-walk-v0', seed=0)
    env.reset(seed=0)
    for _ in range(10):
        env.step(np.zeros(6))
    env.physics.data.qvel[:] = np.nan          # what a blown-up simulation looks like
    result = env.step(np.zeros(6))
    assert result.instability is not None and result.truncated
    assert env.step_count == 0                  # a fresh episode
    assert np.all(np.isfinite(result.observation))
    assert np.all(np.isfinite(env.step(np.zeros(6)).observation))


def test_reward_in_the_observation_is_the_reward_into_the_state_and_changes_nothing_else():
    plain = ParamEnv('cheetah-run-v1', 1.5, seed=4)
    with_reward = ParamEnv('cheetah-run-v1', 1.5, seed=4, reward_in_obs=True)
    assert with_reward.obs_dim == plain.obs_dim + 1
    first = with_reward.reset(seed=4)
    np.testing.assert_array_equal(first[:-1], plain.reset(seed=4))
    assert first[-1] == 0.0
    for action in np.random.RandomState(0).uniform(-1, 1, (30, plain.action_dim)):
        a, b = plain.step(action), with_reward.step(action)
        np.testing.assert_array_equal(b.observation[:-1], a.observation)
        assert b.observation[-1] == b.reward == a.reward
    with_reward.reset()
    assert with_reward.observation()[-1] == 0.0


@pytest.mark.parametrize('value, shown', [(3.000001, '3.000001'), (0.0499999999, '0.0499999999'),
                                          (3.0000000000000004, '3.0000000000000004')])
def test_refusal_shows_the_value_that_was_refused(value, shown):
    """A value just past a bound is printed exactly, not rounded onto the bound (#39)."""
    friction = next(p for p in get_family('walker-walk-v0').live_params
                    if p.name == 'friction')
    assert friction.live_range == (0.05, 3.0)
    assert friction.check(value) == (f'friction={shown} is outside the allowed range '
                                     '[0.05, 3.0]')


def test_reacher_length_target_is_observed_and_still_and_the_tip_depends_on_the_length():
    short, long_ = (ParamEnv('reacher-length', v, seed=0) for v in (0.08, 0.17))
    obs = short.reset(seed=4)
    long_.reset(seed=4)
    names = short.joint_names
    assert names == ('shoulder', 'wrist', 'target_x', 'target_y')
    target = short.joint_positions()[2:]
    assert 0.10 <= np.hypot(*target) <= 0.17 and np.array_equal(obs[3:5], target)
    for _ in range(50):
        a = np.array([1.0, -0.5])
        r_short, r_long = short.step(a).reward, long_.step(a).reward
    assert np.array_equal(short.joint_positions()[2:], target)     # no force moves it
    tips = [e.physics.named.data.geom_xpos['finger', :2].copy() for e in (short, long_)]
    assert np.linalg.norm(tips[0] - tips[1]) > 0.05                # same command, other tip
    assert r_short != r_long


def test_reacher_orbit_target_circles_the_base_at_its_rate_through_a_length_swap():
    env = ParamEnv('reacher-length-orbit', 0.12, seed=0)
    obs = env.reset(seed=4)
    start = env.joint_positions()[2:]
    radius = np.hypot(*start)
    assert 0.10 <= radius <= 0.17 and np.array_equal(obs[3:5], start)
    angles, radii = [np.arctan2(start[1], start[0])], []
    for step in range(1000):
        if step == 500:
            env.set_values((0.2,))   # the spring and the target's state survive the swap
        env.step(np.array([0.3, -0.3]))
        x, y = env.joint_positions()[2:]
        angles.append(np.arctan2(y, x))
        radii.append(np.hypot(x, y))
    np.testing.assert_allclose(radii, radius, rtol=0.02)          # stays on its circle
    travelled = abs(np.unwrap(angles)[-1] - angles[0])
    np.testing.assert_allclose(travelled, TARGET_ORBIT_RATE * 1000 * env.control_timestep,
                               rtol=0.02)
    still = ParamEnv('reacher-length', 0.12, seed=0)
    still.reset(seed=4)
    assert not np.array_equal(still.joint_positions()[2:], env.joint_positions()[2:])


def test_a_one_parameter_env_takes_a_value_tuple_of_one():
    env = ParamEnv('walker-walk-v0', 1.0)
    for values in ((), (0.4, 0.5), (10.0,)):
        with pytest.raises(ValueError):
            env.set_values(values)
        with pytest.raises(ValueError):
            env.prepare_values(values)
    assert env.param_values == (1.0,) and env.param_names == ('friction',)
    assert not hasattr(env, 'param_value') and not hasattr(env, 'set_param')
