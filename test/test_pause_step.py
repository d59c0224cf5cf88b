"""sim_node's ~/pause, ~/resume and ~/step over real DDS, in both modes (issue #38.7).

The test process is the controller: it answers every state it receives
with a command, as a policy would, so lockstep steps go on as in a graph.
"""

from conftest import spin_until
import numpy as np
import pytest
from rclpy.qos import qos_profile_parameters
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from zeus_ros.ros.protocol import stamp_to_ns
from sim_driver import collect, QOS, start_sim, WALKER_ACTUATORS as ACTUATORS
from std_srvs.srv import Trigger
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Step
from zeus_ros.ros.util import call_service, stamp_ns

DT_NS = 25_000_000   # walker's control period
ACTION = [0.3, -0.2, 0.1, 0.3, -0.2, 0.1]


class Services:
    """Clients of the sim's pause, resume and step services."""

    def __init__(self, node):
        self.node = node
        self.pause_client = node.create_client(Trigger, '/sim_node/pause')
        self.resume_client = node.create_client(Trigger, '/sim_node/resume')
        self.step_client = node.create_client(Step, '/sim_node/step',
                                              qos_profile=qos_profile_parameters)

    def _wait(self, done, seconds):
        return spin_until(self.node, done, seconds)

    def pause(self):
        return call_service(self.pause_client, Trigger.Request(), self._wait)

    def resume(self):
        return call_service(self.resume_client, Trigger.Request(), self._wait)

    def refused_step(self, steps):
        """Send a request that must be refused (repeatable: call_service re-sends one lost)."""
        return call_service(self.step_client, Step.Request(steps=steps), self._wait)

    def step(self, steps, timeout=60.0):
        # Sent once (a repeat would find this one under way); a refused request
        # answered before proves that the server's answers reach this client.
        future = self.step_client.call_async(Step.Request(steps=steps))
        assert spin_until(self.node, future.done, timeout), f'~/step {steps} never answered'
        return future.result()


def answer_every_state(node):
    """Answer each /joint_states message with a command for its stamp (a controller)."""
    publisher = node.create_publisher(JointState, '/joint_commands', QOS)

    def answer(state):
        publisher.publish(JointState(header=state.header, name=list(ACTUATORS),
                                     effort=list(ACTION)))
    node.create_subscription(JointState, '/joint_states', answer, QOS)


def clock_ns(msg: Clock) -> int:
    return stamp_to_ns(msg.clock.sec, msg.clock.nanosec)


def quiet_for(ros_node, received, seconds):
    """Whether nothing arrives on `received` for `seconds` (after a drain of 0.5 s)."""
    spin_until(ros_node, lambda: False, 0.5)
    count = len(received)
    spin_until(ros_node, lambda: False, seconds)
    return len(received) == count


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_pause_stops_the_sim_step_takes_exactly_n_and_resume_runs_on(spawn, ros_node, mode):
    states, infos = collect(ros_node, JointState, '/joint_states'), collect(
        ros_node, StepInfo, '/zeus/step')
    clocks = collect(ros_node, Clock, '/clock')
    proc, driver = start_sim(spawn, ros_node, family='walker-walk-v0', mode=mode,
                             command_timeout=10.0, friction=1.0)
    answer_every_state(ros_node)
    services = Services(ros_node)
    driver.reset(seed=1)
    assert spin_until(ros_node, lambda: len(infos) > 20, 60.0), 'the sim does not step'

    assert services.pause().success
    assert 'already paused' in services.pause().message
    assert quiet_for(ros_node, states, 1.0) and quiet_for(ros_node, clocks, 0.2), \
        'states or /clock still published while paused'
    last, clock_before = infos[-1], clock_ns(clocks[-1])

    # Bad requests: a clear refusal, nothing stepped, the node alive.
    for steps, reason in ((0, 'steps must be in [1, 10000], got 0'),
                          (10**6, 'steps must be in [1, 10000], got 1000000')):
        response = services.refused_step(steps)
        assert not response.success and reason in response.message, response.message

    count = len(infos)
    response = services.step(5)
    assert response.success and response.steps_taken == 5, response.message
    assert [i.step for i in response.step_infos] == list(range(last.step + 1, last.step + 6))
    stamps = [stamp_ns(i.header) for i in response.step_infos]
    assert stamps == [stamp_ns(last.header) + DT_NS * n for n in range(1, 6)]
    assert [stamp_ns(s.header) for s in response.joint_states] == stamps
    # Exactly those five went out on the topics, and /clock moved by five periods.
    assert quiet_for(ros_node, infos, 0.5)
    assert [stamp_ns(i.header) for i in infos[count:]] == stamps
    assert clock_ns(clocks[-1]) - clock_before == 5 * DT_NS
    assert np.allclose(response.step_infos[-1].applied_action, ACTION)

    # A swap while paused is in force at the next step.
    assert driver.set_param('friction', 0.4).successful
    response = services.step(1)
    assert response.success and list(response.step_infos[0].param_values) == [0.4]
    assert list(response.step_infos[0].param_values) != list(last.param_values)

    assert 'resumed' in services.resume().message
    assert spin_until(ros_node, lambda: len(infos) > count + 30, 60.0), 'resume did not run on'
    refused = services.refused_step(3)
    assert not refused.success and 'call ~/pause first' in refused.message
    assert proc.alive()
