"""The Fast DDS participant profile the nodes start with (issue #39.2).

On a loaded machine a (re)started node's first discovery exchange is often
lost, and it then waits for the running nodes' next periodic announcement:
0-3 s with Fast DDS's default period. The nodes load a profile that announces
every 0.5 s, unless the user names a profile of their own.
"""

import os
from pathlib import Path
import time
from xml.etree import ElementTree

from conftest import installed_exe
import pytest
from zeus_ros.ros.discovery import PROFILE_ENV, PROFILE_ENVS, profile_path, use_discovery_profile

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
    env = {name: value for name, value in os.environ.items() if name not in PROFILE_ENVS}
    env.update(env_extra)
    proc = spawn([installed_exe('sim_node'), '--ros-args', '--log-level',
                  'zeus_ros.discovery:=debug'], 'sim_node', env)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        lines = [line for line in proc.output().splitlines() if 'participant profile' in line]
        if lines:
            return lines[0]
        assert proc.alive(), proc.output()
        time.sleep(0.2)
    raise AssertionError(proc.output())


@pytest.mark.ros
def test_a_node_starts_with_the_profile_unless_the_user_names_one(spawn, tmp_path):
    assert str(profile_path()) in started_with(spawn, {})
    own = tmp_path / 'own.xml'
    own.write_text('<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"/>')
    assert "not zeus_ros's" in started_with(spawn, {'FASTRTPS_DEFAULT_PROFILES_FILE': str(own)})
