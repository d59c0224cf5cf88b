"""check_parity: one episode in process and through ROS, compared step by step.

    check_parity --weights weights/walker-walk-v0-zeus --steps 200
    python -m zeus_ros.ros_tools.check_parity --weights DIR [--family F] [--value V]
        [--seed S] [--steps N]

The same episode twice: in process (`zeus_ros.learning_tools.evaluate.run_episode`, the
reference order of operations) and through sim_node, context_node and
policy_node in lockstep, separate processes on a ROS_DOMAIN_ID of their own
(claimed free, as the test suite's). The tool holds each command of the
policy until it has every message of the step, so nothing is lost however
slow the machine. It reports the first step whose observation (rebuilt from
/joint_states as the policy does), context (/zeus/context latent), action
(/joint_commands) or reward (/zeus/step) differs, bit for bit, or that all
N steps are identical. --ros-seed, --ros-value and --ros-weights run the ROS
side otherwise (a deliberate mismatch, or a converted controller against its
original). Exit 0: identical; 1: a difference, or the ROS episode did not
run through; 2: bad arguments or weights.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import os
from pathlib import Path
import sys
import time
from typing import Callable, TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    # Imported where they are used (a report needs no ROS), named here for the types.
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from zeus_msgs.msg import Context, StepInfo

    from sim_node.families import SimFamily
    from sim_node.layout import ObservationLayout
    from zeus_ros.deploy.inference import DeployedModel

QUANTITIES = ('observation', 'context', 'action', 'reward')   # in the order a step makes them
STARTUP_S = 300.0  # the nodes' start-up (minutes on a loaded machine), before the episode's limit
POKE_S = 2.0       # warm-up: a reset this often until the loop answers


class ParityFailure(RuntimeError):
    """The ROS side could not be run through (a node exited, time ran out)."""


@dataclass
class Trace:
    """The first steps of one episode: what each step saw, inferred, did and got."""

    observation: np.ndarray   # [T, obs_dim] the observation the action was chosen at
    context: np.ndarray       # [T, context_dim] float32 latent
    action: np.ndarray        # [T, action_dim] as sent to the sim (clipped to [-1, 1])
    reward: np.ndarray        # [T] reward of the step

    def __len__(self) -> int:
        return len(self.reward)


@dataclass(frozen=True)
class Difference:
    """Where two traces first differ."""

    step: int
    quantity: str             # one of QUANTITIES, or 'length'
    index: int = 0            # the first differing element
    in_process: float = 0.0
    through_ros: float = 0.0
    largest: float = 0.0      # largest |difference| of that quantity at that step
    also: tuple[str, ...] = ()   # the other quantities differing at that step


def first_difference(reference: Trace, ros: Trace) -> Difference | None:
    """Return the first step and quantity where `ros` differs from `reference`, or None."""
    for step in range(min(len(reference), len(ros))):
        differing = [q for q in QUANTITIES if not np.array_equal(
            getattr(reference, q)[step], getattr(ros, q)[step])]
        if differing:
            return _difference(step, differing, getattr(reference, differing[0])[step],
                               getattr(ros, differing[0])[step])
    if len(reference) != len(ros):
        return Difference(min(len(reference), len(ros)), 'length', 0, len(reference), len(ros))
    return None


def _difference(step: int, differing: list[str], a: np.ndarray | float,
                b: np.ndarray | float) -> Difference:
    a, b = np.atleast_1d(np.asarray(a, np.float64)), np.atleast_1d(np.asarray(b, np.float64))
    if a.shape != b.shape:
        return Difference(step, differing[0], 0, a.size, b.size, np.inf, tuple(differing[1:]))
    gaps = np.abs(a - b)
    index = int(np.flatnonzero(~((a == b) | (np.isnan(a) & np.isnan(b))))[0])
    return Difference(step, differing[0], index, float(a[index]), float(b[index]),
                      float(np.nanmax(gaps)), tuple(differing[1:]))


def describe(difference: Difference | None, steps: int) -> str:
    """One line: identical for N steps, or the first difference."""
    if difference is None:
        return (f'identical for {steps} steps: observations, contexts, actions and rewards '
                'equal bit for bit')
    d = difference
    if d.quantity == 'length':
        return (f'the episodes differ in length: {d.in_process:g} steps in process, '
                f'{d.through_ros:g} through ROS')
    if np.isinf(d.largest):
        what = f'{d.in_process:g} values in process, {d.through_ros:g} through ROS'
    else:
        what = (f'element {d.index}: {d.in_process!r} in process, {d.through_ros!r} through '
                f'ROS; largest |difference| {d.largest:.3g}')
    also = f'; also {", ".join(d.also)}' if d.also else ''
    return f'first difference at step {d.step}: {d.quantity} ({what}){also}'


def in_process_trace(model: DeployedModel, family: str, values: tuple, seed: int,
                     steps: int) -> Trace:
    """Run the episode's first `steps` steps in process (the reference)."""
    from zeus_ros.learning_tools.evaluate import run_episode
    record = run_episode(model, family, values, seed, max_steps=steps)
    return Trace(record.observations, record.latents, np.clip(record.actions, -1.0, 1.0),
                 record.rewards)


