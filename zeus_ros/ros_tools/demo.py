"""demo: one ROS episode with live parameter swaps, recorded, plotted and rendered.

Brings up sim_node, context_node and policy_node in lockstep (separate
processes, real DDS), starts an episode, swaps the physical parameter at the
scheduled steps through the sim's parameter service (what `ros2 param set`
does), and prints the return of each segment with the decoded parameter
against the true one. With --reference-weights it then runs the same seed and
schedule through the same three nodes with a context-free reference policy
and prints both returns side by side.

The demo is the one way the policy's commands reach the sim (the policy's
output is remapped to it), so it decides exactly where the episode goes: a
swap is put into force between two given steps, and the sim stops where the
demo says (in lockstep it waits for a command that never comes), whatever the
machine's load. It exits with 1 and says why when a step, a context or the
end of the episode was not seen, or the time ran out.

Writes to --out: `demo/` (a rosbag2 bag of every topic: `ros2 bag info
demo_out/demo`; `demo_reference/` for the reference), `demo.png` (return per
segment, true vs decoded parameter), `demo.gif` (the robot, rendered from the
recorded joint states) and `segments.json`.

    ros2 run zeus_ros demo --weights weights/walker-walk-v0-zeus
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
import gc
import json
import math
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import threading
import time
from typing import Any, Callable, TYPE_CHECKING

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# The video's off-screen GL: the caller's MUJOCO_GL, else EGL. 'disable' is
# what sim_node sets for itself on import (it never renders), so any process
# that imported it, and its children, carry it: not a choice against video.
_CALLER_GL = os.environ.get('MUJOCO_GL', '')
VIDEO_GL = _CALLER_GL if _CALLER_GL not in ('', 'disable') else 'egl'

import numpy as np  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from zeus_msgs.msg import Context, StepInfo  # noqa: E402
from zeus_msgs.srv import Reset  # noqa: E402

from zeus_ros.ros_tools.bringup import Bringup, node_commands, parse_args as bringup_args  # noqa: E402
from zeus_ros.deploy.checkpoint import CheckpointError, load_metadata  # noqa: E402
from zeus_ros.ros.graph import (DomainClaim, foreign_publishers, publisher_names,  # noqa: E402
                                use_free_domain)
from zeus_ros.ros.loop_spin import (create_loop_subscription, spin_in_background,  # noqa: E402
                                wait_until)
from zeus_ros.ros_tools.recording import BagRecorder, RECORD_DEPTH, TopicSpec  # noqa: E402
from zeus_ros.ros.util import call_service, LOOP_QOS, stamp_ns  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from rclpy.client import Client
    from rclpy.node import Node

RECORDED_TOPICS = {
    '/joint_states': TopicSpec('sensor_msgs/msg/JointState', LOOP_QOS),
    '/joint_commands': TopicSpec('sensor_msgs/msg/JointState', LOOP_QOS),
    '/zeus/step': TopicSpec('zeus_msgs/msg/StepInfo', LOOP_QOS),
    '/zeus/context': TopicSpec('zeus_msgs/msg/Context', LOOP_QOS),
    '/clock': TopicSpec('rosgraph_msgs/msg/Clock', LOOP_QOS),
    '/diagnostics': TopicSpec('diagnostic_msgs/msg/DiagnosticArray', QoSProfile(depth=10)),
}
# The topics whose every message of the episode the demo must receive.
LOOP_TOPICS = frozenset(t for t in RECORDED_TOPICS if t != '/diagnostics')
# Where the policy's commands go instead of /joint_commands (see CommandGate).
POLICY_COMMANDS = '/zeus/demo/policy_commands'
# The one node that may publish each topic the demo reads its loop from (the
# demo's own node is zeus_demo): anything else is another graph's traffic.
LOOP_PUBLISHERS = {'/joint_states': '/sim_node', '/zeus/step': '/sim_node',
                   '/clock': '/sim_node', '/zeus/context': '/context_node',
                   '/joint_commands': '/zeus_demo', POLICY_COMMANDS: '/policy_node'}
GRAPH_CHECK_S = 0.5   # how often the demo looks at the loop topics' publishers
# The nodes' start-up, before the episode's time limit: a limit to give up at,
# not a wait (60 s was not enough at a load of 15-20 on 2 cores).
STARTUP_S = 180.0
# In lockstep the sim waits this long for the command the demo holds (the
# maximum): it must never step on a zero action while the demo swaps.
COMMAND_TIMEOUT_S = 60.0
POKE_S = 2.0    # warm-up: a reset this often until the loop answers
# Only one state is in flight in lockstep: the policy may wait for its context
# as long as it takes on a loaded machine, rather than answer with zeros.
CONTEXT_TIMEOUT_S = 30.0


class DemoFailure(RuntimeError):
    """The demo could not do what it says (a step lost, the end not seen, time out)."""


@dataclass(frozen=True)
class Swap:
    """From `step` on, the state is simulated under `value` (set before step-1 -> step)."""

    step: int
    value: float


def parse_schedule(text: str) -> list[Swap]:
    """'0:1.0,333:0.4,666:1.7' -> swaps at steps 0, 333, 666, sorted by step."""
    schedule = []
    for item in text.split(','):
        step, value = item.split(':')
        schedule.append(Swap(int(step), float(value)))
    schedule.sort(key=lambda s: s.step)
    if not schedule or schedule[0].step != 0:
        raise ValueError('the schedule must start at step 0')
    if len({s.step for s in schedule}) != len(schedule):
        raise ValueError('two values for one step')
    return schedule


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', required=True, help='checkpoint directory')
    parser.add_argument('--reference-weights', type=Path,
                        help='a context-free checkpoint (method sac) run on the same schedule')
    parser.add_argument('--schedule', default='0:1.0,333:0.4,666:1.7',
                        help='step:value swaps of the physical parameter, from step 0')
    parser.add_argument('--seed', type=int, default=0, help='episode seed')
    parser.add_argument('--steps', type=int, default=1000,
                        help='steps to run (an episode has 1000)')
    parser.add_argument('--out', type=Path, default=Path('demo_out'), help='output folder')
    parser.add_argument('--max-seconds', '--timeout', type=float, default=90.0,
                        dest='max_seconds', help="give up on an episode after this (s; "
                        "the nodes' start-up not counted)")
    # Every 5th: 201 frames, 5-25 s of software rendering here (idle to loaded).
    parser.add_argument('--video-every', type=int, default=5,
                        help='render every Nth step into demo.gif (0: no video)')
    parser.add_argument('--composed', action='store_true',
                        help='run the three nodes in one process (bringup --composed)')
    parser.add_argument('--domain-id', default='auto',
                        help='ROS_DOMAIN_ID of the graph: auto (default) claims a free one, '
                        'so demos never hear each other; a number joins that domain')
    return parser.parse_args(argv)


class CommandGate:
    """The policy's commands reach the sim only through here, up to a step the demo sets.

    The policy publishes on POLICY_COMMANDS; the gate republishes on
    /joint_commands a command that answers a state of the demo's episode
    before `until` and holds the one that answers state `until`. In lockstep
    the sim then waits, so a swap goes in between two exact steps and the
    episode stops where the demo says. Before the episode (warm-up) every
    command goes through, which proves the whole loop is connected.
    Callbacks come from spin_loop's thread, `open_until` from the demo's.
    """

    def __init__(self, node: Node):
        self._lock = threading.Lock()
        self._publisher = node.create_publisher(JointState, '/joint_commands', LOOP_QOS)
        self.states: dict[int, tuple[int, int]] = {}   # stamp -> (episode, step)
        self.forwarded: dict[int, JointState] = {}     # by the stamp of the state answered
        self.held: JointState | None = None
        self.warm_up, self.episode, self.until = True, -1, -1
        create_loop_subscription(node, JointState, POLICY_COMMANDS, self._on_command,
                                 LOOP_QOS)

    def on_state(self, msg: StepInfo) -> None:
        with self._lock:
            self.states[stamp_ns(msg.header)] = (msg.episode, msg.step)
            self._release()   # a command may have come before its state's StepInfo

    def _on_command(self, msg: JointState) -> None:
        with self._lock:
            self.held = msg   # lockstep: a newer command answers a newer state
            self._release()

    def _release(self) -> None:
        if self.held is None:
            return
        stamp = stamp_ns(self.held.header)
        where = self.states.get(stamp)
        if where is None:
            return
        if self.warm_up or (where[0] == self.episode and where[1] < self.until):
            self._publisher.publish(self.held)
            self.forwarded[stamp], self.held = self.held, None

    def open_until(self, episode: int, until: int) -> None:
        """Forward the episode's commands answering states before step `until`, hold that one."""
        with self._lock:
            self.warm_up, self.episode, self.until = False, episode, until
            self._release()

    def close(self) -> None:
        """Forward nothing (the end of the warm-up)."""
        self.open_until(-1, -1)

    def held_at(self) -> tuple[int, int] | None:
        """(episode, step) of the state whose command is held, if one is."""
        with self._lock:
            return None if self.held is None else self.states.get(stamp_ns(self.held.header))


