"""Why rclpy's EventsExecutor.spin() fires a timer once and then never again (issue #38.9).

    python research/benchmarks/events_executor_repro.py        # about 10 s; needs no other node

A node with one 20 Hz timer, spun for 1 s by rclpy.experimental.EventsExecutor
(rclpy 7.1.6, requirements.lock), in a child process per variant; each line
gives the timer callbacks (20 expected) and the share of 10 ms samples in
which the spinning thread was runnable (never asleep: a busy loop):

* `spin()`: 0 or 1 callback, the thread runnable in every sample, and neither
  spin() nor rclpy.shutdown() (called from another thread) ever returns;
* `spin_once(timeout_sec=0.1)` in a loop: 20 callbacks, the thread asleep.

The cause, in rclpy's C++ (src/rclpy/events_executor/events_queue.cpp):
spin() runs `EventsQueue::Run()`, that is `RunUntil(steady_clock::time_point::max())`,
a `condition_variable::wait_until` on that deadline, under the queue's mutex.
The PyPI wheel is built for manylinux_2_28 (glibc 2.28), which has no
pthread_cond_clockwait (glibc 2.30), so libstdc++ converts the steady
deadline to the system clock by adding it to the system clock's now: the
sum overflows into a negative time, whose nanoseconds are negative too, and
pthread_cond_timedwait refuses it at once (EINVAL) without ever releasing
the mutex. Run() loops on that, holding the mutex for good, so every
thread that posts to the queue blocks on it: the DelayedEventThread that
schedules the timer's next expiry (hence at most the one callback already due),
the middleware's callbacks for messages and service requests, and
rclpy.shutdown()'s wake-up (holding the GIL, which freezes the process).
With a finite timeout the deadline is small, nothing overflows, and the
executor works. Neither the timer's clock (ROS, system, steady) nor its
creation before or after add_node changes anything; guard conditions are
refused outright ("Guard conditions not supported"). A build against glibc
2.30 or later (the ROS apt packages on Ubuntu 24.04) would not have the fault.

So the nodes may use it only through spin_once with a timeout, as
zeus_ros.ros.loop_spin does with `executor:=events`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
import subprocess
import sys
import threading
import time

PERIOD_S = 0.05
SPIN_S = 1.0


def child(variant: str) -> None:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    rclpy.init()
    node = rclpy.create_node('events_executor_repro')
    fired = []
    node.create_timer(PERIOD_S, lambda: fired.append(time.monotonic()))
    executor = EventsExecutor()
    executor.add_node(node)
    start = time.monotonic()
    spinner = threading.get_native_id()
    runnable = []

    def report_and_stop():
        while time.monotonic() - start < SPIN_S:
            runnable.append(thread_state(spinner) == 'R')
            time.sleep(0.01)
        print(f'{variant:>26}: {len(fired):2d} timer callbacks in {SPIN_S:g} s '
              f'(expected {SPIN_S / PERIOD_S:.0f}); spinning thread runnable in '
              f'{100 * sum(runnable) / max(len(runnable), 1):.0f}% of samples', flush=True)
        rclpy.shutdown()
        print(f'{"":>26}  rclpy.shutdown() returned', flush=True)

    threading.Thread(target=report_and_stop, daemon=True).start()
    if variant == 'spin()':
        executor.spin()
        print(f'{"":>26}  spin() returned', flush=True)
    else:
        with contextlib.suppress(ExternalShutdownException):   # its way to say shutdown
            while rclpy.ok():
                executor.spin_once(timeout_sec=0.1)
        time.sleep(0.5)   # the report's last line
    os._exit(0)


def thread_state(tid: int) -> str:
    """Return a thread's scheduler state: R runnable, S asleep, D in the kernel."""
    return Path(f'/proc/self/task/{tid}/stat').read_text().rsplit(')', 1)[1].split()[0]


def links_clockwait() -> bool:
    """Whether rclpy's extension imports pthread_cond_clockwait (the name is in its .dynstr)."""
    import rclpy
    library = next(Path(rclpy.__file__).parent.glob('_rclpy_pybind11*.so'))
    return b'pthread_cond_clockwait' in library.read_bytes()


def main() -> int:
    if len(sys.argv) > 2 and sys.argv[1] == '--child':
        child(sys.argv[2])
    print(f'rclpy extension links pthread_cond_clockwait: {links_clockwait()}')
    for variant in ('spin()', 'spin_once(timeout_sec=0.1)'):
        run_child(variant)
    return 0


def run_child(variant: str, grace_s: float = 3.0) -> None:
    """Run one variant; kill it if it is still there `grace_s` after its report."""
    child = subprocess.Popen([sys.executable, __file__, '--child', variant],
                             stdout=subprocess.PIPE, text=True)
    killer = threading.Timer(grace_s, child.kill)
    for line in child.stdout:
        print(line, end='', flush=True)
        if 'timer callbacks' in line:
            killer.start()
    killer.cancel()
    if child.wait() == -9:
        print(f'{"":>26}  still blocked {grace_s:g} s after rclpy.shutdown() was called: '
              'killed')


if __name__ == '__main__':
    sys.exit(main())
