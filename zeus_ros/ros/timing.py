"""ROS-free timing of the controllers on a free-running robot (#49.3).

A robot publishes states at its own rate; the weights were trained at one
control period (the checkpoint's `control_timestep`). `Decimator` keeps the
states that lie one control period apart, by their stamps, so that the
context node and the policy node, each deciding alone, keep the same ones
(rl_sar's `decimation`, driven by the robot's clock instead of a count).
`LatencyWindow` keeps the last latencies for their p50 and p99.
"""

from __future__ import annotations

from collections import deque

import numpy as np

# A state up to this share of a period early still counts as the next control
# step: a robot's stamps jitter (a wall clock), a sim's are exact.
EARLY_SHARE = 0.25


class Decimator:
    """Accepts a state when its stamp is at least one control period after the last accepted.

    A period of 0 accepts every state. A stamp before the last accepted is
    a restarted clock: accepted, and the count starts again from it. So a
    source at the trained period (the sim, in either mode) loses nothing; one
    at twice the rate loses every other state; one slower loses nothing (and
    its transitions then span more than a period: not what the weights saw).
    """

    def __init__(self, period_ns: int):
        if period_ns < 0:
            raise ValueError(f'control period must be >= 0 ns, got {period_ns}')
        self.period_ns = int(period_ns)
        self.min_gap_ns = self.period_ns - int(self.period_ns * EARLY_SHARE)
        self.last: int | None = None
        self.skipped = 0

    def accept(self, stamp_ns: int) -> bool:
        """Whether the state stamped `stamp_ns` is a control step."""
        last = self.last
        if last is None or stamp_ns < last or stamp_ns - last >= self.min_gap_ns:
            self.last = stamp_ns
            return True
        if stamp_ns == last:
            return True   # the state itself again (a duplicate: its reader decides)
        self.skipped += 1
        return False


class LatencyWindow:
    """The last `size` latencies (s), for their median and 99th percentile in ms."""

    def __init__(self, size: int = 2000):
        self._values: deque[float] = deque(maxlen=size)

    def record(self, seconds: float) -> None:
        """Add one latency."""
        self._values.append(seconds)

    def report(self) -> dict[str, str]:
        """Return latency_p50_ms and latency_p99_ms ('nan' before any latency)."""
        if not self._values:
            return {'latency_p50_ms': 'nan', 'latency_p99_ms': 'nan'}
        p50, p99 = np.percentile(np.asarray(self._values) * 1e3, [50, 99])
        return {'latency_p50_ms': f'{p50:.3f}', 'latency_p99_ms': f'{p99:.3f}'}