@dataclass(frozen=True)
class Policy:
    """One checkpoint the demo runs through the graph."""

    label: str           # 'adaptive' or 'reference'
    weights: Path
    family: str
    method: str
    param_name: str
    k: int
    context_dim: int

    @classmethod
    def load(cls, label: str, weights: Path) -> 'Policy':
        meta = load_metadata(weights)
        return cls(label, Path(weights), meta.family, meta.context.method, meta.param_name,
                   meta.context.k, meta.context.context_dim)


@dataclass
class RunRecord:
    """One policy's episode through the graph, as the demo received it."""

    policy: Policy
    episode: int
    rows: list[StepInfo]            # the episode's states, step 0 to the last, in order
    contexts: dict[int, Context]    # by stamp
    seconds: float                  # wall time of the episode
    counts: dict[str, int]          # messages recorded per topic
    bag: Path

    @property
    def real_time_factor(self) -> float:
        """Achieved simulated seconds per wall second over the episode (reset to last step)."""
        simulated = (stamp_ns(self.rows[-1].header) - stamp_ns(self.rows[0].header)) * 1e-9
        return simulated / self.seconds if self.seconds > 0 else math.nan


@dataclass
class Segment:
    """A run of steps under one true value; its return and the mean decoded value."""

    first_step: int
    true: float
    steps: int = 0
    episode_return: float = 0.0
    mean_estimate: float = math.nan
    reference_return: float | None = None


