"""The documented Ray cluster commands, run by scripts/ray_local_cluster.sh on this machine.

Two nodes on loopback with token authentication, a two-trial sweep across them
whose driver is killed mid-run and resumed, and the cluster stopped (~2-3 min).
"""

import json
import os
from pathlib import Path
import re
import signal
import subprocess

import pytest

from sweep_helpers import assert_resumed_not_restarted, checkpoint_timestep

pytestmark = pytest.mark.ros   # starts processes of its own

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / 'scripts' / 'ray_local_cluster.sh'


def readme_cluster_commands() -> list[str]:
    """Return the command lines of the docs' cluster block, without their comments."""
    text = (REPO / 'docs' / 'pages' / 'training.md').read_text()
    block = re.search(r'### Sweeps on a Ray cluster\n.*?```bash\n(.*?)```', text, re.S)
    assert block, 'docs/pages/training.md has no "Sweeps on a Ray cluster" block'
    lines = [re.sub(r'\s+# .*$', '', line) for line in block.group(1).splitlines()]
    return [line for line in lines if line and not line.startswith('#')]


@pytest.mark.unit
def test_the_readme_gives_exactly_the_cluster_commands_the_script_runs():
    commands = readme_cluster_commands()
    assert commands[0].startswith('HEAD=')   # the addresses and paths each machine sets
    script = SCRIPT.read_text().splitlines()
    # a script line may add its plumbing: where the output goes, `&`, `|| fail ...`
    plumbing = re.compile(r'( [0-9]?>.*| &| \|\| .*)?')
    missing = [command for command in commands[1:] if not any(
        line.startswith(command) and plumbing.fullmatch(line[len(command):])
        for line in script)]
    assert not missing, missing
    assert any(line.startswith('export RAY_AUTH_MODE=token ') for line in commands)


@pytest.mark.timeout(900)   # its own wait for the sweep is 600 s
def test_two_node_loopback_cluster_with_token_auth_runs_a_sweep_that_survives_its_driver(
        tmp_path):
    work = tmp_path / 'cluster'
    proc = subprocess.Popen([str(SCRIPT), str(work)], start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:   # the namespaces end with the script: nothing stays
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, out[-4000:]
    for step in ('listening on loopback only (two nodes)',
                 'wrong token and a node without one are refused',
                 'listening on loopback only (sweep running)', 'driver killed mid-run',
                 'the trials trained on both nodes', 'no Ray process left'):
        assert step in out, (step, out[-4000:])
    assert (work / 'ray_token').stat().st_mode & 0o077 == 0   # the token is the user's only
    runs = work / 'sweeps' / 'cluster_smoke' / 'runs'
    for seed in (1, 2):
        run = runs / f'finger-spin-v0.sac.s{seed}'
        assert checkpoint_timestep(run) == 240
        assert_resumed_not_restarted(run, steps=240, log_every=10, lost_rows=2)
    nodes = {json.loads(line)['node'] for path in (work / 'sweeps' / 'cluster_smoke' / 'tune')
             .glob('*/result.json') for line in path.read_text().splitlines()}
    assert len(nodes) == 2
    sessions = subprocess.run(['ps', '-eo', 'sid='], capture_output=True, text=True).stdout
    assert str(proc.pid) not in sessions.split()   # no process of the cluster outlived it
