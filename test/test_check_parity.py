"""check_parity (issue #38.10): the same episode in process and through ROS, compared.

Through real processes: the tool spawns sim_node, context_node and
policy_node on a domain of its own and runs the episode in process too.
"""

import subprocess
import sys

from conftest import REPO
import numpy as np
import pytest
from sim_driver import WALKER_WEIGHTS
from zeus_ros.ros_tools.check_parity import describe, first_difference, Trace


def run_tool(*args, timeout=600):
    return subprocess.run([sys.executable, '-m', 'zeus_ros.ros_tools.check_parity',
                           '--weights', str(WALKER_WEIGHTS), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


@pytest.mark.ros   # the tool starts the three nodes (no fixture of ours says so)
@pytest.mark.timeout(1200)   # two runs of the tool, its own wait 600 s each
def test_the_shipped_weights_are_identical_through_ros_and_a_mismatch_is_found():
    same = run_tool('--steps', '40', '--seed', '2', '--value', '1.25')
    assert same.returncode == 0, same.stdout + same.stderr
    assert 'identical for 40 steps' in same.stdout
    # The ROS side started from another initial state: the first observation differs.
    other = run_tool('--steps', '40', '--seed', '2', '--value', '1.25', '--ros-seed', '3')
    assert other.returncode == 1, other.stdout + other.stderr
    assert 'first difference at step 0: observation' in other.stdout


@pytest.mark.ros   # starts the tool (rclpy, torch) three times: seconds, not unit speed
def test_bad_arguments_are_refused_with_exit_2():
    for args, message in ((('--steps', '0'), '--steps must be in [1, 1000]'),
                          (('--value', '9'), 'friction=9.0 is outside the allowed range')):
        result = run_tool(*args, timeout=120)
        assert result.returncode == 2 and message in result.stderr, result.stderr


def trace(steps=10, seed=0):
    rng = np.random.RandomState(seed)
    return Trace(rng.randn(steps, 4), rng.randn(steps, 3).astype(np.float32),
                 rng.uniform(-1, 1, (steps, 2)), rng.randn(steps))


def test_first_difference_names_the_step_the_quantity_and_the_element():
    reference, ros = trace(), trace()
    assert first_difference(reference, ros) is None
    assert describe(None, 10).startswith('identical for 10 steps')
    ros.context[4, 2] += 1e-6
    ros.reward[6] += 1.0
    difference = first_difference(reference, ros)
    assert (difference.step, difference.quantity, difference.index) == (4, 'context', 2)
    assert difference.through_ros == float(ros.context[4, 2])
    assert 'first difference at step 4: context (element 2' in describe(difference, 10)
    ros.action[4, 0] = 0.0
    assert first_difference(reference, ros).also == ('action',)
    short = Trace(reference.observation[:5], reference.context[:5], reference.action[:5],
                  reference.reward[:5])
    assert first_difference(reference, short).quantity == 'length'
