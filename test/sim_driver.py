"""Drive a running sim_node in lockstep from the test process, over real DDS."""

from __future__ import annotations

from conftest import installed_exe, REPO, spin_until
import numpy as np
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from zeus_msgs.msg import StepInfo
from zeus_msgs.srv import Reset
from zeus_ros.ros.util import call_service, reset_episode, stamp_ns as stamp_key

QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
WALKER_ACTUATORS = ('right_hip', 'right_knee', 'right_ankle', 'left_hip', 'left_knee',
                    'left_ankle')




class LockstepDriver:
    """Answers each published state with a command, like a policy would."""

    def __init__(self, node, sim_name: str = 'sim_node', timeout: float = 30.0):
        self.node, self.timeout = node, timeout
        self.states: dict[int, JointState] = {}
        self.steps: dict[int, StepInfo] = {}
        self.subscriptions = (
            node.create_subscription(JointState, '/joint_states', self._on_state, QOS),
            node.create_subscription(StepInfo, '/zeus/step', self._on_step, QOS))
        self.command_pub = node.create_publisher(JointState, '/joint_commands', QOS)
        self.reset_client = node.create_client(Reset, f'/{sim_name}/reset')
        self.param_client = node.create_client(SetParameters, f'/{sim_name}/set_parameters')
        self.current: int | None = None

    def _on_state(self, msg):
        self.states[stamp_key(msg.header)] = msg

    def _on_step(self, msg):
        self.steps[stamp_key(msg.header)] = msg

    def wait_ready(self):
        ready = spin_until(self.node, lambda: (
            self.reset_client.service_is_ready() and self.param_client.service_is_ready()
            and self.command_pub.get_subscription_count() > 0
            # matched to this driver's own readers, not only seen on the graph:
            # a state published before its reader matched is lost (volatile topics)
            and all(sub.get_publisher_count() > 0 for sub in self.subscriptions)),
            self.timeout)
        assert ready, 'sim_node did not come up on the graph'

    def follow_latest(self):
        """Take the newest state the sim published as current (after another driver stopped)."""
        paired = [key for key in self.steps if key in self.states]
        assert paired, 'no state received from the sim yet'
        self.current = max(paired)
        return self._pair(self.current)

    def _call(self, client, request):
        return call_service(client, request,
                            lambda done, seconds: spin_until(self.node, done, seconds),
                            self.timeout)

    def _pair(self, key):
        return self.states.get(key), self.steps.get(key)

    def _wait_for(self, match) -> int:
        found = []

        def check():
            for key, info in self.steps.items():
                if key in self.states and match(info):
                    found.append(key)
                    return True
            return False
        assert spin_until(self.node, check, self.timeout), 'expected state never arrived'
        return found[0]

    def reset(self, seed: int, params: dict | None = None):
        params = params or {}
        self.states.clear()
        self.steps.clear()
        self.reset_client.wait_for_service(timeout_sec=30.0)
        episode = reset_episode(self.reset_client,
                                lambda done, seconds: spin_until(self.node, done, seconds),
                                seed, params, self.timeout)
        self.current = self._wait_for(lambda i: i.episode == episode and i.step == 0)
        return self._pair(self.current)

    def set_param(self, name: str, value):
        request = SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()])
        return self._call(self.param_client, request).results[0]

    def command(self, action, names, stamp_of=None, efforts=None):
        msg = JointState(name=list(names),
                         effort=[float(a) for a in (action if efforts is None else efforts)])
        msg.header = (stamp_of if stamp_of is not None else self.states[self.current]).header
        self.command_pub.publish(msg)

    def step(self, action, names):
        info = self.steps[self.current]
        self.command(action, names)
        self.current = self._wait_for(
            lambda i: (i.episode == info.episode and i.step == info.step + 1)
            or i.episode == info.episode + 1)
        return self._pair(self.current)


# -- the three-node loop, shared by the closed-loop tests ------------------------------
FAMILY = 'walker-walk-v0'
WALKER_WEIGHTS = REPO / 'weights' / 'walker-walk-v0-zeus'
# Deep enough for a whole episode (1001 states) and the warm-up before it, should
# a loaded test fall seconds behind the loop: keep-last drops the oldest.
COLLECT_QOS = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)


