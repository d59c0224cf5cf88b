"""The nodes' stamp bookkeeping rebuilds exactly the training window (no ROS graph)."""

import numpy as np
from sim_node.env import ParamEnv
from zeus_ros.core.window import ContextWindow
from zeus_ros.pairing import StateContextPairer, TransitionAssembler

K = 5


def episode_messages(steps=12, seed=0):
    """(stamp, joint state fields, step info fields) per state, and the reference window."""
    env = ParamEnv('walker-walk-v0', 1.0, seed=seed)
    obs = env.reset(seed=seed)
    reference = ContextWindow(K, env.obs_dim, env.action_dim)
    messages = [(1, (env.joint_names, env.joint_positions(), env.joint_velocities()),
                 (0, 0, 0.0, [], False))]
    actions = np.random.RandomState(seed).uniform(-1, 1, (steps, env.action_dim))
    for i, action in enumerate(actions, start=1):
        result = env.step(action)
        reference.push(obs, result.applied_action, result.reward, result.observation)
        obs = result.observation
        messages.append((i + 1, (env.joint_names, env.joint_positions(),
                                 env.joint_velocities()),
                         (0, i, result.reward, result.applied_action, False)))
    return env, messages, reference


def test_assembler_rebuilds_the_training_window_whatever_the_arrival_order():
    env, messages, reference = episode_messages()
    window = ContextWindow(K, env.obs_dim, env.action_dim)
    assembler = TransitionAssembler(window, env.layout)
    fills = []
    for n, (stamp, joint_state, info) in enumerate(messages):
        # StepInfo first on odd states, JointState first on even ones.
        first, second = ((assembler.add_step_info, info), (assembler.add_joint_state,
                                                            joint_state))
        if n % 2 == 0:
            first, second = second, first
        assert first[0](stamp, *first[1]) is None
        record = second[0](stamp, *second[1])
        assert record is not None and record.stamp_ns == stamp
        fills.append(window.fill)
    assert fills == [0, 1, 2, 3, 4, 5, 5, 5, 5, 5, 5, 5, 5]
    for got, want in zip(window.arrays(), reference.arrays(), strict=True):
        np.testing.assert_array_equal(got, want)
    assert assembler.gaps == 0 and assembler.dropped == 0


def test_assembler_clears_on_episode_start_and_on_a_missed_state():
    env, messages, _ = episode_messages()
    window = ContextWindow(K, env.obs_dim, env.action_dim)
    assembler = TransitionAssembler(window, env.layout)
    for stamp, joint_state, info in messages[:4]:
        assembler.add_joint_state(stamp, *joint_state)
        assembler.add_step_info(stamp, *info)
    assert window.fill == 3
    stamp, joint_state, info = messages[5]          # state 4 never arrives
    assembler.add_joint_state(stamp, *joint_state)
    assembler.add_step_info(stamp, *info)
    assert window.fill == 0 and assembler.gaps == 1
    stamp, joint_state, _ = messages[6]             # a new episode starts
    assembler.add_joint_state(stamp + 100, *joint_state)
    assembler.add_step_info(stamp + 100, 1, 0, 0.0, [], False)
    assert window.fill == 0 and assembler.gaps == 1
    assembler.add_joint_state(stamp, *joint_state)  # late, out of order: dropped
    assert assembler.add_step_info(stamp, 0, 6, 0.0, np.zeros(6), False) is None
    assert assembler.dropped == 1


def test_pairer_answers_newest_pair_and_times_out_blind():
    pairer = StateContextPairer(context_timeout=0.5)
    obs, latent = np.zeros(3), np.ones(2, dtype=np.float32)
    pairer.add_state(10, obs, now=0.0)
    assert pairer.ready() is None
    pairer.add_state(20, obs + 1, now=0.1)
    pairer.add_context(10, latent)
    pairer.add_context(20, latent * 2)
    stamp, got_obs, got_latent = pairer.ready()
    assert stamp == 20 and got_obs[0] == 1 and got_latent[0] == 2
    assert pairer.dropped == 1                      # state 10 skipped: a newer pair was in
    assert pairer.ready() is None
    pairer.add_context(10, latent)                  # older than what was answered: ignored
    assert pairer.ready() is None
    pairer.add_state(30, obs, now=1.0)
    assert pairer.expired(now=1.4) is None
    assert pairer.expired(now=1.6) == 30
    assert pairer.expired(now=5.0) is None
