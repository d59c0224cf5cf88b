"""sim_node's parameters, resets and diagnostics as a ROS user meets them (issues #16, #17).

Process tests on real DDS (the node as `ros2 run` starts it), plus unit tests
of the ROS-free pieces they rest on (zeus_ros.ros.protocol).
"""

import math
import time

from conftest import installed_exe, spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
import pytest
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from sim_driver import LockstepDriver, WALKER_ACTUATORS as ACTUATORS
from sim_node.env import ParamEnv
from sim_node.families import get_family
from zeus_ros.ros.protocol import check_reset_request, loop_problem, RecentCounts, SEED_MAX
from zeus_msgs.srv import Reset
from zeus_ros.ros.util import call_service

FAMILY = 'walker-walk-v0'


def sim_argv(**params):
    argv = [installed_exe('sim_node'), '--ros-args']
    for name, value in params.items():
        argv += ['-p', f'{name}:={value}']
    return argv


@pytest.fixture
def sim(spawn, ros_node):
    def start(**params):
        params = {'family': FAMILY, 'command_timeout': 10.0, **params}
        proc = spawn(sim_argv(**params), 'sim_node')
        driver = LockstepDriver(ros_node)
        driver.wait_ready()
        return proc, driver
    return start


def first_state(family, seed, value=None):
    """Joint positions of the first state after `reset(seed)` in process."""
    env = ParamEnv(family, value, seed=0)
    env.reset(seed=seed)
    return env.joint_positions()


def call_reset(driver, seed, names=(), values=()):
    return driver._call(driver.reset_client, Reset.Request(
        seed=seed, param_names=list(names), param_values=[float(v) for v in values]))


def reset_state(driver, seed):
    """Reset; return the response's message and the new episode's first state."""
    response = call_reset(driver, seed)
    assert response.success, response.message
    episode = response.episode
    driver.current = driver._wait_for(lambda i: i.episode == episode and i.step == 0)
    return response.message, driver.states[driver.current]


def get_parameters(ros_node, names):
    client = ros_node.create_client(GetParameters, '/sim_node/get_parameters')
    assert spin_until(ros_node, client.service_is_ready, 30.0)
    return call_service(client, GetParameters.Request(names=list(names)),
                        lambda done, seconds: spin_until(ros_node, done, seconds)).values


# -- the seed parameter and the reset rule (#16.2, #16.3, #17.1) ---------------------------
def test_a_seed_set_as_parameter_starts_its_stream_at_the_next_keep_the_stream_reset(sim):
    _, driver = sim()
    driver.reset(seed=3)
    driver.reset(seed=-1)
    assert driver.set_param('seed', 7).successful
    state, _ = driver.reset(seed=-1)
    np.testing.assert_array_equal(state.position, first_state(FAMILY, 7))
    # ...and that stream then goes on, as in process.
    state, _ = driver.reset(seed=-1)
    env = ParamEnv(FAMILY, seed=0)
    env.reset(seed=7)
    env.reset(seed=None)
    np.testing.assert_array_equal(state.position, env.joint_positions())


def test_seed_minus_one_keeps_the_stream_and_a_seed_restarts_it_and_reads_back(sim, ros_node):
    _, driver = sim()
    driver.reset(seed=5)
    message, state = reset_state(driver, -1)
    assert 'stream of seed 5 continued' in message
    env = ParamEnv(FAMILY, seed=0)
    env.reset(seed=5)
    env.reset(seed=None)
    np.testing.assert_array_equal(state.position, env.joint_positions())
    # The largest seed numpy takes is a valid one, and the parameter reads it back.
    message, state = reset_state(driver, SEED_MAX)
    assert f'stream restarted at seed {SEED_MAX}' in message
    np.testing.assert_array_equal(state.position, first_state(FAMILY, SEED_MAX))
    assert get_parameters(ros_node, ['seed'])[0].integer_value == SEED_MAX


def test_an_empty_reset_request_keeps_the_stream_and_names_its_episode(sim):
    """The .srv default seed is -1: `ros2 service call ... "{}"` continues the stream."""
    _, driver = sim()
    driver.reset(seed=5)
    assert Reset.Request().seed == -1
    response = driver._call(driver.reset_client, Reset.Request())
    assert response.success and 'stream of seed 5 continued' in response.message
    assert response.message.startswith(f'episode {response.episode}:')
    key = driver._wait_for(lambda i: i.episode == response.episode and i.step == 0)
    assert driver.steps[key].episode == response.episode


