"""ROS graph tools: bring-up, the composed process, the demo, parity check, recording.

Command-line programs that start, drive or watch the nodes' ROS graph
(`python -m zeus_ros.ros_tools.demo --help`).
"""