def check_episode(rows: list[StepInfo], contexts: dict[int, Context],
                  forwarded: dict[int, JointState], steps: int, episode_steps: int) -> None:
    """Raise DemoFailure unless every state 0..steps came, with its context, on the policy."""
    if not rows:
        raise DemoFailure('no state of the episode was received')
    last = rows[-1]
    if last.step < steps and (last.truncated or last.terminal):
        raise DemoFailure(f'the episode ended at step {last.step} before step {steps}')
    numbers = [s.step for s in rows]
    missing = sorted(set(range(steps + 1)) - set(numbers))
    if missing or len(numbers) != len(set(numbers)):
        raise DemoFailure(f'{len(missing)} of {steps + 1} states not received '
                          f'(first missing: step {missing[0] if missing else "-"}), or twice')
    if steps >= episode_steps and not last.truncated:
        raise DemoFailure(f'no truncation seen at step {steps}, the end of the episode')
    no_context = [s.step for s in rows if stamp_ns(s.header) not in contexts]
    if no_context:
        raise DemoFailure(f'{len(no_context)} states without a context '
                          f'(first: step {no_context[0]})')
    off_policy = [now.step for before, now in zip(rows[:-1], rows[1:], strict=True)
                  if not _stepped_on(now, forwarded.get(stamp_ns(before.header)))]
    if off_policy:
        raise DemoFailure(f"{len(off_policy)} steps not stepped on the policy's command "
                          f'(first: step {off_policy[0]}): a command timeout?')


