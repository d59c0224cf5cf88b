"""Benchmark the ROS closed loop against the in-process loop, in one run.

    python research/benchmarks/bench_loop.py --weights weights/walker-walk-v0-zeus \
        [--realtime-seconds 600]

Measures, with the same checkpoint:
1. in-process loop (evaluate.run_episode: ParamEnv + InferenceModel, no middleware): steps/s;
2. lockstep through the three ROS processes: control steps/s, the median (and
   range) over --episodes episodes, and the ratio of the median to (1); then
   the same with the three nodes composed in one process (`bringup --composed`,
   figures prefixed composed_), and under each --profiles NAME=FILE (the nodes'
   Fast DDS participant profile: e.g. shared memory against UDPv4, which
   FASTDDS_BUILTIN_TRANSPORTS cannot choose under ROS_AUTOMATIC_DISCOVERY_RANGE=
   LOCALHOST) and --executors value (the nodes' background
   executor: events), so the modes come from one run; each with
   the CPU ms per step of every process of the graph and of the observer;
3. step latency, state published -> its command, p50 / p99 / max (seen from an
   observer process that receives both topics; the sim's own view is in /diagnostics);
4. realtime mode: how late the sim's control ticks start (its own clock, from its
   /diagnostics: every tick of the window), ticks more than a period late, the
   period jitter of the state stream at the observer (so including DDS
   delivery), and missed control
   deadlines: states whose command arrived after the next state (the sim then
   stepped on the older command).
   The realtime run gives the nodes SCHED_FIFO (--realtime-priority, default 50);
   --compare-normal-scheduler repeats it under the normal scheduler.
5. live swap: from the parameter set request to the first StepInfo under the new value;
   in realtime, how late the sim's ticks start while swaps arrive at 10 per second
   (--realtime-swap-seconds), beside the same figures without swaps from (4).
Prints a table and writes the figures as JSON (--json).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
from pathlib import Path
import sys
import time
from typing import NamedTuple

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import numpy as np  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from zeus_msgs.msg import StepInfo  # noqa: E402
from zeus_msgs.srv import Reset  # noqa: E402
from zeus_ros.ros_tools.bringup import Bringup, node_commands, parse_args as bringup_args  # noqa: E402
from zeus_ros.deploy.checkpoint import load_metadata  # noqa: E402
from zeus_ros.ros.discovery import PROFILE_ENV  # noqa: E402
from zeus_ros.deploy.metadata import CheckpointMetadata  # noqa: E402
from zeus_ros.deploy.inference import InferenceModel  # noqa: E402
from zeus_ros.learning_tools.evaluate import model_env, run_episode  # noqa: E402
from zeus_ros.ros.loop_spin import (create_loop_subscription, spin_in_background,  # noqa: E402
                                wait_until)
from zeus_ros.ros.util import call_service, LOOP_QOS, reset_episode, stamp_ns  # noqa: E402


def in_process_rate(weights: Path, steps: int, samples: int = 5) -> tuple[float, float]:
    """Steps/s of simulation plus inference in one process: `evaluate.run_episode`.

    The median of `samples` episodes of `steps` steps (the evaluator the
    trainer and the eval CLI use): one short sample on this machine varies by
    a quarter from run to run. Also the CPU ms per step, which depends less
    on what else runs on the machine than the rate does.
    """
    model = InferenceModel.load(weights)
    env = model_env(model, episode_steps=steps)
    rates, cpu_start, total = [], time.process_time(), 0
    for sample in range(samples):
        start = time.perf_counter()
        record = run_episode(model, model.family, env.param_values, seed=sample, env=env)
        rates.append(len(record.actions) / (time.perf_counter() - start))
        total += len(record.actions)
    return float(np.median(rates)), 1e3 * (time.process_time() - cpu_start) / total


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (all its threads)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rpartition(')')[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


class Observer:
    """Receipt times of states, commands and step infos, by stamp; the sim's diagnostics.

    It takes the loop's topics with `spin_loop` in a background thread, the way
    the nodes do: on two cores an observer on rclpy's executor would take CPU
    from the loop it measures.
    """

    def __init__(self, node, graph_pids: dict[str, int]):
        self.node = node
        self.graph_pids = graph_pids   # name -> pid of each process of the graph measured
        self.state_at: dict[int, float] = {}
        self.command_at: dict[int, float] = {}
        self.steps: list[tuple[float, StepInfo]] = []
        self.sim_diagnostics: list[dict] = []
        create_loop_subscription(node, JointState, '/joint_states', self._on_state, LOOP_QOS)
        create_loop_subscription(node, JointState, '/joint_commands', self._on_command,
                                 LOOP_QOS)
        create_loop_subscription(node, StepInfo, '/zeus/step', self._on_step, LOOP_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        self.spinner = spin_in_background(node)

    def _on_state(self, msg):
        self.state_at[stamp_ns(msg.header)] = time.perf_counter()

    def _on_command(self, msg):
        self.command_at.setdefault(stamp_ns(msg.header), time.perf_counter())

    def _on_step(self, msg):
        self.steps.append((time.perf_counter(), msg))

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name.startswith('sim_node'):
                self.sim_diagnostics.append({kv.key: kv.value for kv in status.values})

    @staticmethod
    def spin_until(predicate, timeout):
        """Wait (the spinner thread receives) until `predicate()` or the timeout."""
        return wait_until(predicate, timeout)

    def call(self, client, request):
        client.wait_for_service(timeout_sec=30.0)
        return call_service(client, request, self.spin_until)


def episode_rate(observer: Observer, reset_client, seed: int) -> float:
    """Run one lockstep episode from a reset; its control steps per second."""
    reset_client.wait_for_service(timeout_sec=30.0)
    episode = reset_episode(reset_client, observer.spin_until, seed)
    observer.spin_until(lambda: any(m.episode == episode and m.truncated
                                    for _, m in observer.steps[-5:]), 300.0)
    times = [t for t, m in observer.steps if m.episode == episode]
    return (len(times) - 1) / (times[-1] - times[0])


def sim_real_time_factor(observer: Observer) -> float | None:
    """Return the achieved real-time factor in the sim's last diagnostics report (#38.6)."""
    if not observer.sim_diagnostics:
        return None
    value = observer.sim_diagnostics[-1].get('real_time_factor_achieved')
    return None if value is None else float(value)


