"""Small pieces every zeus_ros node shares: QoS, stamps, diagnostics, parameters, shutdown."""

from __future__ import annotations

import gc
import os
import re
import signal
import sys
import threading
import time
from typing import Any, Callable, Sequence, TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, ParameterType
import rclpy
import rclpy.logging
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import get_logger_level, LoggingSeverity, set_logger_level
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from zeus_ros.ros.discovery import use_discovery_profile
from zeus_ros.ros.protocol import ns_to_stamp, stamp_to_ns
from zeus_ros.ros.loop_spin import EXECUTORS, spin_loop
from zeus_ros.ros.parent_watch import end_with_launcher
from zeus_ros.ros.unique_name import DISCOVERY_WAIT_S, DuplicateNode, NameGuard

if TYPE_CHECKING:
    from types import FrameType

    from rclpy.client import Client
    from rclpy.impl.rcutils_logger import RcutilsLogger
    from rclpy.node import Node
    from std_msgs.msg import Header

# `wait(predicate, seconds) -> bool`: spins a client's node until predicate() or the time is up.
Wait = Callable[[Callable[[], bool], float], bool]

# Reliable, keep-last 10, volatile on every topic of the loop. Lockstep needs
# reliability (a lost state or command stalls a step until the timeout and
# breaks determinism); the shallow queue bounds the backlog in realtime mode,
# where only the newest state matters.
LOOP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE)


def stamp_ns(header: Header) -> int:
    """Return a header's stamp as integer nanoseconds."""
    return stamp_to_ns(header.stamp.sec, header.stamp.nanosec)


def set_stamp(header: Header, ns: int) -> None:
    """Set a header's stamp from integer nanoseconds."""
    header.stamp.sec, header.stamp.nanosec = ns_to_stamp(ns)


def describe(text: str, read_only: bool = False, **ranges) -> ParameterDescriptor:
    """Parameter descriptor with a description, optional ranges and read-only flag."""
    return ParameterDescriptor(description=text, read_only=read_only, **ranges)


def declare_thread_priority(node: Node) -> int:
    """Declare `thread_priority` once and return it; a value outside [0, 99] raises.

    A node declares it among its own parameters, so that a bad value ends it
    before it logs or starts anything; run_node declares it for the others.
    """
    if not node.has_parameter('thread_priority'):
        node.declare_parameter('thread_priority', 0, describe(
            "SCHED_FIFO priority (1-99) of the node's loop thread; 0 keeps the normal "
            'scheduler. Needs root, CAP_SYS_NICE or an rtprio limit; if refused, the node '
            'warns and runs on (read-only).', read_only=True,
            integer_range=[IntegerRange(from_value=0, to_value=99, step=1)]))
    return node.get_parameter('thread_priority').value


def declare_executor(node: Node) -> str:
    """Declare `executor` once and return it; a value not in EXECUTORS raises BadParameter."""
    if not node.has_parameter('executor'):
        node.declare_parameter('executor', 'single', describe(
            "The executor of the node's services and timers beside the control loop: "
            "'single' (rclpy's SingleThreadedExecutor) or 'events' (rclpy's experimental "
            "EventsExecutor). Composed nodes use the first node's (read-only).",
            read_only=True))
    value = node.get_parameter('executor').value
    if value not in EXECUTORS:
        raise BadParameter(f"parameter executor: {value!r} is not one of {', '.join(EXECUTORS)}")
    return value


def apply_thread_priority(node: Node) -> int:
    """Run the calling thread under SCHED_FIFO at `thread_priority` if it is > 0.

    The convention of ros2_control's controller_manager: a node that must meet a
    period asks for a real-time priority and, if the system refuses it, warns
    and runs on under the normal scheduler. Returns the priority in force.
    Threads started afterwards (spin_loop's executor thread) inherit it.
    """
    priority = declare_thread_priority(node)
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


class UnknownParameters(ValueError):
    """Parameters given at start (-p, a params file) that the node does not have."""


class BadParameter(ValueError):
    """A value given at start that the node's own checks refuse."""


def _overrides(node: Node) -> dict:
    # The values given at start, as rclpy 7.1.6 (requirements.lock) keeps them:
    # there is no public accessor.
    return node._parameter_overrides


def parameter_names(node: Node) -> list[str]:
    """Return the node's declared parameters, in declaration order."""
    return list(node.list_parameters([], 0).names)