def loop_closed(recent: list[StepInfo], contexts: dict[int, Context], matched: bool) -> bool:
    """Whether the warm-up may end: the policy's commands step the sim, and the demo hears all.

    A demo subscription that matched its publisher late loses what came
    before (volatile topics): under load the context topic matched hundreds
    of steps into the episode. So besides a stepped command, one of the
    recent states' contexts must have arrived here and every loop topic's
    subscription (the recorder's too) must have a publisher.
    """
    return (matched and any(any(s.applied_action) for s in recent)
            and any(stamp_ns(s.header) in contexts for s in recent))


def _stepped_on(state: StepInfo, command: JointState | None) -> bool:
    """Whether the sim applied `command` (clipped, as MuJoCo does) to reach `state`."""
    return command is not None and np.allclose(
        state.applied_action, np.clip(np.asarray(command.effort), -1.0, 1.0))


class DemoRun:
    """The demo's in-process ROS side for one graph: gate, reset, swaps, recording.

    It receives with `spin_loop` in a background thread, as the nodes do (a
    receiver on rclpy's executor falls behind the loop), with deep queues.
    """

    def __init__(self, node: Node, param_name: str, bag_dir: Path,
                 node_failure: Callable[[], tuple[str, int] | None]):
        self.node, self.param_name, self.node_failure = node, param_name, node_failure
        self.rows: list[StepInfo] = []
        self.contexts: dict[int, Context] = {}
        self.gate = CommandGate(node)
        deep = QoSProfile(depth=RECORD_DEPTH, reliability=LOOP_QOS.reliability)
        create_loop_subscription(node, StepInfo, '/zeus/step', self._on_step, deep)
        create_loop_subscription(node, Context, '/zeus/context', self._on_context, deep)
        self.reset_client = node.create_client(Reset, '/sim_node/reset')
        self.param_client = node.create_client(SetParameters, '/sim_node/set_parameters')
        self.recorder = BagRecorder(node, bag_dir, RECORDED_TOPICS)
        self.spinner = spin_in_background(node)
        self._graph_checked = -math.inf

    def _on_step(self, msg: StepInfo) -> None:
        self.rows.append(msg)
        self.gate.on_state(msg)

    def _on_context(self, msg: Context) -> None:
        self.contexts[stamp_ns(msg.header)] = msg

    def stop(self) -> None:
        """End the receiving thread (call after its context's shutdown), close the bag."""
        self.spinner.join(timeout=5.0)
        self.recorder.close()

    def wait(self, predicate: Callable[[], object], deadline: float, what: str) -> None:
        """Wait for `predicate()`; DemoFailure if a node exits or `deadline` passes first."""
        while not predicate():
            self._check_nodes(what)
            if time.monotonic() > deadline:
                raise DemoFailure(f'gave up waiting for {what}: the time limit passed')
            time.sleep(0.002)

    def _check_nodes(self, what: str) -> None:
        failure = self.node_failure()
        if failure is not None:
            raise DemoFailure(f'{failure[0]} exited with code {failure[1]} while the demo '
                              f'waited for {what}')
        if time.monotonic() - self._graph_checked >= GRAPH_CHECK_S:
            self.check_graph()

    def check_graph(self) -> None:
        """Refuse to go on when anything but the demo's own nodes publishes on its loop."""
        self._graph_checked = time.monotonic()
        problems = foreign_publishers(
            {topic: publisher_names(self.node, topic) for topic in LOOP_PUBLISHERS},
            LOOP_PUBLISHERS)
        if problems:
            domain = os.environ.get('ROS_DOMAIN_ID', '0')
            raise DemoFailure(f'foreign publishers on the loop of ROS_DOMAIN_ID {domain}: '
                              f'{"; ".join(problems)}. Not reporting over traffic the demo '
                              'did not produce: run it on a domain of its own '
                              '(--domain-id auto)')

    # `request`: the client's service type's Request message, passed on as it is.
    def call(self, client: Client, request: object, timeout: float = 30.0) -> Any:
        if not client.wait_for_service(timeout_sec=timeout):
            raise DemoFailure(f'{client.srv_name} is not available')
        try:
            return call_service(client, request, wait_until, timeout)
        except TimeoutError as error:
            raise DemoFailure(str(error)) from None

    def set_sim_parameter(self, name: str, value: float) -> None:
        result = self.call(self.param_client, SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg()])).results[0]
        if not result.successful:
            raise DemoFailure(f'the sim refused {name}={value:g}: {result.reason}')

    def warm_up(self, seed: int) -> None:
        """Reset until the policy's commands, through the gate, step the sim; close the gate.

        The sim never steps without a command (COMMAND_TIMEOUT_S), so a state
        it published before the other nodes listened is answered by no one:
        each reset publishes a new one.
        """
        deadline = time.monotonic() + STARTUP_S
        while not self._loop_closed():
            self._check_nodes('the three nodes to close the loop')
            if time.monotonic() > deadline:
                raise DemoFailure(f'the three nodes did not close the loop within '
                                  f'{STARTUP_S:g} s')
            # The sim's service comes up with its process: as late as the start-up allows.
            self.reset(seed, None, max(deadline - time.monotonic(), 1.0))
            wait_until(self._loop_closed, POKE_S)
        self.gate.close()

    def _loop_closed(self) -> bool:
        matched = all(sub.get_publisher_count() > 0 for sub in self.node.subscriptions
                      if sub.topic_name in LOOP_TOPICS)
        return loop_closed(self.rows[-3:], self.contexts, matched)

    def reset(self, seed: int, value: float | None, timeout: float = 30.0) -> int:
        """Start an episode (under `value`, if given); return its number."""
        names, values = ([self.param_name], [value]) if value is not None else ([], [])
        response = self.call(self.reset_client, Reset.Request(
            seed=seed, param_names=names, param_values=values), timeout)
        if not response.success:
            raise DemoFailure(f'the sim refused the reset: {response.message}')
        if getattr(response, 'episode', 0):   # Reset.srv with the episode field
            return int(response.episode)
        match = re.match(r'episode (\d+)', response.message)
        if match is None:
            raise DemoFailure(f'the reset did not say which episode started: {response.message}')
        return int(match.group(1))

    def drive(self, episode: int, schedule: list[Swap], steps: int, deadline: float) -> None:
        """Step the episode to `steps`, each swap put into force right before its step."""
        for swap in (s for s in schedule[1:] if s.step <= steps):
            self.gate.open_until(episode, swap.step - 1)
            self.wait(lambda s=swap: self.gate.held_at() == (episode, s.step - 1), deadline,
                      f'step {swap.step - 1} (before the swap to {swap.value:g})')
            self.set_sim_parameter(self.param_name, swap.value)
        self.gate.open_until(episode, steps)
        self.wait(lambda: self._ended(episode, steps), deadline,
                  f'step {steps} of episode {episode} and its context')

    def _ended(self, episode: int, steps: int) -> bool:
        last = next((s for s in reversed(self.rows) if s.episode == episode), None)
        return (last is not None and (last.step >= steps or last.truncated or last.terminal)
                and stamp_ns(last.header) in self.contexts)

    def run(self, policy: Policy, schedule: list[Swap], seed: int, steps: int,
            max_seconds: float) -> RunRecord:
        """Warm up, reset, drive the episode; check and return what was received."""
        from sim_node.families import get_sim_family
        self.warm_up(seed)
        self.check_graph()   # the loop runs: every publisher on it has been discovered
        started = time.monotonic()
        episode = self.reset(seed, schedule[0].value)
        self.drive(episode, schedule, steps, started + max_seconds)
        seconds = time.monotonic() - started
        # The nodes report at 1 Hz: a short run must still record a report.
        wait_until(lambda: self.recorder.counts['/diagnostics'] > 0, 2.0)
        self.check_graph()   # still only the demo's own nodes, to the end
        rows = sorted((s for s in self.rows if s.episode == episode), key=lambda s: s.step)
        check_episode(rows, self.contexts, self.gate.forwarded, steps,
                      get_sim_family(policy.family).episode_steps)
        return RunRecord(policy, episode, rows, dict(self.contexts), seconds,
                         self.recorder.counts, self.recorder.bag.bag_dir)


