"""The Fast DDS participant profile every zeus_ros node starts with (issue #39).

Fast DDS reads a default XML profile named by an environment variable when the
process creates its first participant (rclpy.init). `use_discovery_profile`
names zeus_ros's own (config/fastdds_discovery.xml: participants announce
themselves every 0.5 s instead of 3 s, and topics and services travel over
UDPv4, not shared memory, whose ports a killed node can leave stale) unless
the user already named one, or the middleware is not Fast DDS.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import MutableMapping

PROFILE_NAME = 'fastdds_discovery.xml'
# Fast DDS 2.x reads the first; 3.x the second. A user's own profile wins.
PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
PROFILE_ENVS = (PROFILE_ENV, 'FASTDDS_DEFAULT_PROFILES_FILE')
FAST_DDS = 'rmw_fastrtps_cpp'   # ROS 2 Jazzy's default middleware


def profile_path() -> Path | None:
    """Return the installed profile (the package's share/config), else None."""
    from ament_index_python.packages import (get_package_share_directory,
                                             PackageNotFoundError)
    try:
        path = Path(get_package_share_directory('zeus_ros')) / 'config' / PROFILE_NAME
    except PackageNotFoundError:
        return None
    return path if path.is_file() else None


def use_discovery_profile(environ: MutableMapping[str, str] = os.environ,
                          path: Path | None = None) -> Path | None:
    """Name zeus_ros's profile for Fast DDS in `environ`; return it, or None if left alone.

    Left alone: another middleware, a profile the user already named, or no
    installed profile (the node then runs with Fast DDS's defaults).
    """
    if environ.get('RMW_IMPLEMENTATION', FAST_DDS) != FAST_DDS:
        return None
    if any(environ.get(name) for name in PROFILE_ENVS):
        return None
    path = path or profile_path()
    if path is None:
        return None
    environ[PROFILE_ENV] = str(path)
    return path
