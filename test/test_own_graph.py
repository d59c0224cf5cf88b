"""A loop of its own (#38.1, #39.4), a clean first contact (#38.5), the achieved RTF (#38.6)."""

import json
import logging
import math
import os
import subprocess
import sys

from conftest import helper_script, REPO, spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import pytest
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from sim_driver import (collect, FAMILY, LockstepDriver, start_node, wait_loop_running,
                        WALKER_ACTUATORS, WALKER_WEIGHTS)
from zeus_ros.ros.protocol import AchievedRealTimeFactor, command_problem
from zeus_msgs.msg import StepInfo
from zeus_ros.deploy.inference import InferenceModel
from zeus_ros.learning_tools.evaluate import run_episode
from zeus_ros.ros.graph import (claim_free_domain, foreign_publishers, LOCK_PATTERN,
                                UNKNOWN_NODE)
from zeus_ros.ros.util import FirstContact, ThrottledWarnings


# -- the ROS-free pieces ----------------------------------------------------------------
def test_claim_free_domain_skips_ids_held_elsewhere(tmp_path):
    pattern = str(tmp_path / 'domain_{}.lock')
    first = claim_free_domain(range(3), pattern, seed=0)
    second = claim_free_domain(range(3), pattern, seed=0)
    third = claim_free_domain(range(3), pattern, seed=0)
    assert sorted(c.domain_id for c in (first, second, third)) == [0, 1, 2]
    with pytest.raises(RuntimeError, match='no free ROS_DOMAIN_ID in'):
        claim_free_domain(range(3), pattern, seed=0)
    # Held by another process: never handed out.
    second.release()
    holder = subprocess.Popen([sys.executable, '-c', (
        'import fcntl, sys, time; h = open(sys.argv[1], "w"); fcntl.flock(h, fcntl.LOCK_EX); '
        'print("held", flush=True); time.sleep(30)'), pattern.format(second.domain_id)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == 'held\n'
        with pytest.raises(RuntimeError):
            claim_free_domain(range(3), pattern, seed=0)
    finally:
        holder.kill()
        holder.wait()
    assert claim_free_domain(range(3), pattern).domain_id == second.domain_id



def test_this_pytest_process_holds_the_domain_its_nodes_inherit(spawn):
    """Each pytest process (each xdist worker of `make test`) talks on a domain it holds.

    conftest claims one at import, in every worker: another worker, or another
    checkout's run, cannot claim it while this one lives, and a node a test
    starts inherits it. Were the claim made once in the controller, the workers
    would share one domain and hear each other's loops.
    """
    domain = os.environ['ROS_DOMAIN_ID']
    # The kernel's lock table names the process that took the lock: this one,
    # not the xdist controller (whose claim the workers' environment starts with).
    lock = os.stat(LOCK_PATTERN.format(domain))
    where = f'{os.major(lock.st_dev):02x}:{os.minor(lock.st_dev):02x}:{lock.st_ino}'
    with open('/proc/locks') as table:
        rows = [line.split() for line in table]
    holders = [int(row[4]) for row in rows if row[1] == 'FLOCK' and row[5] == where]
    assert holders == [os.getpid()], (domain, holders, os.getpid())
    child = spawn([sys.executable, '-c', 'import os; print(os.environ["ROS_DOMAIN_ID"])'])
    assert child.proc.wait(30) == 0 and child.output().split() == [domain]


def test_foreign_publishers_names_each_topic_not_the_expected_node_alone():
    expected = {'/joint_states': '/sim_node', '/joint_commands': '/zeus_demo'}
    assert foreign_publishers({'/joint_states': ['/sim_node'], '/joint_commands': []},
                              expected) == []   # not published yet: the start-up waits
    assert foreign_publishers({'/joint_states': ['/sim_node', '/sim_node'],
                               '/joint_commands': ['/zeus_demo', '/test_x']}, expected) == [
        '/joint_states has 2 publishers (/sim_node, /sim_node), expected /sim_node alone',
        '/joint_commands has 2 publishers (/test_x, /zeus_demo), expected /zeus_demo alone']
    assert foreign_publishers({'/joint_states': ['/other']}, expected) == [
        '/joint_states has 1 publisher (/other), expected /sim_node alone']
    # A writer seen before its node's name: alone it may be the expected one...
    assert foreign_publishers({'/joint_states': [UNKNOWN_NODE]}, expected) == []
    # ...beside it, it is one too many.
    assert len(foreign_publishers({'/joint_states': [UNKNOWN_NODE, '/sim_node']},
                                  expected)) == 1


def test_achieved_real_time_factor_over_a_sliding_window():
    rtf = AchievedRealTimeFactor(window_s=5.0)
    assert math.isnan(rtf.update(0.0, 0.0))
    assert rtf.update(1.0, 0.5) == 0.5
    for second in range(2, 11):           # half speed until 10 s...
        rtf.update(float(second), 0.5 * second)
    for second in range(11, 17):          # ...then twice real time
        value = rtf.update(float(second), 5.0 + 2.0 * (second - 10))
    assert value == 2.0                   # the window holds only the new speed
    for second in range(17, 23):          # standing still (lockstep waiting)
        value = rtf.update(float(second), 17.0)
    assert value == 0.0


def test_command_problem_is_two_publishers_or_many_stale_commands():
    assert command_problem(['/policy_node'], 10, 10.0) is None
    assert command_problem([], 0, 10.0) is None
    two = command_problem(['/policy_node', '/policy_node'], 0, 10.0)
    assert two == ('2 publishers on the command topic (/policy_node, /policy_node): '
                   'more than one controller')
    stale = command_problem(['/policy_node'], 11, 10.0)
    assert stale.startswith('11 stale commands in the last 10 s')


def test_first_contact_notes_the_wait_once_then_warns(caplog):
    logger = logging.getLogger('zeus_first_contact_test')
    caplog.set_level(logging.INFO, logger=logger.name)
    contact = FirstContact(logger, ThrottledWarnings(logger, period_s=0.0), 'waiting')
    contact.timed_out('timeout', 'late')
    contact.timed_out('timeout', 'late')
    contact.seen()
    contact.timed_out('timeout', 'late')
    assert [(r.levelname, r.message) for r in caplog.records] == [
        ('INFO', 'waiting'), ('WARNING', 'late')]


def test_the_demo_domain_is_auto_or_a_valid_id(monkeypatch):
    from zeus_ros.ros_tools.demo import DemoFailure, own_domain
    monkeypatch.setenv('ROS_DOMAIN_ID', os.environ['ROS_DOMAIN_ID'])   # restored after
    for bad in ('abc', '-1', '233', ''):
        with pytest.raises(DemoFailure, match='--domain-id must be auto or a ROS_DOMAIN_ID'):
            own_domain(bad)
    assert own_domain('7') is None and os.environ['ROS_DOMAIN_ID'] == '7'


# -- through real processes -------------------------------------------------------------
def sim_statuses(ros_node):
    statuses = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: statuses.extend(
        s for s in m.status if s.name.startswith('sim_node:')), 10)
    return statuses


def values_of(status) -> dict:
    return {kv.key: kv.value for kv in status.values}


def test_a_clean_lockstep_start_logs_no_warning(spawn, ros_node):
    # The defaults (command and context timeouts of 0.5 s) and the nodes started
    # at once, as bringup does: the sim's first states go out before anyone listens.
    steps = collect(ros_node, StepInfo, '/zeus/step')
    procs = [start_node(spawn, 'sim_node', {'family': FAMILY})] + [
        start_node(spawn, name, {'weights': WALKER_WEIGHTS})
        for name in ('context_node', 'policy_node')]
    wait_loop_running(ros_node, steps, timeout=120.0)
    seen = len(steps)
    assert spin_until(ros_node, lambda: len(steps) > seen + 100, 60.0)
    for proc in procs:
        assert proc.alive()
        assert 'WARN' not in proc.output(), proc.output()


@pytest.mark.alone   # bounds the achieved real-time factor
def test_the_sim_reports_its_achieved_real_time_factor_in_both_modes(spawn, ros_node):
    statuses = sim_statuses(ros_node)
    start_node(spawn, 'sim_node', {'family': FAMILY, 'mode': 'realtime',
                                   'real_time_factor': 1.0, 'command_timeout': 0.05})
    assert spin_until(ros_node, lambda: len(statuses) >= 4, 30.0)
    values = values_of(statuses[-1])
    achieved = float(values['real_time_factor_achieved'])
    # Never above the schedule; below it only as far as a loaded machine makes
    # ticks late (a tick a period late restarts the schedule: time is lost).
    assert 0.3 <= achieved <= 1.1, values
    # lockstep with nobody answering: a step per command timeout, 0.025 s / 0.1 s.
    driver = LockstepDriver(ros_node)
    driver.wait_ready()
    assert driver.set_param('command_timeout', 0.1).successful
    assert driver.set_param('mode', 'lockstep').successful
    switched = len(statuses)
    assert spin_until(ros_node, lambda: len(statuses) >= switched + 7, 30.0)
    values = values_of(statuses[-1])
    assert values['mode'] == 'lockstep'
    assert 0.05 <= float(values['real_time_factor_achieved']) <= 0.26, values


def test_a_second_controller_is_a_warning_in_diagnostics_and_the_log(spawn, ros_node):
    statuses = sim_statuses(ros_node)
    sim = start_node(spawn, 'sim_node', {'family': FAMILY, 'command_timeout': 5.0})
    for name in ('first_controller', 'second_controller'):
        spawn(helper_script('answer_node.py') + [name, *WALKER_ACTUATORS], name)

    def warned():
        last = statuses[-1] if statuses else None
        return (last is not None and last.level == DiagnosticStatus.WARN
                and 'more than one controller' in last.message
                and 'stale commands' in last.message)
    assert spin_until(ros_node, warned, 60.0), [s.message for s in statuses[-3:]]
    message = statuses[-1].message
    assert '/first_controller' in message and '/second_controller' in message, message
    assert spin_until(ros_node, lambda: 'more than one controller' in sim.output(), 10.0)
    assert '[WARN]' in sim.output()


# -- the demo on a graph of its own (#38.1) ----------------------------------------------
SHORT = dict(schedule='0:1.0,30:0.4', steps=60)


def demo_command(out, *extra):
    return [sys.executable, '-m', 'zeus_ros.ros_tools.demo', '--weights', WALKER_WEIGHTS,
            '--composed',
            '--schedule', SHORT['schedule'], '--steps', SHORT['steps'], '--video-every', 0,
            '--out', out, *extra]


@pytest.mark.ros   # two demos, each its three nodes (no fixture of ours says so)
@pytest.mark.timeout(600)   # its own wait for the demos is 400 s
def test_two_demos_at_once_both_give_the_deterministic_episode(tmp_path):
    expected = run_episode(InferenceModel.load(WALKER_WEIGHTS), FAMILY, 1.0, 0,
                           swap_schedule={29: 0.4}).rewards[:SHORT['steps']]
    outs = [tmp_path / f'demo_{i}' for i in range(2)]
    procs = [subprocess.Popen([str(a) for a in demo_command(out)], cwd=REPO, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for out in outs]
    results = [(proc, *proc.communicate(timeout=400)) for proc in procs]
    domains = []
    for (proc, stdout, stderr), out in zip(results, outs, strict=True):
        assert proc.returncode == 0, stdout + stderr
        assert 'all 61 states received' in stdout and 'achieved real-time factor' in stdout
        domains.append(stdout.split('ROS_DOMAIN_ID ')[1].split()[0])
        segments = json.loads((out / 'segments.json').read_text())
        assert [s['episode_return'] for s in segments] == pytest.approx(
            [sum(expected[:29]), sum(expected[29:])], rel=1e-12, abs=1e-12)
    assert domains[0] != domains[1] and os.environ['ROS_DOMAIN_ID'] not in domains


def run_demo_beside(ros_node, argv):
    """Run the demo on this test's domain, spinning `ros_node` meanwhile; return its output."""
    proc = subprocess.Popen([str(a) for a in argv], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert spin_until(ros_node, lambda: proc.poll() is not None, 300.0)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, *proc.communicate()


def test_the_demo_refuses_a_foreign_publisher_on_its_loop(ros_node, tmp_path):
    foreign = ros_node.create_publisher(Clock, '/clock', 10)
    ros_node.create_timer(0.05, lambda: foreign.publish(Clock()))
    returncode, stdout, stderr = run_demo_beside(ros_node, demo_command(
        tmp_path, '--domain-id', os.environ['ROS_DOMAIN_ID']))
    assert returncode == 1, stdout + stderr
    assert 'demo: foreign publishers on the loop' in stderr, stderr
    assert '/clock has' in stderr and f'/{ros_node.get_name()}' in stderr, stderr
    assert 'Traceback' not in stderr and 'total' not in stdout


def test_the_demo_refuses_a_publisher_that_joins_while_it_runs(ros_node, tmp_path):
    # Three processes (slower than composed) and a whole episode: a second
    # /joint_states writer appears once the episode is under way.
    joined = []

    def on_step(msg):
        if msg.step >= 20 and not joined:
            joined.append(ros_node.create_publisher(JointState, '/joint_states', 10))
    ros_node.create_subscription(StepInfo, '/zeus/step', on_step, 10)
    returncode, stdout, stderr = run_demo_beside(ros_node, [
        sys.executable, '-m', 'zeus_ros.ros_tools.demo', '--weights', WALKER_WEIGHTS,
        '--steps', 1000,
        '--schedule', '0:1.0', '--video-every', 0, '--out', tmp_path,
        '--domain-id', os.environ['ROS_DOMAIN_ID']])
    assert joined, f'the episode never started: {stdout}{stderr}'
    assert returncode == 1, stdout + stderr
    assert 'demo: foreign publishers on the loop' in stderr, stderr
    assert '/joint_states has 2 publishers' in stderr and 'total' not in stdout, stderr
