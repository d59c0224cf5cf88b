"""foxglove_view serves the graph to a real Foxglove WebSocket client (foxglove.sdk.v1).

A small rclpy publisher stands in for the nodes (/zeus/step, /zeus/context,
/joint_states, /camera/image_raw); the client is `websockets` speaking the
Foxglove WebSocket protocol: serverInfo and advertise (JSON text), subscribe,
then binary message frames (opcode 1, subscription id, log time, payload).
"""

import base64
import contextlib
import json
import math
import os
from pathlib import Path
import re
import struct
import sys
import time

import pytest

from conftest import REPO

SUBPROTOCOL = 'foxglove.sdk.v1'
LAYOUT = REPO / 'config' / 'foxglove_layout.json'
TOPICS = ('/zeus/step', '/zeus/context', '/joint_states', '/camera/image_raw')


def start_view(spawn, port: int = 0, name: str = 'foxglove_view'):
    # This checkout's zeus_ros first, not an older colcon install.
    path = os.pathsep.join([str(REPO), os.environ.get('PYTHONPATH', '')])
    return spawn([sys.executable, '-m', 'zeus_ros.ros_tools.foxglove_view', '--port', str(port)],
                 name,
                 env=dict(os.environ, PYTHONPATH=path))


def served_port(proc, timeout: float = 60.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.alive():
        found = re.search(r'serving on ws://127\.0\.0\.1:(\d+)', proc.output())
        if found:
            return int(found.group(1))
        time.sleep(0.1)
    pytest.fail(f'foxglove_view did not start:\n{proc.output()}')


@contextlib.contextmanager
def foxglove_client(port: int):
    """Connect as the Foxglove app does; yield the client once the channels are advertised."""
    from websockets.sync.client import connect
    with connect(f'ws://127.0.0.1:{port}', subprotocols=[SUBPROTOCOL], open_timeout=10,
                 max_size=None) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        yield FoxgloveClient(ws)


class FoxgloveClient:
    """The client side of the Foxglove WebSocket protocol, as the Foxglove app speaks it."""

    def __init__(self, ws):
        self.ws = ws
        self.server_info = self._next_text('serverInfo')
        self.channels = {c['topic']: c for c in self._next_text('advertise')['channels']}
        self._by_subscription = {}

    def _next_text(self, op: str) -> dict:
        while True:
            message = json.loads(self.ws.recv(timeout=10))
            if message['op'] == op:
                return message

    def subscribe(self, topics) -> None:
        subscriptions = []
        for number, topic in enumerate(topics):
            self._by_subscription[number] = self.channels[topic]
            subscriptions.append({'id': number, 'channelId': self.channels[topic]['id']})
        self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subscriptions}))

    def receive(self, timeout: float):
        """Return (topic, log time ns, decoded message) of the next data frame, or None."""
        try:
            frame = self.ws.recv(timeout=timeout)
        except TimeoutError:
            return None
        if isinstance(frame, str):
            return None  # status and the like
        opcode, subscription, log_time = struct.unpack_from('<BIQ', frame)
        assert opcode == 1, f'binary opcode {opcode}'
        channel = self._by_subscription[subscription]
        return channel['topic'], log_time, decode(channel, frame[13:])


def decode(channel: dict, payload: bytes):
    if channel['encoding'] == 'json':
        return json.loads(payload)
    assert channel['encoding'] == 'protobuf' and channel['schemaEncoding'] == 'protobuf'
    return protobuf_class(channel['schema'], channel['schemaName']).FromString(payload)