def graph_commands(weights: Path, seed: int, composed: bool = False) -> dict[str, list[str]]:
    """Return the nodes' command lines: lockstep, the policy's output to the gate.

    `composed`: one process runs the three nodes (bringup --composed); the
    remapping then names the policy node, so only its commands go to the gate.
    """
    commands = node_commands(bringup_args(
        ['--weights', str(weights), '--mode', 'lockstep', '--seed', str(seed),
         '--command-timeout', str(COMMAND_TIMEOUT_S), '--context-timeout',
         str(CONTEXT_TIMEOUT_S), '--log-level', 'warn', *(['--composed'] * composed)]))
    if composed:
        commands['composed'] += ['-r', f'policy_node:/joint_commands:={POLICY_COMMANDS}']
    else:
        commands['policy_node'] += ['-r', f'/joint_commands:={POLICY_COMMANDS}']
    return commands


def fresh_bag_dir(path: Path) -> Path:
    """Remove the bag a previous demo left at `path` (a bag is written once)."""
    if path.exists():
        if not (path / 'metadata.yaml').exists() and not any(path.glob('*.mcap')):
            raise DemoFailure(f'{path} exists and is not a bag: not overwriting it')
        shutil.rmtree(path)
    return path


def run_graph(policy: Policy, args: argparse.Namespace, bag_dir: Path) -> RunRecord:
    """Bring the three nodes up with `policy`, run the episode, bring them down."""
    bringup = Bringup(graph_commands(policy.weights, args.seed, args.composed))
    context = rclpy.Context()   # one per graph: its shutdown ends this run's receiver
    rclpy.init(context=context)
    node = rclpy.create_node('zeus_demo', context=context)
    demo = DemoRun(node, policy.param_name, fresh_bag_dir(bag_dir), bringup.failed)
    # The demo is in the loop (the gate): a full garbage collection over the
    # imported modules (torch) would stall it for tens of ms. What exists now
    # lives for the process anyway.
    gc.freeze()
    try:
        return demo.run(policy, parse_schedule(args.schedule), args.seed, args.steps,
                        args.max_seconds)
    finally:
        rclpy.try_shutdown(context=context)   # ends the receiving thread's spin_loop
        demo.stop()
        node.destroy_node()
        bringup.stop()


