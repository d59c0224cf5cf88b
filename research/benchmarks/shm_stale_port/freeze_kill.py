"""Freeze a process until its shared-memory listener is in a given state, then SIGKILL it.

    python freeze_kill.py PID [PORT] [--mode window|waiting|processing]

Repeatedly SIGSTOPs process PID, waits until all its threads have stopped,
reads the first listener slot of /dev/shm/fastrtps_port<PORT> and, if the slot
is in the wanted state, SIGKILLs the still-frozen process; otherwise it
SIGCONTs it and tries again 0-4 ms later. The states: window = in use but
neither waiting nor processing (the fault's window), waiting = idle, waiting
for a buffer, processing = handling one. Without PORT (no shared-memory
listener, as with a UDPv4-only profile) there is nothing to wait for: it kills
the process frozen after a random 100-800 freezes, a random moment, and says
so. trial.py calls kill_frozen().
"""

import argparse
import glob
import os
import random
import signal
import time

from shmstat import listener_state

WANTED = {
    'window': lambda s: not s['waiting'] and not s['processing'],
    'waiting': lambda s: bool(s['waiting']),
    'processing': lambda s: bool(s['processing']),
}
FALLBACK = 'no shared-memory listener: killed frozen at a random moment'


def all_stopped(pid):
    """Tell whether every thread of process PID is stopped."""
    for path in glob.glob(f'/proc/{pid}/task/*/stat'):
        try:
            with open(path) as f:
                state = f.read().rsplit(')', 1)[1].split()[0]
        except OSError:   # the thread exited
            continue
        if state not in ('T', 't'):
            return False
    return True


def freeze(pid, limit=0.2):
    """SIGSTOP process PID and wait (up to LIMIT seconds) until all its threads stop."""
    os.kill(pid, signal.SIGSTOP)
    deadline = time.time() + limit
    while not all_stopped(pid) and time.time() < deadline:
        time.sleep(0.0005)


def kill_frozen(pid, port=None, mode='window', max_probes=12000):
    """Freeze PID until PORT's listener is in MODE's state, SIGKILL it; return what happened."""
    target = random.randint(100, 800) if port is None else None
    state, hit, probe = None, False, 0
    while not hit and probe < max_probes:
        if probe:
            os.kill(pid, signal.SIGCONT)
            time.sleep(random.uniform(0, 0.004))
        probe += 1
        freeze(pid)
        if port is None:
            hit = probe >= target
        else:
            state = listener_state(port)
            hit = state is not None and WANTED[mode](state)
    os.kill(pid, signal.SIGKILL)
    if port is None:
        kill = FALLBACK
    elif hit:
        kill = f'listener {mode}'
    else:
        kill = f'listener never {mode} in {max_probes} probes: killed anyway'
    return dict(probes=probe, kill=kill, listener=state)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('pid', type=int)
    parser.add_argument('port', type=int, nargs='?')
    parser.add_argument('--mode', default='window', choices=sorted(WANTED))
    parser.add_argument('--max-probes', type=int, default=12000)
    args = parser.parse_args()
    print(kill_frozen(args.pid, args.port, args.mode, args.max_probes))


if __name__ == '__main__':
    main()
