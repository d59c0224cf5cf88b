"""A launcher's nodes end with it; a second node of a name already on the graph is refused.

Issue #38.2: SIGTERM to `ros2 launch` or `ros2 run` (which pass it on to no
one) left sim_node running, and the orphan joined the next launch's graph.
Real processes: a small launcher (test/helpers/launcher.py) starts the node,
as `ros2 launch` and `ros2 run` do, and is then killed with SIGKILL.
"""

import os
from pathlib import Path
import re
import signal
import time
from types import SimpleNamespace

from conftest import helper_script, installed_exe
import pytest

STARTED = 'control period'    # what sim_node logs last before it spins


def wait_for(read, pattern: str, timeout: float, alive=lambda: True) -> re.Match:
    deadline = time.monotonic() + timeout
    while (found := re.search(pattern, read())) is None:
        assert alive(), f'ended before {pattern!r}:\n{read()}'
        assert time.monotonic() < deadline, f'no {pattern!r} within {timeout} s:\n{read()}'
        time.sleep(0.1)
    return found


def test_a_sim_ends_cleanly_when_its_launcher_is_killed(spawn, tmp_path):
    log = tmp_path / 'sim.log'
    # Started from a thread of the launcher that ends on SIGUSR1: the kernel's
    # parent-death signal comes then, with the launcher alive; it must not end the node.
    reaper = spawn([*helper_script('launcher.py'), '--reaper', '--from-thread', log, '--',
                    installed_exe('sim_node'), '--ros-args', '-r', '__node:=orphan_sim'],
                   'reaper')
    launcher = int(wait_for(reaper.output, r'launcher (\d+)', 30, reaper.alive)[1])
    sim = int(wait_for(reaper.output, r'started (\d+)', 30, reaper.alive)[1])
    try:
        launcher_killed(reaper, launcher, sim, log)
    finally:   # an orphan that outlived the test (the failure before the fix)
        if Path(f'/proc/{sim}').exists():
            os.kill(sim, signal.SIGKILL)


def launcher_killed(reaper, launcher: int, sim: int, log: Path) -> None:
    """Kill the launcher once the sim runs; the sim must end within 5 s, with 0."""
    wait_for(lambda: log.read_text() if log.exists() else '', STARTED, 120,
             lambda: Path(f'/proc/{sim}').exists())
    os.kill(launcher, signal.SIGUSR1)
    wait_for(lambda: str(len(os.listdir(f'/proc/{launcher}/task'))), r'^1$', 10)
    time.sleep(1.0)
    assert 'orphan' not in reaper.output(), 'the node ended while its launcher lived'
    os.kill(launcher, signal.SIGKILL)
    ended = wait_for(reaper.output, r'orphan (\d+) exited (-?\d+) after ([\d.]+) s', 15,
                     reaper.alive)
    assert int(ended[1]) == sim
    assert int(ended[2]) == 0, f'exit code {ended[2]}:\n{log.read_text()}'
    assert float(ended[3]) < 5.0, ended[0]
    assert 'Traceback' not in log.read_text(), log.read_text()


def test_a_second_sim_node_on_the_graph_is_refused(spawn):
    first = spawn([installed_exe('sim_node')], 'first')
    wait_for(first.output, STARTED, 120, first.alive)
    second = spawn([installed_exe('sim_node')], 'second')
    code = second.proc.wait(120)
    assert code == 1, f'exit code {code}:\n{second.output()}'
    assert 'a node named /sim_node is already on this graph' in second.output(), \
        second.output()
    assert 'Traceback' not in second.output(), second.output()
    assert first.alive(), first.output()


REFUSED = 'a node named /sim_node is already on this graph'
YOUNGER = 'a younger node named /sim_node'


def no_look_at_start() -> dict:
    # What a loaded machine did: discovery reported the first sim only after the
    # second's look at start had ended. Without the look, only the watch over the
    # node's life can refuse it.
    return dict(os.environ, ZEUS_NAME_WAIT_S='0')


