"""MuJoCo simulation of parameter-varied robots (no ROS: its node is zeus_ros.nodes.sim_node)."""

import os

# Nothing here renders; without this, importing dm_control probes for a display.
os.environ.setdefault('MUJOCO_GL', 'disable')
