"""End a node when the process that started it ends (`ros2 launch`, `ros2 run`, bringup).

A launcher killed without a chance to stop its nodes (SIGKILL, or a SIGTERM
that `ros2 launch` and `ros2 run` do not pass on) left sim_node and the
controllers running; the orphaned sim then joined the next launch's graph.
`end_with_launcher()` asks Linux for a parent-death signal (prctl
PR_SET_PDEATHSIG): when the parent process ends, this process sends itself a
SIGTERM, so the node stops through its usual clean stop (the stop guard while
it imports, `StopSignals` once it runs) and exits 0.

The kernel sends that signal when the parent *thread* that started this
process ends, which may be well before its process does (a launcher that
starts nodes from a short-lived thread). So the signal is one of our own, not
SIGTERM itself, and its handler acts only once this process has been
re-parented, i.e. the launcher's process is gone. Imports nothing heavy: it is
armed first thing, before a node's heavy imports. ZEUS_OUTLIVE_PARENT=1 turns
it off (a node started by hand that must outlive its shell, e.g. with nohup).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from types import FrameType

PR_SET_PDEATHSIG = 1
# A real-time signal, which nothing else here uses.
PARENT_DEATH_SIGNAL = signal.SIGRTMIN + 3 if hasattr(signal, 'SIGRTMIN') else None

_launcher_pid: int | None = None


def _parent_gone(_signum: int | None = None, _frame: FrameType | None = None) -> None:
    if os.getppid() != _launcher_pid:
        os.kill(os.getpid(), signal.SIGTERM)


def end_with_launcher() -> bool:
    """SIGTERM this process once its parent process ends; True if armed (Linux only).

    Call it from the main thread (it installs a signal handler). Idempotent.
    Not armed when the parent is already init (nothing to follow) or when
    ZEUS_OUTLIVE_PARENT=1.
    """
    global _launcher_pid
    if _launcher_pid is not None:
        return True
    if (not sys.platform.startswith('linux') or PARENT_DEATH_SIGNAL is None
            or os.environ.get('ZEUS_OUTLIVE_PARENT') == '1'):
        return False
    parent = os.getppid()
    if parent <= 1:
        return False
    _launcher_pid = parent
    signal.signal(PARENT_DEATH_SIGNAL, _parent_gone)
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(PARENT_DEATH_SIGNAL), 0, 0, 0) != 0:
        _launcher_pid = None
        return False
    _parent_gone()   # the parent may have ended before the request took effect
    return True
