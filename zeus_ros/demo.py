"""demo: zero-shot adaptation through ROS, with a recording and a plot.

Brings up sim_node, context_node and policy_node in lockstep (separate
processes, real DDS), starts an episode, swaps the physical parameter at fixed
steps through the sim's parameter service (what `ros2 param set` does), and
prints the return of each segment with the decoded parameter against the true
one. Writes to --out: `demo.mcap` (every topic, readable by `ros2 bag info` and
Foxglove) and `demo.png` (true vs estimated parameter, reward over time).

    ros2 run zeus_ros demo --weights weights/walker-walk-v0-zeus
"""

from __future__ import annotations

import argparse
import gc
import json
import os
from pathlib import Path
import sys
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import numpy as np  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from zeus_msgs.msg import Context, StepInfo  # noqa: E402
from zeus_msgs.srv import Reset  # noqa: E402

from zeus_ros.bringup import Bringup, node_commands, parse_args as bringup_args  # noqa: E402
from zeus_ros.checkpoint import CheckpointError, load_metadata  # noqa: E402
from zeus_ros.loop_spin import (create_loop_subscription, spin_in_background,  # noqa: E402
                                wait_until)
from zeus_ros.recording import McapRecorder  # noqa: E402
from zeus_ros.ros_util import call_service, LOOP_QOS, stamp_ns  # noqa: E402

RECORDED_TOPICS = {
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/joint_commands': 'sensor_msgs/msg/JointState',
    '/zeus/step': 'zeus_msgs/msg/StepInfo',
    '/zeus/context': 'zeus_msgs/msg/Context',
    '/clock': 'rosgraph_msgs/msg/Clock',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
}


def parse_schedule(text: str) -> list[tuple[int, float]]:
    """'0:1.0,333:0.4,666:1.7' -> [(0, 1.0), (333, 0.4), (666, 1.7)], sorted by step."""
    schedule = []
    for item in text.split(','):
        step, value = item.split(':')
        schedule.append((int(step), float(value)))
    schedule.sort()
    if not schedule or schedule[0][0] != 0:
        raise ValueError('the schedule must start at step 0')
    return schedule


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', required=True, help='checkpoint directory')
    parser.add_argument('--schedule', default='0:1.0,333:0.4,666:1.7',
                        help='step:value swaps of the physical parameter, from step 0')
    parser.add_argument('--seed', type=int, default=0, help='episode seed')
    parser.add_argument('--steps', type=int, default=1000,
                        help='steps to run (an episode has 1000)')
    parser.add_argument('--out', type=Path, default=Path('demo_out'), help='output folder')
    parser.add_argument('--timeout', type=float, default=90.0, help='give up after (s)')
    return parser.parse_args(argv)


class DemoRun:
    """The demo's in-process ROS side: reset, swaps, collection, recording.

    It receives with `spin_loop` in a background thread, as the nodes do: the
    loop runs at a few hundred steps per second, and a receiver on rclpy's
    executor falls behind and loses messages (the loop's publishers keep 10).
    """

    def __init__(self, node, param_name: str, out: Path):
        self.node, self.param_name = node, param_name
        self.steps: list[StepInfo] = []
        self.contexts: dict[int, Context] = {}
        create_loop_subscription(node, StepInfo, '/zeus/step', self.steps.append, LOOP_QOS)
        create_loop_subscription(node, Context, '/zeus/context', self._on_context, LOOP_QOS)
        self.reset_client = node.create_client(Reset, '/sim_node/reset')
        self.param_client = node.create_client(SetParameters, '/sim_node/set_parameters')
        self.recorder = McapRecorder(node, out / 'demo.mcap', RECORDED_TOPICS)
        self.spinner = spin_in_background(node)

    def _on_context(self, msg: Context) -> None:
        self.contexts[stamp_ns(msg.header)] = msg

    def stop(self) -> None:
        """End the receiving thread (call after rclpy shutdown), then close the recording."""
        self.spinner.join(timeout=5.0)
        self.recorder.close()

    @staticmethod
    def spin_until(predicate, timeout: float) -> bool:
        """Wait (the spinner thread receives) until `predicate()` or the timeout."""
        return wait_until(predicate, timeout)

    def call(self, client, request, timeout: float = 30.0):
        if not client.wait_for_service(timeout_sec=timeout):
            raise RuntimeError(f'{client.srv_name} is not available')
        try:
            return call_service(client, request, self.spin_until, timeout)
        except TimeoutError as error:
            raise RuntimeError(str(error)) from None

    def loop_closed(self) -> bool:
        return any(any(s.applied_action) for s in self.steps[-3:])

    def run(self, schedule, seed: int, steps: int, timeout: float) -> int:
        """Run the episode; return its number."""
        if not self.spin_until(self.loop_closed, 60.0):
            raise RuntimeError('the three nodes never closed the loop')
        response = self.call(self.reset_client, Reset.Request(
            seed=seed, param_names=[self.param_name], param_values=[schedule[0][1]]))
        if not response.success:
            raise RuntimeError(response.message)
        episode = int(response.message.split(':')[0].split()[1])
        pending = list(schedule[1:])
        deadline = time.monotonic() + timeout

        def current_step():
            return max((s.step for s in self.steps if s.episode == episode), default=-1)
        while current_step() < steps and time.monotonic() < deadline:
            if pending and current_step() >= pending[0][0]:
                _, value = pending.pop(0)
                result = self.call(self.param_client, SetParameters.Request(parameters=[
                    Parameter(self.param_name, value=value).to_parameter_msg()]))
                if not result.results[0].successful:
                    raise RuntimeError(result.results[0].reason)
            if any(s.episode == episode and s.truncated for s in self.steps[-5:]):
                break
            time.sleep(0.002)
        self.spin_until(lambda: False, 0.3)  # let the last contexts arrive
        # The nodes report at 1 Hz: a short run must still record a report.
        self.spin_until(lambda: self.recorder.counts.get('/diagnostics', 0) > 0, 2.0)
        return episode