def lockstep_figures(observer: Observer, reset_client, param_client, param_name: str,
                     swaps: int, episodes: int) -> dict:
    closed = observer.spin_until(
        lambda: any(any(m.applied_action) for _, m in observer.steps[-3:]), 60.0)
    if not closed:
        raise RuntimeError('the loop never closed')
    cpu_before = {name: cpu_seconds(pid) for name, pid in observer.graph_pids.items()}
    observer_before, steps_before = time.process_time(), len(observer.steps)
    rates = [episode_rate(observer, reset_client, seed) for seed in range(episodes)]
    observer.sim_diagnostics.clear()
    observer.spin_until(lambda: observer.sim_diagnostics, 5.0)  # the next 1 Hz report
    achieved = sim_real_time_factor(observer)
    steps = len(observer.steps) - steps_before
    cpu = {f'cpu_ms_per_step_{name}': 1e3 * (cpu_seconds(pid) - cpu_before[name]) / steps
           for name, pid in observer.graph_pids.items()}
    cpu['cpu_ms_per_step_observer'] = 1e3 * (time.process_time() - observer_before) / steps
    latencies = np.array([observer.command_at[s] - observer.state_at[s]
                          for s in observer.state_at if s in observer.command_at
                          and observer.command_at[s] > observer.state_at[s]]) * 1e3
    swap_ms = []
    for i in range(swaps):
        value = (0.4, 1.7)[i % 2]
        sent = time.perf_counter()
        observer.call(param_client, SetParameters.Request(
            parameters=[Parameter(param_name, value=value).to_parameter_msg()]))
        observer.spin_until(lambda v=value: observer.steps[-1][1].param_values[0] == v, 10.0)
        first = next(t for t, m in observer.steps if t >= sent and m.param_values[0] == value)
        swap_ms.append((first - sent) * 1e3)
    return {**cpu, 'lockstep_steps_per_s': float(np.median(rates)),
            'lockstep_real_time_factor_achieved': achieved,
            'lockstep_steps_per_s_min': min(rates), 'lockstep_steps_per_s_max': max(rates),
            'lockstep_episodes': episodes,
            'latency_ms_p50': float(np.percentile(latencies, 50)),
            'latency_ms_p99': float(np.percentile(latencies, 99)),
            'latency_ms_max': float(latencies.max()),
            'latency_samples': int(latencies.size),
            'swap_ms_median': float(np.median(swap_ms)), 'swap_ms_max': float(max(swap_ms))}


