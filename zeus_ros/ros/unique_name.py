"""Refuse to run a node beside an older node of its fully qualified name.

ROS 2 lets two nodes share a name (ros2cli only warns), and an orphaned
sim_node left by a killed launch silently joined the next launch's graph:
two sims answering one loop. Every node started through `run_node` has a
`NameGuard`, which looks twice:

* at start (the fast path, `NameGuard.check_at_start`): once discovery has had
  time to report the nodes already on the graph, a node of its own name there
  means this one refuses to run (DuplicateNode; run_node exits 1);
* for the node's whole life (the backstop): on a loaded machine discovery
  reported the first sim only after a second sim's look had ended, and the
  second ran unrefused. So each guard publishes its node's `StartRecord` once
  on START_TOPIC (transient local: a node that joins later still gets it) and
  reads everyone's. A record of its own name from another process, while the
  graph shows two nodes of that name, settles it by age, whichever node hears
  of the other first and however late: the younger raises DuplicateNode (from
  a callback it ends spin_loop, and run_node exits 1 as at start), the older
  logs one warning and runs on. A graph alone cannot tell which of two
  same-named nodes came first; the records can.

Nodes composed in one process never refuse each other: a guard ignores the
records of its own process. A record counts only while the graph shows a
second node of the name, so a replayed bag that holds START_TOPIC refuses
nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
import os
import socket
import time
from typing import Callable, TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

if TYPE_CHECKING:
    from rclpy.node import Node

# How long after its creation a node waits for discovery to report the nodes
# already on the graph (on this loopback graph they appear within tenths of a
# second; this leaves room for a loaded machine). A node's own start-up work
# (a MuJoCo model, weights) overlaps it, so it seldom waits the whole time.
# The backstop covers a discovery slower than that.
DISCOVERY_WAIT_S = 1.5
POLL_S = 0.05
# Looked for at least this long even when the node's own start-up took longer
# than DISCOVERY_WAIT_S: one look can come before discovery has reported anyone.
MIN_LOOK_S = 0.75
# At start, how long a same-named node on the graph may go without a record
# before this one refuses to run beside it, as it did before the records (a
# node not started through run_node publishes none, and then nothing says which
# is older). A node is on the graph from its creation but publishes its record
# after its constructor (a MuJoCo model, weights: seconds on a loaded machine),
# so two nodes that start together need this long to hear each other's records.
RECORD_WAIT_S = 10.0
# A record whose node the graph has not shown within this long is dropped: its
# node ended before discovery reported it, or a bag is replaying it.
PENDING_S = 30.0
# How often the backstop looks again at the graph while a record waits for its node.
RECHECK_S = 1.0

START_TOPIC = '/zeus/node_starts'
START_KEY = 'start_time_ns'
# Transient local: a node that joins later gets the records of the nodes already
# there. A writer keeps its one record; the reader's depth covers a graph's worth
# of records arriving before its node spins.
START_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)

REFUSE, WARN = 'refuse', 'warn'


class DuplicateNode(RuntimeError):
    """Another node of the graph has this node's fully qualified name."""


@dataclass(frozen=True)
class StartRecord:
    """When a node started, and in which process: what it publishes on START_TOPIC."""

    name: str           # fully qualified node name
    hardware_id: str    # host:pid of its process
    started_ns: int     # wall clock (time.time_ns()) when the node was created

    def older_than(self, other: StartRecord) -> bool:
        """Whether this node came first; the same nanosecond is broken by hardware_id."""
        return (self.started_ns, self.hardware_id) < (other.started_ns, other.hardware_id)

    def to_status(self) -> DiagnosticStatus:
        return DiagnosticStatus(level=DiagnosticStatus.OK, name=self.name, message='started',
                                hardware_id=self.hardware_id,
                                values=[KeyValue(key=START_KEY, value=str(self.started_ns))])

    @classmethod
    def from_status(cls, status: DiagnosticStatus) -> StartRecord | None:
        """Read the record a status carries; None if it is not one (no valid start time)."""
        values = {kv.key: kv.value for kv in status.values}
        try:
            started_ns = int(values[START_KEY])
        except (KeyError, ValueError):
            return None
        return cls(status.name, status.hardware_id, started_ns)


def verdict(own: StartRecord, other: StartRecord) -> str | None:
    """Say what `own`'s node does about the node of `other`, if both are on one graph.

    REFUSE: `other` is an older node of its name in another process; WARN: a
    younger one (which refuses); None: another name, or its own process.
    """
    if other.name != own.name or other.hardware_id == own.hardware_id:
        return None
    return REFUSE if other.older_than(own) else WARN


def hardware_id() -> str:
    return f'{socket.gethostname()}:{os.getpid()}'


