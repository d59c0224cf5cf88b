"""Offline learning tools: train, evaluate, adaptation reports, sweeps, ONNX export.

Command-line programs over the simulation, the learning core and deployment;
none of them starts ROS (`python -m zeus_ros.learning_tools.train --help`).
"""
