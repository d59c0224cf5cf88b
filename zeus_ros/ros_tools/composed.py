"""composed: sim_node, context_node and policy_node in one process (composition).

rclpy has no component container; here the three node classes, unchanged,
are built in one process with one rclpy context and spun together by
`zeus_ros.ros.loop_spin.spin_loop` on one loop thread. Their topics stay on
DDS (Fast DDS hands a message to a reader of the same process without a
network transport), so `ros2 topic echo`, a recording or the bench observer
see the graph exactly as with three processes: the same node names, topics,
parameters and services. Per-node parameters take the node's name:

    python -m zeus_ros.ros_tools.composed --ros-args -p sim_node:family:=walker-walk-v0
        -p context_node:weights:=DIR -p policy_node:weights:=DIR

(`bringup --composed` and `ros2 launch zeus_ros zeus.launch.py composed:=true`
build that command line.) Ctrl-C or SIGTERM stops all three cleanly (exit 0);
a node that fails to start, or a fatal error in any of them, ends all three
with 1 and one line naming it.
"""

# ruff: noqa: E402
# (The stop guard must come before the heavy imports: torch and MuJoCo load for seconds.)
from __future__ import annotations

from zeus_ros.ros import stop_guard

stop_guard.install('composed', __name__)

import sys

from zeus_ros.nodes.sim_node import SimNode
from zeus_ros.nodes.context_node import ContextNode
from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.nodes.policy_node import PolicyNode
from zeus_ros.ros.controller import GraphMismatch
from zeus_ros.ros.util import run_nodes

# In the order a control step crosses them: the loop thread dispatches each
# wake-up's messages in this order, so one pass often carries a whole step.
NODE_CLASSES = (SimNode, ContextNode, PolicyNode)
# What ends each node with one line when run alone (see each node's main).
FATAL = (ValueError, CheckpointError, GraphMismatch)


def main(args: list[str] | None = None) -> int:
    return run_nodes(NODE_CLASSES, args, fatal=FATAL, name='composed')


if __name__ == '__main__':
    sys.exit(main())
