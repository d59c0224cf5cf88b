"""Sawyer-Peg-v0 over real DDS: the sim, its goal swaps, checkpoints through three nodes.

The sim in both modes with live goal swaps and bad input; trained checkpoints
through sim, context and policy nodes, bit for bit.
"""


from conftest import installed_exe, spin_until, tiny_checkpoints
import numpy as np
import pytest
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.parameter import Parameter
from sim_driver import (assert_same_rewards, collect, episode_rewards, LockstepDriver, QOS,
                        start_node, start_sim)
from sim_node.families import table7_goals, values_with
from sim_node.sawyer import ACTION_NAMES, ENTRIES, SawyerPegEnv
from zeus_msgs.msg import Context, StepInfo
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode
from zeus_ros.ros.util import call_service

FAMILY = 'sawyer-peg-v0'
GOAL = table7_goals('train')[0]
SWAPS = {10: {'goal_x': 0.6}, 20: {'goal_x': 0.45, 'goal_y': 0.075}}   # step: changes


def actions(n, seed=0):
    return np.random.RandomState(seed).uniform(-1, 1, (n, len(ACTION_NAMES)))


def set_atomically(driver, changes: dict):
    """One SetParametersAtomically call: all the changes are validated and applied together."""
    client = driver.node.create_client(SetParametersAtomically,
                                       '/sim_node/set_parameters_atomically')
    assert client.wait_for_service(timeout_sec=30.0)
    request = SetParametersAtomically.Request(parameters=[
        Parameter(name, value=value).to_parameter_msg() for name, value in changes.items()])
    return call_service(client, request,
                        lambda done, seconds: spin_until(driver.node, done, seconds), 30.0).result


def in_process_episode(seed, sequence):
    env = SawyerPegEnv(GOAL, seed=seed)
    env.reset(seed)
    positions, rewards, goals = [env.joint_positions()], [], [env.param_values]
    for i, action in enumerate(sequence):
        if i in SWAPS:
            env.set_values(values_with(env.spec, env.param_values, SWAPS[i]))   # one swap
        rewards.append(env.step(action).reward)
        positions.append(env.joint_positions())
        goals.append(env.param_values)
    return positions, rewards, goals


def test_lockstep_with_live_goal_swaps_equals_the_in_process_episode(spawn, ros_node):
    seed, sequence = 4, actions(30, seed=1)
    expected_positions, expected_rewards, expected_goals = in_process_episode(seed, sequence)
    _, driver = start_sim(spawn, ros_node, family=FAMILY, command_timeout=10.0)
    goal = dict(zip(('goal_x', 'goal_y'), GOAL, strict=True))
    state, info = driver.reset(seed=seed, params=goal)
    assert list(state.name) == list(ENTRIES) and list(info.param_names) == ['goal_x', 'goal_y']
    positions, rewards, goals = [np.array(state.position)], [], [tuple(info.param_values)]
    for i, action in enumerate(sequence):
        if i in SWAPS:
            result = set_atomically(driver, SWAPS[i])
            assert result.successful, result.reason
        state, info = driver.step(action, ACTION_NAMES)
        positions.append(np.array(state.position))
        rewards.append(info.reward)
        goals.append(tuple(info.param_values))
    # Bit-exact: the swaps took effect at the same step boundaries, the state carried over.
    np.testing.assert_array_equal(np.array(positions), np.array(expected_positions))
    assert rewards == expected_rewards and goals == expected_goals
    assert goals[10] == GOAL and goals[11] == (0.6, GOAL[1]) and goals[21] == (0.45, 0.075)


def test_realtime_steps_on_its_own_and_takes_a_live_goal_swap(spawn, ros_node):
    _, driver = start_sim(spawn, ros_node, family=FAMILY, mode='realtime',
                          command_timeout=0.2)
    seen = []
    ros_node.create_subscription(StepInfo, '/zeus/step', seen.append, QOS)
    assert spin_until(ros_node, lambda: len(seen) >= 20, 30.0), 'realtime did not step'
    result = driver.set_param('goal_y', -0.1)
    assert result.successful, result.reason
    assert spin_until(ros_node, lambda: seen and tuple(seen[-1].param_values)[1] == -0.1, 10.0)
    # 40-step episodes at 20 Hz: a new one started on its own meanwhile.
    assert spin_until(ros_node, lambda: len({s.episode for s in seen}) >= 2, 10.0)
    assert all(len(s.param_values) == 2 for s in seen)