def episode_table(steps: list[StepInfo], contexts: dict[int, Context], episode: int,
                  k: int) -> tuple[dict, list[dict]]:
    """Per-step series and per-segment summary (segments = runs of one true value)."""
    rows = [s for s in steps if s.episode == episode]
    series = {'step': [], 'reward': [], 'true': [], 'estimate': []}
    for s in rows:
        context = contexts.get(stamp_ns(s.header))
        series['step'].append(s.step)
        series['reward'].append(s.reward)
        series['true'].append(s.param_values[0])
        series['estimate'].append(context.param_estimates[0] if context else float('nan'))
    segments = []
    for i, (value, reward, estimate) in enumerate(zip(series['true'], series['reward'],
                                                      series['estimate'], strict=True)):
        if not segments or segments[-1]['true'] != value:
            segments.append({'true': value, 'first_step': series['step'][i], 'steps': 0,
                             'return': 0.0, 'estimates': []})
        segment = segments[-1]
        if series['step'][i] > 0:
            segment['steps'] += 1
            segment['return'] += reward
        # The window needs k steps under the new value to describe it fully.
        if series['step'][i] - segment['first_step'] >= k:
            segment['estimates'].append(estimate)
    for segment in segments:
        estimates = segment.pop('estimates')
        segment['mean_estimate'] = float(np.nanmean(estimates)) if estimates else float('nan')
    return series, segments


def plot(series: dict, param_name: str, path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    top.plot(series['step'], series['true'], label=f'true {param_name}', color='black')
    top.plot(series['step'], series['estimate'], label='decoded from the latent context',
             color='tab:orange', alpha=0.8)
    top.set_ylabel(param_name)
    top.legend(loc='best')
    top.set_title('Zero-shot adaptation through ROS 2 (lockstep)')
    bottom.plot(series['step'], series['reward'], color='tab:blue')
    bottom.set_ylabel('reward per step')
    bottom.set_xlabel('step')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    schedule = parse_schedule(args.schedule)
    try:
        metadata = load_metadata(args.weights)
    except CheckpointError as error:
        print(f'demo: {error}', file=sys.stderr)
        return 1
    param_name, k = metadata['param_name'], int(metadata['context']['k'])
    args.out.mkdir(parents=True, exist_ok=True)
    bringup = Bringup(node_commands(bringup_args(
        ['--weights', str(args.weights), '--mode', 'lockstep', '--seed', str(args.seed),
         '--log-level', 'warn'])))
    rclpy.init()
    node = rclpy.create_node('zeus_demo')
    demo = DemoRun(node, param_name, args.out)
    # The loop's publishers keep 10 messages (about 20 ms at full speed): a
    # full garbage collection over the imported modules would outlast that
    # and lose steps. What exists now lives for the process anyway.
    gc.freeze()
    started = time.monotonic()
    try:
        episode = demo.run(schedule, args.seed, args.steps, args.timeout)
    except RuntimeError as error:
        print(f'demo: {error}', file=sys.stderr)
        return 1
    finally:
        rclpy.try_shutdown()  # ends the receiving thread's spin_loop
        demo.stop()
        node.destroy_node()
        bringup.stop()
    series, segments = episode_table(demo.steps, demo.contexts, episode, k)
    plot(series, param_name, args.out / 'demo.png')
    (args.out / 'segments.json').write_text(json.dumps(segments, indent=2))
    print(f'\n{metadata["family"]}, weights {args.weights}, seed {args.seed}, '
          f'{series["step"][-1]} steps in {time.monotonic() - started:.1f} s')
    print(f'{"from step":>9} {"true " + param_name:>14} {"decoded (mean)":>15} '
          f'{"steps":>6} {"return":>8}')
    for s in segments:
        print(f'{s["first_step"]:>9} {s["true"]:>14.3f} {s["mean_estimate"]:>15.3f} '
              f'{s["steps"]:>6} {s["return"]:>8.1f}')
    missing = series['step'][-1] + 1 - len(series['step'])
    if missing:
        print(f'WARNING: {missing} steps of the episode were not received; the returns '
              'above are short by their rewards')
    print(f'total return {sum(series["reward"]):.1f}; recorded '
          f'{sum(demo.recorder.counts.values())} messages to {args.out / "demo.mcap"}; '
          f'plot {args.out / "demo.png"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
