"""A graph of one's own: a free ROS_DOMAIN_ID, and who publishes on a loop's topics.

Every graph of this project uses the same topic names, so two of them on one
domain answer each other's states. A self-contained tool (the demo, the
test suite) claims a domain no other tool of this project holds, and one
that reads its own loop checks that each loop topic is published by the
node it started, once, and by nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass
import fcntl
import os
import random
from typing import IO, Iterable, Mapping, Sequence, TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.node import Node

# The lock files the test suite has always taken: demos, tests and test runs
# of other checkouts on one machine then never pick the same domain.
LOCK_PATTERN = '/tmp/zeus_ros_test_domain_{}.lock'
# Fast DDS maps domain ids to ports up to 232; 0-19 are left to people's own graphs.
DOMAIN_IDS = range(20, 100)
# What rmw reports for a writer discovered before its node's name.
UNKNOWN_NODE = '_NODE_NAMESPACE_UNKNOWN_/_NODE_NAME_UNKNOWN_'


@dataclass
class DomainClaim:
    """A ROS_DOMAIN_ID held (its lock file locked) for as long as this process lives."""

    domain_id: int
    handle: IO

    def release(self) -> None:
        self.handle.close()


def claim_free_domain(ids: Iterable[int] = DOMAIN_IDS, lock_pattern: str = LOCK_PATTERN,
                      seed: int | None = None) -> DomainClaim:
    """Claim a domain id whose lock no other process holds (random order); RuntimeError if none."""
    candidates = list(ids)
    random.Random(os.getpid() if seed is None else seed).shuffle(candidates)
    for domain_id in candidates:
        handle = open(lock_pattern.format(domain_id), 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        return DomainClaim(domain_id, handle)
    raise RuntimeError(f'no free ROS_DOMAIN_ID in {candidates[0]}-{candidates[-1]}'
                       if candidates else 'no ROS_DOMAIN_ID to claim')


def use_free_domain() -> DomainClaim:
    """Claim a free domain and put it in ROS_DOMAIN_ID (for rclpy.init and child processes)."""
    claim = claim_free_domain()
    os.environ['ROS_DOMAIN_ID'] = str(claim.domain_id)
    return claim


def foreign_publishers(observed: Mapping[str, Sequence[str]],
                       expected: Mapping[str, str]) -> list[str]:
    """Return, per topic, what publishes it besides the one expected node; [] if nothing.

    `observed`: topic -> the full names of its publishers, one per writer;
    `expected`: topic -> the node that must be its only publisher. A topic
    not yet published is not a problem here (the loop's own start-up waits
    for it); a second writer of the expected name is (another graph's node).
    A writer whose node is not known yet (UNKNOWN_NODE: its participant's
    node list comes after its endpoints) counts, but is not itself foreign.
    """
    problems = []
    for topic, owner in expected.items():
        names = list(observed.get(topic, ()))
        others = [name for name in names if name not in (owner, UNKNOWN_NODE)]
        if others or len(names) > 1:
            count = f'{len(names)} publisher{"s" if len(names) != 1 else ""}'
            problems.append(f'{topic} has {count} ({", ".join(sorted(names))}), '
                            f'expected {owner} alone')
    return problems


def publisher_names(node: Node, topic: str) -> list[str]:
    """Full names of the nodes publishing `topic` on the graph `node` sees, one per writer."""
    return [_full_name(info.node_namespace, info.node_name)
            for info in node.get_publishers_info_by_topic(topic)]


def _full_name(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'
