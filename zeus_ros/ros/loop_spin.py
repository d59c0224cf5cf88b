"""A lean spin for the control loop's hot path.

rclpy's executors rebuild a wait set over every entity of a node and wrap each
callback in a Task at every wake-up; on this 2-core machine that costs more
than the message hop itself, and a control step crosses three hops (see
docs/pages/benchmarks.md). `spin_loop` splits a node's work in two:

* the LOOP subscriptions (created with `create_loop_subscription`) are waited
  on in the calling thread through one small wait set, and every ready
  message is taken straight into its callback;
* everything else the node has (parameter services for `ros2 param set`, other
  services, timers such as the 1 Hz diagnostics) stays with rclpy's
  SingleThreadedExecutor, spinning in a background thread that sleeps until
  one of them is due.

The node may also have one loop DEADLINE (`loop_deadline()` returning a
`LoopDeadline` or None): the realtime control tick, the lockstep command
watchdog. The loop's wait ends at it. The wait on messages returns late
(here: 0.25 ms at the median, 1 ms at p99; a plain sleep: 0.19 / 0.37 ms), so
a deadline that must be punctual (the realtime tick) asks for `sleep_lead_s`:
that long before it, the loop stops waiting on messages, sleeps until the
deadline, takes what arrived meanwhile, then fires it. (Polling instead of
sleeping was worse: a spinning process loses the CPU to the sleeping ones it
competes with on two cores, right when it must act.)

Callbacks never run concurrently: both threads run them under one lock, and
the background thread wakes the loop after each of its callbacks (a reset or a
parameter change may have moved the deadline).

The background executor is rclpy's SingleThreadedExecutor, or with
`executor='events'` its experimental EventsExecutor (callbacks called from the
middleware's events, no wait set), driven by spin_once with a timeout: its
spin() fires a timer at most once in the pinned rclpy 7.1.6 wheel (see
research/benchmarks/events_executor_repro.py for why).
"""

from __future__ import annotations

import functools
import threading
import time
from typing import Callable, NamedTuple, Sequence, TYPE_CHECKING

from rclpy.callback_groups import CallbackGroup
from rclpy.executors import (ConditionReachedException, Executor, ExternalShutdownException,
                             ShutdownException, SingleThreadedExecutor, TimeoutException,
                             TimeoutObject)
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.subscription import Subscription

if TYPE_CHECKING:
    # The native classes behind _rclpy.GuardCondition and _rclpy.WaitSet.
    from rclpy._rclpy_pybind11 import GuardCondition, WaitSet
    from rclpy.client import Client
    from rclpy.context import Context
    from rclpy.qos import QoSProfile
    from rclpy.service import Service
    from rclpy.timer import Timer
    from rclpy.waitable import Waitable

    # What a callback group is asked about: any entity of a node.
    Entity = Subscription | Timer | Client | Service | Waitable

# Longest the loop sleeps without a message or deadline (it then checks shutdown).
IDLE_WAKE_S = 0.1
# The background executors spin_loop offers (the `executor` node parameter).
EXECUTORS = ('single', 'events')


class LoopDeadline(NamedTuple):
    """When the node must act without a message, and what to call then."""

    when: float                  # time.monotonic() seconds
    callback: Callable[[], None]
    sleep_lead_s: float = 0.0    # plain sleep, not a wait on messages, this long before `when`


class LoopCallbackGroup(CallbackGroup):
    """Marks the loop's subscriptions: `spin_loop` takes them, rclpy's executors never do."""

    def can_execute(self, entity: Entity) -> bool:  # noqa: D102, ARG002 (CallbackGroup's)
        return False

    def beginning_execution(self, entity: Entity) -> bool:  # noqa: D102, ARG002 (CallbackGroup's)
        return False

    def ending_execution(self, entity: Entity) -> None:  # noqa: D102
        pass


def create_loop_subscription(node: Node, msg_type: type, topic: str, callback: Callable,
                             qos: QoSProfile | int, **options) -> Subscription:
    """Create a subscription on the control loop's hot path (see `spin_loop`).

    `options` go to `Node.create_subscription` (e.g. raw=True for CDR bytes).
    """
    group = getattr(node, '_loop_callback_group', None)
    if group is None:
        group = node._loop_callback_group = LoopCallbackGroup()
    return node.create_subscription(msg_type, topic, callback, qos, callback_group=group,
                                    **options)


def loop_subscriptions(node: Node) -> list:
    """Return the node's subscriptions created with `create_loop_subscription`."""
    return [sub for sub in node.subscriptions
            if isinstance(sub.callback_group, LoopCallbackGroup)]


