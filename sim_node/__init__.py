"""MuJoCo simulation of parameter-varied robots: the core and its ROS 2 node."""

import os

# Nothing here renders; without this, importing dm_control probes for a display.
os.environ.setdefault('MUJOCO_GL', 'disable')