def unknown_overrides(node: Node) -> list[str]:
    """Names given at start that the node never declared.

    rclpy ignores such an override without a word (-p friction:=0.5 on a
    walker-walk-v1 sim ran on at the default foot length). Call it after the
    node's last declaration.
    """
    return sorted(name for name in _overrides(node) if not node.has_parameter(name))


def refuse_unknown_overrides(node: Node) -> None:
    """Raise UnknownParameters, naming the node's parameters, for an unknown override."""
    unknown = unknown_overrides(node)
    if unknown:
        raise UnknownParameters(f'unknown parameter {", ".join(unknown)}; '
                                f'{node.get_name()} has {", ".join(parameter_names(node))}')


def declare_double(node: Node, name: str, default: float,
                   descriptor: ParameterDescriptor) -> float:
    """Declare a double parameter that also takes an integer at start (-p friction:=1)."""
    override = _overrides(node).get(name)
    if override is not None and override.type_ == Parameter.Type.INTEGER:
        return node.declare_parameter(name, float(override.value), descriptor,
                                      ignore_override=True).value
    return node.declare_parameter(name, float(default), descriptor).value


def accept_integers_for_doubles(node: Node) -> None:
    """Let an integer set a double parameter (`ros2 param set /sim_node friction 1`).

    rclpy refuses it ('expected Type.DOUBLE got Type.INTEGER'), yet people type 1
    for 1.0. A pre-set callback turns it into that double before the type and
    range checks, so the parameter keeps its type and range. Idempotent (rclpy
    would run a second such callback and set each parameter twice).
    """
    if getattr(node, '_integers_as_doubles', False):
        return
    node._integers_as_doubles = True

    def as_doubles(params: list[Parameter]) -> list[Parameter]:
        return [Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
                if p.type_ == Parameter.Type.INTEGER and _is_double(node, p.name) else p
                for p in params]
    node.add_pre_set_parameters_callback(as_doubles)


def _is_double(node: Node, name: str) -> bool:
    return (node.has_parameter(name)
            and node.describe_parameter(name).type == ParameterType.PARAMETER_DOUBLE)


# `request`: the service type's Request message (any service's), passed on as it is.
def call_service(client: Client, request: object, wait: Wait, timeout: float = 30.0,
                 attempt_s: float = 3.0) -> Any:
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


class ResetRefused(RuntimeError):
    """The sim refused a reset request; the message says why."""


def reset_episode(client: Client, wait: Wait, seed: int = -1, params: dict | None = None,
                  timeout: float = 30.0) -> int:
    """Ask `sim_node` for a new episode and return its number (ResetRefused if refused).

    `seed` -1 keeps the random stream; `params` {name: value} are set first.
    `wait(predicate, seconds)` spins the client's node, as for `call_service`.
    """
    from zeus_msgs.srv import Reset
    params = params or {}
    request = Reset.Request(seed=int(seed), param_names=list(params),
                            param_values=[float(v) for v in params.values()])
    response = call_service(client, request, wait, timeout)
    if not response.success:
        raise ResetRefused(response.message)
    return int(response.episode)


def diagnostic_array(node: Node, name: str, hardware_id: str, values: dict,
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

    def __init__(self, logger: RcutilsLogger, period_s: float = 2.0):
        self.logger, self.period_s = logger, period_s
        self._last: dict[str, float] = {}

    def warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, float('-inf')) >= self.period_s:
            self._last[key] = now
            self.logger.warning(text)


class FirstContact:
    """A loop's timeouts before its first message are the start-up, not a fault.

    Nodes start in any order and a topic's first messages go out before every
    reader has matched, so a timeout before the awaited message has ever come
    is said once at INFO (`waiting`); after first contact each one is a
    throttled warning. The diagnostics count both either way.
    """

    def __init__(self, logger: RcutilsLogger, warnings: ThrottledWarnings, waiting: str):
        self.logger, self.warnings, self.waiting = logger, warnings, waiting
        self.contacted = False
        self._noted = False

    def seen(self) -> None:
        """Record that the awaited message came: from now on a timeout is a warning."""
        self.contacted = True

    def timed_out(self, key: str, text: str) -> bool:
        """Warn of a timeout after first contact; before it, note the wait once.

        Return whether contact was made (before it, a caller may hold back
        what it does on a timeout).
        """
        if self.contacted:
            self.warnings.warn(key, text)
        elif not self._noted:
            self._noted = True
            self.logger.info(self.waiting)
        return self.contacted


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


