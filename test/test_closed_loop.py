"""The three nodes on real DDS are the trained agent: equal returns, faults survived."""

from conftest import built_once, spin_until, tiny_checkpoints, train_tiny
import numpy as np
import pytest
from sim_driver import (assert_same_rewards, COLLECT_QOS, collect, episode_rewards, FAMILY,
                        LockstepDriver, start_node, WALKER_ACTUATORS as ACTUATORS,
                        wait_loop_running, WALKER_WEIGHTS)
from zeus_msgs.msg import Context, StepInfo
from zeus_ros.learning_tools.evaluate import run_episode
from zeus_ros.deploy.inference import InferenceModel



@pytest.fixture
def loop(spawn, ros_node, request):
    def start(nodes=('sim_node', 'context_node', 'policy_node'), weights=None, **sim_params):
        # small_checkpoint only when asked for: a test of other weights need not
        # wait for its training (a minute beside other work) when run on its own.
        if weights is None:
            weights = request.getfixturevalue('small_checkpoint')
        procs = {}
        # A generous command timeout: a loaded CI machine must not make the sim
        # step on its own (a zero action would break the equality test).
        params = {'sim_node': {'family': FAMILY, 'command_timeout': 5.0, **sim_params},
                  'context_node': {'weights': weights},
                  'policy_node': {'weights': weights, 'context_timeout': 5.0}}
        for name in nodes:
            procs[name] = start_node(spawn, name, params[name])
        driver = LockstepDriver(ros_node)
        driver.wait_ready()
        return procs, driver
    return start


@pytest.mark.parametrize('which', ['small_checkpoint', 'shipped_walker_weights'])
def test_ros_episode_return_equals_in_process_eval(loop, ros_node, request, which):
    weights = (request.getfixturevalue('small_checkpoint') if which == 'small_checkpoint'
               else WALKER_WEIGHTS)
    seed, friction = 5, 1.25
    expected = run_episode(InferenceModel.load(weights), FAMILY, friction, seed)
    rewards = ros_episode_rewards(loop, ros_node, weights, seed, friction)
    assert_same_rewards(rewards, expected.rewards)


def ros_episode_rewards(loop, ros_node, weights, seed: int, friction: float) -> np.ndarray:
    """Return the rewards of one full episode through the three nodes, from a reset."""
    steps = collect(ros_node, StepInfo, '/zeus/step')
    _, driver = loop(weights=weights)
    return episode_rewards(ros_node, driver, steps, seed, friction)


def test_policy_killed_then_restarted(loop, ros_node, spawn, small_checkpoint):
    steps = collect(ros_node, StepInfo, '/zeus/step')
    procs, driver = loop(command_timeout=0.3)
    wait_loop_running(ros_node, steps)
    driver.reset(seed=1)
    assert spin_until(ros_node, lambda: len(steps) > 50, 30.0)
    procs['policy_node'].stop()
    # An episode begun after the policy exited: none of its states reached the
    # policy. (A length of `steps` taken now is no such mark: the steps the old
    # policy controlled but this test had not yet taken in come after it.)
    driver.reset(seed=2)
    episode = driver.steps[driver.current].episode

    def stepped():
        return [s for s in steps if s.episode == episode]
    # Without a policy the sim times out (0.3 s) and applies zero actions, still stepping.
    assert spin_until(ros_node, lambda: len(stepped()) > 5, 30.0), 'the sim stopped'
    assert not any(any(s.applied_action) for s in stepped())
    start_node(spawn, 'policy_node', {'weights': small_checkpoint})
    assert spin_until(ros_node, lambda: any(any(s.applied_action) for s in stepped()),
                      60.0), 'control did not resume after the policy restarted'


