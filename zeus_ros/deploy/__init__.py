"""Deployment: checkpoints (safetensors + typed JSON metadata) and the inference model.

Imports the learning core and the simulation's MuJoCo-free tables (families,
layouts, robot structures: what the metadata is checked against) only: no
rclpy, no MuJoCo (a deployed policy runs in a process that never loads it).
"""
