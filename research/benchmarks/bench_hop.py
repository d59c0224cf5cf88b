"""The cost of one message hop between two Python processes: the floor under the loop.

    python research/benchmarks/bench_hop.py [--round-trips 3000]

A JointState (the walker's 9 joints) goes back and forth between this process
and an echo process, both on the same transport and QoS as the control loop.
Measured twice in one run: both sides on rclpy's SingleThreadedExecutor, and
both sides taking messages straight from a wait set as `zeus_ros.ros.loop_spin`
does. A lockstep control step crosses three such hops (sim -> context ->
policy -> sim), so 1 / (3 x hop) bounds the lockstep rate of the three
processes before any simulation or inference. Then the same hop between two
nodes of ONE process on one thread, as the composed nodes run (Fast DDS
hands the message over inside the process, no transport, no wake-up).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import rclpy  # noqa: E402
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from zeus_ros.ros.util import LOOP_QOS  # noqa: E402

NAMES = [f'joint_{i}' for i in range(9)]


def make_node(role: str, on_message):
    """Create a node that publishes on one topic of the pair and listens on the other."""
    node = rclpy.create_node(f'hop_{role}')
    out_topic, in_topic = ('/hop/ping', '/hop/pong') if role == 'ping' else ('/hop/pong',
                                                                            '/hop/ping')
    publisher = node.create_publisher(JointState, out_topic, LOOP_QOS)
    subscription = node.create_subscription(JointState, in_topic, on_message, LOOP_QOS)
    return node, publisher, subscription


def spin_raw(node, subscription, until) -> None:
    """Take messages straight from a wait set until `until()`."""
    wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
    while not until():
        wait_set.clear_entities()
        wait_set.add_subscription(subscription.handle)
        wait_set.wait(100_000_000)
        while (taken := subscription.handle.take_message(JointState, False)) is not None:
            subscription.callback(taken[0])


def spin_executor(node, until) -> None:
    """Spin rclpy's SingleThreadedExecutor until `until()`."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    while not until():
        executor.spin_once(timeout_sec=0.1)
    executor.remove_node(node)


def echo(mode: str, seconds: float) -> None:
    """Be the far side: send every message straight back."""
    rclpy.init()
    node, publisher, subscription = make_node('pong', lambda msg: publisher.publish(msg))
    deadline = time.monotonic() + seconds

    def over():
        return time.monotonic() > deadline or not node.context.ok()
    try:
        if mode == 'raw':
            spin_raw(node, subscription, over)
        else:
            spin_executor(node, over)
    except ExternalShutdownException:  # terminated by the measuring side
        pass
    rclpy.try_shutdown()


def measure(mode: str, round_trips: int) -> float:
    """Round trips per second against an echo process of the same mode."""
    peer = subprocess.Popen([sys.executable, __file__, '--echo', mode])
    rclpy.init()
    count = [0]

    def answer(_msg):
        count[0] += 1
        publisher.publish(JointState(name=NAMES, position=[0.1] * 9, velocity=[0.2] * 9))
    node, publisher, subscription = make_node('ping', answer)
    try:
        deadline = time.monotonic() + 30.0
        while publisher.get_subscription_count() == 0 or subscription.get_publisher_count() == 0:
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError('the echo process never appeared')
        time.sleep(0.5)
        start = time.perf_counter()
        answer(None)
        count[0] = 0
        done = lambda: count[0] >= round_trips  # noqa: E731
        if mode == 'raw':
            spin_raw(node, subscription, done)
        else:
            spin_executor(node, done)
        return round_trips / (time.perf_counter() - start)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        peer.terminate()
        peer.wait()


def measure_same_process(round_trips: int) -> float:
    """Round trips per second between two nodes of this process, on one thread."""
    rclpy.init()
    count = [0]

    def answer(_msg):
        count[0] += 1
        ping_pub.publish(JointState(name=NAMES, position=[0.1] * 9, velocity=[0.2] * 9))
    ping, ping_pub, ping_sub = make_node('ping', answer)
    pong, pong_pub, pong_sub = make_node('pong', lambda msg: pong_pub.publish(msg))
    wait_set = _rclpy.WaitSet(2, 0, 0, 0, 0, 0, ping.context.handle)
    try:
        answer(None)
        count[0] = 0
        start = time.perf_counter()
        while count[0] < round_trips:
            wait_set.clear_entities()
            for subscription in (pong_sub, ping_sub):
                wait_set.add_subscription(subscription.handle)
            wait_set.wait(100_000_000)
            for subscription in (pong_sub, ping_sub):
                while (taken := subscription.handle.take_message(JointState, False)):
                    subscription.callback(taken[0])
        return round_trips / (time.perf_counter() - start)
    finally:
        ping.destroy_node()
        pong.destroy_node()
        rclpy.try_shutdown()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--round-trips', type=int, default=3000)
    parser.add_argument('--echo', choices=('raw', 'executor'), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo(args.echo, 60.0)
        return 0
    rates = {mode: measure(mode, args.round_trips) for mode in ('executor', 'raw')}
    for mode, rate in rates.items():
        hop_us = 1e6 / rate / 2
        print(f'hop ({mode:8s}): {rate:7.0f} round trips/s = {hop_us:5.0f} us per hop; '
              f'three hops bound lockstep at {1e6 / (3 * hop_us):5.0f} steps/s')
    print(f'raw / executor: {rates["raw"] / rates["executor"]:.2f}x')
    same_rate = measure_same_process(args.round_trips)
    print(f'hop (one process, one thread): {1e6 / same_rate / 2:5.0f} us per hop; '
          f'{same_rate / rates["raw"]:.1f}x fewer us than between processes (raw)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
