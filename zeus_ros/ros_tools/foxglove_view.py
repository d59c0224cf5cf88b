"""foxglove_view: the running graph, live in Foxglove, with no ROS desktop install.

    python -m zeus_ros.ros_tools.foxglove_view --port 8765   # or: ros2 run zeus_ros foxglove_view

joins the graph as a ROS node and serves what it hears over WebSocket with
foxglove-sdk (subprotocol foxglove.sdk.v1), on 127.0.0.1 only. In Foxglove:
Open connection > Foxglove WebSocket > ws://127.0.0.1:8765, then import the
layout config/foxglove_layout.json (the camera, true vs decoded parameter,
reward, joint states).

| channel | from | encoding |
|---|---|---|
| /camera/image_raw | sensor_msgs/Image | foxglove.RawImage (protobuf): the Image panel |
| /joint_states | sensor_msgs/JointState | JSON: name, position, velocity, effort |
| /zeus/step | zeus_msgs/StepInfo | JSON: the message's fields, plus `param_true` |
| /zeus/context | zeus_msgs/Context | JSON: the message's fields, plus `param_decoded` |

`param_true` and `param_decoded` are the first (every family has one)
parameter's true and decoded values as plain numbers, so that one plot needs
no array index and reads the same for every family. JSON has no NaN: a value
that is not finite (no decoder in the weights) is null.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Callable, Sequence, TYPE_CHECKING

import foxglove
from foxglove.channels import RawImageChannel
from foxglove.messages import RawImage, Timestamp
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import Image, JointState
from zeus_msgs.msg import Context, StepInfo

from zeus_ros.ros.util import run_node

if TYPE_CHECKING:
    from std_msgs.msg import Header

# Never beyond this machine: the view has no authentication.
HOST = '127.0.0.1'
DEFAULT_PORT = 8765
# A viewer must never hold the loop up: best effort, shallow (a lost sample
# is a gap in a plot, not a stalled step).
VIEW_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
IMAGE_QOS = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT)

_NUMBER = {'type': ['number', 'null']}
_NUMBERS = {'type': 'array', 'items': _NUMBER}
_STRINGS = {'type': 'array', 'items': {'type': 'string'}}
_HEADER = {'type': 'object', 'properties': {
    'stamp': {'type': 'object', 'properties': {'sec': {'type': 'integer'},
                                               'nsec': {'type': 'integer'}}},
    'frame_id': {'type': 'string'}}}


def _schema(title: str, **properties) -> dict:
    return {'title': title, 'type': 'object',
            'properties': {'header': _HEADER, **properties}}


SCHEMAS = {
    '/joint_states': _schema('zeus_ros.JointState', name=_STRINGS, position=_NUMBERS,
                             velocity=_NUMBERS, effort=_NUMBERS),
    '/zeus/step': _schema('zeus_ros.StepInfo', episode={'type': 'integer'},
                          step={'type': 'integer'}, reward=_NUMBER,
                          applied_action=_NUMBERS, terminal={'type': 'boolean'},
                          truncated={'type': 'boolean'}, family={'type': 'string'},
                          param_names=_STRINGS, param_values=_NUMBERS, param_true=_NUMBER),
    '/zeus/context': _schema('zeus_ros.Context', latent=_NUMBERS,
                             window_fill={'type': 'integer'}, param_names=_STRINGS,
                             param_estimates=_NUMBERS, param_decoded=_NUMBER),
}
IMAGE_TOPIC = '/camera/image_raw'


class ServeError(RuntimeError):
    """The WebSocket server could not start (port taken, bad port)."""


def finite(value: float) -> float | None:
    """Return a float for JSON: None for NaN and inf, which JSON cannot carry."""
    value = float(value)
    return value if math.isfinite(value) else None


def header_json(header: Header) -> dict:
    """Return a header with its stamp as Foxglove reads one (sec, nsec)."""
    return {'stamp': {'sec': int(header.stamp.sec), 'nsec': int(header.stamp.nanosec)},
            'frame_id': header.frame_id}


def _first(values: Sequence[float]) -> float | None:
    return finite(values[0]) if len(values) else None


def step_json(msg: StepInfo) -> dict:
    """Return a StepInfo as JSON, with `param_true` the first parameter's true value."""
    return {'header': header_json(msg.header), 'episode': int(msg.episode),
            'step': int(msg.step), 'reward': finite(msg.reward),
            'applied_action': [finite(a) for a in msg.applied_action],
            'terminal': bool(msg.terminal), 'truncated': bool(msg.truncated),
            'family': msg.family, 'param_names': list(msg.param_names),
            'param_values': [finite(v) for v in msg.param_values],
            'param_true': _first(msg.param_values)}