def realtime_figures(observer: Observer, param_client, seconds: float, period_s: float) -> dict:
    observer.spin_until(lambda: len(observer.command_at) > 50, 60.0)  # loop closed
    # Setting the mode (again) restarts the sim's tick schedule and its lateness
    # statistics: they then cover exactly the measured window.
    observer.call(param_client, SetParameters.Request(
        parameters=[Parameter('mode', value='realtime').to_parameter_msg()]))
    observer.state_at.clear()
    observer.command_at.clear()
    observer.spin_until(lambda: False, seconds)
    observer.sim_diagnostics.clear()
    observer.spin_until(lambda: observer.sim_diagnostics, 5.0)  # the next 1 Hz report
    states = sorted(observer.state_at.items())
    stamps = [s for s, _ in states]
    arrivals = np.array([t for _, t in states])
    intervals = np.diff(arrivals)
    jitter = np.abs(intervals - period_s) * 1e3
    # A command that reached the observer after the next state did not reach the
    # sim before its next tick either (same DDS path): that control period missed.
    late_commands = sum(1 for stamp, next_at in zip(stamps[:-1], arrivals[1:], strict=True)
                        if observer.command_at.get(stamp, np.inf) > next_at)
    sim = observer.sim_diagnostics[-1]
    return {'realtime_seconds': seconds, 'realtime_states': int(arrivals.size),
            'realtime_rate_hz': float((arrivals.size - 1) / (arrivals[-1] - arrivals[0])),
            'realtime_real_time_factor_achieved': sim_real_time_factor(observer),
            'sim_ticks': int(sim['ticks']),
            'sim_tick_late_ms_p50': float(sim['tick_late_ms_p50']),
            'sim_tick_late_ms_p99': float(sim['tick_late_ms_p99']),
            'sim_tick_late_ms_p999': float(sim['tick_late_ms_p999']),
            'sim_tick_late_ms_max': float(sim['tick_late_ms_max']),
            'sim_missed_ticks': int(sim['missed_ticks']),
            'sim_unanswered_ticks': int(sim['unanswered_ticks']),
            'jitter_ms_p50': float(np.percentile(jitter, 50)),
            'jitter_ms_p99': float(np.percentile(jitter, 99)),
            'jitter_ms_max': float(jitter.max()),
            'missed_deadlines': int(np.sum(intervals > 2 * period_s)),
            'late_commands': late_commands}


def realtime_swap_figures(observer: Observer, param_client, seconds: float,
                          param_name: str, values: tuple[float, float]) -> dict:
    """Tick lateness while the parameter is swapped 10 times a second for `seconds`."""
    set_mode = SetParameters.Request(
        parameters=[Parameter('mode', value='realtime').to_parameter_msg()])
    swaps_before = int(observer.sim_diagnostics[-1]['swaps'])  # counted since the sim started
    observer.call(param_client, set_mode)   # restarts the lateness statistics
    swaps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        value = values[swaps % 2]
        observer.call(param_client, SetParameters.Request(
            parameters=[Parameter(param_name, value=value).to_parameter_msg()]))
        swaps += 1
        observer.spin_until(lambda: False, start + 0.1 * swaps - time.perf_counter())
    observer.sim_diagnostics.clear()
    observer.spin_until(lambda: observer.sim_diagnostics, 5.0)  # the next 1 Hz report
    sim = observer.sim_diagnostics[-1]
    return {'swaps_sent': swaps, 'swaps_in_force': int(sim['swaps']) - swaps_before,
            'swaps_sim_ticks': int(sim['ticks']),
            'swaps_sim_tick_late_ms_p99': float(sim['tick_late_ms_p99']),
            'swaps_sim_tick_late_ms_p999': float(sim['tick_late_ms_p999']),
            'swaps_sim_tick_late_ms_max': float(sim['tick_late_ms_max']),
            'swaps_sim_missed_ticks': int(sim['missed_ticks'])}


