"""Live swaps through ROS (issue #17.3): they never hold up the loop, and take effect in order.

Process tests on real DDS: the sim as `ros2 run` starts it, `SetParameters`
requests as `ros2 param set` sends them. Tick lateness is read from the sim's
own /diagnostics (lateness since the schedule last restarted: setting
`real_time_factor` restarts it), the values in force from /zeus/step and
from the sim's log (one line per value put into force, none lost).
"""

import re
import subprocess
import sys

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sim_driver import start_sim, WALKER_ACTUATORS as ACTUATORS
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Reset

pytestmark = pytest.mark.ros   # starts processes of its own

FAMILY = 'walker-walk-v0'   # friction; control period 25 ms
PERIOD_MS = 25.0


def may_use_sched_fifo() -> bool:
    probe = 'import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))'
    return subprocess.run([sys.executable, '-c', probe], capture_output=True).returncode == 0


# What this test guards against is a swap that holds up the loop: the old swap
# (the model rebuilt on the loop thread) made ticks around it 30-330 ms late.
# How late a tick is otherwise depends on the machine, not on the swap: under
# SCHED_FIFO on a quiet machine the latest tick starts 0.1-0.75 ms late without
# swaps, 0.2-1.4 ms with them (README); under the normal scheduler a busy 2-core
# machine alone makes ticks up to ~12 ms late, and a shared CI machine made one
# 10 ms late under SCHED_FIFO. So the bound is the same for both schedulers,
# below a control period; that no tick waits for a build is asserted without a
# clock in test_stepper.py.
FIFO = may_use_sched_fifo()
LATE_BOUND_MS = 20.0


@pytest.fixture
def sim(spawn, ros_node):
    def start(**params):
        return start_sim(spawn, ros_node, **{'family': FAMILY, **params})
    return start


