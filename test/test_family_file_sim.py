"""sim_node running a family file (#48): the Hopper's leg length set live, as `ros2 param set`.

Real processes on real DDS: the sim as `ros2 run` starts it, with
`family_file:=examples/hopper/hopper.yaml`; the test drives it in lockstep and
sends `SetParameters` requests as `ros2 param set` does.
"""

import subprocess

from conftest import installed_exe, REPO
import numpy as np
import pytest
from sim_driver import start_sim

pytestmark = pytest.mark.ros   # starts processes of its own

HOPPER = REPO / 'examples' / 'hopper' / 'hopper.yaml'
ACTUATORS = ('actuator0', 'actuator1', 'actuator2')   # the Hopper's motors have no names


def test_the_leg_length_swaps_live_and_the_state_carries_on(spawn, ros_node):
    _, driver = start_sim(spawn, ros_node, family_file=str(HOPPER))
    state, info = driver.reset(seed=1)
    assert info.family == 'hopper-friction-leg'
    assert list(info.param_names) == ['floor_friction', 'leg_length']
    assert list(info.param_values) == [1.0, 0.5]
    assert list(state.name) == ['rootx', 'rootz', 'rooty', 'thigh_joint', 'leg_joint',
                                'foot_joint']
    for _ in range(5):
        state, info = driver.step(np.zeros(3), ACTUATORS)
    result = driver.set_param('leg_length', 0.58)
    assert result.successful, result.reason
    before = np.array(state.position)
    state, info = driver.step(np.zeros(3), ACTUATORS)
    # In force at the next step boundary, in the same episode: the motion continues.
    assert list(info.param_values) == [1.0, 0.58] and info.step == 6
    assert np.abs(np.array(state.position) - before).max() < 0.05
    refused = driver.set_param('leg_length', 0.0)    # a segment of no length
    assert not refused.successful and 'leg_length' in refused.reason
    result = driver.set_param('floor_friction', 0.3)
    assert result.successful, result.reason
    state, info = driver.step(np.zeros(3), ACTUATORS)
    assert list(info.param_values) == [0.3, 0.58]


def test_a_bad_family_file_stops_the_sim_with_one_line(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text(HOPPER.read_text().replace('mjcf: hopper.xml', 'mjcf: hopper.xml\n  urdf: x'))
    done = subprocess.run([installed_exe('sim_node'), '--ros-args', '-p',
                           f'family_file:={bad}'], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert f'{bad}: model.urdf: unknown field' in done.stderr + done.stdout
    assert 'Traceback' not in done.stderr + done.stdout
