"""ROS-free pieces of the sim node's protocol: stamps and command checking."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from sim_node.env import check_action

NANOSECONDS = 1_000_000_000


def stamp_to_ns(sec: int, nanosec: int) -> int:
    """Collapse a builtin_interfaces/Time into integer nanoseconds."""
    return int(sec) * NANOSECONDS + int(nanosec)


def ns_to_stamp(ns: int) -> tuple[int, int]:
    """Split integer nanoseconds into (sec, nanosec)."""
    return divmod(int(ns), NANOSECONDS)


def parse_command(names: Sequence[str], efforts: Sequence[float],
                  actuator_names: Sequence[str]) -> tuple[np.ndarray | None, str | None]:
    """Turn a JointState command into an action in actuator order.

    The names must be exactly the actuators (any order); the efforts one per
    name, finite. Values beyond [-1, 1] are clipped. Returns (action, None)
    or (None, reason).
    """
    names = list(names)
    if sorted(names) != sorted(actuator_names) or len(set(names)) != len(names):
        return None, f'names {names} are not the actuators {list(actuator_names)}'
    if len(efforts) != len(names):
        return None, f'{len(efforts)} efforts for {len(names)} names'
    order = [names.index(a) for a in actuator_names]
    return check_action(np.asarray(efforts, dtype=np.float64)[order], len(actuator_names))