class RosEpisode:
    """The tool's node on the graph: it gates the policy's commands and keeps every message.

    The policy's commands reach the sim only through the demo's CommandGate,
    so the sim steps no further than the tool has heard (lockstep waits).
    """

    def __init__(self, node: Node, layout: ObservationLayout,
                 node_failure: Callable[[], tuple[str, int] | None]):
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import JointState
        from zeus_msgs.msg import Context, StepInfo
        from zeus_msgs.srv import Reset
        from zeus_ros.ros_tools.demo import CommandGate
        from zeus_ros.ros.loop_spin import create_loop_subscription, spin_in_background
        from zeus_ros.ros.util import LOOP_QOS
        self.node, self.layout, self.node_failure = node, layout, node_failure
        self.gate = CommandGate(node)
        self.rows, self.states, self.contexts = [], {}, {}
        deep = QoSProfile(depth=100, reliability=LOOP_QOS.reliability)
        for msg_type, topic, keep in ((StepInfo, '/zeus/step', self._on_step),
                                      (JointState, '/joint_states', self._on_state),
                                      (Context, '/zeus/context', self._on_context)):
            create_loop_subscription(node, msg_type, topic, keep, deep)
        self.reset_client = node.create_client(Reset, '/sim_node/reset')
        self.spinner = spin_in_background(node)

    def _on_step(self, msg: StepInfo) -> None:
        self.rows.append(msg)
        self.gate.on_state(msg)

    def _on_state(self, msg: JointState) -> None:
        self.states[_stamp(msg)] = msg

    def _on_context(self, msg: Context) -> None:
        self.contexts[_stamp(msg)] = msg

    def _wait(self, predicate: Callable[[], object], deadline: float, what: str,
              heard: Callable[[], str] = lambda: '') -> None:
        from zeus_ros.ros.loop_spin import wait_until
        while not wait_until(predicate, 0.2):
            failure = self.node_failure()
            if failure is not None:
                raise ParityFailure(f'{failure[0]} exited with code {failure[1]} while '
                                    f'waiting for {what}')
            if time.monotonic() > deadline:
                raise ParityFailure(f'gave up waiting for {what}: the time limit passed'
                                    f'{heard()}')

    def _heard(self) -> str:
        silent = [sub.topic_name for sub in self.node.subscriptions
                  if sub.get_publisher_count() == 0]
        return (f' (heard {len(self.rows)} states, {len(self.contexts)} contexts, '
                f'{len(self.gate.forwarded)} commands; no publisher on '
                f'{", ".join(silent) or "none"})')

    def _reset(self, seed: int, params: dict) -> int:
        from zeus_ros.ros.loop_spin import wait_until
        from zeus_ros.ros.util import reset_episode, ResetRefused
        try:
            return reset_episode(self.reset_client, wait_until, seed, params)
        except (ResetRefused, TimeoutError) as error:
            raise ParityFailure(f'reset: {error}') from None

    def run(self, seed: int, params: dict, steps: int, max_seconds: float) -> int:
        """Close the loop, then run an episode to state `steps`; return its number."""
        from zeus_ros.ros_tools.demo import loop_closed
        deadline = time.monotonic() + STARTUP_S

        def closed():
            matched = all(sub.get_publisher_count() > 0 for sub in self.node.subscriptions)
            return loop_closed(self.rows[-3:], self.contexts, matched)
        self._wait(self.reset_client.service_is_ready, deadline, 'the sim')
        while not closed():   # a state sent before the others listened is answered by no one
            self._reset(seed, params)
            poke = time.monotonic() + POKE_S
            self._wait(lambda at=poke: closed() or time.monotonic() > at, deadline,
                       'the three nodes to close the loop', self._heard)
        self.gate.close()
        episode = self._reset(seed, params)
        self.gate.open_until(episode, steps)
        self._wait(lambda: self._ended(episode, steps), time.monotonic() + max_seconds,
                   f'state {steps} of the episode')
        return episode

    def _ended(self, episode: int, steps: int) -> bool:
        last = next((s for s in reversed(self.rows) if s.episode == episode), None)
        return last is not None and (last.step >= steps or last.truncated or last.terminal)

    def trace(self, episode: int, steps: int) -> Trace:
        """Return the episode's first steps as received (ParityFailure if a message is missing)."""
        from zeus_ros.ros.pairing import observation_from_message
        rows = sorted((s for s in self.rows if s.episode == episode), key=lambda s: s.step)
        if [s.step for s in rows] != list(range(len(rows))):
            raise ParityFailure(f'states of episode {episode} missing or repeated')
        columns = {q: [] for q in QUANTITIES}
        for info, after in zip(rows[:steps], rows[1:steps + 1], strict=False):
            stamp = _stamp(info)
            state, context = self.states.get(stamp), self.contexts.get(stamp)
            command = self.gate.forwarded.get(stamp)
            if state is None or context is None or command is None:
                raise ParityFailure(f'step {info.step}: no joint state, context or command')
            obs = observation_from_message(self.layout, state.name, state.position,
                                           state.velocity)
            columns['observation'].append(self.layout.with_reward(obs, info.reward))
            columns['context'].append(np.asarray(context.latent, np.float32))
            columns['action'].append(np.asarray(command.effort, np.float64))
            columns['reward'].append(after.reward)
        return Trace(*(np.asarray(columns[q]) for q in QUANTITIES))


