"""What both controller nodes (context_node, policy_node) do with their weights and the sim.

Load the checkpoint named by the read-only `weights` parameter (run by the
`backend` parameter's torch or ONNX Runtime), refuse a sim
of another family, and word the warnings about the sim's clock. Plain
functions over rclpy's Node API; shared here so that neither node imports
the other.
"""

from __future__ import annotations

from rclpy.exceptions import ParameterException
from rclpy.node import Node

from zeus_ros.deploy.checkpoint import CheckpointError
from zeus_ros.deploy.backends import BACKENDS, load_deployed
from zeus_ros.deploy.inference import DeployedModel
from zeus_ros.ros.pairing import OUTLIER
from zeus_ros.ros.util import describe


class GraphMismatch(RuntimeError):
    """The running simulation is not the one the weights were trained for."""


def load_weights_parameter(node: Node) -> DeployedModel:
    """Declare the read-only `weights` and `backend` parameters; load the checkpoint for it."""
    weights = node.declare_parameter('weights', '', describe(
        'Checkpoint directory (safetensors + metadata.json), or an ONNX export '
        'directory for the onnx backend; read-only.', read_only=True)).value
    backend = node.declare_parameter('backend', 'torch', describe(
        f'What runs the networks, one of {", ".join(BACKENDS)}: onnx runs the ONNX '
        'export (made and cached on the fly if the checkpoint has none; read-only).',
        read_only=True)).value
    if backend not in BACKENDS:
        raise ParameterException(f'must be one of {", ".join(BACKENDS)}, got {backend!r}',
                                 'backend')
    if not weights:
        raise CheckpointError('parameter "weights" is empty: pass -p weights:=<checkpoint>')
    model = load_deployed(weights, backend)
    node.get_logger().info(f'{model.family} weights from {weights}: k={model.k}, '
                           f'latent {model.context_dim} ({model.backend_note})')
    return model


def check_family(sim_family: str, model: DeployedModel) -> None:
    """Refuse (GraphMismatch) a sim that runs another family than the weights'."""
    if sim_family != model.family:
        raise GraphMismatch(f'the sim runs {sim_family!r} but the weights are for '
                            f'{model.family!r}')


def describe_clock_event(event: str, stamp: int, previous: int | None) -> str:
    """One line for a warning about the sim clock (see zeus_ros.ros.pairing.StampFollower)."""
    jump = '' if previous is None else f' ({(stamp - previous) / 1e9:+.3f} s)'
    if event.endswith(OUTLIER):
        return (f'{event}: ignored a message stamped {stamp / 1e9:.3f} s, far ahead of '
                f'the sim clock{jump}')
    return (f'{event}: the sim clock went to {stamp / 1e9:.3f} s{jump}, a restarted sim? '
            'Starting over')
