"""ROS-free ZeUS learning core: context window, networks, losses, replay, agent, inference.

Nothing in this package imports rclpy; the ROS nodes import from it.
"""
