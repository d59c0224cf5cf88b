"""Bursts of service requests (issue #17.4): every reset and every swap request gets an answer.

A service keeps its waiting requests in a DDS history; rclpy's default for
services keeps 10, and from a burst of 200 resets only 10 were answered, the
rest dropped without a word. The sim's ~/reset keeps 1000, as rclpy's
parameter services do; a client sending that many at once needs as deep a
history itself (its requests wait in its writer, the answers in its reader):
`qos_profile_parameters`, as here.
"""

from conftest import installed_exe, spin_until
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_parameters
from sim_driver import LockstepDriver
from zeus_msgs.srv import Reset

BURST = 200


def start_sim(spawn, ros_node, **params):
    argv = [installed_exe('sim_node'), '--ros-args', '-p', 'family:=walker-walk-v0']
    for name, value in params.items():
        argv += ['-p', f'{name}:={value}']
    proc = spawn(argv, 'sim_node')
    LockstepDriver(ros_node).wait_ready()
    return proc


def burst(ros_node, client, requests, timeout=60.0):
    """Send every request at once, then wait for the answers; return the futures."""
    assert spin_until(ros_node, client.service_is_ready, 30.0)
    # One request alone first: its answer proves the server has matched our
    # reader too (discovery is not symmetric), so no answer of the burst is lost to it.
    first = client.call_async(requests[0])
    assert spin_until(ros_node, first.done, 10.0), 'the first request was never answered'
    futures = [client.call_async(request) for request in requests]
    spin_until(ros_node, lambda: all(f.done() for f in futures), timeout)
    return futures


def test_200_concurrent_resets_from_one_client_are_all_answered(spawn, ros_node):
    proc = start_sim(spawn, ros_node, mode='lockstep', command_timeout=10.0)
    client = ros_node.create_client(Reset, '/sim_node/reset', qos_profile=qos_profile_parameters)
    # Seeds 0..199 (all valid, each restarts its stream) and every 20th one refused (-5).
    requests = [Reset.Request(seed=-5 if i % 20 == 0 else i) for i in range(BURST)]
    futures = burst(ros_node, client, requests)
    unanswered = sum(not f.done() for f in futures)
    assert unanswered == 0, f'{unanswered} of {BURST} resets never answered'
    results = [f.result() for f in futures]
    for i, result in enumerate(results):
        if i % 20 == 0:
            assert not result.success and 'seed must be -1' in result.message, result.message
        else:
            assert result.success and f'stream restarted at seed {i}' in result.message
    # Answered in order, one episode each.
    episodes = [r.episode for r in results if r.success]
    assert episodes == list(range(episodes[0], episodes[0] + len(episodes)))
    assert proc.alive()


def test_200_concurrent_parameter_sets_are_all_answered(spawn, ros_node):
    start_sim(spawn, ros_node, mode='lockstep', command_timeout=10.0)
    client = ros_node.create_client(SetParameters, '/sim_node/set_parameters',
                                    qos_profile=qos_profile_parameters)

    def request(value):
        return SetParameters.Request(
            parameters=[Parameter('friction', value=value).to_parameter_msg()])
    # Lockstep without commands: nothing steps, so 8 swaps wait and the rest are refused.
    values = [round(0.3 + 0.01 * i, 2) for i in range(BURST)]
    futures = burst(ros_node, client, [request(0.7)] + [request(v) for v in values])
    unanswered = sum(not f.done() for f in futures)
    assert unanswered == 0, f'{unanswered} of {BURST + 1} sets never answered'
    results = [f.result().results[0] for f in futures]
    assert [r.successful for r in results] == [True] * 9 + [False] * (BURST - 8)
    assert all('already waiting' in r.reason for r in results[9:])
