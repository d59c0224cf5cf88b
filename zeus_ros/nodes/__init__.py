"""The ROS 2 nodes: thin `Node` shells over the layers below (`ros2 run zeus_ros <name>`).

`sim_node` steps the MuJoCo simulation, `context_node` estimates the context,
`policy_node` acts. No node imports another; `zeus_ros.ros_tools.composed`
runs all three in one process.
"""