def segments_of(run: RunRecord) -> list[Segment]:
    """Segments = runs of one true value; a step's reward comes from its value's physics."""
    segments: list[Segment] = []
    estimates: list[list[float]] = []
    for s in run.rows:
        true = s.param_values[0]
        if not segments or segments[-1].true != true:
            segments.append(Segment(first_step=s.step, true=true))
            estimates.append([])
        if s.step > 0:
            segments[-1].steps += 1
            segments[-1].episode_return += s.reward
        # The window needs k steps under the new value to describe it fully.
        if s.step - segments[-1].first_step >= run.policy.k:
            estimates[-1].append(_estimate(run.contexts[stamp_ns(s.header)]))
    for segment, values in zip(segments, estimates, strict=True):
        if values and not all(math.isnan(v) for v in values):
            segment.mean_estimate = float(np.nanmean(values))
    return segments


def _estimate(context: Context) -> float:
    return float(context.param_estimates[0]) if len(context.param_estimates) else math.nan


def paired_segments(adaptive: RunRecord, reference: RunRecord | None) -> list[Segment]:
    """Return the adaptive run's segments, with the reference's return beside each."""
    segments = segments_of(adaptive)
    if reference is None:
        return segments
    theirs = segments_of(reference)
    if [(s.first_step, s.true) for s in theirs] != [(s.first_step, s.true) for s in segments]:
        raise DemoFailure('the reference run did not see the same swaps at the same steps')
    for mine, other in zip(segments, theirs, strict=True):
        mine.reference_return = other.episode_return
    return segments


def _policy_name(policy: Policy) -> str:
    return f'{policy.method}, no context' if policy.context_dim == 0 else policy.method