class Watch:
    """What the sim reports: StepInfo param values in arrival order, its diagnostics."""

    def __init__(self, node):
        self.values, self.reports = [], []
        node.create_subscription(StepInfo, '/zeus/step', self._on_step,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    def _on_step(self, msg):
        self.values.append(msg.param_values[0])

    def _on_diagnostics(self, msg):
        self.reports.extend({kv.key: kv.value for kv in status.values}
                            for status in msg.status if status.name.startswith('sim_node:'))

    def values_in_force(self, since=0):
        """Return the values seen from message `since` on, once per stretch in force."""
        seen = self.values[since:]
        return [v for i, v in enumerate(seen) if i == 0 or seen[i - 1] != v]


def swaps_logged(proc):
    """(old, new) of every value the sim put into force, from its log, in order."""
    return [(float(a), float(b)) for a, b in
            re.findall(r'friction: ([\d.e+-]+) -> ([\d.e+-]+) at ', proc.output())]


def values_logged(ros_node, proc, last):
    """Return the values the log shows put into force, once `last` is among them (it lags)."""
    spin_until(ros_node, lambda: swaps_logged(proc) and swaps_logged(proc)[-1][1] == last, 5.0)
    return [new for _, new in swaps_logged(proc)]


def send_sets(driver, values, gap_s):
    """Send one SetParameters request per value, `gap_s` apart; return the futures."""
    futures = []
    for value in values:
        request = SetParameters.Request(
            parameters=[Parameter('friction', value=float(value)).to_parameter_msg()])
        futures.append(driver.param_client.call_async(request))
        spin_until(driver.node, lambda: False, gap_s)
    return futures


def next_report(ros_node, watch):
    """Wait for the next diagnostics report (the sim sends one a second)."""
    mark = len(watch.reports)
    assert spin_until(ros_node, lambda: len(watch.reports) > mark, 5.0), 'no diagnostics'
    return watch.reports[-1]


@pytest.mark.alone   # the bound on tick lateness is a wall-clock one
def test_realtime_swaps_at_10_per_s_never_make_a_tick_late_and_all_take_effect_in_order(
        sim, ros_node):
    params = {'mode': 'realtime', 'command_timeout': 0.05}
    if FIFO:
        params['thread_priority'] = 50
    proc, driver = sim(**params)
    watch = Watch(ros_node)
    assert driver.set_param('friction', 0.9).successful     # the set-up's own first swap
    assert spin_until(ros_node, lambda: watch.values and watch.values[-1] == 0.9, 5.0)
    # Restart the schedule (and its lateness statistics): they cover the swaps only.
    assert driver.set_param('real_time_factor', 1.0).successful
    mark = len(watch.values) - 1   # a state at 0.9: nothing else was set since
    values = [0.4, 1.2, 0.6, 1.5, 0.8, 1.9, 0.5, 1.1, 0.3, 1.3]
    futures = send_sets(driver, values, 0.1)
    assert spin_until(ros_node, lambda: all(f.done() for f in futures), 10.0)
    assert [f.result().results[0].successful for f in futures] == [True] * 10, \
        [f.result().results[0].reason for f in futures]
    assert spin_until(ros_node, lambda: watch.values[-1] == values[-1], 5.0)
    report = next_report(ros_node, watch)   # its statistics cover every swap
    # Every value took effect, in the order set (StepInfo and the log agree).
    assert watch.values_in_force(mark) == [0.9] + values
    assert values_logged(ros_node, proc, values[-1]) == [0.9] + values
    # No tick waited for a swap: none more than a period late, none more than a few ms.
    assert int(report['ticks']) >= 30, report
    assert int(report['missed_ticks']) == 0, report
    assert float(report['tick_late_ms_max']) < LATE_BOUND_MS, report


def test_100_swaps_in_a_second_are_all_answered_and_the_accepted_take_effect_in_order(
        sim, ros_node):
    proc, driver = sim(mode='realtime', command_timeout=0.05)
    watch = Watch(ros_node)
    assert driver.set_param('friction', 0.9).successful     # discovery settled
    values = [round(1.3 + 0.01 * i, 2) for i in range(100)]   # none is 0.7 or 0.9
    futures = send_sets(driver, values, 0.01)
    assert spin_until(ros_node, lambda: all(f.done() for f in futures), 10.0), \
        f'{sum(not f.done() for f in futures)} of 100 requests never answered'
    results = [f.result().results[0] for f in futures]
    accepted = [v for v, r in zip(values, results, strict=True) if r.successful]
    refused = [r.reason for r in results if not r.successful]
    # A refusal says why: the queue of values waiting to take effect is full.
    assert all('already waiting to be put into force' in reason for reason in refused), refused
    assert len(accepted) >= 40      # one value per 25 ms step boundary, plus the queue
    assert spin_until(ros_node, lambda: watch.values[-1] == accepted[-1], 5.0)
    # Every accepted value took effect, in order; nothing else did.
    assert values_logged(ros_node, proc, accepted[-1]) == [0.9] + accepted
    seen = watch.values_in_force()
    assert seen == [v for v in [0.7, 0.9] + accepted if v in seen]   # in order, none extra


def test_lockstep_queues_swaps_until_its_steps_and_a_reset_value_supersedes_them(sim):
    proc, driver = sim(mode='lockstep', command_timeout=10.0)
    driver.reset(seed=0)
    # No command comes, so nothing steps: the values wait, one per coming step.
    for value in (0.4, 0.5, 0.6, 0.8, 0.9, 1.0, 1.1, 1.2):
        assert driver.set_param('friction', value).successful
    full = driver.set_param('friction', 2.0)
    assert not full.successful and '8 values are already waiting' in full.reason, full.reason
    for expected in (0.4, 0.5):
        _, info = driver.step(np.zeros(6), ACTUATORS)
        assert list(info.param_values) == [expected]
    response = driver._call(driver.reset_client, Reset.Request(
        seed=1, param_names=['friction'], param_values=[1.7]))
    assert response.success, response.message
    assert 'friction 0.6, 0.8, 0.9, 1, 1.1, 1.2 set before it' in response.message
    assert 'superseded' in response.message
    key = driver._wait_for(lambda i: i.episode == response.episode and i.step == 0)
    assert list(driver.steps[key].param_values) == [1.7]
    assert values_logged(driver.node, proc, 1.7) == [0.4, 0.5, 1.7]


def test_a_reset_without_values_puts_the_waiting_ones_into_force_first(sim):
    proc, driver = sim(mode='lockstep', command_timeout=10.0)
    driver.reset(seed=0)
    for value in (0.4, 1.3):
        assert driver.set_param('friction', value).successful
    _, info = driver.reset(seed=-1)
    assert list(info.param_values) == [1.3]
    assert values_logged(driver.node, proc, 1.3) == [0.4, 1.3]
    assert [line.endswith(f'at the start of episode {info.episode}') for line in
            proc.output().splitlines() if 'friction: ' in line] == [True, True]
