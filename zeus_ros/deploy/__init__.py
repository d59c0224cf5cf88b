"""Deployment: checkpoints (safetensors + typed JSON metadata) and the inference model.

Imports the learning core only: no rclpy, no simulation (a deployed policy
runs in a process that never loads MuJoCo).
"""