@pytest.mark.parametrize('seed', [2**32, 2**40, 2**63 - 1, -2, -3, -2**63])
def test_an_out_of_range_seed_is_refused_with_a_reason_and_the_sim_lives_on(sim, seed):
    proc, driver = sim()
    _, info = driver.reset(seed=1)
    response = call_reset(driver, seed)
    assert not response.success
    assert 'seed must be -1' in response.message and str(seed) in response.message
    assert proc.alive(), proc.output()
    _, after = driver.reset(seed=2)       # it still answers, one episode later
    assert after.episode == info.episode + 1


def test_a_reset_naming_a_parameter_twice_is_refused(sim):
    _, driver = sim()
    _, info = driver.reset(seed=0)
    response = call_reset(driver, 0, ['friction', 'friction'], [0.4, 1.2])
    assert not response.success and 'friction given more than once' in response.message
    _, info = driver.step(np.zeros(6), ACTUATORS)
    assert list(info.param_values) == [0.7]


def test_the_log_and_the_response_name_the_same_episode(sim):
    proc, driver = sim()
    driver.reset(seed=0)
    response = call_reset(driver, 4, ['friction'], [1.2])
    assert response.success, response.message
    episode = response.episode
    driver.current = driver._wait_for(lambda i: i.episode == episode and i.step == 0)
    assert list(driver.steps[driver.current].param_values) == [1.2]
    assert spin_until(driver.node, lambda: f'reset to episode {episode}:' in proc.output(), 5.0)
    swap = [line for line in proc.output().splitlines() if 'friction: 0.7 -> 1.2' in line]
    assert len(swap) == 1 and swap[0].endswith(f'at the start of episode {episode}'), swap


# -- parameter mistakes (#16.5, #16.6, #17.8) -----------------------------------------
def run_to_exit(spawn, **params):
    proc = spawn(sim_argv(**params), 'sim_node')
    code = proc.proc.wait(30)
    return code, proc.output()


def test_an_unknown_parameter_at_start_is_refused_naming_the_familys(spawn):
    code, output = run_to_exit(spawn, family='walker-walk-v1', friction=0.5)
    assert code == 1, output
    lines = output.strip().splitlines()
    assert len(lines) == 1, output
    assert 'unknown parameter friction for walker-walk-v1' in lines[0]
    assert 'foot_length' in lines[0] and 'Traceback' not in output


@pytest.mark.parametrize('param, value', [('thread_priority', 200), ('friction', 9.0),
                                          ('mode', 'fast'), ('bogus', 1)])
def test_every_start_up_check_comes_before_the_start_up_line(spawn, param, value):
    code, output = run_to_exit(spawn, family=FAMILY, **{param: value})
    assert code == 1, output
    assert len(output.strip().splitlines()) == 1, output
    assert 'control period' not in output and 'Traceback' not in output


def test_an_empty_family_is_a_one_line_refusal(spawn):
    proc = spawn([installed_exe('sim_node'), '--ros-args', '-p', 'family:='], 'sim_node')
    code, output = proc.proc.wait(60), proc.output()
    assert code == 1, output
    assert output.strip().splitlines() == [
        "SimNode: bad command line: Couldn't parse parameter override rule: "
        "'-p family:=' (no value after :=)"], output


def test_setting_another_familys_parameter_names_the_valid_ones(sim):
    _, driver = sim()
    result = driver.set_param('foot_length', 0.1)
    assert not result.successful
    assert "walker-walk-v0 has no parameter 'foot_length'" in result.reason
    assert 'friction' in result.reason and 'seed' in result.reason


def test_integers_set_float_parameters_as_floats_with_their_ranges(sim, ros_node):
    _, driver = sim(friction=1, real_time_factor=2)  # integers at start
    doubles = get_parameters(ros_node, ['friction', 'real_time_factor'])
    assert [(v.type, v.double_value) for v in doubles] == [
        (ParameterType.PARAMETER_DOUBLE, 1.0), (ParameterType.PARAMETER_DOUBLE, 2.0)]
    driver.reset(seed=0)
    assert driver.set_param('friction', 2).successful      # and live
    _, info = driver.step(np.zeros(6), ACTUATORS)
    assert list(info.param_values) == [2.0]
    value = get_parameters(ros_node, ['friction'])[0]
    assert (value.type, value.double_value) == (ParameterType.PARAMETER_DOUBLE, 2.0)
    result = driver.set_param('friction', 99)
    assert not result.successful and 'out of range' in result.reason, result.reason
    assert driver.set_param('command_timeout', 5).successful
    assert not driver.set_param('seed', 1.5).successful    # an int stays an int


