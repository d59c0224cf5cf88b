"""ROS plumbing shared by the nodes; never imports MuJoCo or torch directly.

QoS, stamps, diagnostics and the node life cycle (`util`), the lean loop spin
(`loop_spin`), message pairing and the stamp rule (`pairing`), and what both
controller nodes do with their weights (`controller`).
"""