def protobuf_class(schema_b64: str, name: str):
    """Return the message class an advertised FileDescriptorSet describes."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    files = list(descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64)).file)
    pool, added = descriptor_pool.DescriptorPool(), set()
    while files:  # dependencies first, whatever order the set lists them in
        ready = [f for f in files if set(f.dependency) <= added]
        assert ready, 'unresolvable descriptor set'
        for f in ready:
            pool.Add(f)
            added.add(f.name)
            files.remove(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def ros_messages():
    """One message per topic, with values the client must see unchanged."""
    from sensor_msgs.msg import Image, JointState
    from zeus_msgs.msg import Context, StepInfo
    step = StepInfo(episode=3, step=7, reward=0.25, applied_action=[0.5, -1.0],
                    truncated=False, family='walker-walk-v0', param_names=['friction'],
                    param_values=[0.4])
    context = Context(latent=[0.5, -0.25], window_fill=5, param_names=['friction', 'other'],
                      param_estimates=[1.07, math.nan])
    joints = JointState(name=['rootz', 'rootx'], position=[1.25, 0.5], velocity=[0.0, 2.0])
    image = Image(height=3, width=4, encoding='rgb8', step=12, data=bytes(range(36)))
    for msg in (step, context, joints, image):
        msg.header.stamp.sec, msg.header.stamp.nanosec = 42, 125
        msg.header.frame_id = 'sim_camera_optical' if msg is image else ''
    return dict(zip(TOPICS, (step, context, joints, image), strict=True))


def receive_all(client, publishers, messages, timeout: float = 30.0) -> dict:
    """Publish until the client has had a message on every topic; return the first of each."""
    got, deadline = {}, time.monotonic() + timeout
    while len(got) < len(TOPICS) and time.monotonic() < deadline:
        for topic, msg in messages.items():
            publishers[topic].publish(msg)
        frame = client.receive(timeout=0.2)
        while frame is not None:
            got.setdefault(frame[0], frame[1:])
            frame = client.receive(timeout=0.05)
    missing = set(TOPICS) - set(got)
    assert not missing, f'nothing received on {sorted(missing)}'
    return got


def test_a_real_client_receives_every_channel_with_its_values(ros_node, spawn):
    from sensor_msgs.msg import Image, JointState
    from zeus_msgs.msg import Context, StepInfo
    proc = start_view(spawn)
    port = served_port(proc)
    assert listening_addresses(port) == {'127.0.0.1'}
    types = dict(zip(TOPICS, (StepInfo, Context, JointState, Image), strict=True))
    publishers = {t: ros_node.create_publisher(types[t], t, 10) for t in TOPICS}
    with foxglove_client(port) as client:
        assert set(TOPICS) <= set(client.channels)
        client.subscribe(TOPICS)
        started = time.time_ns()
        got = receive_all(client, publishers, ros_messages())
    check_values({topic: message for topic, (_, message) in got.items()})
    for topic, (log_time, _) in got.items():  # receive time: plots run on wall time
        assert started - 60e9 < log_time < time.time_ns() + 1e9, topic
    assert proc.stop() == 0, proc.output()


def check_values(got: dict) -> None:
    step, context, joints, image = (got[t] for t in TOPICS)
    stamp = {'sec': 42, 'nsec': 125}
    assert step['header']['stamp'] == stamp and context['header']['stamp'] == stamp
    assert (step['episode'], step['step'], step['reward']) == (3, 7, 0.25)
    assert step['param_names'] == ['friction'] and step['param_true'] == 0.4
    assert step['param_values'] == [0.4] and step['applied_action'] == [0.5, -1.0]
    assert step['truncated'] is False and step['family'] == 'walker-walk-v0'
    assert context['window_fill'] == 5 and context['param_names'] == ['friction', 'other']
    assert context['param_decoded'] == pytest.approx(1.07, abs=1e-6)  # float32 on the wire
    assert context['param_estimates'][1] is None  # NaN: JSON has none, the view says null
    assert context['latent'] == [0.5, -0.25]
    assert joints['name'] == ['rootz', 'rootx'] and joints['position'] == [1.25, 0.5]
    assert joints['velocity'] == [0.0, 2.0]
    assert (image.width, image.height, image.encoding, image.step) == (4, 3, 'rgb8', 12)
    assert image.data == bytes(range(36)) and image.frame_id == 'sim_camera_optical'
    assert (image.timestamp.seconds, image.timestamp.nanos) == (42, 125)


def listening_addresses(port: int) -> set:
    """Local addresses of the TCP sockets listening on `port` (from /proc/net/tcp{,6})."""
    addresses = set()
    for table in ('/proc/net/tcp', '/proc/net/tcp6'):
        for line in Path(table).read_text().splitlines()[1:]:
            local, _, state = line.split()[1:4]
            address, hex_port = local.split(':')
            if state == '0A' and int(hex_port, 16) == port:  # 0A: LISTEN
                addresses.add(_ip(address))
    return addresses


def _ip(hex_address: str) -> str:
    if len(hex_address) == 8:  # IPv4, little-endian
        return '.'.join(str(b) for b in bytes.fromhex(hex_address)[::-1])
    return f'ipv6:{hex_address}'


def test_layout_shows_what_the_view_serves_and_a_taken_port_is_refused(spawn):
    proc = start_view(spawn)
    port = served_port(proc)
    with foxglove_client(port) as client:
        channels = client.channels
    layout = json.loads(LAYOUT.read_text())
    panels = layout['configById']
    assert _panel_ids(layout['layout']) == set(panels)
    image_topics = [c['imageMode']['imageTopic'] for k, c in panels.items()
                    if k.startswith('Image!')]
    assert image_topics == ['/camera/image_raw']
    assert channels['/camera/image_raw']['schemaName'] == 'foxglove.RawImage'
    plotted = [p['value'] for k, c in panels.items() if k.startswith('Plot!') for p in c['paths']]
    assert {'/zeus/step.param_true', '/zeus/context.param_decoded',
            '/zeus/step.reward'} <= set(plotted)
    for path in plotted:
        topic, field = path.split('.', 1)
        schema = json.loads(channels[topic]['schema'])
        assert 'number' in schema['properties'][field]['type'], path
    raw = [c['topicPath'] for k, c in panels.items() if k.startswith('RawMessages!')]
    assert raw and all(topic in channels for topic in raw)
    second = start_view(spawn, port, 'second_view')
    assert second.proc.wait(60) == 1
    assert f'cannot serve on 127.0.0.1:{port}' in second.output(), second.output()


def _panel_ids(node) -> set:
    if isinstance(node, str):
        return {node}
    return _panel_ids(node['first']) | _panel_ids(node['second'])




def test_rendered_frames_of_the_sim_reach_the_client(spawn, tmp_path):
    """End to end: a CameraPublisher over a stepping ParamEnv, the view, a client."""
    import numpy as np
    from PIL import Image as PILImage
    from test_camera import camera_node_command, robot_mask
    camera = spawn(*camera_node_command(rate=5.0))
    proc = start_view(spawn)
    with foxglove_client(served_port(proc)) as client:
        client.subscribe(['/camera/image_raw'])
        deadline, frame = time.monotonic() + 60, None
        while frame is None and time.monotonic() < deadline:
            frame = client.receive(timeout=0.5)
    assert frame is not None, camera.output()
    image = frame[2]
    assert (image.width, image.height, image.encoding) == (320, 240, 'rgb8')
    pixels = np.frombuffer(image.data, np.uint8).reshape(240, 320, 3)
    PILImage.fromarray(pixels).save(tmp_path / 'foxglove_frame.png')
    assert robot_mask(pixels).mean() > 0.01