@pytest.mark.parametrize('executor', ['single', 'events'])
def test_a_duplicate_discovered_after_its_start_is_refused(spawn, executor):
    first = spawn([installed_exe('sim_node')], 'first')
    wait_for(first.output, STARTED, 120, first.alive)
    second = spawn([installed_exe('sim_node'), '--ros-args', '-p', f'executor:={executor}'],
                   'second', no_look_at_start())
    code = second.proc.wait(120)
    assert code == 1, f'exit code {code}:\n{second.output()}'
    assert REFUSED in second.output() and STARTED in second.output(), second.output()
    # One line, whichever executor ran the callback that refused (the events one
    # logged an exception as FATAL, with its stack).
    assert 'Traceback' not in second.output() and 'FATAL' not in second.output(), \
        second.output()
    time.sleep(2.0)   # the first's watch looks again every second
    assert first.alive(), first.output()
    assert first.output().count(YOUNGER) <= 1, first.output()


def test_of_two_same_named_nodes_started_together_the_older_stays(spawn, ros_node):
    from conftest import spin_until
    from zeus_ros.ros.unique_name import START_QOS, START_TOPIC, StartRecord
    from diagnostic_msgs.msg import DiagnosticStatus
    records = {}
    ros_node.create_subscription(DiagnosticStatus, START_TOPIC, lambda status: records.update(
        {status.hardware_id.rpartition(':')[2]: StartRecord.from_status(status)}), START_QOS)
    sims = [spawn([installed_exe('sim_node')], name, no_look_at_start()) for name in 'ab']
    assert spin_until(ros_node, lambda: not all(sim.alive() for sim in sims), 180), \
        [sim.output() for sim in sims]
    refused, stayed = sorted(sims, key=lambda sim: sim.alive())
    assert refused.proc.wait(30) == 1 and REFUSED in refused.output(), refused.output()
    # The refusal names both nodes' records: the one it refused beside is the survivor's, older.
    older, own = refusal_records(refused.output())
    assert older.hardware_id.endswith(f':{stayed.proc.pid}'), refused.output()
    assert own.hardware_id.endswith(f':{refused.proc.pid}'), refused.output()
    assert older.older_than(own), (older, own)
    # ...and it is the record the survivor published. The refused node's own record
    # may never reach this node: it can end before discovery matches its publisher here.
    pid = str(stayed.proc.pid)
    assert spin_until(ros_node, lambda: pid in records, 30), records
    assert (records[pid].hardware_id, records[pid].started_ns) == \
        (older.hardware_id, older.started_ns), records
    assert records.get(str(refused.proc.pid), own).started_ns == own.started_ns, records
    time.sleep(2.0)
    assert stayed.alive(), stayed.output()


def refusal_records(output: str) -> tuple:
    """Return the (older, own) start records a refusal names, read from its log line."""
    from zeus_ros.ros.unique_name import START_KEY, StartRecord
    found = re.findall(rf'process (\S+), {START_KEY} (\d+)', output)
    assert len(found) == 2, output
    return tuple(StartRecord('/sim_node', host, int(ns)) for host, ns in found)


# -- the duplicate-name refusal's rule, without ROS --------------------------------------
def test_the_older_of_two_same_named_nodes_stays_whichever_hears_first():
    from diagnostic_msgs.msg import DiagnosticStatus
    from zeus_ros.ros.unique_name import REFUSE, StartRecord, verdict, WARN
    older = StartRecord('/sim_node', 'host:100', 1_000)
    younger = StartRecord('/sim_node', 'host:200', 2_000)
    assert verdict(younger, older) == REFUSE and verdict(older, younger) == WARN
    # The same nanosecond: hardware_id decides, and both sides agree on it.
    a, b = StartRecord('/sim_node', 'host:1', 5), StartRecord('/sim_node', 'host:2', 5)
    assert (verdict(a, b), verdict(b, a)) == (WARN, REFUSE)
    # Its own process (nodes composed together, or its own record) and other names: nothing.
    assert verdict(younger, StartRecord('/sim_node', 'host:200', 1)) is None
    assert verdict(younger, StartRecord('/sim_node2', 'host:100', 1)) is None
    assert verdict(younger, StartRecord('/ns/sim_node', 'host:100', 1)) is None
    # A record goes out and comes back as itself; a status that is not one is ignored.
    assert StartRecord.from_status(older.to_status()) == older
    assert StartRecord.from_status(DiagnosticStatus(name='/sim_node')) is None


