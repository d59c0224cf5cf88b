"""Soak the lockstep loop: live swaps, a kill -9 and restart of every node, figures per minute.

    python research/benchmarks/soak.py --minutes 30 [--weights weights/walker-walk-slippery-zeus]

Starts sim_node, context_node and policy_node in lockstep (the command lines
`bringup` builds), observes /zeus/step and /diagnostics from an rclpy node in
this process, swaps the family's parameter every --swap-every seconds over its
live range (the sim's parameter service), and kills (SIGKILL) and restarts
each node once, at the --restart-at fractions of the run, in the order
sim_node, context_node, policy_node. A node that exits on its own is a crash:
it is recorded and restarted, so that the soak goes on.

Reports, and writes as JSON (--json): steps/s per minute (all steps, and the
controlled ones: non-zero applied action); stalls (gaps between consecutive
StepInfo messages > --stall-seconds); crashes; for each restart, the time from
the new process's spawn and from its start-up line until control is back (a
non-zero applied action in StepInfo again); VmRSS per process per minute and
its growth from minute --rss-baseline-minutes to the process's end. The goals
(issue 17): 0 crashes, control back within 2 s of a restarted node's start
(taken as its start-up line: the first line it logs, once its imports and
weights are loaded), RSS growth < 5 %, no stall > 1 s outside a restart's
recovery (from its kill to 2 s after the new start-up line). Exit code 0 when
every goal is met, 1 when one is missed, 2 when the soak could not run or its figures are not valid
(signs of another loop on the same ROS domain).

The run's clock starts when the loop first closes. The sim's own downtime
(from its kill to the first step of the new sim) has no StepInfo at all; that
gap is reported but is not counted as a stall.
"""

from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import asdict, dataclass, field
import gc
import json
import math
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Callable

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from sim_node.families import get_family  # noqa: E402
from zeus_msgs.msg import StepInfo  # noqa: E402
from zeus_ros.ros_tools.bringup import node_commands, NODES, parse_args as bringup_args  # noqa: E402
from zeus_ros.deploy.checkpoint import load_metadata  # noqa: E402
from zeus_ros.deploy.metadata import CheckpointMetadata  # noqa: E402
from zeus_ros.ros.discovery import use_discovery_profile  # noqa: E402
from zeus_ros.ros.loop_spin import (create_loop_subscription, spin_in_background,  # noqa: E402
                                wait_until)
from zeus_ros.ros.util import call_service, LOOP_QOS, stamp_ns  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
NODE_NAMES = tuple(name for name, _ in NODES)
# rcutils' default format, set explicitly: the restart figures read the
# wall-clock time of a node's start-up line from its log.
LOG_FORMAT = '[{severity}] [{time}] [{name}]: {message}'
LOG_LINE = re.compile(r'^\[(DEBUG|INFO|WARN|ERROR|FATAL)\] \[(\d+\.\d+)\]')
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


class SoakError(RuntimeError):
    """The soak could not run (the loop never closed, bad weights)."""


@dataclass(frozen=True)
class SoakConfig:
    weights: Path
    minutes: float
    swap_every_s: float = 10.0
    restart_at: tuple[float, ...] = (0.25, 0.5, 0.75)   # fractions, for NODE_NAMES in order
    # Faults to check the goals with: (node, fraction, seconds) SIGSTOPs, each
    # ended by a SIGCONT; the node neither dies nor restarts.
    pauses: tuple[tuple[str, float, float], ...] = ()
    down_s: float = 2.0              # a killed node stays down this long
    stall_s: float = 1.0
    control_goal_s: float = 2.0
    rss_goal_pct: float = 5.0
    rss_baseline_minutes: float = 2.0
    rss_every_s: float = 1.0
    startup_timeout_s: float = 120.0
    log_dir: Path | None = None


# ---- results ---------------------------------------------------------------------------

@dataclass
class MinuteRate:
    minute: int                      # 1-based minute of the run
    seconds: float                   # its length (the last one may be partial)
    steps_per_s: float
    controlled_steps_per_s: float    # steps whose applied action was not all zeros
    # Steps the sim took on a zero action (no fresh command: the lockstep
    # timeout, or a rejected command), and swaps unanswered within their 5 s.
    uncontrolled_steps: int = 0
    unanswered_swaps: int = 0


@dataclass
class Spell:
    """Consecutive uncontrolled steps: the loop ran on, nothing controlled it."""

    at_s: float                      # run time of its first uncontrolled step
    seconds: float                   # to the next controlled step (or the run's end)
    steps: int
    # Seconds of it outside every restart's recovery (kill -> start-up line +
    # the control goal): what the goal judges.
    outside_restarts_s: float = 0.0


@dataclass
class Stall:
    at_s: float                      # run time of the last StepInfo before the gap
    seconds: float
    sim_down: bool                   # the gap holds a deliberate kill of the sim
    # The part of the gap outside every restart's recovery window (kill to
    # start-up line + control goal): what the stall goal judges. A restarted
    # sim waits for its first command until the policy has discovered it; that
    # wait is the restart's, judged by the control-back goal.
    outside_restarts_s: float
    # (episode, step) of the StepInfo on either side (None: still stalled at the
    # end). Consecutive steps: the loop itself stood still; a jump: steps were
    # taken that this observer never received.
    before: tuple[int, int]
    after: tuple[int, int] | None


@dataclass
class Crash:
    node: str
    pid: int
    exit_code: int
    at_s: float
    log_tail: list[str]