def run_graph(weights: Path, mode: str, measure, thread_priority: int = 0,
              composed: bool = False, executor: str = 'single') -> dict:
    bringup = Bringup(node_commands(bringup_args([
        '--weights', str(weights), '--mode', mode, '--log-level', 'warn',
        '--thread-priority', str(thread_priority), '--executor', executor,
        *(['--composed'] if composed else [])])))
    rclpy.init()
    node = rclpy.create_node('zeus_bench')
    observer = Observer(node, {name: proc.pid for name, proc in bringup.procs.items()})
    gc.freeze()   # as the nodes do: a full collection would stall the observer
    try:
        return measure(observer, node)
    finally:
        rclpy.try_shutdown()          # ends the observer's spin_loop first
        observer.spinner.join(timeout=5.0)
        node.destroy_node()
        bringup.stop()


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', type=Path, required=True)
    parser.add_argument('--realtime-weights', type=Path,
                        help='checkpoint for the realtime run (default --weights); a '
                             'cheetah checkpoint gives the 100 Hz case')
    parser.add_argument('--inprocess-steps', type=int, default=1000,
                        help='steps per in-process sample (the median of 5 is reported)')
    parser.add_argument('--swaps', type=int, default=10)
    parser.add_argument('--episodes', type=int, default=5,
                        help='lockstep episodes (1000 steps each); the median rate is reported')
    parser.add_argument('--realtime-seconds', type=float, default=60.0)
    parser.add_argument('--realtime-swap-seconds', type=float, default=10.0,
                        help='after the realtime window, swap the parameter 10 times a '
                             'second for this long (figures prefixed swaps_; 0 = skip)')
    parser.add_argument('--realtime-priority', type=int, default=50,
                        help="the nodes' SCHED_FIFO priority in the realtime run (bringup "
                             "--thread-priority; 0 = normal scheduler). Lockstep runs under "
                             "the normal scheduler: FIFO measured slower there")
    parser.add_argument('--compare-normal-scheduler', action='store_true',
                        help='run the realtime part a second time under the normal '
                             'scheduler (figures prefixed normal_sched_)')
    parser.add_argument('--composed', action='store_true',
                        help='measure lockstep a second time with the three nodes composed '
                             'in one process (figures prefixed composed_)')
    parser.add_argument('--profiles', nargs='*', default=[], metavar='NAME=FILE',
                        type=profile_arg,
                        help='measure three-process lockstep again with the nodes on each '
                             'Fast DDS profile (FASTRTPS_DEFAULT_PROFILES_FILE; figures '
                             'prefixed NAME_). This process keeps the first profile it '
                             'loaded (Fast DDS reads it once per process)')
    parser.add_argument('--executors', nargs='*', default=[], choices=('events',),
                        help="measure three-process lockstep again with the nodes' "
                             'services and timers on each other executor (figures '
                             'prefixed with it; the default run is `single`)')
    parser.add_argument('--lockstep-only', action='store_true',
                        help='skip the realtime part')
    parser.add_argument('--json', type=Path, help='write the figures here')
    return parser.parse_args(argv)


def profile_arg(text: str) -> tuple[str, Path]:
    """`udp=config/x.xml` -> ('udp', Path); the file must exist."""
    name, _, path = text.partition('=')
    if not name or not Path(path).is_file():
        raise argparse.ArgumentTypeError(f'{text!r}: want NAME=FILE, an existing file')
    return name, Path(path).resolve()