class FakeNode:
    """What NameGuard uses of a node; the test sets the graph and delivers the records."""

    def __init__(self):
        self.graph = [('sim_node', '/')]
        self.published, self.warnings, self.arrived = [], [], []
        self.deliver = self.recheck = None

    def get_name(self):
        return 'sim_node'

    def get_namespace(self):
        return '/'

    def get_node_names_and_namespaces(self):
        return list(self.graph)

    def create_publisher(self, *_):
        return SimpleNamespace(publish=self.published.append)

    def create_subscription(self, _type, _topic, callback, _qos):
        self.deliver = callback
        return SimpleNamespace(handle=SimpleNamespace(take_message=self._take))

    def _take(self, *_):
        return (self.arrived.pop(0), {}) if self.arrived else None

    def create_timer(self, _period, callback):
        self.recheck = callback

    def get_logger(self):
        return SimpleNamespace(warning=self.warnings.append)


def record(pid: int, started_ns: int, name: str = '/sim_node'):
    from zeus_ros.ros.unique_name import StartRecord
    return StartRecord(name, f'host:{pid}', started_ns).to_status()


def test_the_watch_refuses_for_an_older_record_once_the_graph_shows_its_node():
    from zeus_ros.ros.unique_name import DuplicateNode, NameGuard, StartRecord
    node = FakeNode()
    guard = NameGuard(node, 2_000)
    assert [StartRecord.from_status(s) for s in node.published] == [guard.own]
    node.deliver(record(1, 1_000))    # its node not on the graph yet: nothing to settle
    node.recheck()
    node.deliver(record(2, 1_500))    # two older ones: the refusal names the oldest
    node.graph.append(('sim_node', '/'))
    with pytest.raises(DuplicateNode, match='a node named /sim_node is already on this graph') \
            as refused:
        node.recheck()
    older, own = refusal_records(str(refused.value))
    assert (older.hardware_id, older.started_ns) == ('host:1', 1_000)
    assert (own.hardware_id, own.started_ns) == (guard.own.hardware_id, 2_000)


def test_the_older_warns_once_of_a_younger_and_ignores_its_own_process():
    from zeus_ros.ros.unique_name import NameGuard, StartRecord
    node = FakeNode()
    guard = NameGuard(node, 2_000)
    node.graph.append(('sim_node', '/'))
    node.deliver(guard.own.to_status())                                        # its own
    node.deliver(StartRecord('/sim_node', guard.own.hardware_id, 1).to_status())  # composed
    assert node.warnings == []
    node.deliver(record(7, 3_000))
    node.recheck()
    node.recheck()
    assert len(node.warnings) == 1 and 'a younger node named /sim_node' in node.warnings[0]


def test_a_record_whose_node_never_shows_is_dropped():
    """A replayed bag's old record, or a node that ended unseen, refuses nothing later."""
    from zeus_ros.ros import unique_name
    now = [0.0]
    node = FakeNode()
    unique_name.NameGuard(node, 2_000, clock=lambda: now[0])
    node.deliver(record(1, 1_000))
    now[0] = unique_name.PENDING_S + 1
    node.recheck()
    node.graph.append(('sim_node', '/'))   # a younger duplicate comes later
    node.recheck()                         # its record settles it, not the stale one


def test_the_look_at_start_decides_by_the_records_it_has(monkeypatch):
    from zeus_ros.ros import unique_name
    from zeus_ros.ros.unique_name import DuplicateNode, NameGuard
    start = time.monotonic()
    node = FakeNode()
    node.graph.append(('sim_node', '/'))
    node.arrived.append(record(1, 1_000))           # an older one
    with pytest.raises(DuplicateNode):
        NameGuard(node, 2_000).check_at_start(start, 0.1)
    node = FakeNode()
    node.graph.append(('sim_node', '/'))
    node.arrived.append(record(1, 3_000))           # a younger one: it gives way
    NameGuard(node, 2_000).check_at_start(start, 0.1)
    node.recheck()
    assert len(node.warnings) == 1
    # One without a record (not started through run_node): refused, as before records.
    monkeypatch.setattr(unique_name, 'RECORD_WAIT_S', 0.2)
    node = FakeNode()
    node.graph.append(('sim_node', '/'))
    with pytest.raises(DuplicateNode, match='it published no start record'):
        NameGuard(node, 2_000).check_at_start(start, 0.1)
    NameGuard(FakeNode(), 2_000).check_at_start(start, 0.0)   # 0: no look at all