class _SerializedExecutor(SingleThreadedExecutor):
    """rclpy's executor, running each callback under the loop's lock, then waking the loop.

    It overrides SingleThreadedExecutor's private `_spin_once_impl` (the same
    steps, plus the lock and the wake-up), which is written against rclpy
    7.1.6 as pinned in requirements.lock: check it when rclpy is upgraded.
    """

    def __init__(self, lock: threading.Lock, wake_loop: GuardCondition, context: Context):
        super().__init__(context=context)
        self._lock, self._wake_loop = lock, wake_loop

    def _spin_once_impl(self, timeout_sec: float | TimeoutObject | None = None,
                        wait_condition: Callable[[], bool] = lambda: False) -> None:
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ShutdownException, TimeoutException, ConditionReachedException):
            return
        with self._lock:
            handler()
        self._wake_loop.trigger_guard_condition()
        if handler.exception() is not None:
            raise handler.exception()
        handler.result()


def _serialized(callback: Callable, lock: threading.Lock, wake_loop: GuardCondition,
                errors: list[BaseException]) -> Callable:
    """Wrap `callback` to run under the loop's lock, then wake the loop (signature kept).

    An exception goes to `errors`, which ends the loop and is raised by
    spin_loop, as with the single executor: left to the EventsExecutor, it
    was first logged as FATAL with its stack (a node refusing a duplicate name
    said more than its one line).
    """
    @functools.wraps(callback)   # Subscription reads the signature to choose its call
    def run(*args):
        try:
            with lock:
                return callback(*args)
        except Exception as error:  # noqa: BLE001 (handed to the loop thread to re-raise)
            errors.append(error)
            return None
        finally:
            wake_loop.trigger_guard_condition()
    return run


class _ServicesView:
    """What the EventsExecutor is given of a node: everything but the loop's subscriptions.

    The EventsExecutor ignores callback groups, so it would take the loop's
    messages too; it reads only these attributes. Each callback is wrapped once
    to run under the loop's lock (QoS-event waitables only log, and are left as
    they are). Entities a node creates after spin_loop started are not seen:
    the nodes create theirs in __init__.
    """

    def __init__(self, node: Node, lock: threading.Lock, wake_loop: GuardCondition,
                 errors: list[BaseException]):
        self.node, self.executor = node, None   # add_node sets `executor`
        for entity in (*self.subscriptions, *node.timers, *node.services):
            entity.callback = _serialized(entity.callback, lock, wake_loop, errors)

    @property
    def subscriptions(self) -> list:
        loop = set(loop_subscriptions(self.node))
        return [sub for sub in self.node.subscriptions if sub not in loop]

    def __getattr__(self, name: str):   # timers, services, clients, waitables, guards
        return getattr(self.node, name)


def _services_executor(kind: str, nodes: Sequence[Node], lock: threading.Lock,
                       wake_loop: GuardCondition, context: Context,
                       errors: list[BaseException]) -> Executor:
    """Build the background executor `kind` (EXECUTORS) over `nodes`' services and timers.

    A callback's exception goes to `errors` (the events one's; the single
    one's spin_once raises it, and `_spin_services` hands it over).
    """
    if kind == 'events':
        executor = EventsExecutor(context=context)
        for each in nodes:
            executor.add_node(_ServicesView(each, lock, wake_loop, errors))
        return executor
    if kind != 'single':
        raise ValueError(f"executor {kind!r}: use one of {', '.join(EXECUTORS)}")
    executor = _SerializedExecutor(lock, wake_loop, context)
    for each in nodes:
        executor.add_node(each)
    return executor


def spin_in_background(node: Node) -> threading.Thread:
    """Run `spin_loop(node)` in a daemon thread, for tools that wait in their main thread.

    It ends when the node's context shuts down; join it before destroying the node.
    """
    spinner = threading.Thread(target=spin_loop, args=(node,), name='spin-loop', daemon=True)
    spinner.start()
    return spinner


