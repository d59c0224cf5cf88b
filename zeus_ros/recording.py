"""Record ROS 2 topics to MCAP, as `ros2 bag record -s mcap` would.

Messages are taken serialized (CDR, straight from DDS: no conversion) and
written with `ros2msg` schemas built from the installed `.msg` files, so the
file opens in `ros2 bag info`, Foxglove and the `mcap` readers.
"""

from __future__ import annotations

import importlib
from pathlib import Path
import re
import time

from ament_index_python.packages import get_package_share_directory
from mcap.writer import CompressionType, Writer
from rclpy.qos import QoSProfile, ReliabilityPolicy

from zeus_ros.loop_spin import create_loop_subscription

_SEPARATOR = '=' * 80
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16',
               'uint16', 'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'}
RECORD_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


def message_class(type_name: str):
    """Import the Python class of `pkg/msg/Type`."""
    package, kind, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def _msg_text(type_name: str) -> str:
    package, _, name = type_name.split('/')
    return (Path(get_package_share_directory(package)) / 'msg' / f'{name}.msg').read_text()


def _field_types(text: str, package: str) -> list[str]:
    types = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line or '=' in line.split()[1 if len(line.split()) > 1 else 0]:
            continue
        base = re.sub(r'<=\d+|\[.*\]', '', line.split()[0])
        if base in _PRIMITIVES:
            continue
        if '/' not in base:
            base = 'std_msgs/Header' if base == 'Header' else f'{package}/{base}'
        pkg, name = base.split('/')[0], base.split('/')[-1]
        types.append(f'{pkg}/msg/{name}')
    return types


def message_definition(type_name: str) -> str:
    """Full ros2msg definition of `pkg/msg/Type`, dependencies appended once each."""
    text = _msg_text(type_name)
    parts, seen = [text.rstrip('\n')], {type_name}
    queue = _field_types(text, type_name.split('/')[0])
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dep_text = _msg_text(dep)
        package, _, name = dep.split('/')
        parts.append(f'{_SEPARATOR}\nMSG: {package}/{name}\n{dep_text.rstrip()}')
        queue.extend(_field_types(dep_text, package))
    return '\n'.join(parts) + '\n'


class McapRecorder:
    """Subscribe to topics (raw CDR) on an existing node and write them to an MCAP file."""

    def __init__(self, node, path: Path, topics: dict[str, str]):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, 'wb')
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile='ros2', library='zeus_ros')
        self.counts: dict[str, int] = {}
        self._channels = {}
        for topic, type_name in topics.items():
            schema = self._writer.register_schema(
                name=type_name, encoding='ros2msg',
                data=message_definition(type_name).encode())
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding='cdr', schema_id=schema)
            self.counts[topic] = 0
            # Loop subscriptions: taken by spin_loop, which keeps up with the
            # loop's rate where rclpy's executor drops messages.
            create_loop_subscription(node, message_class(type_name), topic,
                                     self._writer_for(topic), RECORD_QOS, raw=True)

    def _writer_for(self, topic: str):
        channel = self._channels[topic]

        def write(data: bytes) -> None:
            now = time.time_ns()
            self._writer.add_message(channel_id=channel, log_time=now, publish_time=now,
                                     sequence=self.counts[topic], data=data)
            self.counts[topic] += 1
        return write

    def close(self) -> None:
        self._writer.finish()
        self._file.close()