def test_bad_goals_are_refused_with_a_reason_and_change_nothing(spawn, ros_node):
    _, driver = start_sim(spawn, ros_node, family=FAMILY, command_timeout=10.0)
    driver.reset(seed=0)
    for name, value, expected in (('goal_x', 0.9, 'out of range'),
                                  ('goal_y', float('nan'), 'out of range'),
                                  ('goal_x', 'hole', 'Wrong parameter type'),
                                  ('friction', 0.4, 'no parameter')):
        result = driver.set_param(name, value)
        assert not result.successful and expected in result.reason, result.reason
    # Atomic: one bad value refuses the whole set.
    assert not set_atomically(driver, {'goal_x': 0.6, 'goal_y': 0.5}).successful
    _, info = driver.step(np.zeros(4), ACTION_NAMES)
    assert tuple(info.param_values) == (0.525, 0.0)        # the defaults, untouched


def test_the_sim_node_shows_the_sawyer_on_its_camera(spawn, ros_node):
    """`camera_rate` for this family too: frames of the arm (red) while it steps in realtime."""
    from sensor_msgs.msg import Image
    images = []
    ros_node.create_subscription(Image, '/camera/image_raw', images.append, 10)
    proc = spawn([str(installed_exe('sim_node')), '--ros-args', '-p', f'family:={FAMILY}',
                  '-p', 'mode:=realtime', '-p', 'camera_rate:=4.0'], 'sim_node_camera')
    assert spin_until(ros_node, lambda: len(images) >= 2, 90), proc.output()
    msg = images[-1]
    frame = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, 3)
    red = (frame[..., 0] > 120) & (frame[..., 1] < 80) & (frame[..., 2] < 80)
    assert (msg.width, msg.height) == (320, 240) and red.mean() > 0.01, red.mean()


@pytest.fixture(scope='module')
def sawyer_checkpoints(tmp_path_factory):
    """Train a tiny checkpoint of a method a few real steps on sawyer-peg-v0, once."""
    return tiny_checkpoints(tmp_path_factory, FAMILY)


@pytest.mark.parametrize('method', ['zeus', 'oracle'])
def test_a_trained_sawyer_checkpoint_runs_through_the_three_nodes_bit_exactly(
        spawn, ros_node, sawyer_checkpoints, method):
    """Both goal coordinates reach the context (oracle) and come back decoded (zeus)."""
    weights = sawyer_checkpoints(method)
    model = InferenceModel.load(weights)
    assert model.param_names == ('goal_x', 'goal_y') and model.reward_in_observation
    seed, goal = 6, table7_goals('interpolation')[2]
    expected = run_episode(model, FAMILY, goal, seed)
    steps = collect(ros_node, StepInfo, '/zeus/step')
    contexts = collect(ros_node, Context, '/zeus/context')
    start_node(spawn, 'sim_node', {'family': FAMILY, 'command_timeout': 5.0})
    for name, extra in (('context_node', {}), ('policy_node', {'context_timeout': 5.0})):
        start_node(spawn, name, {'weights': weights, **extra})
    driver = LockstepDriver(ros_node)
    driver.wait_ready()
    rewards = episode_rewards(ros_node, driver, steps, seed,
                              params=dict(zip(('goal_x', 'goal_y'), goal, strict=True)),
                              length=len(expected.rewards))
    assert len(expected.rewards) == 40
    assert_same_rewards(rewards, expected.rewards)
    published = [c for c in contexts if list(c.param_names) == ['goal_x', 'goal_y']]
    assert published and all(len(c.param_estimates) == 2 for c in published)
    if method == 'oracle':   # its estimate is the truth it was given
        assert any(np.allclose(c.param_estimates, goal, atol=1e-6) for c in published)
