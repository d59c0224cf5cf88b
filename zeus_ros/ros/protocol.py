"""ROS-free pieces of the sim node's protocol: stamps, commands, resets, loop health."""

from __future__ import annotations

from collections import deque
import math
from typing import Sequence

import numpy as np

from sim_node.layout import check_action
from sim_node.families import SimFamily

NANOSECONDS = 1_000_000_000
# Reset.seed: -1 keeps the random stream of initial states; 0 <= seed < 2**32
# restarts it there (numpy's RandomState takes no other seed). Reset.srv gives
# the field no default, so an empty request carries 0.
KEEP_STREAM = -1
SEED_MAX = 2**32 - 1


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


def check_seed(seed: int) -> str | None:
    """Return why a Reset.seed is refused, or None."""
    if seed == KEEP_STREAM or 0 <= seed <= SEED_MAX:
        return None
    return (f'seed must be {KEEP_STREAM} (keep the current stream) or in [0, {SEED_MAX}], '
            f'got {seed}')


def check_reset_request(seed: int, names: Sequence[str], values: Sequence[float],
                        spec: SimFamily) -> str | None:
    """Return why a reset request is refused, or None.

    A valid seed (check_seed); one value per name; each name one of the
    family's live parameters, at most once (two values for one name leave nothing to choose
    between), each value in its live range.
    """
    names, values = list(names), list(values)
    problem = check_seed(seed)
    if problem is not None:
        return problem
    if len(names) != len(values):
        return f'{len(names)} parameter names but {len(values)} values'
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        return f'parameter {", ".join(repeated)} given more than once'
    for name, value in zip(names, values, strict=True):
        reason = spec.check_param(name, value)
        if reason is not None:
            return reason
    return None


class RecentCounts:
    """How much each counter rose over the last `window_s` seconds.

    Diagnostic levels read this, not the totals since start, so that one gap at
    start-up does not keep a node at WARN for ever. Fed once per report (1 Hz)
    with the totals; used by the sim node and both controller nodes.
    """

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        # (time, totals); the first entry is the baseline the rises are taken from.
        self._snapshots: deque[tuple[float, dict]] = deque([(-math.inf, {})])

    def rises(self, now: float, totals: dict) -> dict:
        """Rise of each counter in (now - window_s, now], given its total now."""
        self._snapshots.append((now, dict(totals)))
        while len(self._snapshots) > 1 and self._snapshots[1][0] <= now - self.window_s:
            self._snapshots.popleft()
        base = self._snapshots[0][1]
        return {key: value - base.get(key, 0) for key, value in totals.items()}

    def problem(self, now: float, totals: dict) -> str | None:
        """'<rise> <counter>, ... in the last N s' for the counters that rose, or None."""
        risen = [f'{rise} {key}' for key, rise in self.rises(now, totals).items() if rise > 0]
        if not risen:
            return None
        return f'{", ".join(risen)} in the last {self.window_s:g} s'


def loop_problem(recent: dict, window_s: float) -> str | None:
    """Return what is wrong with the sim's loop over the recent window, or None.

    `recent` holds the rises of: steps, answered (steps whose command answered
    the state before them), timeouts, rejected, instabilities, late_ticks.
    Nobody answering at all is a problem even though every count of errors is
    zero: the robot runs on zero actions (or, in lockstep, waits).
    """
    problems = []
    if recent['answered'] == 0:
        problems.append(f'no controller: none of {recent["steps"]} steps answered by a command')
    elif recent['timeouts']:
        problems.append(f'{recent["timeouts"]} command timeouts')
    for key, text in (('rejected', 'bad commands rejected'),
                      ('instabilities', 'MuJoCo instabilities'),
                      ('late_ticks', 'ticks more than a period late')):
        if recent[key]:
            problems.append(f'{recent[key]} {text}')
    return f'{"; ".join(problems)} in the last {window_s:g} s' if problems else None


class AchievedRealTimeFactor:
    """Simulated seconds per wall-clock second over the last `window_s` seconds.

    `real_time_factor` asks for a speed (realtime mode); this measures the one
    achieved, in either mode, from the sim clock read at each report (1 Hz),
    so it costs nothing per step. 0 while the sim stands still (lockstep
    waiting); NaN until two reports span some time.
    """

    def __init__(self, window_s: float = 5.0):
        self.window_s = window_s
        self._samples: deque[tuple[float, float]] = deque()   # (wall s, sim s)

    def update(self, wall_s: float, sim_s: float) -> float:
        """Take the sim clock `sim_s` at wall time `wall_s`; return the factor over the window."""
        self._samples.append((wall_s, sim_s))
        # Keep one sample at or before the window's start: the interval spans it.
        while len(self._samples) > 2 and self._samples[1][0] <= wall_s - self.window_s:
            self._samples.popleft()
        first_wall, first_sim = self._samples[0]
        if wall_s <= first_wall:
            return math.nan
        return (sim_s - first_sim) / (wall_s - first_wall)


# More stale commands than this per second of the window: someone else answers too.
STALE_PER_S_LIMIT = 1.0


def command_problem(publishers: Sequence[str], recent_stale: int,
                    window_s: float) -> str | None:
    """Return why the commands look like more than one controller's, or None.

    `publishers`: the nodes publishing the command topic (one per writer);
    `recent_stale`: lockstep commands for a state not awaited, over the window.
    Two controllers answer each state twice; the second answer is stale.
    """
    problems = []
    if len(publishers) > 1:
        problems.append(f'{len(publishers)} publishers on the command topic '
                        f'({", ".join(publishers)}): more than one controller')
    if recent_stale > STALE_PER_S_LIMIT * window_s:
        problems.append(f'{recent_stale} stale commands in the last {window_s:g} s '
                        '(answers to states not awaited: a second controller?)')
    return '; '.join(problems) or None