def context_json(msg: Context) -> dict:
    """Return a Context as JSON, with `param_decoded` the first parameter's estimate."""
    return {'header': header_json(msg.header), 'latent': [finite(v) for v in msg.latent],
            'window_fill': int(msg.window_fill), 'param_names': list(msg.param_names),
            'param_estimates': [finite(v) for v in msg.param_estimates],
            'param_decoded': _first(msg.param_estimates)}


def joint_state_json(msg: JointState) -> dict:
    """Return a JointState as JSON."""
    return {'header': header_json(msg.header), 'name': list(msg.name),
            'position': [finite(v) for v in msg.position],
            'velocity': [finite(v) for v in msg.velocity],
            'effort': [finite(v) for v in msg.effort]}


def raw_image(msg: Image) -> RawImage:
    """Return a sensor_msgs/Image as Foxglove's RawImage (same encoding, rows and bytes)."""
    stamp = Timestamp(sec=int(msg.header.stamp.sec), nsec=int(msg.header.stamp.nanosec))
    return RawImage(timestamp=stamp, frame_id=msg.header.frame_id, width=int(msg.width),
                    height=int(msg.height), encoding=msg.encoding, step=int(msg.step),
                    data=bytes(msg.data))


class FoxgloveView(Node):
    """Subscribe to the loop's topics and the camera; log each message on its Foxglove channel."""

    def __init__(self, port: int):
        super().__init__('foxglove_view')
        # Channels exist from the start, so a client sees them all before data flows.
        self.channels = {topic: foxglove.Channel(topic, schema=schema)
                         for topic, schema in SCHEMAS.items()}
        self.channels[IMAGE_TOPIC] = RawImageChannel(IMAGE_TOPIC)
        try:
            self.server = foxglove.start_server(name='zeus_ros', host=HOST, port=port)
        except Exception as error:  # the SDK raises RuntimeError for a taken port
            raise ServeError(f'cannot serve on {HOST}:{port}: {error}') from error
        for topic, msg_type, convert in ((IMAGE_TOPIC, Image, raw_image),
                                         ('/joint_states', JointState, joint_state_json),
                                         ('/zeus/step', StepInfo, step_json),
                                         ('/zeus/context', Context, context_json)):
            qos = IMAGE_QOS if topic == IMAGE_TOPIC else VIEW_QOS
            self.create_subscription(msg_type, topic, self._forward(topic, convert), qos)
        self.get_logger().info(f'serving on ws://{HOST}:{self.server.port} (Foxglove: Open '
                               'connection > Foxglove WebSocket; layout '
                               'config/foxglove_layout.json)')

    # `convert`: the topic's message -> what its channel logs (raw_image, step_json, ...).
    def _forward(self, topic: str, convert: Callable):
        channel = self.channels[topic]

        def callback(msg: Image | JointState | StepInfo | Context) -> None:
            if channel.has_sinks():  # no client subscribed: skip the conversion
                channel.log(convert(msg))
        return callback

    def destroy_node(self) -> None:
        self.server.stop()
        super().destroy_node()


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='foxglove_view', description=__doc__.split('\n')[0])
    parser.add_argument('--port', type=int, default=DEFAULT_PORT,
                        help=f'WebSocket port on {HOST} (0: any free one; default '
                             f'{DEFAULT_PORT})')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(remove_ros_args(['foxglove_view', *argv])[1:])

    def foxglove_view():  # run_node builds the node and names it in its messages
        return FoxgloveView(args.port)

    return run_node(foxglove_view, ['foxglove_view', *argv], fatal=(ServeError,))


if __name__ == '__main__':
    sys.exit(main())
