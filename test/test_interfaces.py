"""zeus_msgs messages and the Reset service round-trip over real DDS between processes."""

import math

from conftest import helper_script, spin_until
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from zeus_msgs.msg import Context, StepInfo
from zeus_msgs.srv import Reset
from zeus_ros.ros.util import call_service

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def _round_trip(node, msg_type, topic_in, topic_out, message, timeout=20.0):
    received = []
    node.create_subscription(msg_type, topic_out, received.append, QOS)
    pub = node.create_publisher(msg_type, topic_in, QOS)
    assert spin_until(node, lambda: pub.get_subscription_count() > 0
                      and node.count_publishers(topic_out) > 0, timeout), \
        'echo process never appeared on the graph'
    # Matching is asynchronous on both sides: publish until the echo comes back.
    for _ in range(int(timeout / 0.5)):
        pub.publish(message)
        if spin_until(node, lambda: received, 0.5):
            break
    assert received, f'no echo on {topic_out}'
    return received[0]


def test_context_round_trip(ros_node, spawn):
    spawn(helper_script('echo_node.py'), 'echo')
    sent = Context(header=Header(frame_id='ctx'), latent=[0.5, -1.25, 3.0],
                   window_fill=4, param_names=['friction'],
                   param_estimates=[float('nan')])
    sent.header.stamp.sec, sent.header.stamp.nanosec = 12, 345
    got = _round_trip(ros_node, Context, 'echo/context_in', 'echo/context_out', sent)
    assert got.header.frame_id == 'ctx'
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (12, 345)
    assert list(got.latent) == [0.5, -1.25, 3.0]
    assert got.window_fill == 4
    assert list(got.param_names) == ['friction']
    assert math.isnan(got.param_estimates[0])


def test_step_info_round_trip(ros_node, spawn):
    spawn(helper_script('echo_node.py'), 'echo')
    sent = StepInfo(episode=3, step=999, reward=0.123456789012345, terminal=False,
                    truncated=True, family='walker-walk-v0',
                    param_names=['friction'], param_values=[0.4])
    got = _round_trip(ros_node, StepInfo, 'echo/step_in', 'echo/step_out', sent)
    assert (got.episode, got.step, got.truncated, got.terminal) == (3, 999, True, False)
    assert got.reward == 0.123456789012345  # float64 survives exactly
    assert got.family == 'walker-walk-v0'
    assert list(got.param_names) == ['friction'] and list(got.param_values) == [0.4]


def test_reset_service_round_trip(ros_node, spawn):
    spawn(helper_script('echo_node.py'), 'echo')
    client = ros_node.create_client(Reset, 'echo/reset')
    assert client.wait_for_service(timeout_sec=20.0), 'echo/reset never appeared'
    def wait(done, seconds):
        return spin_until(ros_node, done, seconds)
    response = call_service(client, Reset.Request(seed=7, param_names=['friction'],
                                                  param_values=[1.7]), wait)
    assert response.success is True
    assert response.message == 'seed=7;friction=1.7'
    assert call_service(client, Reset.Request(seed=-1), wait).success is False