def fully_qualified_name(node: Node) -> str:
    namespace = node.get_namespace().rstrip('/')
    return f'{namespace}/{node.get_name()}'


def same_named_count(node: Node) -> int:
    """How many nodes of the graph, this one included, have this node's name and namespace."""
    own = (node.get_name(), node.get_namespace())
    return sum(1 for entry in node.get_node_names_and_namespaces() if tuple(entry) == own)


def refusal(node: Node, own: StartRecord, older: StartRecord | None = None) -> DuplicateNode:
    """Return the error a node refuses with; it names both processes, for the user to stop one."""
    domain = os.environ.get('ROS_DOMAIN_ID', '0')
    other = (f'process {older.hardware_id}, {START_KEY} {older.started_ns}' if older
             else 'it published no start record')
    return DuplicateNode(
        f'a node named {fully_qualified_name(node)} is already on this graph '
        f'(ROS_DOMAIN_ID {domain}; {other}; this one: process {own.hardware_id}, '
        f'{START_KEY} {own.started_ns}), perhaps one a stopped launch left behind; '
        'refusing to run beside it: stop it, or give this one another name '
        '(--ros-args -r __node:=NAME) or another ROS_DOMAIN_ID')


class NameGuard:
    """One node's duplicate-name checks: at start, and for its life through the records.

    Create it right after the node, so that its record goes out while the
    node finishes starting; it publishes the record at once.
    """

    def __init__(self, node: Node, started_ns: int, clock: Callable[[], float] = time.monotonic):
        self.node, self._clock = node, clock
        self.own = StartRecord(fully_qualified_name(node), hardware_id(), started_ns)
        self._pending: dict[str, tuple[StartRecord, float]] = {}   # by hardware_id
        self._publisher = node.create_publisher(DiagnosticStatus, START_TOPIC, START_QOS)
        self._subscription = node.create_subscription(DiagnosticStatus, START_TOPIC,
                                                      self._on_record, START_QOS)
        node.create_timer(RECHECK_S, self.enforce)
        self._publisher.publish(self.own.to_status())

    def check_at_start(self, created_at: float, wait_s: float = DISCOVERY_WAIT_S) -> None:
        """Raise DuplicateNode for an older (or unrecorded) same-named node on the graph.

        Looks until `created_at + wait_s` (`created_at`: time.monotonic() when
        the node was created), and on while a same-named node it saw has no
        record yet. `wait_s` 0 skips the look: the backstop alone guards.
        """
        if wait_s <= 0:
            return
        deadline = max(created_at + wait_s, self._clock() + min(MIN_LOOK_S, wait_s))
        unrecorded_since = None
        while True:
            self._take_arrived()
            others = same_named_count(self.node) - 1
            records = [record for record, _ in self._pending.values()]
            if others > 0 and (older := self._older(records)):
                raise refusal(self.node, self.own, older)
            now = self._clock()
            if others <= len(records):   # each one the graph shows has a younger record
                unrecorded_since = None
                if now >= deadline:
                    return
            elif unrecorded_since is None:
                unrecorded_since = now
            elif now - unrecorded_since >= RECORD_WAIT_S:
                raise refusal(self.node, self.own)
            time.sleep(POLL_S)

    def enforce(self) -> None:
        """Settle the records whose nodes the graph shows: refuse, or warn once of each."""
        if not self._pending:
            return
        now = self._clock()
        if same_named_count(self.node) < 2:
            self._pending = {key: (record, came) for key, (record, came)
                             in self._pending.items() if now - came < PENDING_S}
            return
        records = [record for record, _ in self._pending.values()]
        self._pending.clear()
        if older := self._older(records):
            raise refusal(self.node, self.own, older)
        for record in records:
            self.node.get_logger().warning(
                f'a younger node named {self.own.name} ({record.hardware_id}) joined this '
                'graph; it refuses to run beside this one')

    def _older(self, records: list[StartRecord]) -> StartRecord | None:
        """Return the oldest of `records` that this node must refuse to run beside, if any."""
        older = [record for record in records if verdict(self.own, record) == REFUSE]
        return min(older, key=lambda record: (record.started_ns, record.hardware_id),
                   default=None)

    def _on_record(self, status: DiagnosticStatus) -> None:
        self._keep(status)
        self.enforce()

    def _keep(self, status: DiagnosticStatus) -> None:
        other = StartRecord.from_status(status)
        if other is not None and verdict(self.own, other) is not None:
            self._pending[other.hardware_id] = (other, self._clock())

    def _take_arrived(self) -> None:
        """Take the records that came while the node starts (no executor takes them yet)."""
        while (taken := self._subscription.handle.take_message(DiagnosticStatus, False)):
            self._keep(taken[0])
