"""The colcon install is what `ros2 run` expects, and every Python source lints clean."""

import os
from pathlib import Path
import re
import subprocess

from ament_index_python.packages import get_package_share_directory, get_packages_with_prefixes
from conftest import INSTALL_BIN, REPO


def declared_executables():
    setup_py = (REPO / 'setup.py').read_text()
    return re.findall(r"'([\w-]+) = [\w.]+:\w+'", setup_py)


def test_ament_index_lists_both_packages():
    packages = get_packages_with_prefixes()
    assert 'zeus_ros' in packages and 'zeus_msgs' in packages
    share = Path(get_package_share_directory('zeus_ros'))
    assert (share / 'package.xml').is_file()


def test_declared_executables_are_installed_where_ros2_run_looks():
    names = declared_executables()
    assert 'sim_node' in names
    for name in names:
        path = INSTALL_BIN / name
        assert path.is_file(), f'{name} missing from {INSTALL_BIN}'
        assert os.access(path, os.X_OK), f'{path} is not executable'


def test_discovery_is_confined_to_localhost():
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    assert 20 <= int(os.environ['ROS_DOMAIN_ID']) < 100


def test_ruff_lint_clean():
    result = subprocess.run(['ruff', 'check', '--no-cache', str(REPO)], cwd=REPO,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
