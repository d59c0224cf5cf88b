"""The nodes' stamp bookkeeping rebuilds exactly the training window (no ROS graph)."""

import math

import numpy as np
import pytest
from sim_node.env import ParamEnv
from zeus_ros.ros.protocol import RecentCounts
from zeus_ros.core.window import ContextWindow
from zeus_ros.ros.pairing import (BadMessage, DUPLICATE, JUMP, NEXT, observation_from_message,
                                  OUTLIER, RESTART, StampFollower, StateContextPairer,
                                  TransitionAssembler)

K = 5
NS = 1_000_000_000
DT = 25_000_000   # the walker's control period


def episode_messages(steps=12, seed=0, family='walker-walk-v0', value=1.0,
                     reward_in_obs=False):
    """(stamp, joint state fields, step info fields) per state, and the reference window."""
    env = ParamEnv(family, value, seed=seed, reward_in_obs=reward_in_obs)
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


def test_assembler_puts_the_step_infos_reward_into_observations_that_read_it():
    # cheetah-run-v1 (the reward is all that differs between its tasks): the
    # reward into each state is the observation's last entry, from StepInfo.
    env, messages, reference = episode_messages(family='cheetah-run-v1', value=2.0,
                                                reward_in_obs=True)
    assert env.obs_dim == env.layout.size and env.layout.reward_in_observation
    window = ContextWindow(K, env.obs_dim, env.action_dim)
    assembler = TransitionAssembler(window, env.layout)
    records = []
    for stamp, joint_state, info in messages:
        assembler.add_joint_state(stamp, *joint_state)
        records.append(assembler.add_step_info(stamp, *info))
    for got, want in zip(window.arrays(), reference.arrays(), strict=True):
        np.testing.assert_array_equal(got, want)
    assert records[0].observation[-1] == 0.0
    assert [r.observation[-1] for r in records[1:]] == [m[2][2] for m in messages[1:]]
    assert all(r.observation[-1] < 0 for r in records[1:])   # -|v - 2| - control cost


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
    assembler.add_joint_state(stamp + 100, *joint_state)  # the same stamp again: dropped
    assert assembler.add_step_info(stamp + 100, 1, 0, 0.0, [], False) is None
    assert assembler.dropped == 1 and assembler.restarts == 0


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
    pairer.add_context(10, latent)                  # its state was skipped: pairs with nothing
    assert pairer.ready() is None
    pairer.add_state(30, obs, now=1.0)
    assert pairer.expired(now=1.4) is None
    assert pairer.expired(now=1.6) == 30
    assert pairer.expired(now=5.0) is None


def feed(assembler, messages, offset=0):
    """Each state's StepInfo then JointState, stamps shifted by `offset`; the records."""
    records = []
    for stamp, joint_state, info in messages:
        assembler.add_step_info(stamp + offset, *info)
        records.append(assembler.add_joint_state(stamp + offset, *joint_state))
    return records


def assert_window_is(window, reference):
    for got, want in zip(window.arrays(), reference.arrays(), strict=True):
        np.testing.assert_array_equal(got, want)


def test_stamp_follower_takes_a_clock_going_back_and_ignores_one_stamp_far_ahead():
    follower = StampFollower(max_jump_ns=10 * NS)
    seen = [(s, follower.observe(s * NS)) for s in
            (1, 2, 2, 1000, 3, 1001, 4, 5, 15, 26, 0.5, 0.525)]
    assert seen == [(1, NEXT), (2, NEXT), (2, DUPLICATE),
                    (1000, OUTLIER),   # alone, far ahead: the clock stays at 2
                    (3, NEXT),
                    (1001, JUMP),      # continues the 1000 of before: a clock that jumped
                    (4, RESTART),      # and the old one goes on: the clock went back
                    (5, NEXT), (15, NEXT),
                    (26, OUTLIER),     # 11 s ahead: more than the bound
                    (0.5, RESTART),    # a restarted sim
                    (0.525, NEXT)]
    assert follower.high == 0.525 * NS


