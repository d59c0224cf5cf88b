"""bringup: start sim_node, context_node and policy_node without ROS launch.

Each node runs in its own process, or with --composed all three in one
(`zeus_ros.ros_tools.composed`: the same node classes and topics, on one loop thread);
Ctrl-C (or SIGTERM) stops all of them cleanly, and if any node exits the
others are stopped and bringup exits with that node's code. The family
defaults to the one the weights were trained for.

    ros2 run zeus_ros bringup --weights weights/walker-walk-v0-zeus --mode lockstep [--composed]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from zeus_ros.ros.parent_watch import end_with_launcher

NODES = (('sim_node', 'zeus_ros.nodes.sim_node'), ('context_node', 'zeus_ros.nodes.context_node'),
         ('policy_node', 'zeus_ros.nodes.policy_node'))
# The process that runs all three with --composed, and its name in node_commands.
COMPOSED = ('composed', 'zeus_ros.ros_tools.composed')


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', required=True, help='checkpoint directory')
    parser.add_argument('--family', help="environment family (default: the weights')")
    parser.add_argument('--family-file', help='the family file (YAML) to simulate; needed '
                                              'for weights trained on one')
    parser.add_argument('--mode', choices=('lockstep', 'realtime'), default='lockstep')
    parser.add_argument('--seed', type=int, default=0, help='sim seed')
    parser.add_argument('--param', action='append', default=[], metavar='[NAME=]VALUE',
                        help="initial value of the family's physical parameter; NAME=VALUE "
                             'for a family with several (repeat: --param goal_x=0.6 '
                             '--param goal_y=0.07)')
    parser.add_argument('--real-time-factor', type=float, default=1.0)
    parser.add_argument('--command-timeout', type=float, default=0.5)
    parser.add_argument('--context-timeout', type=float, default=0.5)
    parser.add_argument('--thread-priority', type=int, default=0,
                        help="SCHED_FIFO priority (1-99) of every node's loop thread; "
                             '0 keeps the normal scheduler')
    parser.add_argument('--backend', choices=('torch', 'onnx'), default='torch',
                        help="what runs the controllers' networks (onnx: ONNX Runtime)")
    parser.add_argument('--composed', action='store_true',
                        help='all three nodes in one process (same topics, on DDS)')
    parser.add_argument('--executor', choices=('single', 'events'), default='single',
                        help="every node's executor for its services and timers "
                             "(the `executor` parameter; 'events': rclpy's EventsExecutor)")
    parser.add_argument('--log-level', default='info')
    return parser.parse_args(argv)


def node_parameters(args: argparse.Namespace) -> dict[str, dict]:
    """Each node's parameters, by node name."""
    # Checked here, so that bad weights give one clear line, not three node failures.
    from zeus_ros.deploy.checkpoint import load_metadata
    weights = str(Path(args.weights).resolve())
    meta = load_metadata(weights)
    family = args.family or meta.family
    sim_params = {'family': family, 'mode': args.mode, 'seed': args.seed,
                  'real_time_factor': args.real_time_factor,
                  'command_timeout': args.command_timeout}
    if args.family_file is not None:
        sim_params['family_file'] = str(Path(args.family_file).resolve())
    elif meta.family_file is not None:
        # The sim builds the model from a file; the checkpoint holds its text, not a path.
        raise SystemExit(f'the weights were trained on a family file ({meta.family_file.path}):'
                         ' give it with --family-file')
    sim_params.update(initial_values(family, args.param))
    controller = {'weights': weights, 'backend': args.backend}
    params = {'sim_node': sim_params, 'context_node': controller,
              'policy_node': {**controller, 'context_timeout': args.context_timeout}}
    return {name: {**values, 'thread_priority': args.thread_priority,
                   'executor': args.executor} for name, values in params.items()}


def initial_values(family: str, given: list[str]) -> dict[str, float]:
    """`--param` arguments as sim_node parameters: a bare number is the only parameter's."""
    from sim_node.families import get_sim_family
    names = get_sim_family(family).param_names
    values = {}
    for item in given:
        name, _, text = item.rpartition('=')
        name = name or (names[0] if len(names) == 1 else '')
        if name not in names:
            raise SystemExit(f'--param {item}: {family} has ' + ', '.join(names)
                             + ('' if name else '; give NAME=VALUE'))
        try:
            values[name] = float(text)
        except ValueError:
            raise SystemExit(f'--param {item}: {text!r} is not a number') from None
    return values


def _param_args(values: dict, prefix: str = '') -> list[str]:
    return [arg for key, value in values.items() for arg in ('-p', f'{prefix}{key}:={value}')]


def node_commands(args: argparse.Namespace) -> dict[str, list[str]]:
    """Build each process's command line (python -m, so no install layout is assumed).

    One per node, or with `args.composed` one named 'composed' that runs all
    three, each parameter given to its node by name (-p sim_node:mode:=lockstep).
    """
    params = node_parameters(args)

    def command(module: str, param_args: list[str]) -> list[str]:
        return [sys.executable, '-m', module, '--ros-args', '--log-level', args.log_level,
                *param_args]
    if args.composed:
        name, module = COMPOSED
        return {name: command(module, [arg for node, values in params.items()
                                       for arg in _param_args(values, f'{node}:')])}
    return {name: command(module, _param_args(params[name])) for name, module in NODES}


class Bringup:
    """The three node processes and their shared fate."""

    def __init__(self, commands: dict[str, list[str]]):
        env = dict(os.environ)
        env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        self.procs = {name: subprocess.Popen(cmd, env=env) for name, cmd in commands.items()}

    def failed(self) -> tuple[str, int] | None:
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                return name, proc.returncode
        return None

    def stop(self, timeout: float = 10.0) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        for proc in self.procs.values():
            try:
                proc.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from zeus_ros.deploy.checkpoint import CheckpointError
    try:
        commands = node_commands(args)
    except CheckpointError as error:
        print(f'bringup: {error}', file=sys.stderr)
        return 1
    stop_requested = []
    signal.signal(signal.SIGTERM, lambda *_: stop_requested.append(True))
    end_with_launcher()   # `ros2 run` killed: a SIGTERM here, which stops the nodes
    bringup = Bringup(commands)
    try:
        while not stop_requested:
            failure = bringup.failed()
            if failure is not None:
                name, code = failure
                print(f'bringup: {name} exited with code {code}; stopping the others',
                      file=sys.stderr)
                return code or 1
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        bringup.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
