"""zeus_ros: ZeUS zero-shot adaptation (learning core, trainer, evaluation) for ROS 2."""
