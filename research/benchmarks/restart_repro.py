"""Reproduce issue 39.2: kill -9 and restart a node N times against the rest of a running loop.

    python research/benchmarks/restart_repro.py --restarts 20 [--node policy_node] \
        [--profile FILE] [--json out.json]

Starts the lockstep loop as the soak does (research/benchmarks/soak.py's Supervisor and
Observer), then N times: SIGKILL the --node (default sim_node), keep it down --down-seconds,
restart it, and measure the time from its start-up line (its first log line)
to the first controlled step (a StepInfo with a non-zero applied action) and
whether a parameter request is answered. A restart with no control within
--stuck-after seconds is the stuck case: the stacks of every process (py-spy
and gdb, as the tests dump them) and the /dev/shm Fast DDS files are written
to the log directory with --dump, and the sim is killed again.

--profile names the Fast DDS profile of the nodes and the observer (default:
the nodes' own, config/fastdds_discovery.xml; research/benchmarks/
fastdds_shared_memory.xml is the shared-memory one it replaced). An earlier
--transports option set FASTDDS_BUILTIN_TRANSPORTS, which rmw_fastrtps
ignores under ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: it changed nothing.
Exit code 0 when every restart got control back, 1 otherwise.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
import json
import os
from pathlib import Path
import statistics
import sys
import tempfile
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[2] / 'test'))

from conftest import _stack_dump  # noqa: E402
import rclpy  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sim_node.families import get_family  # noqa: E402
from soak import (check_domain_free, NODE_NAMES, Observer, REPO,  # noqa: E402
                  startup_line_monotonic, Supervisor)
from zeus_ros.ros_tools.bringup import node_commands, parse_args as bringup_args  # noqa: E402
from zeus_ros.deploy.checkpoint import load_metadata  # noqa: E402
from zeus_ros.ros.discovery import PROFILE_ENV, use_discovery_profile  # noqa: E402
from zeus_ros.ros.loop_spin import wait_until  # noqa: E402
from zeus_ros.ros.util import call_service  # noqa: E402


@dataclass
class Trial:
    index: int
    startup_to_control_s: float | None   # None: stuck (no control within --stuck-after)
    spawn_to_startup_s: float | None
    swap_answered: bool
    shm_files_before: int                # fastrtps_* in /dev/shm, as the sim restarts


def shm_files() -> list[str]:
    return sorted(p.name for p in Path('/dev/shm').glob('fastrtps_*'))


def swap_answered(node, param: str, value: float) -> bool:
    client = node.create_client(SetParameters, '/sim_node/set_parameters')
    try:
        request = SetParameters.Request(parameters=[Parameter(param, value=value)
                                                    .to_parameter_msg()])
        call_service(client, request, wait_until, timeout=5.0, attempt_s=1.0)
        return True
    except TimeoutError:
        return False
    finally:
        node.destroy_client(client)


def dump_stuck(sup: Supervisor, log_dir: Path, index: int) -> None:
    text = ''.join(_stack_dump(p.popen.pid, f'{p.node}#{p.incarnation}')
                   for p in sup.current.values() if p.popen.poll() is None)
    text += '--- this observer ---\n' + _stack_dump(os.getpid(), 'restart_repro')
    text += '--- /dev/shm ---\n' + '\n'.join(shm_files()) + '\n'
    (log_dir / f'stuck_{index}.txt').write_text(text)


def trial(index: int, sup: Supervisor, observer: Observer, node, args, spec) -> Trial:
    sup.kill9(args.node)
    time.sleep(args.down_seconds)
    before = len(shm_files())
    new = sup.spawn(args.node)
    watch = observer.watch(new.spawned_at)
    wait_until(lambda: watch.control_at is not None, args.stuck_after, poll_s=0.05)
    startup = startup_line_monotonic(new.log_path)
    back = None if watch.control_at is None or startup is None else watch.control_at - startup
    lo, hi = spec.live_range
    answered = swap_answered(node, spec.param_name, lo + (hi - lo) * (index % 7) / 7.0)
    if back is None and args.dump:
        dump_stuck(sup, args.log_dir, index)
    return Trial(index, None if back is None else round(back, 3),
                 None if startup is None else round(startup - new.spawned_at, 3),
                 answered, before)


def summary(trials: list[Trial], goal_s: float) -> dict:
    times = sorted(t.startup_to_control_s for t in trials if t.startup_to_control_s is not None)
    return {'restarts': len(trials), 'stuck': sum(t.startup_to_control_s is None for t in trials),
            'unanswered_swaps': sum(not t.swap_answered for t in trials),
            'within_goal': sum(t <= goal_s for t in times),
            'median_s': statistics.median(times) if times else None,
            'max_s': max(times) if times else None,
            'sorted_s': times}


def parse(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', type=Path,
                        default=REPO / 'weights' / 'walker-walk-slippery-zeus')
    parser.add_argument('--restarts', type=int, default=20)
    parser.add_argument('--node', choices=NODE_NAMES, default='sim_node',
                        help='the node killed and restarted each time')
    parser.add_argument('--down-seconds', type=float, default=1.0)
    parser.add_argument('--stuck-after', type=float, default=60.0)
    parser.add_argument('--goal', type=float, default=2.0, help='seconds after the start-up line')
    parser.add_argument('--profile', type=Path,
                        help="Fast DDS profile for the nodes and the observer (default: the "
                             "nodes' own)")
    parser.add_argument('--dump', action='store_true',
                        help='stacks of every process when stuck (py-spy and gdb: slow)')
    parser.add_argument('--log-dir', type=Path)
    parser.add_argument('--json', type=Path)
    args = parser.parse_args(argv)
    args.log_dir = args.log_dir or Path(tempfile.mkdtemp(prefix='zeus_restart_'))
    args.log_dir.mkdir(parents=True, exist_ok=True)
    return args


def main(argv=None) -> int:
    args = parse(argv)
    if args.profile:   # before use_discovery_profile, which then leaves it alone
        os.environ[PROFILE_ENV] = str(args.profile.resolve())
    spec = get_family(load_metadata(args.weights).family)
    commands = node_commands(bringup_args(['--weights', str(args.weights),
                                           '--mode', 'lockstep']))
    use_discovery_profile()   # the observer announces itself as often as the nodes do
    rclpy.init()
    node = rclpy.create_node('zeus_restart_repro')
    observer = Observer(node, 1.0, spec.name)
    sup = Supervisor(commands, args.log_dir)
    trials = []
    try:
        check_domain_free(node)
        for name in NODE_NAMES:
            sup.spawn(name)
        first = observer.watch(time.monotonic())
        if not wait_until(lambda: first.control_at is not None, 120.0, poll_s=0.1):
            print('restart_repro: the loop never closed', file=sys.stderr)
            return 2
        for index in range(args.restarts):
            trials.append(trial(index, sup, observer, node, args, spec))
            print(json.dumps(asdict(trials[-1])), flush=True)
    finally:
        sup.stop()
        rclpy.try_shutdown()
        observer.spinner.join(timeout=5.0)
    result = {'node': args.node,
              'profile': os.environ.get(PROFILE_ENV),
              'load_avg': os.getloadavg()[0], 'log_dir': str(args.log_dir),
              'summary': summary(trials, args.goal), 'trials': [asdict(t) for t in trials]}
    print(json.dumps(result['summary']))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + '\n')
    return 0 if result['summary']['stuck'] == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