def test_assembler_follows_a_restarted_sim():
    env, messages, reference = episode_messages()
    window = ContextWindow(K, env.obs_dim, env.action_dim)
    events = []
    assembler = TransitionAssembler(window, env.layout, on_clock=lambda *e: events.append(e))
    feed(assembler, messages, offset=500 * NS)   # the first sim ran for 500 s
    assert window.fill == K
    records = feed(assembler, messages)          # killed and restarted: its clock starts again
    assert all(record is not None for record in records)
    assert events == [(RESTART, messages[0][0], messages[-1][0] + 500 * NS)]
    assert assembler.restarts == 1 and assembler.gaps == 0
    assert_window_is(window, reference)


def test_assembler_ignores_one_state_stamped_far_ahead():
    env, messages, reference = episode_messages()
    window = ContextWindow(K, env.obs_dim, env.action_dim)
    assembler = TransitionAssembler(window, env.layout)
    feed(assembler, messages[:6])
    stamp, joint_state, info = messages[6]
    assert feed(assembler, [(stamp + 1000 * NS, joint_state, info)]) == [None]
    assembler.add_joint_state(stamp + 2000 * NS, *joint_state)   # a half, never completed
    records = feed(assembler, messages[6:])
    assert all(record is not None for record in records)
    assert_window_is(window, reference)
    assert assembler.outliers == 1 and assembler.restarts == 0 and assembler.gaps == 0
    assert assembler.dropped == 1                                  # the lone half


def test_assembler_recovers_from_a_stray_state_stamped_in_the_past():
    env, messages, reference = episode_messages()
    window = ContextWindow(K, env.obs_dim, env.action_dim)
    assembler = TransitionAssembler(window, env.layout)
    feed(assembler, messages[:6], offset=500 * NS)
    stamp, joint_state, info = messages[6]
    assert feed(assembler, [(stamp, joint_state, info)])[0] is not None   # taken as a restart
    # The sim goes on from its own clock: a jump back to it, and the window refills.
    records = feed(assembler, messages[6:], offset=500 * NS)
    assert all(record is not None for record in records)
    assert assembler.restarts == 2 and window.fill == K


def test_bad_joint_states_are_refused_with_a_reason_and_leave_nothing_behind():
    env, messages, _ = episode_messages()
    names, positions, velocities = messages[0][1]
    layout = env.layout
    for bad, reason in (((['a', 'b'], [0.0, 0.0], [0.0, 0.0]), 'lacks joints'),
                        ((names, positions[:-1], velocities), 'positions'),
                        ((names, positions, []), 'velocities'),
                        ((names, [math.nan, *positions[1:]], velocities), 'non-finite')):
        with pytest.raises(BadMessage, match=reason):
            observation_from_message(layout, *bad)
    assembler = TransitionAssembler(ContextWindow(K, env.obs_dim, env.action_dim), layout)
    assembler.add_step_info(1, *messages[0][2])
    with pytest.raises(BadMessage):
        assembler.add_joint_state(1, ['a'], [0.0], [0.0])
    assert assembler.add_joint_state(1, *messages[0][1]) is not None
    _, _, (episode, step, reward, action, truncated) = messages[1]
    for bad in ((episode, step, reward, action[:-1], truncated),
                (episode, step, math.inf, action, truncated),
                (episode, step, reward, [math.nan, *action[1:]], truncated)):
        with pytest.raises(BadMessage):
            assembler.add_step_info(2, *bad)
    assembler.add_joint_state(2, *messages[1][1])
    assert assembler.add_step_info(2, *messages[1][2]) is not None and assembler.window.fill == 1


def answer(pairer, stamp, now=0.0):
    pairer.add_state(stamp, np.zeros(3), now)
    pairer.add_context(stamp, np.ones(2, dtype=np.float32))
    return pairer.ready()


