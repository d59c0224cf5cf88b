"""The three nodes composed in one process: the same graph, the same episode to the bit."""

import ast
import signal

from conftest import installed_exe, REPO, spin_until
import pytest
import rclpy
from rclpy.context import Context
from sim_driver import (assert_same_rewards, collect, episode_rewards, FAMILY,
                        LockstepDriver, WALKER_WEIGHTS)
from zeus_msgs.msg import StepInfo
from zeus_ros.ros_tools.bringup import node_commands, parse_args as bringup_args
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode

NODE_NAMES = {'sim_node', 'context_node', 'policy_node'}


def composed_argv(weights, **sim_params):
    # The same generous timeouts as the three-process test: a loaded machine
    # must not make the sim step on a zero action (it would break the equality).
    params = {'sim_node': {'family': FAMILY, 'command_timeout': 5.0, **sim_params},
              'context_node': {'weights': weights},
              'policy_node': {'weights': weights, 'context_timeout': 5.0}}
    argv = [installed_exe('composed'), '--ros-args']
    for node, values in params.items():
        for key, value in values.items():
            argv += ['-p', f'{node}:{key}:={value}']
    return argv


@pytest.fixture
def composed(spawn, ros_node):
    """Start the composed process; return it and a driver that has seen its sim."""
    def start(weights=WALKER_WEIGHTS, **sim_params):
        proc = spawn(composed_argv(weights, **sim_params), 'composed')
        driver = LockstepDriver(ros_node)
        driver.wait_ready()
        return proc, driver
    return start


def test_composed_episode_equals_in_process_eval_and_shows_the_three_nodes(composed,
                                                                           ros_node):
    seed, friction = 5, 1.25
    expected = run_episode(InferenceModel.load(WALKER_WEIGHTS), FAMILY, friction, seed)
    steps = collect(ros_node, StepInfo, '/zeus/step')
    proc, driver = composed()
    rewards = episode_rewards(ros_node, driver, steps, seed, friction)
    assert_same_rewards(rewards, expected.rewards)
    # Composition is a deployment choice: the graph is the three-process one.
    assert NODE_NAMES <= set(ros_node.get_node_names())
    assert proc.alive()


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_all_three_cleanly(composed, ros_node, signum):
    proc, _ = composed()
    assert spin_until(ros_node, lambda: NODE_NAMES <= set(ros_node.get_node_names()), 30.0)
    proc.proc.send_signal(signum)
    assert proc.proc.wait(20) == 0, proc.output()
    assert 'Traceback' not in proc.output()


def test_a_node_that_cannot_start_ends_the_process_naming_it(spawn):
    proc = spawn(composed_argv('/nonexistent/ckpt'), 'composed')
    assert proc.proc.wait(60) == 1
    output = proc.output()
    assert 'ContextNode: ' in output and '/nonexistent/ckpt' in output, output
    assert 'Traceback' not in output


def test_bringup_composed_is_one_process_with_each_parameter_named_by_its_node():
    commands = node_commands(bringup_args(['--weights', str(WALKER_WEIGHTS), '--composed',
                                           '--mode', 'realtime', '--thread-priority', '5']))
    assert list(commands) == ['composed']
    argv = commands['composed']
    assert argv[1:3] == ['-m', 'zeus_ros.ros_tools.composed']
    assert 'sim_node:mode:=realtime' in argv and 'policy_node:thread_priority:=5' in argv
    assert f'context_node:weights:={WALKER_WEIGHTS.resolve()}' in argv
    assert not any(arg.startswith(('mode:=', 'weights:=')) for arg in argv)
    assert 'context_node:backend:=torch' in argv and 'policy_node:backend:=torch' in argv
    onnx = node_commands(bringup_args(['--weights', str(WALKER_WEIGHTS), '--backend', 'onnx']))
    for node in ('context_node', 'policy_node'):
        assert 'backend:=onnx' in onnx[node], onnx[node]


def test_bringup_takes_a_bare_value_or_named_values_and_refuses_the_rest():
    from zeus_ros.ros_tools.bringup import initial_values
    assert initial_values('walker-walk-v0', ['1.2']) == {'friction': 1.2}
    assert initial_values('walker-walk-v0', ['friction=0.9']) == {'friction': 0.9}
    assert initial_values('sawyer-peg-v0', ['goal_x=0.6', 'goal_y=0.07']) == {
        'goal_x': 0.6, 'goal_y': 0.07}
    for family, given, reason in (('sawyer-peg-v0', ['0.6'], 'give NAME=VALUE'),
                                  ('sawyer-peg-v0', ['goal_z=1'], 'goal_x, goal_y'),
                                  ('walker-walk-v0', ['friction=slippery'], 'not a number')):
        with pytest.raises(SystemExit, match=reason):
            initial_values(family, given)


def _composed_launch_arguments(*values):
    """Run the launch file's composed_ros_arguments (it needs no `launch` import)."""
    tree = ast.parse((REPO / 'launch' / 'zeus.launch.py').read_text())
    func = next(n for n in tree.body if isinstance(n, ast.FunctionDef)
                and n.name == 'composed_ros_arguments')
    namespace = {}
    # The file's own future import: its annotations name launch types, never evaluated.
    future = ast.parse('from __future__ import annotations').body
    exec(compile(ast.Module(body=[*future, func], type_ignores=[]), 'zeus.launch.py', 'exec'),
         namespace)
    # launch joins a list of substitutions into one argument; here they are strings.
    return [''.join(a) if isinstance(a, list) else a
            for a in namespace['composed_ros_arguments'](*values)]


def test_launch_composed_gives_each_node_its_parameters_over_the_config_file():
    arguments = _composed_launch_arguments(str(REPO / 'config' / 'zeus.yaml'),
                                           'walker-walk-v1', '/w', 'realtime', '7', 'onnx')
    context = Context()
    rclpy.init(args=['composed', '--ros-args', *arguments], context=context)
    try:
        overrides = {}
        for name in sorted(NODE_NAMES):
            node = rclpy.create_node(name, context=context)
            overrides[name] = {k: p.value for k, p in node._parameter_overrides.items()}
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    assert overrides['sim_node']['family'] == 'walker-walk-v1'
    assert overrides['sim_node']['mode'] == 'realtime'
    assert overrides['sim_node']['command_timeout'] == 0.5   # from the config file
    assert 'weights' not in overrides['sim_node']
    assert overrides['context_node']['weights'] == overrides['policy_node']['weights'] == '/w'
    assert overrides['context_node']['backend'] == overrides['policy_node']['backend'] == 'onnx'
    assert 'backend' not in overrides['sim_node']
    assert {o['thread_priority'] for o in overrides.values()} == {7}
