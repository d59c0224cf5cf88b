"""sim_node over real DDS: live swaps, rejected values, lockstep determinism, bad commands."""

import os
import subprocess
import sys

from conftest import installed_exe, spin_until
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import pytest
from sim_driver import start_sim, WALKER_ACTUATORS as ACTUATORS
from sim_node.env import ParamEnv

FAMILY = 'walker-walk-v0'


@pytest.fixture
def sim(spawn, ros_node):
    def start(family=FAMILY, **params):
        return start_sim(spawn, ros_node,
                         **{'family': family, 'command_timeout': 10.0, **params})
    return start


def actions(n, dim=6, seed=0):
    return np.random.RandomState(seed).uniform(-1, 1, (n, dim))


def test_live_friction_swap_is_continuous_and_reported(sim):
    _, driver = sim(friction=1.0)
    state, info = driver.reset(seed=3)
    positions = [np.array(state.position)]
    for i, action in enumerate(actions(60)):
        if i == 30:
            result = driver.set_param('friction', 0.4)
            assert result.successful, result.reason
        state, info = driver.step(action, ACTUATORS)
        positions.append(np.array(state.position))
        assert list(info.param_values) == ([1.0] if i < 30 else [0.4])
    jumps = np.abs(np.diff(positions, axis=0)).max(axis=1)
    # Across the swap (step 30 -> 31) the motion continues like any other step.
    assert jumps[30] <= 2.0 * np.percentile(jumps, 95)


def test_bad_parameter_values_are_rejected_with_reason(sim):
    _, driver = sim(friction=1.0)
    driver.reset(seed=0)
    for value, expected in ((float('nan'), 'out of range'), (9.0, 'out of range'),
                            ('slippery', 'Wrong parameter type')):
        result = driver.set_param('friction', value)
        assert not result.successful and expected in result.reason
    read_only = driver.set_param('family', 'cheetah-run-v0')
    assert not read_only.successful and 'read-only' in read_only.reason
    _, info = driver.step(np.zeros(6), ACTUATORS)
    assert list(info.param_values) == [1.0]


def test_lockstep_matches_in_process_core_exactly(sim):
    seed, value, sequence = 11, 0.85, actions(120, seed=5)
    env = ParamEnv(FAMILY, value, seed=seed)
    env.reset(seed=seed)
    expected_positions, expected_rewards = [env.joint_positions()], []
    for action in sequence:
        expected_rewards.append(env.step(action).reward)
        expected_positions.append(env.joint_positions())

    _, driver = sim()  # default friction; the reset request sets the value
    state, _ = driver.reset(seed=seed, params={'friction': value})
    positions, rewards = [np.array(state.position)], []
    for action in sequence:
        state, info = driver.step(action, ACTUATORS)
        positions.append(np.array(state.position))
        rewards.append(info.reward)
    np.testing.assert_array_equal(np.array(positions), np.array(expected_positions))
    assert rewards == expected_rewards


def test_observation_rebuilt_from_joint_state_is_exact(sim):
    _, driver = sim(family='cheetah-run-v0')
    env = ParamEnv('cheetah-run-v0', seed=2)
    env.reset(seed=2)
    state, _ = driver.reset(seed=2)
    for action in actions(20, seed=1):
        env.step(action)
        state, _ = driver.step(action, env.actuator_names)
    rebuilt = env.layout.observation_from_joint_state(state.name, state.position,
                                                      state.velocity)
    np.testing.assert_array_equal(rebuilt, env.observation())


def test_bad_commands_are_rejected_counted_and_stepping_goes_on(sim, ros_node):
    _, driver = sim()
    diagnostics = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)
    _, info = driver.reset(seed=1)
    bad = [
        dict(names=ACTUATORS[:5], efforts=[0.0] * 5),                 # wrong names
        dict(names=ACTUATORS, efforts=[0.0] * 5),                     # wrong length
        dict(names=ACTUATORS, efforts=[float('nan')] + [0.0] * 5),    # NaN
        dict(names=ACTUATORS, efforts=[float('inf')] + [0.0] * 5),    # inf
    ]
    for command in bad:
        step_before = driver.steps[driver.current].step
        driver.command(None, command['names'], efforts=command['efforts'])
        driver.current = driver._wait_for(lambda i, s=step_before: i.step == s + 1)
        state = driver.states[driver.current]
        assert np.all(np.isfinite(state.position))

    def rejected_count():
        for array in diagnostics:
            for status in array.status:
                values = {kv.key: kv.value for kv in status.values}
                if int(values.get('rejected', 0)) >= len(bad):
                    return values
        return None
    values = spin_until(ros_node, rejected_count, 5.0)
    assert values, 'diagnostics never reported the rejected commands'
    assert int(values['rejected']) == len(bad)
    _, info = driver.step(np.zeros(6), ACTUATORS)  # and it still steps on good commands
    assert info.step == len(bad) + 1


def test_unknown_family_stops_with_a_message(spawn):
    proc = spawn([installed_exe('sim_node'), '--ros-args', '-p', 'family:=walker-fly-v9'])
    proc.proc.wait(30)
    assert proc.proc.returncode != 0
    assert "unknown family 'walker-fly-v9'" in proc.output()