def _stamp(msg: StepInfo | JointState | Context) -> int:
    from zeus_ros.ros.util import stamp_ns
    return stamp_ns(msg.header)


def ros_trace(weights: Path, family: str, layout: ObservationLayout, values: tuple, seed: int,
              steps: int, max_seconds: float) -> Trace:
    """Run the episode's first `steps` steps through the three nodes (own processes)."""
    import rclpy
    from sim_node.families import get_sim_family
    from zeus_ros.ros_tools.bringup import Bringup
    from zeus_ros.ros_tools.demo import graph_commands
    from zeus_ros.deploy.checkpoint import load_metadata
    commands = graph_commands(weights, seed)   # lockstep, the policy's commands to the gate
    if family != load_metadata(weights).family:   # the last -p of a name wins
        commands['sim_node'] += ['-p', f'family:={family}']
    params = dict(zip(get_sim_family(family).param_names, values, strict=True))
    bringup = Bringup(commands)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('zeus_check_parity', context=context)
    episode = RosEpisode(node, layout, bringup.failed)
    try:
        number = episode.run(seed, params, steps, max_seconds)
        return episode.trace(number, steps)
    finally:
        rclpy.try_shutdown(context=context)   # ends the receiving thread
        episode.spinner.join(timeout=5.0)
        node.destroy_node()
        bringup.stop()


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='check_parity', description=__doc__.split('\n')[0])
    parser.add_argument('--weights', type=Path, required=True, help='checkpoint directory')
    parser.add_argument('--family', help="environment family (default: the weights')")
    parser.add_argument('--value', help="the physical parameter's value; comma-separated "
                        "for a family with several (default: the family's default)")
    parser.add_argument('--seed', type=int, default=0, help='episode seed')
    parser.add_argument('--steps', type=int, default=1000, help='steps to compare, 1-1000')
    parser.add_argument('--ros-weights', type=Path, help='weights of the ROS side')
    parser.add_argument('--ros-value', help='value of the ROS side (a deliberate mismatch)')
    parser.add_argument('--ros-seed', type=int, help='seed of the ROS side')
    parser.add_argument('--max-seconds', type=float, default=300.0,
                        help='give up on the ROS episode after this (s; the start-up not '
                        'counted)')
    return parser.parse_args(argv)


