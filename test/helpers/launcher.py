"""A launcher to kill: starts a node as `ros2 launch` or `ros2 run` does, then stands by.

launcher.py [--from-thread] LOG -- COMMAND... starts COMMAND (its output to
LOG), prints 'started PID' and sleeps until killed. --from-thread starts it
from a thread that ends on SIGUSR1 (the kernel's parent-death signal comes
when that thread ends, not the process).

launcher.py --reaper [--from-thread] LOG -- COMMAND... is a child subreaper:
it runs the launcher above (printing 'launcher PID') and, once the launcher
is gone, waits for the orphaned COMMAND, which the kernel hands to it, and
prints 'orphan PID exited CODE after S s'.
"""

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time

PR_SET_CHILD_SUBREAPER = 36


def launch(argv: list[str]) -> None:
    from_thread = argv[0] == '--from-thread'
    if from_thread:
        argv = argv[1:]
    log, command = argv[0], argv[argv.index('--') + 1:]
    started, release = [], threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: release.set())

    def start():
        with open(log, 'w') as out:
            started.append(subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT))
    if from_thread:
        threading.Thread(target=lambda: (start(), release.wait())).start()
        while not started:
            time.sleep(0.01)
    else:
        start()
    print(f'started {started[0].pid}', flush=True)
    while True:
        time.sleep(60)


def reap(argv: list[str]) -> None:
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0)
    launcher = subprocess.Popen([sys.executable, __file__, *argv])
    print(f'launcher {launcher.pid}', flush=True)
    launcher.wait()
    gone = time.monotonic()
    print(f'launcher exited {launcher.returncode}', flush=True)
    pid, status = os.wait()          # the orphan, handed to this subreaper
    print(f'orphan {pid} exited {os.waitstatus_to_exitcode(status)} '
          f'after {time.monotonic() - gone:.2f} s', flush=True)


if __name__ == '__main__':
    if sys.argv[1] == '--reaper':
        reap(sys.argv[2:])
    else:
        launch(sys.argv[1:])