# -- diagnostics (#16.7) ----------------------------------------------------------------
def sim_statuses(ros_node):
    statuses = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: statuses.extend(
        s for s in m.status if s.name.startswith('sim_node:')), 10)
    return statuses


def test_nobody_controlling_the_sim_is_a_warning(sim, ros_node):
    statuses = sim_statuses(ros_node)
    sim(mode='realtime', command_timeout=0.05)
    assert spin_until(ros_node, lambda: len(statuses) >= 2, 10.0)
    assert statuses[-1].level == DiagnosticStatus.WARN
    assert statuses[-1].message.startswith('no controller'), statuses[-1].message


def test_the_level_reflects_the_recent_window_not_all_time(sim, ros_node):
    statuses = sim_statuses(ros_node)
    _, driver = sim()
    driver.reset(seed=0)
    driver.command(None, ACTUATORS[:5], efforts=[0.0] * 5)   # one bad command
    driver.current = driver._wait_for(lambda i: i.step == 1)
    assert spin_until(ros_node, lambda: statuses and 'rejected' in statuses[-1].message, 5.0)
    assert statuses[-1].level == DiagnosticStatus.WARN
    # A controller answering every state for longer than the window: OK again.
    window_s = float({kv.key: kv.value for kv in statuses[-1].values}['window_s'])
    until = time.monotonic() + window_s + 3.0
    while time.monotonic() < until:
        driver.step(np.zeros(6), ACTUATORS)
        spin_until(ros_node, lambda: False, 0.05)
    assert statuses[-1].level == DiagnosticStatus.OK, statuses[-1].message
    values = {kv.key: kv.value for kv in statuses[-1].values}
    assert values['rejected'] == '1'     # the total since start is still reported


# -- the ROS-free pieces ------------------------------------------------------------------
SPEC = get_family(FAMILY)


@pytest.mark.parametrize('seed, names, values, expected', [
    (-1, [], [], None), (0, [], [], None), (SEED_MAX, ['friction'], [1.0], None),
    (SEED_MAX + 1, [], [], 'seed must be -1'), (-2, [], [], 'seed must be -1'),
    (0, ['friction'], [], '1 parameter names but 0 values'),
    (0, ['friction', 'friction'], [1.0, 1.0], 'friction given more than once'),
    (0, ['foot_length'], [0.1], "unknown parameter 'foot_length'"),
    (0, ['friction'], [math.nan], 'must not be NaN'),
    (0, ['friction'], [9.0], 'outside the allowed range'),
])
def test_check_reset_request(seed, names, values, expected):
    problem = check_reset_request(seed, names, values, SPEC)
    assert problem is None if expected is None else expected in problem


def test_recent_rises_forget_what_left_the_window():
    recent = RecentCounts(window_s=10.0)
    assert recent.rises(0.0, {'rejected': 1}) == {'rejected': 1}
    assert recent.rises(5.0, {'rejected': 1}) == {'rejected': 1}
    assert recent.rises(10.5, {'rejected': 1}) == {'rejected': 0}
    assert recent.rises(11.0, {'rejected': 3}) == {'rejected': 2}


def test_loop_problem():
    quiet = dict(steps=100, answered=100, timeouts=0, rejected=0, instabilities=0,
                 late_ticks=0)
    assert loop_problem(quiet, 10.0) is None
    assert loop_problem(dict(quiet, answered=99), 10.0) is None   # one late answer: fine
    assert loop_problem(dict(quiet, answered=0), 10.0).startswith('no controller')
    assert loop_problem(dict(quiet, steps=0, answered=0), 10.0).startswith('no controller')
    assert loop_problem(dict(quiet, rejected=2, timeouts=1), 10.0) == (
        '1 command timeouts; 2 bad commands rejected in the last 10 s')
