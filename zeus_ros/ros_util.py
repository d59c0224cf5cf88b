"""Small pieces every zeus_ros node shares: QoS, stamps, diagnostics, throttled warnings."""

from __future__ import annotations

import gc
import os
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sim_node.protocol import ns_to_stamp, stamp_to_ns
from zeus_ros.loop_spin import spin_loop

# Reliable, keep-last 10, volatile on every topic of the loop. Lockstep needs
# reliability (a lost state or command stalls a step until the timeout and
# breaks determinism); the shallow queue bounds the backlog in realtime mode,
# where only the newest state matters.
LOOP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE)


def stamp_ns(header) -> int:
    """Return a header's stamp as integer nanoseconds."""
    return stamp_to_ns(header.stamp.sec, header.stamp.nanosec)


def set_stamp(header, ns: int) -> None:
    """Set a header's stamp from integer nanoseconds."""
    header.stamp.sec, header.stamp.nanosec = ns_to_stamp(ns)


def describe(text: str, read_only: bool = False, **ranges) -> ParameterDescriptor:
    """Parameter descriptor with a description, optional ranges and read-only flag."""
    return ParameterDescriptor(description=text, read_only=read_only, **ranges)


def apply_thread_priority(node) -> int:
    """Declare `thread_priority`; run the calling thread under SCHED_FIFO at it if > 0.

    The convention of ros2_control's controller_manager: a node that must meet a
    period asks for a real-time priority and, if the system refuses it, warns
    and runs on under the normal scheduler. Returns the priority in force.
    Threads started afterwards (spin_loop's executor thread) inherit it.
    """
    priority = node.declare_parameter('thread_priority', 0, describe(
        "SCHED_FIFO priority (1-99) of the node's loop thread; 0 keeps the normal "
        'scheduler. Needs root, CAP_SYS_NICE or an rtprio limit; if refused, the node '
        'warns and runs on (read-only).', read_only=True,
        integer_range=[IntegerRange(from_value=0, to_value=99, step=1)])).value
    if priority == 0:
        return 0
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as error:
        node.get_logger().warning(f'thread_priority {priority}: SCHED_FIFO refused '
                                  f'({error.strerror}); running under the normal scheduler')
        return 0
    node.get_logger().info(f'loop thread runs under SCHED_FIFO, priority {priority}')
    return priority


def call_service(client, request, wait, timeout: float = 30.0, attempt_s: float = 3.0):
    """Call a service and return its response, re-sending a request left unanswered.

    Discovery is not symmetric: a client can see a new server (so
    `wait_for_service` passes) before the server has matched the client's
    response reader, and the answer to a request sent in that moment is lost.
    Each attempt waits `attempt_s`; `wait(predicate, seconds) -> bool` is
    whatever spins the client's node. Only for requests that may be repeated
    (a repeated reset starts one more episode; the response names the last).
    """
    deadline = time.monotonic() + timeout
    while (remaining := deadline - time.monotonic()) > 0:
        future = client.call_async(request)
        if wait(future.done, min(attempt_s, remaining)):
            return future.result()
        client.remove_pending_request(future)
    raise TimeoutError(f'{client.srv_name} did not answer within {timeout:g} s')


def diagnostic_array(node, name: str, hardware_id: str, values: dict,
                     problem: str | None = None) -> DiagnosticArray:
    """One status for `node`: OK, or WARN with `problem` as its message."""
    status = DiagnosticStatus(
        level=DiagnosticStatus.WARN if problem else DiagnosticStatus.OK,
        name=f'{node.get_name()}: {name}', hardware_id=hardware_id,
        message=problem or 'ok',
        values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
    array = DiagnosticArray(status=[status])
    array.header.stamp = node.get_clock().now().to_msg()
    return array


class ThrottledWarnings:
    """Log a warning per key at most once per period."""

    def __init__(self, logger, period_s: float = 2.0):
        self.logger, self.period_s = logger, period_s
        self._last: dict[str, float] = {}

    def warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, float('-inf')) >= self.period_s:
            self._last[key] = now
            self.logger.warning(text)