@dataclass
class RestartResult:
    node: str
    cause: str                       # 'soak' (killed with SIGKILL) or 'crash'
    old_pid: int
    new_pid: int
    killed_at_s: float | None
    spawned_at_s: float
    startup_line_at_s: float | None  # the new process's first log line
    first_step_at_s: float | None    # first StepInfo received after the spawn
    control_back_at_s: float | None
    control_back_after_spawn_s: float | None
    control_back_after_startup_s: float | None
    # The first StepInfo seen after the spawn was already controlled: control
    # may have come back earlier than seen (the observer had not yet matched a
    # restarted sim's writer), so the figures above are upper bounds.
    upper_bound: bool


@dataclass
class ProcessRss:
    node: str
    incarnation: int                 # 1 = started with the soak, 2 = after a restart...
    pid: int
    started_at_s: float
    ended_at_s: float | None
    exit_code: int | None
    killed_by_soak: bool
    per_minute_mb: list[float | None]  # VmRSS at the end of each run minute it lived in
    baseline_at_s: float | None
    baseline_mb: float | None
    end_mb: float | None
    growth_pct: float | None         # None: the process did not outlive its baseline


@dataclass
class SwapStats:
    requested: int = 0
    accepted: int = 0
    refused: int = 0
    unanswered: int = 0
    unanswered_at: list[float] = field(default_factory=list)   # monotonic, when given up
    skipped_sim_down: int = 0        # the sim was killed, or its service not (yet) ready
    seen_in_steps: int = 0           # accepted values later seen in StepInfo.param_values
    values: list[float] = field(default_factory=list)
    refusals: list[str] = field(default_factory=list)


@dataclass
class Goal:
    name: str
    met: bool
    detail: str


@dataclass
class SoakResult:
    family: str
    weights: str
    param_name: str
    live_range: tuple[float, float]
    minutes: float
    duration_s: float
    machine: str
    ros_domain_id: str
    load_avg_start: float
    load_avg_end: float
    steps_total: int
    per_minute: list[MinuteRate]
    stalls: list[Stall]
    max_gap_s: float
    uncontrolled_steps: int
    uncontrolled_spells: list[Spell]
    crashes: list[Crash]
    restarts: list[RestartResult]
    rss: list[ProcessRss]
    swaps: SwapStats
    diagnostics: dict
    goals: list[Goal]
    passed: bool
    # Signs of another graph on this ROS domain; a run with any is not valid.
    interference: list[str]
    log_dir: str


# ---- observer --------------------------------------------------------------------------

@dataclass(frozen=True)
class Gap:
    start: float                     # monotonic receipt time of the StepInfo before it
    seconds: float
    before: tuple[int, int]          # (episode, step) before and after
    after: tuple[int, int] | None


@dataclass(frozen=True)
class UncontrolledRun:
    start: float                     # monotonic receipt time of its first step
    end: float                       # of the next controlled step (or the run's end)
    steps: int


@dataclass
class Watch:
    """What the observer saw of the loop after a moment (a restarted node's spawn)."""

    since: float
    first_step_at: float | None = None
    control_at: float | None = None

    def see(self, now: float, controlled: bool) -> None:
        if self.first_step_at is None:
            self.first_step_at = now
        if controlled and self.control_at is None:
            self.control_at = now


