"""A node whose start-up meets a SIGTERM inside code that swallows it, as native loaders do.

safetensors' Rust loader, interrupted by a signal while it builds tensors,
turns the exception the signal handler raised into an error of its own
("could not determine the shape of ..."). The node must still exit 0: a stop
was asked for, and the error is its consequence, not a corrupt file.
"""

import os
import signal
import sys

from rclpy.node import Node
from zeus_ros.ros.util import run_node


class LoaderError(Exception):
    """Stands for CheckpointError: the one start-up error the node reports as fatal."""


def load_like_native_code():
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):   # Python runs the handler here, inside the "load"
            pass
    except BaseException as error:  # noqa: BLE001 (the swallowing is what it stands for)
        raise LoaderError(f'could not determine the shape of object: {error!r}') from None


class SwallowingNode(Node):

    def __init__(self):
        super().__init__('stop_swallowing_node')
        load_like_native_code()


if __name__ == '__main__':
    sys.exit(run_node(SwallowingNode, fatal=(LoaderError,)))