def start_node(spawn, name, params):
    argv = [installed_exe(name), '--ros-args']
    for key, value in params.items():
        argv += ['-p', f'{key}:={value}']
    return spawn(argv, name)


class Collected(list):
    """Messages received on one topic, in order; `matched()`: a publisher is matched to it."""

    def matched(self) -> bool:
        return self.subscription.get_publisher_count() > 0


def collect(ros_node, msg_type, topic) -> Collected:
    received = Collected()
    received.subscription = ros_node.create_subscription(msg_type, topic, received.append,
                                                         COLLECT_QOS)
    return received


def wait_loop_running(ros_node, steps, timeout=60.0):
    """Wait until the policy's actions reach the sim: every node has discovered the others."""
    assert spin_until(ros_node, lambda: any(any(s.applied_action) for s in steps[-3:]),
                      timeout), 'the loop never closed (no non-zero action applied)'


def episode_rewards(ros_node, driver, steps, seed: int, friction: float | None = None,
                    params: dict | None = None, length: int = 1000,
                    attempts: int = 3) -> np.ndarray:
    """Rewards of one full episode from a reset, once the loop runs (`steps`: collected).

    The reset sets `params` (default: the walker's friction). Index i holds
    step i + 1's reward, NaN where this observer missed the StepInfo: the loop
    runs lockstep at hundreds of steps per second, and a loaded test process
    that falls more than the writer's keep-last 10 behind loses states (the
    loop's own nodes do not; see README, QoS). The episode is deterministic, so
    while this observer has seen less than `assert_same_rewards` asks for, it is
    run again from the same reset (up to `attempts` times) and the views merged;
    where two runs were both seen they must agree bit for bit.
    """
    rewards = np.full(length, np.nan)
    for _ in range(attempts):
        again = _one_episode_rewards(ros_node, driver, steps, seed, friction, params, length)
        both = ~np.isnan(rewards) & ~np.isnan(again)
        np.testing.assert_array_equal(rewards[both], again[both],
                                      err_msg='one reset, two different episodes')
        rewards = np.where(np.isnan(rewards), again, rewards)
        if _seen_enough(rewards):
            break
    return rewards


def _seen_enough(observed: np.ndarray) -> bool:
    seen = ~np.isnan(observed)
    return bool(seen[-1]) and seen.mean() >= 0.95


def _one_episode_rewards(ros_node, driver, steps, seed: int, friction: float | None,
                         params: dict | None, length: int) -> np.ndarray:
    wait_loop_running(ros_node, steps)
    # The episode number comes from the reset's answer: its first state may be
    # pushed out of the driver's queue by the loop's hundreds of steps per second
    # before a loaded test takes it in (`steps` is deep enough for every one).
    episode = reset_episode(driver.reset_client,
                            lambda done, seconds: spin_until(ros_node, done, seconds),
                            seed, params if params is not None else {'friction': friction},
                            driver.timeout)

    def finished():
        return any((s.episode == episode and s.truncated) or s.episode > episode
                   for s in steps[-5:])
    assert spin_until(ros_node, finished, 120.0), 'the episode did not finish through ROS'
    rewards = np.full(length, np.nan)
    for s in steps:
        if s.episode == episode and 0 < s.step <= length:
            rewards[s.step - 1] = s.reward
    return rewards


def assert_same_rewards(observed: np.ndarray, expected) -> None:
    """Assert the ROS episode is the in-process one: every observed reward equal, bit for bit.

    The run is deterministic, so a divergence at any step changes the rewards
    of every later one: equal observed rewards through the last step, with at
    most a few steps unobserved, are the same episode.
    """
    expected = np.asarray(expected)
    seen = ~np.isnan(observed)
    assert len(observed) == len(expected), (len(observed), len(expected))
    assert _seen_enough(observed), f'observed {seen.sum()} of {len(seen)} steps'
    np.testing.assert_array_equal(observed[seen], expected[seen])


def start_sim(spawn, ros_node, **params):
    """Start sim_node with `params` (-p name:=value) and a driver that has seen it."""
    argv = [installed_exe('sim_node'), '--ros-args']
    for name, value in params.items():
        argv += ['-p', f'{name}:={value}']
    proc = spawn(argv, 'sim_node')
    driver = LockstepDriver(ros_node)
    driver.wait_ready()
    return proc, driver