class Observer:
    """Counts StepInfo per minute, gaps between them, and keeps the nodes' diagnostics.

    /zeus/step is taken with `spin_loop` in a background thread, as the nodes
    take their loop topics: rclpy's executor would not keep up with the loop
    on two cores. Nothing per message is kept (a 30-minute run is ~10^6
    steps): counters per minute and the gaps longer than `stall_s`.
    """

    def __init__(self, node, stall_s: float, family: str):
        self.stall_s, self.family = stall_s, family
        # Another graph on this ROS domain makes the figures meaningless: its
        # StepInfo shows another family, or its clock interleaves with ours
        # (the sim clock only goes back when the sim is restarted).
        self.foreign_steps = 0
        self.clock_backsteps = 0
        self.last_stamp = -1
        self.t0: float | None = None       # set once the loop closed: the run's clock
        self.closed = False                # the run is over: what the stop does is not counted
        self.last_at: float | None = None
        self.last_step: tuple[int, int] = (-1, -1)
        self.steps: list[int] = []
        self.controlled: list[int] = []
        self.uncontrolled: list[int] = []
        self.runs: list[UncontrolledRun] = []
        self.run_start: float | None = None    # the current uncontrolled run's first step
        self.run_steps = 0
        self.gaps: list[Gap] = []
        self.last_param: float | None = None
        # Replaced whole, never appended to: the callback may be iterating it.
        self.watches: tuple[Watch, ...] = ()
        self.diagnostics: dict[str, dict[str, str]] = {}
        self.warnings: dict[str, Counter] = {}
        create_loop_subscription(node, StepInfo, '/zeus/step', self._on_step, LOOP_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        self.spinner = spin_in_background(node)

    def watch(self, since: float) -> Watch:
        watch = Watch(since)
        self.watches = (*self.watches, watch)
        return watch

    def _on_step(self, msg: StepInfo) -> None:
        if self.closed:
            return
        now = time.monotonic()
        if msg.family != self.family:
            self.foreign_steps += 1
            return
        stamp = stamp_ns(msg.header)
        self.clock_backsteps += stamp < self.last_stamp
        self.last_stamp = stamp
        controlled = any(msg.applied_action)
        # An empty action is the first state of an episode: no step was taken.
        self._count_uncontrolled(now, controlled, bool(msg.applied_action))
        step = (msg.episode, msg.step)
        if self.last_at is not None and now - self.last_at > self.stall_s:
            self.gaps.append(Gap(self.last_at, now - self.last_at, self.last_step, step))
        self.last_at, self.last_step = now, step
        if msg.param_values:
            self.last_param = msg.param_values[0]
        for watch in self.watches:
            if watch.control_at is None and now >= watch.since:
                watch.see(now, controlled)
        if self.t0 is not None:
            minute = int((now - self.t0) // 60.0)
            while len(self.steps) <= minute:
                self.steps.append(0)
                self.controlled.append(0)
                self.uncontrolled.append(0)
            self.steps[minute] += 1
            self.controlled[minute] += controlled
            self.uncontrolled[minute] += bool(msg.applied_action) and not controlled

    def _count_uncontrolled(self, now: float, controlled: bool, stepped: bool) -> None:
        if controlled and self.run_start is not None:
            self.end_run(now)
        elif stepped and not controlled and self.t0 is not None:
            if self.run_start is None:
                self.run_start, self.run_steps = now, 0
            self.run_steps += 1

    def end_run(self, now: float) -> None:
        """Close the current uncontrolled run at `now` (a controlled step, or the run's end)."""
        if self.run_start is not None:
            self.runs.append(UncontrolledRun(self.run_start, now, self.run_steps))
            self.run_start = None

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            node = status.name.split(':')[0]
            self.diagnostics[status.name] = {kv.key: kv.value for kv in status.values}
            if status.level != DiagnosticStatus.OK:
                # Counted by kind: '3 command timeouts in the last 10 s' and '5 ...'
                # are one kind, 'N command timeouts in the last N s'.
                kind = re.sub(r'\d+(\.\d+)?', 'N', status.message)
                self.warnings.setdefault(node, Counter())[kind] += 1


# ---- node processes --------------------------------------------------------------------

@dataclass
class NodeProc:
    """One process of a node, from spawn to exit."""

    node: str
    incarnation: int
    popen: subprocess.Popen
    log_path: Path
    spawned_at: float                              # monotonic
    killed_at: float | None = None                 # set when the soak killed it
    ended_at: float | None = None
    rss_kb: list[tuple[float, int]] = field(default_factory=list)   # (monotonic, kB)


def read_rss_kb(pid: int) -> int | None:
    """VmRSS of a live process in kB (None once it is gone)."""
    try:
        with open(f'/proc/{pid}/status') as status:
            for line in status:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def log_tail(path: Path, lines: int = 10) -> list[str]:
    try:
        return path.read_text(errors='replace').splitlines()[-lines:]
    except FileNotFoundError:
        return []


def startup_line_monotonic(path: Path) -> float | None:
    """Monotonic time of a node's first log line (its start-up line), from the log's clock."""
    try:
        text = path.read_text(errors='replace')
    except FileNotFoundError:
        return None
    for line in text.splitlines():
        match = LOG_LINE.match(line)
        if match:
            return float(match.group(2)) - (time.time() - time.monotonic())
    return None


class Supervisor:
    """The three node processes: spawn, kill -9, crash detection, RSS sampling, stop."""

    def __init__(self, commands: dict[str, list[str]], log_dir: Path):
        self.commands, self.log_dir = commands, log_dir
        self.current: dict[str, NodeProc] = {}
        self.history: list[NodeProc] = []
        self.env = {**os.environ, 'PYTHONUNBUFFERED': '1',
                    'RCUTILS_CONSOLE_OUTPUT_FORMAT': LOG_FORMAT}

    def spawn(self, node: str) -> NodeProc:
        incarnation = 1 + sum(p.node == node for p in self.history)
        log_path = self.log_dir / f'{node}_{incarnation}.log'
        with open(log_path, 'w') as log:
            # cwd outside the source tree: `python -m` then imports the colcon
            # install (PYTHONPATH), as `ros2 run` would. A session of its own:
            # a Ctrl-C in the terminal reaches the soak only, which stops them.
            popen = subprocess.Popen(self.commands[node], stdout=log, stderr=subprocess.STDOUT,
                                     env=self.env, cwd=self.log_dir, start_new_session=True)
        proc = NodeProc(node, incarnation, popen, log_path, time.monotonic())
        self.current[node] = proc
        self.history.append(proc)
        return proc

    def kill9(self, node: str) -> NodeProc:
        proc = self.current[node]
        proc.killed_at = time.monotonic()
        proc.popen.send_signal(signal.SIGKILL)
        proc.popen.wait()
        proc.ended_at = time.monotonic()
        return proc

    def exited_unasked(self) -> list[NodeProc]:
        """Return the current processes that exited unasked (crashes), marking them ended."""
        crashed = []
        for proc in self.current.values():
            if proc.killed_at is None and proc.ended_at is None and proc.popen.poll() is not None:
                proc.ended_at = time.monotonic()
                crashed.append(proc)
        return crashed

    def sample_rss(self) -> None:
        now = time.monotonic()
        for proc in self.current.values():
            if proc.ended_at is None:
                kb = read_rss_kb(proc.popen.pid)
                if kb is not None:
                    proc.rss_kb.append((now, kb))

    def stop(self, timeout: float = 10.0) -> None:
        """SIGINT every live node (README: it then exits 0), SIGKILL what outlasts the timeout."""
        live = [p for p in self.current.values() if p.popen.poll() is None]
        for proc in live:
            proc.popen.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        for proc in live:
            try:
                proc.popen.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                proc.popen.kill()
                proc.popen.wait()
            proc.ended_at = proc.ended_at or time.monotonic()


# ---- swaps -----------------------------------------------------------------------------

class Swapper:
    """Live swaps of the family's parameter through the sim's parameter service."""

    def __init__(self, node, param_name: str, live_range: tuple[float, float]):
        self.client = node.create_client(SetParameters, '/sim_node/set_parameters')
        self.param_name, self.live_range = param_name, live_range
        self.stats = SwapStats()
        self.pending: float | None = None     # accepted, not yet looked for in StepInfo

    def value(self, index: int) -> float:
        # Golden-ratio steps: consecutive swaps land far apart, and the values
        # fill the live range evenly however long the run.
        lo, hi = self.live_range
        return round(lo + (hi - lo) * ((0.5 + index * GOLDEN) % 1.0), 4)

    def check_seen(self, last_param: float | None) -> None:
        """Count the previous swap as seen if the loop's latest StepInfo carries it."""
        if self.pending is not None and last_param == self.pending:
            self.stats.seen_in_steps += 1
        self.pending = None

    def swap(self, last_param: float | None, sim_up: Callable[[], bool]) -> None:
        self.check_seen(last_param)
        if not sim_up() or not self.client.service_is_ready():
            self.stats.skipped_sim_down += 1
            return
        value = self.value(self.stats.requested)
        self.stats.requested += 1
        self.stats.values.append(value)
        request = SetParameters.Request(
            parameters=[Parameter(self.param_name, value=value).to_parameter_msg()])
        try:
            # Short attempts: a sim killed a moment ago may still look ready.
            response = call_service(self.client, request, wait_until, timeout=5.0,
                                    attempt_s=1.0)
        except TimeoutError:
            if sim_up():
                self.stats.unanswered += 1
                self.stats.unanswered_at.append(time.monotonic())
            else:   # killed by the soak while the request was out
                self.stats.skipped_sim_down += 1
            return
        result = response.results[0]
        if result.successful:
            self.stats.accepted += 1
            self.pending = value
        else:
            self.stats.refused += 1
            self.stats.refusals.append(f'{value:g}: {result.reason}')


# ---- the run ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Event:
    at_s: float                      # run time
    kind: str                        # 'kill', 'restart', 'stop' or 'cont'
    node: str = ''


@dataclass
class Restart:
    """A node process replaced during the run, and what the observer saw after."""

    cause: str
    old: NodeProc
    new: NodeProc
    watch: Watch


def schedule(cfg: SoakConfig) -> list[Event]:
    duration = cfg.minutes * 60.0
    events = []
    # restart_at is empty (no restart) or has one fraction per node.
    for node, fraction in zip(NODE_NAMES[:len(cfg.restart_at)], cfg.restart_at, strict=True):
        events += [Event(fraction * duration, 'kill', node),
                   Event(fraction * duration + cfg.down_s, 'restart', node)]
    for node, fraction, seconds in cfg.pauses:
        events += [Event(fraction * duration, 'stop', node),
                   Event(fraction * duration + seconds, 'cont', node)]
    return sorted(events, key=lambda event: event.at_s)


class Soak:
    """The soak's main thread: fires the schedule, samples RSS, restarts crashed nodes."""

    def __init__(self, cfg: SoakConfig, supervisor: Supervisor, observer: Observer,
                 swapper: Swapper):
        self.cfg, self.sup, self.observer, self.swapper = cfg, supervisor, observer, swapper
        self.t0 = math.nan
        self.end = math.nan
        self.restarts: list[Restart] = []
        self.crashes: list[Crash] = []
        self.sim_kills: list[float] = []

    def rel(self, when: float | None = None) -> float:
        return (time.monotonic() if when is None else when) - self.t0

    def start(self) -> None:
        """Spawn the nodes and wait for the loop to close: the run's clock starts then."""
        for node in NODE_NAMES:
            self.sup.spawn(node)
        first = self.observer.watch(time.monotonic())
        wait_until(lambda: first.control_at is not None or self.sup.exited_unasked(),
                   self.cfg.startup_timeout_s, poll_s=0.05)
        if first.control_at is None:
            dead = [p for p in self.sup.current.values() if p.ended_at is not None]
            detail = '; '.join(f'{p.node} exited {p.popen.returncode}: '
                               f'{" | ".join(log_tail(p.log_path, 3))}' for p in dead)
            raise SoakError('the loop never closed (no non-zero applied action within '
                            f'{self.cfg.startup_timeout_s:g} s){"; " if dead else ""}{detail}')
        self.t0 = self.observer.t0 = first.control_at

    def run(self) -> None:
        duration = self.cfg.minutes * 60.0
        events = schedule(self.cfg)
        next_rss = 0.0
        stop_swaps = threading.Event()
        swaps = threading.Thread(target=self.swap_loop, args=(stop_swaps,), name='swaps',
                                 daemon=True)
        swaps.start()
        while (now := self.rel()) < duration:
            while events and events[0].at_s <= now:
                self.fire(events.pop(0))
            if now >= next_rss:
                self.sup.sample_rss()
                next_rss = now + self.cfg.rss_every_s
            self.handle_crashes()
            time.sleep(0.05)
        self.sup.sample_rss()
        self.end = time.monotonic()
        self.observer.closed = True
        self.observer.end_run(self.end)
        stop_swaps.set()
        swaps.join(timeout=10.0)      # a request in flight ends within its 5 s
        self.swapper.check_seen(self.observer.last_param)
        last = self.observer.last_at
        if last is not None and self.end - last > self.cfg.stall_s:
            # Still stalled at the end.
            self.observer.gaps.append(Gap(last, self.end - last, self.observer.last_step, None))

    def sim_up(self) -> bool:
        sim = self.sup.current['sim_node']
        return sim.killed_at is None and sim.ended_at is None

    def swap_loop(self, stop: threading.Event) -> None:
        """Swap every swap_every_s, in a thread: a slow answer must not delay a kill or restart."""
        duration, index = self.cfg.minutes * 60.0, 1
        while index * self.cfg.swap_every_s < duration:
            if stop.wait(max(0.0, index * self.cfg.swap_every_s - self.rel())):
                return
            self.swapper.swap(self.observer.last_param, self.sim_up)
            index += 1

    def fire(self, event: Event) -> None:
        if event.kind in ('stop', 'cont'):
            sig = signal.SIGSTOP if event.kind == 'stop' else signal.SIGCONT
            self.sup.current[event.node].popen.send_signal(sig)
        elif event.kind == 'kill':
            proc = self.sup.kill9(event.node)
            if event.node == 'sim_node':
                self.sim_kills.append(proc.killed_at)
        else:
            self.respawn(event.node, 'soak')

    def respawn(self, node: str, cause: str) -> None:
        old = self.sup.current[node]
        new = self.sup.spawn(node)
        self.restarts.append(Restart(cause, old, new, self.observer.watch(new.spawned_at)))

    def handle_crashes(self) -> None:
        for proc in self.sup.exited_unasked():
            self.crashes.append(Crash(proc.node, proc.popen.pid, proc.popen.returncode,
                                      round(self.rel(proc.ended_at), 3),
                                      log_tail(proc.log_path)))
            self.respawn(proc.node, 'crash')   # so that the soak goes on


# ---- figures ---------------------------------------------------------------------------

def _offset(when: float | None, origin: float | None) -> float | None:
    return None if when is None or origin is None else round(when - origin, 3)


def run_minutes(minutes: float) -> int:
    """Count the run's minutes; the last one also takes the few ms the run overshoots."""
    return max(1, math.ceil(minutes - 1e-9))


def minute_rates(observer: Observer, minutes: int, duration_s: float,
                 unanswered: list[float]) -> list[MinuteRate]:
    """Count steps per minute; `unanswered`: the unanswered swaps' times, in run seconds."""
    rates = []
    for minute in range(minutes):
        last = minute == minutes - 1
        seconds = duration_s - 60.0 * minute if last else 60.0
        window = slice(minute, None if last else minute + 1)
        steps = sum(observer.steps[window])
        rates.append(MinuteRate(
            minute + 1, round(seconds, 3), round(steps / seconds, 1),
            round(sum(observer.controlled[window]) / seconds, 1),
            uncontrolled_steps=sum(observer.uncontrolled[window]),
            unanswered_swaps=sum(minute <= at / 60.0 and (last or at / 60.0 < minute + 1)
                                 for at in unanswered)))
    return rates


def recovery_windows(cfg: SoakConfig, restarts: list[RestartResult]) -> list[tuple[float, float]]:
    """Run-time windows in which a restart may leave the loop uncontrolled (its own goal)."""
    windows = []
    for r in restarts:
        start = r.killed_at_s if r.killed_at_s is not None else r.spawned_at_s - cfg.down_s
        ready = r.startup_line_at_s if r.startup_line_at_s is not None else math.inf
        windows.append((start, ready + cfg.control_goal_s))
    return windows


def spells(runs: list[UncontrolledRun], t0: float,
           windows: list[tuple[float, float]]) -> list[Spell]:
    """Turn the observer's uncontrolled runs into spells in run time.

    Each spell has its part outside every restart's recovery window.
    """
    found = []
    for run in runs:
        start, end = run.start - t0, run.end - t0
        found.append(Spell(round(start, 3), round(end - start, 3), run.steps,
                           round(outside_windows(start, end, windows), 3)))
    return found


def outside_windows(start: float, end: float, windows: list[tuple[float, float]]) -> float:
    """Seconds of [start, end] after its start is walked past each window it falls in."""
    for lo, hi in sorted(windows):   # windows may chain
        if lo <= start < hi:
            start = hi
    return max(0.0, end - start)


def stalls(gaps: list[Gap], t0: float, sim_kills: list[float],
           windows: list[tuple[float, float]]) -> list[Stall]:
    """Turn the observer's gaps into stalls of the run, in run time.

    A gap that holds a kill of the sim is the sim's own downtime: flagged
    `sim_down`. Each stall has its part outside every restart's recovery window.
    """
    found = []
    for gap in gaps:
        if gap.start < t0:
            continue   # start-up, before the loop first closed
        # The old sim's last message may be taken a moment after the kill.
        sim_down = any(gap.start - 0.5 <= kill <= gap.start + gap.seconds for kill in sim_kills)
        start = gap.start - t0
        outside = outside_windows(start, start + gap.seconds, windows)
        found.append(Stall(round(start, 3), round(gap.seconds, 3), sim_down,
                           round(outside, 3), gap.before, gap.after))
    return found


def restart_result(restart: Restart, t0: float) -> RestartResult:
    startup = startup_line_monotonic(restart.new.log_path)
    back = restart.watch.control_at
    return RestartResult(
        node=restart.new.node, cause=restart.cause, old_pid=restart.old.popen.pid,
        new_pid=restart.new.popen.pid, killed_at_s=_offset(restart.old.killed_at, t0),
        spawned_at_s=_offset(restart.new.spawned_at, t0),
        startup_line_at_s=_offset(startup, t0),
        first_step_at_s=_offset(restart.watch.first_step_at, t0),
        control_back_at_s=_offset(back, t0),
        control_back_after_spawn_s=_offset(back, restart.new.spawned_at),
        control_back_after_startup_s=_offset(back, startup),
        upper_bound=back is not None and back == restart.watch.first_step_at)


def _mb(kb: int | None) -> float | None:
    return None if kb is None else round(kb / 1024.0, 1)


def process_rss(proc: NodeProc, t0: float, minutes: int, baseline_s: float) -> ProcessRss:
    """Summarise a process's RSS: per run minute, and its growth to its last sample.

    Growth is measured from `baseline_s` after the process's start (after the
    run's, for the processes started with the soak), as the goal defines it:
    the start-up allocations are behind by then.
    """
    per_minute = []
    for minute in range(minutes):
        lo = t0 + 60.0 * minute
        hi = math.inf if minute == minutes - 1 else lo + 60.0
        inside = [kb for when, kb in proc.rss_kb if lo <= when < hi]
        per_minute.append(_mb(inside[-1]) if inside else None)
    baseline_at = max(proc.spawned_at, t0) + baseline_s
    base = next(((w, kb) for w, kb in proc.rss_kb if w >= baseline_at), None)
    last = proc.rss_kb[-1] if proc.rss_kb else None
    growth = None
    if base is not None and last is not None and last[0] > base[0]:
        growth = round(100.0 * (last[1] - base[1]) / base[1], 2)
    return ProcessRss(
        node=proc.node, incarnation=proc.incarnation, pid=proc.popen.pid,
        started_at_s=_offset(proc.spawned_at, t0), ended_at_s=_offset(proc.ended_at, t0),
        exit_code=proc.popen.returncode, killed_by_soak=proc.killed_at is not None,
        per_minute_mb=per_minute, baseline_at_s=_offset(base[0] if base else None, t0),
        baseline_mb=_mb(base[1] if base else None), end_mb=_mb(last[1] if last else None),
        growth_pct=growth)


def control_goals(cfg: SoakConfig, found: list[Spell], swaps: SwapStats) -> list[Goal]:
    """Lost control that states still flowing would hide from the stall goal."""
    outside = [s for s in found if s.outside_restarts_s > 0.0]
    worst = max((s.outside_restarts_s for s in outside), default=0.0)
    steps = sum(s.steps for s in outside)
    return [
        Goal(f'no uncontrolled spell > {cfg.control_goal_s:g} s outside restarts',
             worst <= cfg.control_goal_s,
             f'{len(outside)} spell(s) outside restarts ({steps} uncontrolled steps), worst '
             f'{worst:.2f} s'),
        Goal('0 unanswered swaps', swaps.unanswered == 0,
             f'{swaps.unanswered} of {swaps.requested} swap request(s) unanswered within 5 s'),
    ]


def goals(cfg: SoakConfig, crashes: list[Crash], restarts: list[RestartResult],
          rss: list[ProcessRss], found: list[Stall]) -> list[Goal]:
    backs = [r.control_back_after_startup_s for r in restarts]
    back_ok = bool(restarts) and all(b is not None and b <= cfg.control_goal_s for b in backs)
    back_detail = ', '.join(f'{r.node} {"never" if b is None else f"{b:.2f} s"}'
                            for r, b in zip(restarts, backs, strict=True)) or 'no restart'
    measured = [p for p in rss if p.growth_pct is not None]
    unmeasured = [f'{p.node}#{p.incarnation}' for p in rss if p.growth_pct is None]
    rss_ok = bool(measured) and all(p.growth_pct < cfg.rss_goal_pct for p in measured)
    rss_detail = ', '.join(f'{p.node}#{p.incarnation} {p.growth_pct:+.1f} %' for p in measured)
    if unmeasured:
        rss_detail += (f'; not measured (lived < {cfg.rss_baseline_minutes:g} min): '
                       f'{", ".join(unmeasured)}')
    real = [s for s in found if not s.sim_down and s.outside_restarts_s > cfg.stall_s]
    worst = max((s.outside_restarts_s for s in real), default=0.0)
    return [
        Goal('0 crashes', not crashes, f'{len(crashes)} crash(es)'),
        Goal(f"control back within {cfg.control_goal_s:g} s of a restarted node's start-up "
             'line', back_ok, back_detail),
        Goal(f'RSS growth < {cfg.rss_goal_pct:g} % from minute {cfg.rss_baseline_minutes:g}',
             rss_ok, rss_detail or 'nothing measured'),
        Goal(f'no stall > {cfg.stall_s:g} s', not real,
             f"{len(real)} stall(s), worst {worst:.2f} s (the sim's own downtime and "
             "restarts' recovery excluded)"),
    ]


def interference(soak: Soak) -> list[str]:
    observer = soak.observer
    found = []
    if observer.foreign_steps:
        found.append(f'{observer.foreign_steps} StepInfo of another family than '
                     f'{observer.family}')
    expected = sum(p.node == 'sim_node' for p in soak.sup.history) - 1
    if observer.clock_backsteps > expected:
        found.append(f'the sim clock went back {observer.clock_backsteps} times for '
                     f'{expected} sim restart(s): another sim_node on this ROS domain')
    return found


def figures(soak: Soak, meta: CheckpointMetadata, log_dir: Path,
            load_start: float) -> SoakResult:
    cfg, t0, observer = soak.cfg, soak.t0, soak.observer
    duration = soak.end - t0
    spec = get_family(meta.family)
    restarts = [restart_result(r, t0) for r in soak.restarts]
    minutes = run_minutes(cfg.minutes)
    rss = [process_rss(p, t0, minutes, 60.0 * cfg.rss_baseline_minutes)
           for p in soak.sup.history]
    windows = recovery_windows(cfg, restarts)
    found = stalls(observer.gaps, t0, soak.sim_kills, windows)
    lost = spells(observer.runs, t0, windows)
    swaps = soak.swapper.stats
    checked = (goals(cfg, soak.crashes, restarts, rss, found)
               + control_goals(cfg, lost, swaps))
    return SoakResult(
        family=spec.name, weights=str(cfg.weights), param_name=spec.param_name,
        live_range=spec.live_range, minutes=cfg.minutes, duration_s=round(duration, 3),
        machine=f'{os.cpu_count()} cores',
        ros_domain_id=os.environ.get('ROS_DOMAIN_ID', '0'), load_avg_start=load_start,
        load_avg_end=os.getloadavg()[0], steps_total=sum(observer.steps),
        per_minute=minute_rates(observer, minutes, duration,
                                [at - t0 for at in swaps.unanswered_at]),
        stalls=found, max_gap_s=round(max((s.seconds for s in found), default=0.0), 3),
        uncontrolled_steps=sum(observer.uncontrolled), uncontrolled_spells=lost,
        crashes=soak.crashes, restarts=restarts, rss=rss, swaps=swaps,
        diagnostics={'last': observer.diagnostics,
                     'non_ok_reports': {n: dict(c) for n, c in observer.warnings.items()}},
        goals=checked, passed=all(g.met for g in checked),
        interference=interference(soak), log_dir=str(log_dir))


# ---- report ----------------------------------------------------------------------------

def _s(value: float | None) -> str:
    return 'never' if value is None else f'{value:.2f} s'


def rate_lines(result: SoakResult) -> list[str]:
    """Steps/s and each node's RSS (its process of that minute) per minute."""
    lines = [f'{"minute":>6} {"steps/s":>8} {"controlled/s":>12} {"uncontrolled":>12} '
             f'{"unanswered":>10}  ' + '  '.join(f'{n + " MB":>15}' for n in NODE_NAMES)]
    for rate in result.per_minute:
        row = (f'{rate.minute:>6} {rate.steps_per_s:>8.1f} {rate.controlled_steps_per_s:>12.1f}'
               f' {rate.uncontrolled_steps:>12d} {rate.unanswered_swaps:>10d}')
        for node in NODE_NAMES:
            values = [p.per_minute_mb[rate.minute - 1] for p in result.rss if p.node == node]
            live = [v for v in values if v is not None]
            row += f'  {live[-1] if live else math.nan:>15.1f}'
        lines.append(row)
    return lines


def event_lines(result: SoakResult) -> list[str]:
    lines = []
    for r in result.restarts:
        how = f'killed at {r.killed_at_s:.1f} s, ' if r.killed_at_s is not None else 'crashed, '
        lines.append(f'restart {r.node} ({r.cause}): {how}spawned at {r.spawned_at_s:.1f} s, '
                     f'start-up line +{_s(_offset(r.startup_line_at_s, r.spawned_at_s))}, '
                     f'first step +{_s(_offset(r.first_step_at_s, r.spawned_at_s))}, control '
                     f'back +{_s(r.control_back_after_spawn_s)} after the spawn, '
                     f'{_s(r.control_back_after_startup_s)} after the start-up line'
                     + (' (upper bounds: the first step seen was controlled)'
                        if r.upper_bound else ''))
    for stall in result.stalls:
        why = (" (the sim's own downtime, not counted)" if stall.sim_down else
               " (a restart's recovery, not counted)" if stall.outside_restarts_s == 0.0 else '')
        after = 'the end' if stall.after is None else 'episode {} step {}'.format(*stall.after)
        lines.append(f'gap {stall.seconds:.2f} s at {stall.at_s:.1f} s, from episode '
                     f'{stall.before[0]} step {stall.before[1]} to {after}{why}')
    for spell in result.uncontrolled_spells:
        if spell.seconds > 1.0:
            lines.append(f'uncontrolled {spell.seconds:.2f} s ({spell.steps} steps) at '
                         f'{spell.at_s:.1f} s, {spell.outside_restarts_s:.2f} s of it outside '
                         'restarts')
    for crash in result.crashes:
        lines.append(f'CRASH {crash.node} pid {crash.pid} exit {crash.exit_code} at '
                     f'{crash.at_s:.1f} s: {" | ".join(crash.log_tail[-3:])}')
    for p in result.rss:
        if p.growth_pct is None:
            lines.append(f'rss {p.node}#{p.incarnation} pid {p.pid}: {p.end_mb} MB at its end, '
                         'growth n/a (it did not outlive the baseline)')
        else:
            lines.append(f'rss {p.node}#{p.incarnation} pid {p.pid}: {p.baseline_mb} MB at '
                         f'{p.baseline_at_s:.0f} s -> {p.end_mb} MB, growth '
                         f'{p.growth_pct:+.2f} %')
    sw = result.swaps
    lines.append(f'swaps: {sw.requested} requested, {sw.accepted} accepted, {sw.refused} '
                 f'refused, {sw.unanswered} unanswered, {sw.skipped_sim_down} skipped (sim '
                 f'down), {sw.seen_in_steps} seen in StepInfo')
    return lines


def report_lines(result: SoakResult) -> list[str]:
    lo, hi = result.live_range
    head = (f'soak {result.family}, weights {result.weights}: {result.duration_s / 60:.2f} min, '
            f'{result.steps_total} steps, swaps of {result.param_name} over [{lo:g}, {hi:g}], '
            f'load average {result.load_avg_start:.1f} -> {result.load_avg_end:.1f} '
            f'({result.machine})')
    goal_lines = [f'goal {"PASS" if g.met else "FAIL"}: {g.name}: {g.detail}'
                  for g in result.goals]
    verdict = 'PASS' if result.passed else 'FAIL (' + '; '.join(
        g.name for g in result.goals if not g.met) + ')'
    if result.interference:
        verdict = f'INVALID (not this soak\'s graph alone: {"; ".join(result.interference)})'
    return [head, *rate_lines(result), *event_lines(result), *goal_lines,
            f'soak result: {verdict}']


# ---- entry point -----------------------------------------------------------------------

def parse_pause(parser, text: str) -> tuple[str, float, float]:
    node, _, rest = text.partition(':')
    try:
        at, seconds = (float(v) for v in rest.split(':'))
    except ValueError:
        parser.error(f'--pause {text}: expected NODE:AT:SECONDS')
    if node not in NODE_NAMES or not 0 < at < 1 or seconds <= 0:
        parser.error(f'--pause {text}: NODE one of {", ".join(NODE_NAMES)}, AT in (0, 1), '
                     'SECONDS > 0')
    return node, at, seconds


def parse_args(argv=None) -> tuple[SoakConfig, Path]:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--weights', type=Path,
                        default=REPO / 'weights' / 'walker-walk-slippery-zeus')
    parser.add_argument('--minutes', type=float, default=30.0)
    parser.add_argument('--swap-every', type=float, default=10.0, help='seconds')
    parser.add_argument('--restart-at', default='0.25,0.5,0.75',
                        help='fractions of the run at which sim_node, context_node and '
                             "policy_node are killed (SIGKILL); 'none': no restart")
    parser.add_argument('--pause', action='append', default=[], metavar='NODE:AT:SECONDS',
                        help='SIGSTOP NODE at fraction AT of the run for SECONDS (a fault '
                             'the control goals must see); repeatable')
    parser.add_argument('--down-seconds', type=float, default=2.0,
                        help='how long a killed node stays down before its restart')
    parser.add_argument('--rss-baseline-minutes', type=float, default=2.0,
                        help="RSS growth is measured from this long after a process's start")
    parser.add_argument('--startup-timeout', type=float, default=120.0)
    parser.add_argument('--log-dir', type=Path, help='node logs (default: a new temp dir)')
    parser.add_argument('--json', type=Path,
                        default=REPO / 'research' / 'benchmarks' / 'results_soak.json')
    args = parser.parse_args(argv)
    restart_at = () if args.restart_at == 'none' else tuple(
        float(f) for f in args.restart_at.split(','))
    if restart_at and (len(restart_at) != len(NODE_NAMES)
                       or not all(0 < f < 1 for f in restart_at)):
        parser.error('--restart-at takes three fractions in (0, 1)')
    return SoakConfig(weights=args.weights.resolve(), minutes=args.minutes,
                      swap_every_s=args.swap_every, restart_at=restart_at,
                      pauses=tuple(parse_pause(parser, text) for text in args.pause),
                      down_s=args.down_seconds, rss_baseline_minutes=args.rss_baseline_minutes,
                      startup_timeout_s=args.startup_timeout, log_dir=args.log_dir), args.json


def check_domain_free(node, settle_s: float = 2.0) -> None:
    """Refuse a ROS domain that already carries a loop (a test suite, another soak).

    Every graph of this project uses the same names: on a shared domain the
    nodes would answer each other's states and the figures would mean nothing.
    """
    time.sleep(settle_s)   # discovery of the participants already there
    busy = [topic for topic in ('/zeus/step', '/joint_states', '/joint_commands')
            if node.count_publishers(topic)]
    if busy:
        raise SoakError(f'ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID", "0")} is in use '
                        f'({", ".join(busy)} already published): give the soak a domain of '
                        'its own')


def _interrupt(signum: int, frame) -> None:  # noqa: ARG001 (a signal handler's)
    raise KeyboardInterrupt(f'signal {signum}')


def run_soak(cfg: SoakConfig) -> SoakResult:
    meta = load_metadata(cfg.weights)
    spec = get_family(meta.family)
    commands = node_commands(bringup_args(['--weights', str(cfg.weights), '--mode', 'lockstep']))
    log_dir = cfg.log_dir or Path(tempfile.mkdtemp(prefix='zeus_soak_'))
    log_dir.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()[0]
    # rclpy's own handlers would only shut its context down and leave the soak
    # (and its nodes) running: a stop signal ends the run through `finally`.
    # The observer announces itself as often as the nodes do (their profile): with
    # Fast DDS's 3-s default it would see a restarted sim's steps up to 3 s late.
    use_discovery_profile()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _interrupt)
    node = rclpy.create_node('zeus_soak')
    observer = Observer(node, cfg.stall_s, spec.name)
    supervisor = Supervisor(commands, log_dir)
    soak = Soak(cfg, supervisor, observer, Swapper(node, spec.param_name, spec.live_range))
    gc.freeze()   # as the nodes do: a full collection would stall the observer
    try:
        check_domain_free(node)
        soak.start()
        soak.run()
    finally:
        supervisor.stop()
        rclpy.try_shutdown()          # ends the observer's spin_loop first
        observer.spinner.join(timeout=5.0)
        node.destroy_node()
    return figures(soak, meta, log_dir, load_start)


def main(argv=None) -> int:
    cfg, json_path = parse_args(argv)
    from zeus_ros.deploy.checkpoint import CheckpointError
    try:
        result = run_soak(cfg)
    except (SoakError, CheckpointError) as error:
        print(f'soak: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        print(f'soak: interrupted ({stop}); its nodes are stopped', file=sys.stderr)
        return 130
    for line in report_lines(result):
        print(line)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(asdict(result), indent=2) + '\n')
    print(f'figures written to {json_path}; node logs in {result.log_dir}')
    if result.interference:
        return 2
    return 0 if result.passed else 1


if __name__ == '__main__':
    sys.exit(main())