class StopRequested(BaseException):
    """The first SIGINT or SIGTERM, raised in the main thread while a node starts.

    A BaseException, like KeyboardInterrupt, so that no `except Exception` in
    start-up code swallows it.
    """


class StopSignals:
    """SIGINT and SIGTERM stop a node once, quietly; every later signal is ignored.

    With rclpy's own handlers a second SIGINT (a second Ctrl-C, or ros2 launch's
    on top of the terminal's) raised KeyboardInterrupt inside destroy_node, and
    one during start-up gave a traceback. Here the first signal, while the node
    starts, raises StopRequested, which abandons start-up wherever it is; once
    the node spins, it has a helper thread shut the context down, and spin_loop
    ends at its next wake-up (not the handler itself: it runs in the main
    thread, which may be holding the context's lock, and that lock does not
    nest). Once a stop is under way, signals do nothing.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.stopping = False   # a signal came or the node is closing: ignore signals
        self.spinning = False
        self._shutdown_wanted = threading.Event()

    def install(self) -> None:
        threading.Thread(target=self._shut_down_when_wanted, name='stop-signals',
                         daemon=True).start()
        for signum in self.SIGNALS:
            signal.signal(signum, self._handle)

    def ignore(self) -> None:
        """Ignore every signal from now on (the node is closing, then the process ends).

        SIG_IGN, not just the flag: at exit Python puts its own handlers back to
        the default action, and a second SIGINT then would end the process with -2.
        """
        self.stopping = True
        for signum in self.SIGNALS:
            signal.signal(signum, signal.SIG_IGN)

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        if self.stopping:
            return
        self.stopping = True
        if self.spinning:
            self._shutdown_wanted.set()
        else:
            raise StopRequested(signal.Signals(signum).name)

    def _shut_down_when_wanted(self) -> None:
        self._shutdown_wanted.wait()
        try:
            rclpy.try_shutdown()
        except Exception as error:  # noqa: BLE001 (the main thread closes the node anyway)
            print(f'stopping: {error}', file=sys.stderr)


def _rcl_reason(error: Exception) -> str:
    """Return rcl's error text without its prefix and source locations."""
    text = str(error).removeprefix('failed to initialize rcl: ')
    text = re.sub(r'(\. Error: error not set)?(, at \S+:\d+)+$', '', text)
    return text + (' (no value after :=)' if ":='" in text else '')


def _init_rclpy(args: list[str] | None) -> str | None:
    """rclpy.init without rclpy's signal handlers; returns why the command line is bad."""
    # rcl also logs 'Failed to parse global arguments' for a bad one: hushed for
    # the init, so that the refusal is one line (unless --log-level set rcl's).
    set_logger_level('rcl', LoggingSeverity.FATAL)
    profile = use_discovery_profile()   # before the participant exists: Fast DDS reads it then
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except _rclpy.UnknownROSArgsError as error:
        return f'unknown ROS arguments {error}'
    except _rclpy.RCLError as error:
        return f'bad command line: {_rcl_reason(error)}'
    finally:
        if get_logger_level('rcl') == LoggingSeverity.FATAL:
            set_logger_level('rcl', LoggingSeverity.UNSET)
    told = profile if profile is not None else "not zeus_ros's (yours, or none)"
    rclpy.logging.get_logger('zeus_ros.discovery').debug(f'Fast DDS participant profile: {told}')
    return None


# Seconds the start-up name check looks at the graph (unique_name); 0 leaves the
# duplicate-name refusal to the check that runs for the node's life.
NAME_WAIT_ENV = 'ZEUS_NAME_WAIT_S'


def name_wait_s() -> float:
    """Return the start-up name check's wait: $ZEUS_NAME_WAIT_S, else DISCOVERY_WAIT_S."""
    raw = os.environ.get(NAME_WAIT_ENV)
    if raw is None:
        return DISCOVERY_WAIT_S
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not value >= 0:   # also NaN
        raise BadParameter(f'{NAME_WAIT_ENV}={raw!r}: give seconds >= 0')
    return value