class RateMeter:
    """Events per second and mean latency over the last reporting period."""

    def __init__(self):
        self.count, self.latency_sum, self.total = 0, 0.0, 0
        self._since = time.monotonic()

    def record(self, latency_s: float = 0.0) -> None:
        self.count += 1
        self.total += 1
        self.latency_sum += latency_s

    def report(self) -> dict:
        now = time.monotonic()
        elapsed = max(now - self._since, 1e-9)
        mean_ms = 1e3 * self.latency_sum / self.count if self.count else 0.0
        values = {'rate_hz': f'{self.count / elapsed:.1f}', 'latency_ms': f'{mean_ms:.3f}',
                  'total': self.total}
        self.count, self.latency_sum, self._since = 0, 0.0, now
        return values


class TickLateness:
    """How late scheduled ticks start, since the schedule was (re)started.

    A fixed-bin histogram (50 us bins up to 100 ms): O(1) per tick, and the
    percentiles of every tick so far are cheap to read at any time. Two kinds
    of missed deadline are counted: a tick that starts more than a period late
    (the sim's own), and a tick at which the command answering the previous
    state had not arrived (the controller's: the step applies an older one).
    """

    BIN_S = 50e-6
    BINS = 2000

    def __init__(self):
        self.restart()

    def restart(self) -> None:
        self.counts = [0] * self.BINS
        self.ticks = self.missed = self.unanswered = 0
        self.max_s = 0.0

    def record(self, late_s: float, period_s: float, answered: bool = True) -> None:
        self.counts[min(max(int(late_s / self.BIN_S), 0), self.BINS - 1)] += 1
        self.ticks += 1
        self.max_s = max(self.max_s, late_s)
        if late_s > period_s:
            self.missed += 1
        if not answered:
            self.unanswered += 1

    def percentile_ms(self, q: float) -> float:
        """Upper edge of the bin holding the q-th percentile tick, in ms."""
        rank, seen = q / 100.0 * self.ticks, 0
        for index, count in enumerate(self.counts):
            seen += count
            if seen >= rank:
                return 1e3 * (index + 1) * self.BIN_S
        return 1e3 * self.BINS * self.BIN_S

    def report(self) -> dict:
        if not self.ticks:
            return {}
        return {'ticks': self.ticks, 'tick_late_ms_p50': f'{self.percentile_ms(50):.2f}',
                'tick_late_ms_p99': f'{self.percentile_ms(99):.2f}',
                'tick_late_ms_p999': f'{self.percentile_ms(99.9):.2f}',
                'tick_late_ms_max': f'{1e3 * self.max_s:.3f}', 'missed_ticks': self.missed,
                'unanswered_ticks': self.unanswered}


def run_node(node_class, args=None, fatal: tuple = ()) -> int:
    """Spin one node with `spin_loop` until Ctrl-C or shutdown.

    A `fatal` error, or a parameter given on the command line that its
    declaration refuses (out of range, wrong type), ends it with exit code 1 and
    the error on stderr.
    """
    rclpy.init(args=args)
    node = None
    try:
        node = node_class()
        apply_thread_priority(node)
        # Everything built so far (modules, weights, the node) lives for the
        # process: keep it out of the collector's full passes, which would
        # otherwise walk it every time and stall the loop for milliseconds.
        gc.freeze()
        # When a loop deadline comes while spin_loop's background thread runs
        # Python code, the loop thread gets the GIL within 1 ms, not 5.
        sys.setswitchinterval(0.001)
        spin_loop(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterException as error:
        # rclpy words it '<reason>: <parameter name>'; name first reads better.
        reason, _, name = str(error).rpartition(': ')
        print(f'{node_class.__name__}: parameter {name}: {reason}', file=sys.stderr)
        return 1
    except fatal as error:
        print(f'{node_class.__name__}: {error}', file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
