"""Stop quietly on SIGINT/SIGTERM while a node's heavy modules are still importing.

A signal while torch, MuJoCo or rclpy load (seconds on a busy machine) would
otherwise end the node with an import traceback or -15. `install(program,
module_name)` exits with 0 on such a signal, but only when the module is the
program (`python -m ...`, or the console script `program`); `run_node` takes
the signals over once the node starts. It also arms `parent_watch` there, so
that a launcher that dies while the node imports ends it too. Imports nothing
heavy.
"""

from __future__ import annotations

import os
import signal
import sys
from typing import TYPE_CHECKING

from zeus_ros.ros.parent_watch import end_with_launcher

if TYPE_CHECKING:
    from types import FrameType


def _exit_quietly(_signum: int, _frame: FrameType | None) -> None:
    os._exit(0)  # nothing to clean up: no ROS context exists before run_node


def install(program: str, module_name: str) -> bool:
    """Install the quiet exit if this process runs `program`; True when installed."""
    if module_name != '__main__' and os.path.basename(sys.argv[0]) != program:
        return False
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _exit_quietly)
    end_with_launcher()
    return True