class LockstepRun(NamedTuple):
    prefix: str                # of its figures
    composed: bool
    profile: Path | None       # the nodes' Fast DDS profile, None: as set
    executor: str = 'single'   # the nodes' `executor` parameter


def lockstep_runs(args) -> list[LockstepRun]:
    """Each lockstep run: the plain one, composed, per profile, per executor."""
    runs = [LockstepRun('', False, None)] + [LockstepRun('composed_', True, None)] * args.composed
    runs += [LockstepRun(f'{name}_', False, path) for name, path in args.profiles]
    return runs + [LockstepRun(f'{name}_executor_', False, None, name)
                   for name in args.executors]


def lockstep_part(args, meta: CheckpointMetadata, figures: dict) -> None:
    """Run each lockstep measurement; ratios to the in-process rate measured first."""
    def lockstep(observer, node):
        return lockstep_figures(observer, node.create_client(Reset, '/sim_node/reset'),
                                node.create_client(SetParameters, '/sim_node/set_parameters'),
                                meta.param_name, args.swaps, args.episodes)
    for prefix, composed, profile, executor in lockstep_runs(args):
        saved = os.environ.get(PROFILE_ENV)
        if profile is not None:   # the node processes inherit it
            os.environ[PROFILE_ENV] = str(profile)
        try:
            found = run_graph(args.weights, 'lockstep', lockstep, composed=composed,
                              executor=executor)
        finally:
            os.environ.pop(PROFILE_ENV, None)
            if saved is not None:
                os.environ[PROFILE_ENV] = saved
        found['lockstep_ratio_to_inprocess'] = (found['lockstep_steps_per_s']
                                                / figures['inprocess_steps_per_s'])
        figures.update({prefix + key: value for key, value in found.items()})
    # The machine's drift over the lockstep runs (the ratios use the first figure).
    figures['inprocess_steps_per_s_after'] = in_process_rate(args.weights,
                                                             args.inprocess_steps)[0]


def realtime_part(args, figures: dict) -> None:
    rt_weights = args.realtime_weights or args.weights
    rt_meta = load_metadata(rt_weights)
    period = float(rt_meta.control_timestep)
    figures['realtime_family'] = rt_meta.family
    figures['realtime_period_ms'] = period * 1e3

    train_values = rt_meta.param_normalisation.train_values
    swap_values = (min(train_values), max(train_values))

    def realtime(observer, node):
        client = node.create_client(SetParameters, '/sim_node/set_parameters')
        found = realtime_figures(observer, client, args.realtime_seconds, period)
        if args.realtime_swap_seconds > 0:
            found.update(realtime_swap_figures(observer, client, args.realtime_swap_seconds,
                                               rt_meta.param_name, swap_values))
        return found
    figures['realtime_thread_priority'] = args.realtime_priority
    figures.update(run_graph(rt_weights, 'realtime', realtime, args.realtime_priority))
    if args.compare_normal_scheduler:
        normal = run_graph(rt_weights, 'realtime', realtime, thread_priority=0)
        figures.update({f'normal_sched_{key}': value for key, value in normal.items()
                        if key != 'realtime_seconds'})


def main(argv=None) -> int:
    args = parse_args(argv)
    meta = load_metadata(args.weights)
    figures = {'weights': str(args.weights), 'family': meta.family,
               'machine': f'{os.cpu_count()} cores', 'load_avg_start': os.getloadavg()[0]}
    figures['inprocess_steps_per_s'], figures['inprocess_cpu_ms_per_step'] = in_process_rate(
        args.weights, args.inprocess_steps)
    lockstep_part(args, meta, figures)
    if not args.lockstep_only:
        realtime_part(args, figures)
    return report(figures, args.json)


def report(figures: dict, json_path: Path | None) -> int:
    """Print the figures as a table and write them as JSON to `json_path` (if given)."""
    figures['load_avg_end'] = os.getloadavg()[0]
    width = max(len(k) for k in figures)
    for key, value in figures.items():
        text = f'{value:.3f}' if isinstance(value, float) else str(value)
        print(f'{key:<{width}}  {text}')
    if json_path:
        json_path.write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
