"""Checks shared by the sweep tests: where a run stands, whether a resume continued it."""

import csv
from pathlib import Path
import subprocess


def checkpoint_timestep(run: Path) -> int:
    """Return the timestep of a run's last checkpoint."""
    from zeus_ros.deploy.checkpoint import load_metadata
    return load_metadata(run / 'checkpoint').steps.timestep


def assert_resumed_not_restarted(run: Path, steps: int, log_every: int, lost_rows: int) -> None:
    """Check the run's log covers every interval, repeating at most the `lost_rows` it lost."""
    logged = [int(row['timestep']) for row in csv.DictReader(open(run / 'train_log.csv'))]
    assert logged.count(log_every) == 1, logged          # a restart would log it again
    assert sorted(set(logged)) == list(range(log_every, steps + 1, log_every)), logged
    assert len(logged) - len(set(logged)) <= lost_rows, logged


def listening_beyond_loopback(session: int) -> tuple[list[str], list[str]]:
    """Return (all, non-loopback) listening TCP sockets of the processes in one session."""
    pids = {line.split()[0] for line in subprocess.run(
        ['ps', '-eo', 'pid=,sid='], capture_output=True, text=True, check=True).stdout.splitlines()
        if line.split()[1] == str(session)}
    lines = subprocess.run(['ss', '-Hltnp'], capture_output=True, text=True,
                           check=True).stdout.splitlines()
    ours = [line for line in lines if any(f'pid={pid},' in line for pid in pids)]
    loopback = ('127.0.0.1:', '[::ffff:127.0.0.1]:', '[::1]:')
    return ours, [line for line in ours if not line.split()[3].startswith(loopback)]