def test_context_node_restart_refills_the_window(loop, ros_node, spawn, small_checkpoint):
    contexts = []
    context_sub = ros_node.create_subscription(Context, '/zeus/context', contexts.append,
                                               COLLECT_QOS)
    steps = collect(ros_node, StepInfo, '/zeus/step')
    procs, driver = loop()
    wait_loop_running(ros_node, steps)
    driver.reset(seed=2)
    # Counted from the reset: under a loaded parallel run the 20 contexts could all be
    # from before it, the newest the reset's first state (fill 0) (#51).
    after_reset = len(contexts)
    assert spin_until(ros_node, lambda: len(contexts) > after_reset + 20, 30.0)
    assert contexts[-1].window_fill == 5
    # Stop the policy too, so that the test steps the sim itself: at hundreds of
    # steps per second the new node would otherwise refill its window before
    # this test's subscription had matched its publisher. The sim must not step
    # on its own meanwhile.
    assert driver.set_param('command_timeout', 60.0).successful
    procs['policy_node'].stop()
    procs['context_node'].stop()
    spin_until(ros_node, lambda: False, 1.0)  # take in what the old nodes had sent
    driver.follow_latest()
    mark = len(contexts)
    start_node(spawn, 'context_node', {'weights': small_checkpoint})
    assert spin_until(ros_node, lambda: context_sub.get_publisher_count() > 0, 60.0), \
        'the new context node did not come up'
    # Discovery is not symmetric: our reader can see the new writer a moment
    # before the writer sees our reader, and a message sent in between is lost.
    spin_until(ros_node, lambda: False, 1.0)

    def stepped_until_contexts(count, limit=40):
        for _ in range(limit):
            driver.step(np.zeros(len(ACTUATORS)), ACTUATORS)
            if spin_until(ros_node, lambda: len(contexts) >= mark + count, 0.5):
                return True
        return False
    assert stepped_until_contexts(8), 'contexts did not resume'
    fills = [c.window_fill for c in contexts[mark:]]
    # The new node's first state has no transition before it (fill 0); then
    # one transition per step up to k. Steps it saw before its subscriptions
    # matched the sim do not count: it begins at its first whole state.
    assert fills[:8] == [0, 1, 2, 3, 4, 5, 5, 5], fills


def test_mismatched_or_missing_weights_stop_the_node(spawn, small_checkpoint):
    for params, message in (({'weights': '/nonexistent/ckpt'}, '/nonexistent/ckpt'),
                            ({}, 'weights')):
        proc = start_node(spawn, 'context_node', params)
        assert proc.proc.wait(30) == 1
        assert message in proc.output()


def test_context_node_refuses_a_sim_of_another_family(loop, spawn, small_checkpoint):
    loop(nodes=('sim_node',), family='cheetah-run-v0')
    proc = start_node(spawn, 'context_node', {'weights': small_checkpoint})
    assert proc.proc.wait(30) == 1
    # Whichever message arrives first, StepInfo (family) or JointState (joints):
    assert ("the sim runs 'cheetah-run-v0' but the weights are for 'walker-walk-v0'"
            in proc.output()) or ('do not fit the walker-walk-v0 weights: joint state lacks'
                                  in proc.output())


@pytest.fixture(scope='session')
def method_checkpoints(tmp_path_factory):
    """Train a tiny checkpoint of a method a few real steps on walker-walk-v0, once."""
    return tiny_checkpoints(tmp_path_factory, FAMILY)


@pytest.fixture(scope='session')
def reward_observing_checkpoint(tmp_path_factory):
    """Train a tiny zeus-id checkpoint of cheetah-run-v1 (its observation ends with r)."""
    return built_once(tmp_path_factory, 'reward_obs', lambda directory: train_tiny(
        directory / 'run', 'cheetah-run-v1', 'zeus-id'))


def test_a_policy_that_observes_the_reward_runs_through_the_nodes_bit_exactly(
        loop, ros_node, reward_observing_checkpoint):
    """Appendix B.2.1's reward in the observation: the nodes put StepInfo's reward in."""
    weights = reward_observing_checkpoint
    model = InferenceModel.load(weights)
    assert model.reward_in_observation and model.family == 'cheetah-run-v1'
    seed, target = 4, 2.2
    expected = run_episode(model, model.family, target, seed)
    steps = collect(ros_node, StepInfo, '/zeus/step')
    _, driver = loop(weights=weights, family='cheetah-run-v1')
    rewards = episode_rewards(ros_node, driver, steps, seed,
                              params={'target_velocity': target})
    assert_same_rewards(rewards, expected.rewards)
    # The reward entry is read: with it zeroed, the same states get other actions.
    obs, latents = expected.observations[1:50], expected.latents[1:50]
    assert all(o[-1] == r for o, r in zip(obs, expected.rewards[:49], strict=True))
    hidden = [model.act(np.append(o[:-1], 0.0), lat) for o, lat in zip(obs, latents,
                                                                      strict=True)]
    assert not np.array_equal(hidden, expected.actions[1:50])


@pytest.mark.parametrize('method', ['sac', 'oracle', 'zeus-id', 'cadm', 'up-osi',
                                    'hyperdynamics', 'zeus-no-context-loss', 'zeus-osi', 'rma'])
def test_every_methods_checkpoint_runs_through_the_nodes_bit_exactly(loop, ros_node,
                                                                      method_checkpoints,
                                                                      method):
    """The nodes are method-agnostic: each method's ROS episode is its in-process one."""
    weights = method_checkpoints(method)
    seed, friction = 3, 1.1
    expected = run_episode(InferenceModel.load(weights), FAMILY, friction, seed)
    rewards = ros_episode_rewards(loop, ros_node, weights, seed, friction)
    assert_same_rewards(rewards, expected.rewards)