def _plot_returns(ax: Axes, segments: list[Segment], adaptive: Policy,
                  reference: Policy | None) -> None:
    x, width = np.arange(len(segments)), 0.38 if reference else 0.6
    ax.bar(x - width / 2 if reference else x, [s.episode_return for s in segments], width,
           color='tab:orange', label=f'{adaptive.label}: {_policy_name(adaptive)}')
    if reference is not None:
        ax.bar(x + width / 2, [s.reference_return for s in segments], width,
               color='tab:gray', label=f'reference: {_policy_name(reference)}')
    # Three lines: a long parameter name (forearm_length) beside its value overlaps
    # the next segment's label.
    ax.set_xticks(x, [f'from step {s.first_step}\n{adaptive.param_name}\n= {s.true:g}'
                      for s in segments])
    ax.set_ylabel('return of the segment')
    ax.set_title('return per segment')
    top = max([s.episode_return for s in segments]
              + [s.reference_return or 0.0 for s in segments])
    if top > 0:
        ax.set_ylim(0, 1.25 * top)   # room for the legend above the bars
    ax.legend(loc='upper center', ncol=2, fontsize=8)


def _plot_parameter(ax: Axes, run: RunRecord) -> None:
    name, steps = run.policy.param_name, [s.step for s in run.rows]
    ax.plot(steps, [s.param_values[0] for s in run.rows], color='black', label=f'true {name}')
    ax.plot(steps, [_estimate(run.contexts[stamp_ns(s.header)]) for s in run.rows],
            color='tab:orange', alpha=0.8,
            label=f'decoded from the context ({run.policy.method})')
    ax.set_xlabel('step')
    ax.set_ylabel(name)
    ax.set_title(f'true vs decoded {name}, {run.policy.label} run')
    ax.legend(loc='best', fontsize=8)