def _start(node_class: type[Node]) -> Node:
    """Build the node and check what it was given at start, before it spins."""
    created_at, started_ns = time.monotonic(), time.time_ns()
    node = node_class()
    # Its start record goes out now: other nodes' checks see it while this one starts.
    node.name_guard = NameGuard(node, started_ns)
    declare_thread_priority(node)
    declare_executor(node)
    refuse_unknown_overrides(node)
    accept_integers_for_doubles(node)
    apply_thread_priority(node)
    node.name_guard.check_at_start(created_at, name_wait_s())
    # Everything built so far (modules, weights, the node) lives for the
    # process: keep it out of the collector's full passes, which would
    # otherwise walk it every time and stall the loop for milliseconds.
    gc.freeze()
    # When a loop deadline comes while spin_loop's background thread runs
    # Python code, the loop thread gets the GIL within 1 ms, not 5.
    sys.setswitchinterval(0.001)
    return node


def _close(nodes: list, name: str) -> None:
    """Destroy the nodes and shut rclpy down, whatever state a stop left them in."""
    steps = [node.destroy_node for node in reversed(nodes)] + [rclpy.try_shutdown]
    for step in steps:
        try:
            step()
        except Exception as error:  # noqa: BLE001 (closing anyway: say so in a line, go on)
            print(f'{name}: while closing: {error}', file=sys.stderr)


def run_node(node_class: type[Node], args: list[str] | None = None, fatal: tuple = ()) -> int:
    """Spin one node with `spin_loop` until SIGINT, SIGTERM or shutdown; return the exit code.

    0 after a signal at any moment, once or repeatedly (see StopSignals). 1,
    with one line on stderr, for a bad command line, a parameter given at start
    that the node refuses (out of range, wrong type) or does not have, an older
    node of its name on the graph (at start or later: zeus_ros.ros.unique_name),
    or a `fatal` error. A node's `on_started()`, if it has one, is called once
    every check has passed, just before it spins: work that must not begin
    before (the sim's camera thread) starts there.
    """
    return run_nodes((node_class,), args, fatal)


def run_nodes(node_classes: Sequence[type[Node]], args: list[str] | None = None,
              fatal: tuple = (), name: str | None = None) -> int:
    """`run_node` for several nodes in one process, on one `spin_loop` (composition).

    They are built in order with one rclpy context (per-node parameters:
    `-p node_name:param:=value`), share the loop thread, and stop together: a
    signal, a fatal error or a failed start of any one ends them all. Messages
    name the node being started, else `name` (default: the one node's class).
    """
    stop = StopSignals()
    name = name or node_classes[0].__name__
    try:
        stop.install()
        end_with_launcher()   # a launcher's end is a SIGTERM to its nodes (parent_watch)
        return _run(tuple(node_classes), args, fatal, stop, name)
    except StopRequested:
        return 0  # the first signal came while a failed start-up was being reported


def _start_failure(error: Exception, where: str, fatal: tuple) -> int:
    """Exit code 1 and one line for an error a user can fix; re-raise any other."""
    if isinstance(error, ParameterException):
        # rclpy words it '<reason>: <parameter name>'; name first reads better.
        reason, _, parameter = str(error).rpartition(': ')
        print(f'{where}: parameter {parameter}: {reason}', file=sys.stderr)
        return 1
    if isinstance(error, (UnknownParameters, BadParameter, DuplicateNode, *fatal)):
        print(f'{where}: {error}', file=sys.stderr)
        return 1
    raise error


def _run(node_classes: tuple, args: list[str] | None, fatal: tuple, stop: StopSignals,
         name: str) -> int:
    where, nodes = name, []
    try:
        problem = _init_rclpy(args)
        if problem is not None:
            print(f'{name}: {problem}', file=sys.stderr)
            return 1
        for node_class in node_classes:
            where = node_class.__name__
            nodes.append(_start(node_class))
        for node in nodes:   # every check passed: what waited for it may begin
            where = type(node).__name__
            if hasattr(node, 'on_started'):
                node.on_started()
        where = name
        stop.spinning = True
        spin_loop(*nodes, executor=nodes[0].get_parameter('executor').value)
    except (StopRequested, ExternalShutdownException):
        pass
    # Every error is sorted here: a stop's, a user's (one line, exit 1), or re-raised.
    except Exception as error:  # noqa: BLE001
        if stop.stopping:
            # A signal came first: whatever failed after it failed because of the
            # stop (native code, e.g. safetensors' loader, turns the StopRequested
            # raised inside it into an error of its own), so this is the stop asked for.
            return 0
        return _start_failure(error, where, fatal)
    finally:
        stop.ignore()
        _close(nodes, name)
    return 0