@pytest.mark.parametrize('family', ['walker-walk-v1', 'finger-spin-v0', 'cheetah-run-v1'])
def test_every_family_runs_as_a_node(sim, family):
    from sim_node.families import get_family
    spec = get_family(family)
    _, driver = sim(family=family)
    value = spec.train[1]
    state, info = driver.reset(seed=1, params={spec.param_name: value})
    env = ParamEnv(family, value, seed=1)
    env.reset(seed=1)
    for action in actions(5, dim=env.action_dim):
        state, info = driver.step(action, env.actuator_names)
        expected = env.step(action)
    assert info.family == family and list(info.param_names) == [spec.param_name]
    assert list(info.param_values) == [value] and info.reward == expected.reward
    np.testing.assert_array_equal(state.position, env.joint_positions())


@pytest.mark.alone   # counts steps per wall-clock second
def test_realtime_mode_keeps_its_rate_and_switches_live(sim, ros_node):
    """Realtime steps on its own schedule; `mode` switches either way while running."""
    _, driver = sim(family='cheetah-run-v0', mode='realtime', command_timeout=0.05)
    period = ParamEnv('cheetah-run-v0').control_timestep
    reports = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: reports.extend(
        {kv.key: kv.value for kv in s.values} for s in m.status if 'sim_node' in s.name), 10)

    def steps_during(seconds):
        # Counted on the sim's clock (a state's stamp is its tick times the period),
        # not by arrivals: under load a backlog of the old mode's states arrives late.
        spin_until(ros_node, lambda: False, 0.25)   # what the old mode sent is in
        # Stepping, not only started: a node's first state goes out from its
        # constructor, before its name check (up to 1.5 s) and its loop start.
        assert spin_until(ros_node, lambda: len(driver.steps) > 3, 10.0), 'the sim never stepped'
        first = max(driver.steps)
        spin_until(ros_node, lambda: False, seconds)
        return round((max(driver.steps) - first) / (period * 1e9))
    # Nobody commands: the sim still steps at its control rate, on zero actions.
    count = steps_during(2.0)
    assert 0.8 * 2.0 / period <= count <= 1.1 * 2.0 / period, count
    assert not any(any(s.applied_action) for s in list(driver.steps.values())[-20:])
    # ...and every one of those ticks is a controller deadline missed.
    assert spin_until(ros_node, lambda: reports and int(reports[-1]['ticks']) > 50, 5.0)
    assert reports[-1]['unanswered_ticks'] == reports[-1]['ticks'], reports[-1]
    # Switched to lockstep, it waits for commands (a zero action after the 50 ms
    # timeout), so it slows down from 100 to at most 20 steps per second.
    assert driver.set_param('mode', 'lockstep').successful
    count = steps_during(1.0)
    assert count <= 1.0 / 0.05 + 2, count
    assert driver.set_param('mode', 'realtime').successful
    count = steps_during(1.0)
    assert count >= 0.8 * 1.0 / period, count


def _may_use_sched_fifo() -> bool:
    """Whether this machine lets a process of ours run under SCHED_FIFO."""
    probe = ('import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))')
    return subprocess.run([sys.executable, '-c', probe], capture_output=True).returncode == 0


def test_thread_priority_puts_the_loop_under_sched_fifo_or_warns(sim):
    proc, driver = sim(thread_priority=20)
    driver.reset(seed=0)
    _, info = driver.step(np.zeros(6), ACTUATORS)
    assert info.step == 1  # it runs either way
    if _may_use_sched_fifo():
        assert os.sched_getscheduler(proc.proc.pid) == os.SCHED_FIFO
        assert os.sched_getparam(proc.proc.pid).sched_priority == 20
        assert 'SCHED_FIFO, priority 20' in proc.output()
    else:
        assert os.sched_getscheduler(proc.proc.pid) == os.SCHED_OTHER
        assert 'SCHED_FIFO refused' in proc.output()


@pytest.mark.parametrize('param, value', [('thread_priority', 100), ('friction', 9.0),
                                          ('mode', 3), ('mode', 'fast')])
def test_a_bad_startup_parameter_ends_the_node_with_the_reason(spawn, param, value):
    proc = spawn([installed_exe('sim_node'), '--ros-args', '-p', f'family:={FAMILY}',
                  '-p', f'{param}:={value}'], 'sim_node')
    assert proc.proc.wait(30) == 1
    assert f'parameter {param}:' in proc.output()
    assert 'Traceback' not in proc.output()


def test_tick_lateness_counts_both_kinds_of_missed_deadline():
    from zeus_ros.ros.util import TickLateness
    stats = TickLateness()
    period = 0.01
    for late, answered in ((0.0001, True), (0.0004, True), (0.0002, False), (0.012, True)):
        stats.record(late, period, answered)
    report = stats.report()
    assert report['ticks'] == 4
    assert report['missed_ticks'] == 1        # the one more than a period late
    assert report['unanswered_ticks'] == 1    # the one whose command had not come
    assert report['tick_late_ms_p50'] == '0.25'   # 0.2 ms lies in the 0.20-0.25 ms bin
    assert float(report['tick_late_ms_max']) == pytest.approx(12.0)
    stats.restart()
    assert stats.report() == {}
