# Sourced by every Makefile target and script: keep DDS discovery on this
# machine, pick the Fast DDS middleware, and point ament/CMake at the venv.
# For a multi-machine graph, see README ("Networking").
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
_zeus_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export ZEUS_VENV="${ZEUS_VENV:-$_zeus_root/.venv}"
export AMENT_PREFIX_PATH="$ZEUS_VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$ZEUS_VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export PATH="$ZEUS_VENV/bin:$PATH"
unset _zeus_root
