"""Reproduce Fast DDS 2.14.5's stale shared-memory port: SIGKILL and restart a reader.

    python trial.py --mode window [--profile FILE] [--n 1] [--rate 200] [--down 1]
        [--timeout 40] [--out FILE] [--run-dir DIR] [--tag TAG] [--busy] [--sub-first]

Starts pub.py (the long-running writer) and sub.py (the reader and service
server), then per trial SIGKILLs sub.py, keeps it down --down seconds, restarts
it and waits up to --timeout seconds for its first /shmx/data sample and first
/shmx/srv request. A restart that gets either not at all is 'stuck': the
writer's still-mapped copy of the deleted port segment is read into the
record, and the writer is restarted (the reader then receives again).

--mode says when the SIGKILL lands:
  natural     a random moment, 0.3-1.5 s after the reader is receiving;
  window      SIGSTOP the reader, read its shared-memory listener on the
              user-data port, SIGCONT, until the listener is in use but
              neither waiting nor processing (freeze_kill.py): the fault;
  waiting     the same, until the listener is waiting (idle);
  processing  the same, until it is processing a buffer.
With no shared-memory user-data port (a UDPv4-only profile such as
config/fastdds_discovery.xml) there is no listener to wait for: the frozen
modes fall back to killing the frozen reader at a random moment, and say so.

--profile FILE sets FASTRTPS_DEFAULT_PROFILES_FILE for both processes (and
drops FASTDDS_DEFAULT_PROFILES_FILE and FASTDDS_BUILTIN_TRANSPORTS); without
it they get the environment's. Two matter: research/benchmarks/
fastdds_shared_memory.xml (shared memory, the old default) and
config/fastdds_discovery.xml (UDPv4 user traffic, the new default).

Run in the repository's environment (`source scripts/ros_env.sh`) with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_DOMAIN_ID in 151-159, domains
nothing else here uses. Both processes run under `nice -n 19`. Appends one
JSON line per trial to --out (default: results.jsonl in --run-dir); --run-dir
(default: a new temporary directory) holds the status files and logs.
"""

import argparse
import glob
import json
import os
from pathlib import Path
import random
import re
import signal
import subprocess
import sys
import tempfile
import time

from freeze_kill import kill_frozen
from shmstat import deleted_copy, port_summary

HERE = Path(__file__).resolve().parent
DOMAINS = [str(d) for d in range(151, 160)]
# Shared-memory ports are numbered as UDP ports: in domains 151-159 the user-data
# ones are 45161 and up; the reader's other, lower one carries discovery.
USER_PORT_MIN = 40000


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--mode', default='natural',
                        choices=['natural', 'window', 'waiting', 'processing'])
    parser.add_argument('--profile', type=Path, help='FASTRTPS_DEFAULT_PROFILES_FILE')
    parser.add_argument('--n', type=int, default=5, help='trials (kills)')
    parser.add_argument('--rate', type=float, default=200.0, help='writer rate, Hz')
    parser.add_argument('--down', type=float, default=1.0, help='seconds the reader is down')
    parser.add_argument('--timeout', type=float, default=40,
                        help='seconds after the restart before a trial is stuck')
    parser.add_argument('--max-probes', type=int, default=40000)
    parser.add_argument('--busy', action='store_true', help='sub.py --busy')
    parser.add_argument('--sub-first', action='store_true', help='start the reader first')
    parser.add_argument('--run-dir', type=Path, help='status files and logs')
    parser.add_argument('--out', type=Path, help='results file (JSON lines)')
    parser.add_argument('--tag', default='')
    return parser.parse_args()


def set_environment(profile):
    """Check the domain and discovery range; apply PROFILE; return the profile in use."""
    if os.environ.get('ROS_DOMAIN_ID') not in DOMAINS:
        sys.exit(f'ROS_DOMAIN_ID must be one of {DOMAINS[0]}-{DOMAINS[-1]}')
    if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
        sys.exit('ROS_AUTOMATIC_DISCOVERY_RANGE must be LOCALHOST')
    if profile is not None:
        if not profile.is_file():
            sys.exit(f'no profile {profile}')
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile.resolve())
        os.environ.pop('FASTDDS_DEFAULT_PROFILES_FILE', None)
        os.environ.pop('FASTDDS_BUILTIN_TRANSPORTS', None)
    return os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')


def log(*parts):
    print(time.strftime('%H:%M:%S'), *parts, flush=True)


def read_json(path):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def shm_ports(pid):
    """Return the shared-memory ports process PID listens on (holds the _el file of)."""
    ports = []
    for fd in glob.glob(f'/proc/{pid}/fd/*'):
        try:
            match = re.search(r'fastrtps_port(\d+)_el$', os.readlink(fd))
        except OSError:
            continue
        if match:
            ports.append(int(match.group(1)))
    return sorted(ports)


def deleted_maps(pid, port):
    """Count process PID's mappings of PORT's unlinked segment (-1: no process)."""
    try:
        with open(f'/proc/{pid}/maps') as f:
            return sum(1 for line in f if f'fastrtps_port{port} (deleted)' in line)
    except OSError:
        return -1