@dataclass(frozen=True)
class Setup:
    """Both sides of the comparison, checked."""

    model: object             # InferenceModel of the in-process side
    ros_weights: Path
    ros_layout: object        # the ROS weights' ObservationLayout
    family: str
    values: tuple
    ros_values: tuple


def _values(text: str | None, spec: SimFamily) -> tuple:
    if text is None:
        return tuple(p.default for p in spec.live_params)
    values = tuple(float(v) for v in text.split(','))
    problems = [] if len(values) == len(spec.param_names) else [
        f'{len(values)} values for {len(spec.param_names)} parameters']
    problems += [p for p in (spec.check_param(n, v) for n, v in zip(
        spec.param_names, values, strict=False)) if p]
    if problems:
        raise ValueError(f'value {text!r}: {problems[0]}')
    return values


def _text(family: str, values: tuple) -> str:
    from sim_node.families import get_sim_family
    names = get_sim_family(family).param_names
    return ', '.join(f'{n}={v:g}' for n, v in zip(names, values, strict=True))


def setup(args: argparse.Namespace) -> Setup:
    """Load and check the weights and values (CheckpointError or ValueError says why not)."""
    from sim_node.families import get_sim_family
    from zeus_ros.deploy.checkpoint import load_metadata
    from zeus_ros.deploy.inference import InferenceModel
    if not 1 <= args.steps <= 1000:
        raise ValueError(f'--steps must be in [1, 1000] (one episode), got {args.steps}')
    model = InferenceModel.load(args.weights)
    ros_weights = (args.ros_weights or args.weights).resolve()
    family = args.family or model.family
    spec = get_sim_family(family)
    values = _values(args.value, spec)
    ros_values = values if args.ros_value is None else _values(args.ros_value, spec)
    return Setup(model, ros_weights, load_metadata(ros_weights).obs_layout.layout(), family,
                 values, ros_values)


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`check_parity`)."""
    from zeus_ros.deploy.checkpoint import CheckpointError
    from zeus_ros.ros.graph import use_free_domain
    args = parse_args(argv)
    try:
        s = setup(args)
    except (CheckpointError, ValueError, KeyError) as error:
        print(f'check_parity: {error}', file=sys.stderr)
        return 2
    ros_seed = args.seed if args.ros_seed is None else args.ros_seed
    claim = use_free_domain()   # held until the tool exits
    print(f'check_parity: {s.family} {_text(s.family, s.values)}, seed {args.seed}, '
          f'{args.steps} steps; '
          f'in process vs through ROS in lockstep (ROS_DOMAIN_ID {claim.domain_id})'
          + (f'; the ROS side: {s.ros_weights}, {_text(s.family, s.ros_values)}, seed {ros_seed}'
             if (s.ros_values, ros_seed, args.ros_weights) != (s.values, args.seed, None)
             else ''), flush=True)
    reference = in_process_trace(s.model, s.family, s.values, args.seed, args.steps)
    try:
        ros = ros_trace(s.ros_weights, s.family, s.ros_layout, s.ros_values, ros_seed,
                        args.steps, args.max_seconds)
    except ParityFailure as error:
        print(f'check_parity: the ROS episode did not run through: {error}', file=sys.stderr)
        return 1
    difference = first_difference(reference, ros)
    print(describe(difference, len(reference)))
    return 0 if difference is None else 1


if __name__ == '__main__':
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    sys.exit(main())