def wait_until(predicate: Callable[[], object], timeout: float, poll_s: float = 0.002) -> bool:
    """Poll `predicate()` until it is truthy (True) or `timeout` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll_s)
    return True


def _spin_services(executor: Executor, errors: list[BaseException]) -> None:
    # Always with a timeout: the EventsExecutor's wait without one never sleeps.
    try:
        while executor.context.ok() and not errors:   # an error ends the loop: stop too
            executor.spin_once(timeout_sec=IDLE_WAKE_S)
    except ExternalShutdownException:
        pass
    except BaseException as error:  # noqa: BLE001 (handed to the loop thread to re-raise)
        errors.append(error)


def _take_all(subscription: Subscription) -> None:
    """Deliver every message waiting on a subscription to its callback."""
    handle, msg_type, raw, callback = (subscription.handle, subscription.msg_type,
                                       subscription.raw, subscription.callback)
    while True:
        taken = handle.take_message(msg_type, raw)
        if taken is None:
            return
        callback(taken[0])


def spin_loop(node: Node, *more: Node, executor: str = 'single') -> None:
    """Spin `node` (and `more` nodes of its context) until the context shuts down.

    Several nodes (composition: the three in one process) share the one loop
    thread, its wait set and lock, and one background executor: a message one
    of them publishes reaches the next in the same thread, with no wake-up of
    another (see the module docstring). The loop's deadline is the earliest of
    theirs.

    An exception raised by any callback, in either thread, ends the spin and
    is raised here, unless the context was shut down meanwhile (Ctrl-C while a
    callback was publishing): then the spin just ends. `executor` (EXECUTORS)
    chooses the background one.
    """
    nodes = (node, *more)
    context = node.context
    lock = threading.Lock()
    wake_loop = _rclpy.GuardCondition(context.handle)
    errors: list[BaseException] = []
    background = _services_executor(executor, nodes, lock, wake_loop, context, errors)
    services = threading.Thread(target=_spin_services, args=(background, errors),
                                name='rclpy-executor', daemon=True)
    services.start()
    subscriptions = [sub for each in nodes for sub in loop_subscriptions(each)]
    try:
        _loop(context, lock, wake_loop, _earliest_deadline(nodes), subscriptions, errors,
              sweep=len(nodes) > 1)
    except Exception:
        if context.ok():
            raise
    finally:
        background.shutdown(timeout_sec=1.0)
        services.join(timeout=1.0)
    if errors and context.ok():
        raise errors[0]


def _earliest_deadline(nodes: Sequence[Node]) -> Callable[[], LoopDeadline | None]:
    """Return a function giving the earliest `loop_deadline()` of `nodes` (None: none)."""
    getters = [node.loop_deadline for node in nodes if hasattr(node, 'loop_deadline')]
    if len(getters) == 1:
        return getters[0]   # one node: no list to build at every wake-up

    def earliest() -> LoopDeadline | None:
        deadlines = [d for d in (get() for get in getters) if d is not None]
        return min(deadlines, key=lambda d: d.when) if deadlines else None
    return earliest


def _loop(context: Context, lock: threading.Lock, wake_loop: GuardCondition,
          deadline_of: Callable[[], LoopDeadline | None], subscriptions: list[Subscription],
          errors: list[BaseException], sweep: bool = False) -> None:
    """Wait for loop messages or the deadline and dispatch them, until shutdown or an error."""
    wait_set = _rclpy.WaitSet(len(subscriptions), 1, 0, 0, 0, 0, context.handle)
    while context.ok() and not errors:
        with lock:
            deadline = deadline_of()
            now = time.monotonic()
            if deadline is not None and now >= deadline.when:
                deadline.callback()
                continue
        timeout = IDLE_WAKE_S
        if deadline is not None:
            timeout = min(timeout, deadline.when - deadline.sleep_lead_s - now)
            if timeout <= 0:
                time.sleep(deadline.when - now)
                timeout = 0.0  # take what arrived while sleeping; the deadline fires next
        wait_set.clear_entities()
        for subscription in subscriptions:
            wait_set.add_subscription(subscription.handle)
        wait_set.add_guard_condition(wake_loop)
        wait_set.wait(int(timeout * 1e9))
        if context.ok():
            _dispatch(wait_set, lock, subscriptions, sweep)


def _dispatch(wait_set: WaitSet, lock: threading.Lock, subscriptions: list[Subscription],
              sweep: bool) -> None:
    """Deliver what the wait found; with `sweep`, try every subscription in order.

    Nodes of one process (composition) hand each other their messages inside
    the publishing call, so a subscription later in the order has a message
    that the wait did not report: trying every one, in the order a control
    step crosses the nodes, carries a whole step per wake-up (composed: 608-627
    against 494-521 steps/s in one run). A lone node only takes what the wait
    reported: its peers are other processes, and the tries found too little
    (343-402 against 448-452 steps/s, same run).
    """
    if sweep:
        with lock:
            for subscription in subscriptions:
                _take_all(subscription)
        return
    ready = wait_set.get_ready_entities('subscription')
    if ready:
        with lock:
            for subscription in subscriptions:
                if subscription.handle.pointer in ready:
                    _take_all(subscription)
