"""context_node: keeps the last k transitions and publishes the latent context.

Subscribes /joint_states and /zeus/step, rebuilds each transition (s, a, r, s')
by stamp with the training window's semantics, runs psi, and publishes
/zeus/context once per state, stamped with the state it describes, with the
physical parameter decoded from the latent.

It does not subscribe /joint_commands: StepInfo carries the action MuJoCo
actually applied (after clipping, or zeros after a rejected or late command),
which a command on the wire cannot tell, and one subscription fewer is one
executor wake-up fewer per control step.
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node
from sensor_msgs.msg import JointState
from zeus_msgs.msg import Context, StepInfo
from diagnostic_msgs.msg import DiagnosticArray

from zeus_ros.checkpoint import CheckpointError
from zeus_ros.core.inference import InferenceModel
from zeus_ros.core.window import ContextWindow
from zeus_ros.loop_spin import create_loop_subscription
from zeus_ros.pairing import layout_from_metadata, TransitionAssembler
from zeus_ros.ros_util import (describe, diagnostic_array, LOOP_QOS, RateMeter, run_node,
                               set_stamp, stamp_ns)


class GraphMismatch(RuntimeError):
    """The running simulation is not the one the weights were trained for."""


def load_weights_parameter(node: Node) -> InferenceModel:
    """Declare the read-only `weights` parameter and load the checkpoint it names."""
    weights = node.declare_parameter('weights', '', describe(
        'Checkpoint directory (safetensors + metadata.json); read-only.',
        read_only=True)).value
    if not weights:
        raise CheckpointError('parameter "weights" is empty: pass -p weights:=<checkpoint>')
    model = InferenceModel.load(weights)
    node.get_logger().info(f'{model.family} weights from {weights}: k={model.k}, '
                           f'latent {model.context_dim}')
    return model


class ContextNode(Node):
    """Thin ROS shell around `TransitionAssembler` and the checkpoint's psi."""

    def __init__(self):
        super().__init__('context_node')
        self.model = load_weights_parameter(self)
        self.window = ContextWindow(self.model.k, self.model.obs_dim, self.model.action_dim)
        self.assembler = TransitionAssembler(self.window,
                                             layout_from_metadata(self.model.metadata))
        self.param_name = self.model.metadata['param_name']
        self.family_checked = False
        self.received_at: dict[int, float] = {}
        self.context_rate = RateMeter()    # latency: first message of a stamp -> context out

        self.context_pub = self.create_publisher(Context, '/zeus/context', LOOP_QOS)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        create_loop_subscription(self, JointState, '/joint_states', self.joint_state_callback,
                                 LOOP_QOS)
        create_loop_subscription(self, StepInfo, '/zeus/step', self.step_callback, LOOP_QOS)
        self.create_timer(1.0, self.diagnostics_callback)

    def joint_state_callback(self, msg: JointState) -> None:
        stamp = self._note(msg.header)
        try:
            record = self.assembler.add_joint_state(stamp, msg.name, msg.position,
                                                    msg.velocity)
        except ValueError as error:
            raise GraphMismatch(f'joint states do not fit the {self.model.family} weights: '
                                f'{error}') from None
        self._publish_for(record)

    def step_callback(self, msg: StepInfo) -> None:
        if not self.family_checked:
            if msg.family != self.model.family:
                raise GraphMismatch(f'the sim runs {msg.family!r} but the weights are for '
                                    f'{self.model.family!r}')
            self.family_checked = True
        stamp = self._note(msg.header)
        record = self.assembler.add_step_info(stamp, msg.episode, msg.step, msg.reward,
                                              msg.applied_action, msg.truncated)
        self._publish_for(record)

    def _note(self, header) -> int:
        stamp = stamp_ns(header)
        self.received_at.setdefault(stamp, time.monotonic())
        return stamp

    def _publish_for(self, record) -> None:
        if record is None:
            return
        rows, mask = self.window.arrays()
        latent = self.model.context(rows, mask)
        msg = Context(latent=latent.tolist(), window_fill=self.window.fill,
                      param_names=[self.param_name],
                      param_estimates=[self.model.decode(latent)])
        set_stamp(msg.header, record.stamp_ns)
        self.context_pub.publish(msg)
        first_seen = self.received_at.pop(record.stamp_ns, time.monotonic())
        self.context_rate.record(time.monotonic() - first_seen)
        for stale in [s for s in self.received_at if s < record.stamp_ns]:
            del self.received_at[stale]

    def diagnostics_callback(self) -> None:
        values = dict(self.context_rate.report(), window_fill=self.window.fill,
                      window_k=self.window.k, dropped=self.assembler.dropped,
                      gaps=self.assembler.gaps)
        problem = 'messages dropped or transitions missed' if (
            self.assembler.dropped or self.assembler.gaps) else None
        self.diagnostics_pub.publish(diagnostic_array(self, 'context', self.model.family,
                                                      values, problem))


def main(args=None):
    return run_node(ContextNode, args, fatal=(CheckpointError, GraphMismatch))


if __name__ == '__main__':
    sys.exit(main())
