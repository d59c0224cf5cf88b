"""`python -m zeus_ros.ros_tools.set_param`: `ros2 param set` for a pip-only install.

Against a real sim.
"""

import subprocess
import sys

from conftest import REPO, spin_until
import pytest
from sim_driver import collect, start_node
from zeus_msgs.msg import StepInfo
from zeus_ros.ros_tools.set_param import parse_value

pytestmark = pytest.mark.ros   # starts processes of its own


def set_param(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'zeus_ros.ros_tools.set_param', *argv], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_values_are_read_as_ros2cli_reads_them():
    assert parse_value('0.4') == 0.4 and parse_value('3') == 3
    assert parse_value('true') is True and parse_value('walker') == 'walker'
    assert parse_value('[1, 2]') == '[1, 2]'        # not a scalar: left as text


def test_a_live_swap_and_a_refusal_through_a_running_sim(spawn, ros_node):
    steps = collect(ros_node, StepInfo, '/zeus/step')
    start_node(spawn, 'sim_node', {'family': 'walker-walk-v0', 'mode': 'realtime'})
    assert spin_until(ros_node, lambda: len(steps) > 5, 120.0), 'the sim never stepped'
    done = set_param('/sim_node', 'friction', '0.4', '--timeout', '60')
    assert done.returncode == 0 and done.stdout.strip() == 'Set parameter successful'
    assert spin_until(ros_node, lambda: list(steps[-1].param_values) == [0.4], 30.0)
    refused = set_param('/sim_node', 'friction', '99', '--timeout', '60')
    assert refused.returncode == 1
    assert refused.stdout.startswith('Setting parameter failed: Parameter friction out of range')
    missing = set_param('/no_such_node', 'friction', '0.4', '--timeout', '2')
    assert missing.returncode == 1 and 'node /no_such_node not found' in missing.stdout
