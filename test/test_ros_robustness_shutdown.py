"""Every node stops on SIGINT or SIGTERM, once or twice, at any moment: exit 0, no traceback.

Real processes, real signals (issue #16.1): `ros2 launch` without a terminal
forwards a SIGINT on top of the process group's, so two SIGINTs about 50 ms
apart are what a node meets at every Ctrl-C there.
"""

import itertools
from pathlib import Path
import signal
import time

from conftest import helper_script, installed_exe, REPO
import pytest

WEIGHTS = REPO / 'weights' / 'walker-walk-v0-zeus'
NODES = {
    'sim_node': [],
    'context_node': ['-p', f'weights:={WEIGHTS}'],
    'policy_node': ['-p', f'weights:={WEIGHTS}'],
}
# What each node logs last before it spins.
STARTED = {'sim_node': 'control period', 'context_node': 'weights from',
           'policy_node': 'weights from'}
PATTERNS = {'SIGINT twice': (signal.SIGINT, signal.SIGINT), 'SIGTERM': (signal.SIGTERM,),
            'SIGTERM then SIGINT': (signal.SIGTERM, signal.SIGINT)}
GAP_S = 0.05
_STARTED_COUNT = itertools.count()


def start(spawn, name):
    # Each under a name of its own: a second node of a name on the graph is refused.
    unique = f'{name}_{next(_STARTED_COUNT)}'
    return spawn([installed_exe(name), '--ros-args', '-r', f'__node:={unique}', *NODES[name]],
                 name)


def send(proc, signals):
    for index, signum in enumerate(signals):
        if index:
            time.sleep(GAP_S)
        proc.proc.send_signal(signum)


def wait_output(proc, text, timeout):
    deadline = time.monotonic() + timeout
    while text not in proc.output():
        assert proc.alive(), f'{proc.argv[0]} ended early:\n{proc.output()}'
        assert time.monotonic() < deadline, f'no {text!r} within {timeout} s:\n{proc.output()}'
        time.sleep(0.05)


def assert_quiet_stop(proc, what):
    code = proc.proc.wait(30)
    output = proc.output()
    assert code == 0, f'{what}: exit code {code}\n{output}'
    assert 'Traceback' not in output, f'{what}:\n{output}'


@pytest.mark.parametrize('name', list(NODES))
def test_a_running_node_stops_quietly_on_every_signal_pattern(spawn, name):
    # One process per pattern, all at once: each is signalled once it spins.
    procs = {pattern: start(spawn, name) for pattern in PATTERNS}
    for proc in procs.values():
        wait_output(proc, STARTED[name], 120.0)
    time.sleep(0.5)
    for pattern, proc in procs.items():
        send(proc, PATTERNS[pattern])
    for pattern, proc in procs.items():
        assert_quiet_stop(proc, f'{name}, {pattern} while running')


def wait_loaded(proc, library, timeout=60.0):
    """Wait until the process has mapped a shared library (it is importing past it)."""
    maps = Path(f'/proc/{proc.proc.pid}/maps')
    deadline = time.monotonic() + timeout
    while library not in maps.read_text():
        assert time.monotonic() < deadline, f'{library} never loaded:\n{proc.output()}'
        time.sleep(0.01)


@pytest.mark.parametrize('pattern', list(PATTERNS))
def test_the_sim_stops_quietly_on_a_signal_during_start_up(spawn, pattern):
    # MuJoCo loads halfway through sim_node's imports (before it, only the
    # interpreter's own start-up, which no Python code can guard); at 1.5 s
    # and 2.5 s (on this machine) it is building the node or about to spin.
    importing = start(spawn, 'sim_node')
    later = {delay: start(spawn, 'sim_node') for delay in (1.5, 2.5)}
    began = time.monotonic()
    wait_loaded(importing, 'libmujoco')
    send(importing, PATTERNS[pattern])
    for delay, proc in sorted(later.items()):
        time.sleep(max(0.0, began + delay - time.monotonic()))
        send(proc, PATTERNS[pattern])
    assert_quiet_stop(importing, f'sim_node, {pattern} while importing')
    assert STARTED['sim_node'] not in importing.output(), 'the signal came after start-up'
    for delay, proc in later.items():
        assert_quiet_stop(proc, f'sim_node, {pattern} {delay} s after start')


@pytest.mark.parametrize('name', ['context_node', 'policy_node'])
def test_a_controller_stops_quietly_on_a_signal_while_torch_imports(spawn, name):
    """Torch loads for seconds before a controller's main runs: a signal then ends it with 0."""
    importing = start(spawn, name)
    wait_loaded(importing, 'libtorch')
    send(importing, PATTERNS['SIGINT twice'])
    assert_quiet_stop(importing, f'{name}, SIGINT twice while torch imports')
    assert STARTED[name] not in importing.output(), 'the signal came after start-up'


def test_a_stop_that_start_up_code_turns_into_an_error_still_exits_0(spawn):
    """A signal inside a native loader (safetensors) comes back as its own error: still a stop."""
    proc = spawn(helper_script('stop_swallowing_node.py'), 'swallowing')
    assert_quiet_stop(proc, 'SIGTERM swallowed by start-up code')
    assert 'could not determine' not in proc.output(), proc.output()