@pytest.mark.parametrize('first', ['state', 'context'])
def test_pairer_follows_a_restarted_sim_whichever_message_comes_first(first):
    events = []
    pairer = StateContextPairer(context_timeout=0.5, on_clock=lambda *e: events.append(e))
    for i in range(1, 4):
        assert answer(pairer, 500 * NS + i * DT)[0] == 500 * NS + i * DT
    obs, latent = np.full(3, 7.0), np.full(2, 3.0, dtype=np.float32)
    if first == 'state':
        pairer.add_state(DT, obs, now=1.0)
        pairer.add_context(DT, latent)
    else:
        pairer.add_context(DT, latent)
        pairer.add_state(DT, obs, now=1.0)
    stamp, got_obs, got_latent = pairer.ready()
    assert stamp == DT and got_obs[0] == 7.0 and got_latent[0] == 3.0
    assert answer(pairer, 2 * DT)[0] == 2 * DT
    assert sorted(e[0] for e in events) == ['context restart', 'state restart']
    assert pairer.restarts == 1


def test_pairer_keeps_answering_after_states_stamped_far_ahead():
    pairer = StateContextPairer(context_timeout=0.5)
    assert answer(pairer, DT)[0] == DT
    assert pairer.add_state(DT + 1000 * NS, np.zeros(3), now=1.0) == OUTLIER
    assert pairer.next_expiry() is None and pairer.expired(now=5.0) is None
    assert answer(pairer, 2 * DT, now=5.0)[0] == 2 * DT
    # Two in a row look like a clock that jumped; the sim's next state undoes it.
    assert pairer.add_state(2000 * NS, np.zeros(3), now=6.0) == OUTLIER
    assert pairer.add_state(2000 * NS + DT, np.zeros(3), now=6.0) == JUMP
    assert answer(pairer, 3 * DT, now=6.1)[0] == 3 * DT
    assert pairer.outliers == 2 and pairer.restarts == 2


def test_recent_counts_forget_a_gap_after_the_window():
    recent = RecentCounts(window_s=10.0)
    assert recent.problem(1.0, {'gaps': 0, 'dropped': 0}) is None
    assert recent.problem(2.0, {'gaps': 1, 'dropped': 0}) == '1 gaps in the last 10 s'
    for now in range(3, 12):
        assert recent.problem(float(now), {'gaps': 1, 'dropped': 0}) is not None
    assert recent.problem(12.0, {'gaps': 1, 'dropped': 0}) is None
    assert recent.rises(13.0, {'gaps': 1, 'dropped': 4}) == {'gaps': 0, 'dropped': 4}



def test_pairer_with_a_context_age_bound_answers_at_once_with_the_newest_context():
    # #49: a robot's policy need not wait for its state's own context.
    pairer = StateContextPairer(context_timeout=0.5, max_context_age_ns=25)
    obs, latent = np.zeros(3), np.ones(2, dtype=np.float32)
    pairer.add_state(10, obs, now=0.0)
    assert pairer.ready() is None                   # no context at all yet: it waits
    pairer.add_context(10, latent)
    assert pairer.ready()[0] == 10 and pairer.older_contexts == 0   # its own
    pairer.add_state(20, obs, now=0.1)
    stamp, _, got = pairer.ready()                  # at once, with 10's context
    assert stamp == 20 and got[0] == 1 and pairer.older_contexts == 1
    pairer.add_context(20, latent * 2)              # 20's own context, late: nothing to do
    assert pairer.ready() is None
    pairer.add_state(40, obs, now=0.2)
    assert pairer.ready()[2][0] == 2                # 20's, 20 ns older: within the bound
    pairer.add_state(70, obs, now=0.3)
    assert pairer.ready() is None                   # 30 ns older than 20's: too old, waits
    assert pairer.expired(now=0.9) == 70            # and times out as without a bound
    pairer.add_context(5, latent)                   # a restarted clock: forget the old one
    pairer.add_state(6, obs, now=1.0)
    assert pairer.ready()[0] == 6


def test_pairer_without_an_age_bound_never_uses_another_states_context():
    pairer = StateContextPairer(context_timeout=0.5)
    pairer.add_state(10, np.zeros(3), now=0.0)
    pairer.add_context(10, np.ones(2))
    pairer.ready()
    pairer.add_state(20, np.zeros(3), now=0.1)
    assert pairer.ready() is None and pairer.older_contexts == 0
