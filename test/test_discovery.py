"""The Fast DDS participant profile the nodes start with (issue #39).

On a loaded machine a (re)started node's first discovery exchange is often
lost, and it then waits for the running nodes' next periodic announcement:
0-3 s with Fast DDS's default period. The nodes load a profile that announces
every 0.5 s, unless the user names a profile of their own. The profile also
keeps topics and services off Fast DDS's shared memory, where a node killed
at the wrong moment leaves the running writers pushing into a deleted port
(research/benchmarks/shm_stale_port.md).
"""

import os
from pathlib import Path
import time
from xml.etree import ElementTree

from conftest import installed_exe
import pytest
from zeus_ros.ros.discovery import PROFILE_ENV, PROFILE_ENVS, profile_path, use_discovery_profile

REPO = Path(__file__).resolve().parents[1]
NS = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
MINE = Path('/my/own/profile.xml')


def test_the_profile_is_named_only_when_nothing_else_is():
    env = {}
    assert use_discovery_profile(env, MINE) == MINE and env == {PROFILE_ENV: str(MINE)}
    for own in ({'FASTRTPS_DEFAULT_PROFILES_FILE': '/theirs.xml'},
                {'FASTDDS_DEFAULT_PROFILES_FILE': '/theirs.xml'},
                {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}):
        env = dict(own)
        assert use_discovery_profile(env, MINE) is None and env == own
    env = {'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp'}
    assert use_discovery_profile(env, MINE) == MINE


def test_the_installed_profile_announces_every_half_second():
    path = profile_path()
    assert path is not None, 'config/fastdds_discovery.xml is not installed: run make setup'
    root = ElementTree.parse(path).getroot()
    participant = root.find('f:participant', NS)
    assert participant.get('is_default_profile') == 'true'
    period = participant.find('f:rtps/f:builtin/f:discovery_config/f:leaseAnnouncement', NS)
    seconds = int(period.find('f:sec', NS).text) + int(period.find('f:nanosec', NS).text) / 1e9
    assert seconds == 0.5


def started_with(spawn, env_extra: dict) -> str:
    """Return the line a real sim_node logs about its participant profile."""
    return started_sim(spawn, env_extra)[0]


def started_sim(spawn, env_extra: dict):
    """Start a real sim_node; return the line it logs about its profile, and the process."""
    env = {name: value for name, value in os.environ.items() if name not in PROFILE_ENVS}
    env.update(env_extra)
    proc = spawn([installed_exe('sim_node'), '--ros-args', '--log-level',
                  'zeus_ros.discovery:=debug'], 'sim_node', env)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        lines = [line for line in proc.output().splitlines() if 'participant profile' in line]
        if lines:
            return lines[0], proc
        assert proc.alive(), proc.output()
        time.sleep(0.2)
    raise AssertionError(proc.output())


@pytest.mark.ros
def test_a_node_starts_with_the_profile_unless_the_user_names_one(spawn, tmp_path):
    assert str(profile_path()) in started_with(spawn, {})
    own = tmp_path / 'own.xml'
    own.write_text('<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"/>')
    assert "not zeus_ros's" in started_with(spawn, {'FASTRTPS_DEFAULT_PROFILES_FILE': str(own)})


def test_the_installed_profile_sends_user_data_over_udp():
    root = ElementTree.parse(profile_path()).getroot()
    locators = root.findall('f:participant/f:rtps/f:defaultUnicastLocatorList/f:locator/*', NS)
    assert [loc.tag.split('}')[1] for loc in locators] == ['udpv4']
    assert locators[0].find('f:address', NS) is None   # every interface: machines still talk


def shared_memory_ports(pid: int) -> set[str]:
    """Return the Fast DDS shared-memory ports a process has mapped (its listening ports)."""
    maps = Path(f'/proc/{pid}/maps').read_text().splitlines()
    return {line.split()[-1] for line in maps if '/dev/shm/fastrtps_port' in line}


@pytest.mark.ros
def test_a_node_opens_no_shared_memory_port_with_the_profile(spawn):
    """#39.2: the stale-port fault needs a shared-memory port; with the profile there is none."""
    _, proc = started_sim(spawn, {})
    assert shared_memory_ports(proc.proc.pid) == set()
    before = REPO / 'research' / 'benchmarks' / 'fastdds_shared_memory.xml'
    _, proc = started_sim(spawn, {'FASTRTPS_DEFAULT_PROFILES_FILE': str(before)})
    assert shared_memory_ports(proc.proc.pid)   # the check sees ports where there are some