def stop(proc):
    """SIGINT PROC, and SIGKILL it if it has not exited 5 s later."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class Pair:
    """The writer (pub.py) and the reader (sub.py) with their status files in RUN_DIR."""

    def __init__(self, args, run_dir):
        self.args = args
        self.run_dir = run_dir
        self.pub_status = run_dir / 'pub.status'
        self.sub_status = run_dir / 'sub.status'
        self.pub = self.sub = None

    def _start(self, script, status, extra):
        status.unlink(missing_ok=True)
        cmd = ['nice', '-n', '19', sys.executable, str(HERE / script),
               '--status', str(status), *extra]
        with open(status.with_suffix('.log'), 'a') as out:
            return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)

    def start_pub(self):
        self.pub = self._start('pub.py', self.pub_status, ['--rate', str(self.args.rate)])

    def start_sub(self):
        self.sub = self._start('sub.py', self.sub_status, ['--busy'] if self.args.busy else [])

    def launch(self):
        first, second = ((self.start_sub, self.start_pub) if self.args.sub_first
                         else (self.start_pub, self.start_sub))
        first()
        time.sleep(2.5)
        second()

    def reader_status(self):
        return read_json(self.sub_status) or {}

    def wait_receiving(self, timeout):
        """Wait until the reader has had a sample and a request; return its status."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            status = self.reader_status()
            if status.get('rx') and status.get('srv'):
                break
            time.sleep(0.1)
        return self.reader_status()

    def stop(self):
        stop(self.sub)
        stop(self.pub)


def kill_reader(pair, mode, user_port, max_probes):
    """SIGKILL the reader as MODE says; return the probes made and how it was killed."""
    if mode == 'natural':
        pair.sub.send_signal(signal.SIGKILL)
        return dict(probes=0, kill='random moment')
    done = kill_frozen(pair.sub.pid, user_port, mode, max_probes)
    if user_port is None:
        log(f'--mode {mode}: no shared-memory user-data port, no listener to wait for;',
            f'fell back to killing the frozen reader at a random moment ({done["probes"]}',
            'freezes)')
    return dict(probes=done['probes'], kill=done['kill'])


def watch_restart(pair, user_port, t_start, timeout):
    """Wait for the restarted reader's first sample and request; return status, maps at 3 s."""
    maps_3s = None
    while time.time() - t_start < timeout:
        if user_port is not None and maps_3s is None and time.time() - t_start > 3:
            maps_3s = deleted_maps(pair.pub.pid, user_port)
        status = pair.reader_status()
        if status.get('first_rx') and status.get('first_srv'):
            break
        time.sleep(0.1)
    return pair.reader_status(), maps_3s


def since(status, key, t_start):
    return round(status[key] - t_start, 2) if status.get(key) else None


def restart_writer(pair):
    """Restart the writer after a stuck trial; return seconds to the reader's next sample."""
    rx_before = pair.reader_status().get('rx', 0)
    stop(pair.pub)
    t_restart = time.time()
    pair.start_pub()
    deadline = t_restart + 30
    while time.time() < deadline:
        status = pair.reader_status()
        if status.get('rx', 0) > rx_before:
            first = status['first_rx'] if not rx_before else status['last_rx']
            return round(first - t_restart, 2)
        time.sleep(0.1)
    return None


def run_trial(pair, args, index, profile):
    """Kill the reader once, restart it, and return the trial's record."""
    pair.wait_receiving(30)
    ports = shm_ports(pair.sub.pid)
    user_port = next((p for p in ports if p > USER_PORT_MIN), None)
    time.sleep(random.uniform(0.3, 1.5))
    killed = kill_reader(pair, args.mode, user_port, args.max_probes)
    pair.sub.wait()
    t_kill = time.time()
    at_kill = {p: port_summary(p) for p in ports}
    time.sleep(max(0.0, args.down - (time.time() - t_kill)))
    pair.start_sub()
    t_start = time.time()
    status, maps_3s = watch_restart(pair, user_port, t_start, args.timeout)
    record = dict(
        tag=args.tag, profile=profile,
        transport='SHM+UDP' if user_port else 'UDPv4 (no SHM user-data port)',
        domain=os.environ['ROS_DOMAIN_ID'], trial=index, mode=args.mode, rate=args.rate,
        down=args.down, busy=args.busy, sub_first=args.sub_first, **killed, ports=ports,
        state_at_kill=at_kill, new_ports=shm_ports(pair.sub.pid),
        node_up=since(status, 'node_up', t_start), first_rx=since(status, 'first_rx', t_start),
        first_srv=since(status, 'first_srv', t_start),
        pub_acks_after=(read_json(pair.pub_status) or {}).get('last_ack', 0) > t_start + 1,
        pub_deleted_maps_3s=maps_3s,
        pub_deleted_maps_end=deleted_maps(pair.pub.pid, user_port) if user_port else None)
    record['stuck'] = not (record['first_rx'] and record['first_srv'])
    if record['stuck']:
        record['stale_segment_in_pub'] = deleted_copy(pair.pub.pid, user_port)
        log('STUCK: restarting the writer')
        record['after_pub_restart_rx'] = restart_writer(pair)
    return record


def main():
    args = parse_args()
    profile = set_environment(args.profile)
    run_dir = args.run_dir or Path(tempfile.mkdtemp(prefix='shm_stale_port_'))
    run_dir.mkdir(parents=True, exist_ok=True)
    out = args.out or run_dir / 'results.jsonl'
    log(f'profile {profile}, domain {os.environ["ROS_DOMAIN_ID"]}, run dir {run_dir}')
    pair = Pair(args, run_dir)
    try:
        pair.launch()
        status = pair.wait_receiving(30)
        log('pair up: reader rx', status.get('rx'), 'srv', status.get('srv'),
            '| shm ports: writer', shm_ports(pair.pub.pid), 'reader', shm_ports(pair.sub.pid))
        for index in range(args.n):
            record = run_trial(pair, args, index, profile)
            log(json.dumps(record))
            with open(out, 'a') as f:
                f.write(json.dumps(record) + '\n')
            log(f'trial {index}:', 'STUCK' if record['stuck'] else
                f'first receive {record["first_rx"]} s, first request {record["first_srv"]} s',
                f'({record["kill"]}; appended to {out})')
    finally:
        pair.stop()
    log('done')


if __name__ == '__main__':
    main()