def plot(segments: list[Segment], adaptive: RunRecord, reference: RunRecord | None,
         seed: int, path: Path) -> None:
    """Return per segment (both policies) beside the true vs decoded parameter (adaptive)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (bars, trace) = plt.subplots(1, 2, figsize=(12, 4.6),
                                      gridspec_kw={'width_ratios': [1, 1.5]})
    _plot_returns(bars, segments, adaptive.policy, reference and reference.policy)
    _plot_parameter(trace, adaptive)
    what = 'one episode per policy under the same' if reference else 'one episode with live'
    fig.suptitle(f'{adaptive.policy.family}, seed {seed}, through ROS 2 in lockstep: '
                 f'{what} {adaptive.policy.param_name} swaps')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


VIDEO_TIMEOUT_S = 120.0


def render_video(run: RunRecord, out: Path, every: int) -> str:
    """Render the run's robot from its bag to a GIF; return the line to print.

    In a child process: MUJOCO_GL must be set before dm_control is imported,
    a backend that cannot start fails right there, and the nodes started
    here must not inherit it. Where it fails the demo goes on without video.
    """
    env = dict(os.environ, MUJOCO_GL=VIDEO_GL)
    command = [sys.executable, '-m', 'zeus_ros.ros_tools.recording', 'video', str(run.bag),
               str(out),
               '--every', str(every), '--episode', str(run.episode)]
    started = time.monotonic()
    try:
        result = subprocess.run(command, env=env, capture_output=True, text=True,
                                timeout=VIDEO_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f'video skipped: rendering took over {VIDEO_TIMEOUT_S:g} s'
    if result.returncode != 0:
        # Its own one-line reason, else the last line (a GL library may add noise at exit).
        lines = result.stderr.strip().splitlines() or [f'exit code {result.returncode}']
        reason = next((line for line in lines if line.startswith('no off-screen')), lines[-1])
        return f'video skipped: {reason}'
    return (f'video {out} ({result.stdout.split()[0]} frames, every {every}th step, '
            f'rendered in {time.monotonic() - started:.1f} s)')


def report(args: argparse.Namespace, segments: list[Segment], runs: list[RunRecord],
           video: str, claim: DomainClaim | None = None) -> None:
    """Print what ran, the table of segments, and where the outputs are."""
    adaptive = runs[0]
    name, reference = adaptive.policy.param_name, len(runs) > 1
    mode = 'lockstep, the three nodes in one process' if args.composed else 'lockstep'
    print(f'\n{adaptive.policy.family} through ROS 2 in {mode}, seed {args.seed}, '
          f'{name} schedule {args.schedule}, ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]} '
          f'({"claimed free" if claim is not None else "given"})')
    for run in runs:
        print(f'{run.policy.label:<9} {run.policy.weights} ({_policy_name(run.policy)}): '
              f'{run.rows[-1].step} steps in {run.seconds:.1f} s (achieved real-time factor '
              f'{run.real_time_factor:.2f}), all {len(run.rows)} states received; '
              f'bag {run.bag} ({sum(run.counts.values())} messages)')
    print(f'{"from step":>9} {"true " + name:>14} {"decoded (mean)":>15} {"steps":>6} '
          f'{"return":>8}' + (f' {"reference":>10}' if reference else ''))
    for s in segments:
        print(f'{s.first_step:>9} {s.true:>14.3f} {s.mean_estimate:>15.3f} {s.steps:>6} '
              f'{s.episode_return:>8.1f}' + (f' {s.reference_return:>10.1f}' if reference else ''))
    total = sum(s.episode_return for s in segments)
    line = f'{"total":>9} {"":>14} {"":>15} {sum(s.steps for s in segments):>6} {total:>8.1f}'
    if reference:
        line += f' {sum(s.reference_return for s in segments):>10.1f}'
    print(line)
    print(f'plot {args.out / "demo.png"}; {video}')


def load_policies(args: argparse.Namespace) -> list[Policy]:
    """Return the adaptive policy and the context-free reference, if any, checked."""
    try:
        parse_schedule(args.schedule)
    except ValueError as error:
        raise DemoFailure(f'bad --schedule {args.schedule!r}: {error}') from None
    if args.steps < 1:
        raise DemoFailure('--steps must be at least 1')
    policies = [Policy.load('adaptive', args.weights)]
    if args.reference_weights is not None:
        reference = Policy.load('reference', args.reference_weights)
        if reference.family != policies[0].family:
            raise DemoFailure(f'the reference weights are for {reference.family}, the '
                              f'adaptive ones for {policies[0].family}')
        if reference.context_dim != 0:
            raise DemoFailure(f'the reference must be context-free (method sac, no latent); '
                              f'{reference.weights} is {reference.method} with a latent of '
                              f'{reference.context_dim}')
        policies.append(reference)
    return policies


BAGS = {'adaptive': 'demo', 'reference': 'demo_reference'}


def own_domain(choice: str) -> DomainClaim | None:
    """Set ROS_DOMAIN_ID for the graph: a free one claimed ('auto'), or the number given."""
    if choice == 'auto':
        try:
            return use_free_domain()   # held until the demo exits
        except RuntimeError as error:
            raise DemoFailure(str(error)) from None
    if not choice.isdigit() or not 0 <= int(choice) <= 232:
        raise DemoFailure(f'--domain-id must be auto or a ROS_DOMAIN_ID in [0, 232], '
                          f'got {choice!r}')
    os.environ['ROS_DOMAIN_ID'] = choice
    return None


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        policies = load_policies(args)
        claim = own_domain(args.domain_id)   # its lock is held until the demo exits
        args.out.mkdir(parents=True, exist_ok=True)
        runs = [run_graph(p, args, args.out / BAGS[p.label]) for p in policies]
        segments = paired_segments(runs[0], runs[1] if len(runs) > 1 else None)
    except (CheckpointError, DemoFailure) as error:
        print(f'demo: {error}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:   # the nodes and the bag were closed on the way out
        print('demo: interrupted', file=sys.stderr)
        return 130
    plot(segments, runs[0], runs[1] if len(runs) > 1 else None, args.seed,
         args.out / 'demo.png')
    (args.out / 'segments.json').write_text(json.dumps(
        [asdict(s) for s in segments], indent=2))
    video = (render_video(runs[0], args.out / 'demo.gif', args.video_every)
             if args.video_every > 0 else 'no video (--video-every 0)')
    report(args, segments, runs, video, claim)
    return 0


if __name__ == '__main__':
    sys.exit(main())
