"""Record ROS 2 topics into a rosbag2 bag, as `ros2 bag record -s mcap` writes it.

A bag is a directory `<name>/` holding `<name>_0.mcap` and `metadata.yaml`
(rosbag2 metadata version 9, ROS 2 Jazzy), so `ros2 bag info <name>`,
`ros2 bag play <name>`, Foxglove and the `rosbags` readers open it.
Messages are taken serialized (CDR, straight from DDS: no conversion) and
written with `ros2msg` schemas built from the installed `.msg` files. Each
topic carries the QoS profiles its publishers offer (`offered_qos_profiles`,
which `ros2 bag play` republishes with) and its type description hash.

`python -m zeus_ros.ros_tools.recording video <bag> <out.gif>` renders the robot of a
recorded episode (see `render_video`).
"""

from __future__ import annotations

import argparse
import copy
from dataclasses import dataclass, field
import importlib
import json
import os
from pathlib import Path
import re
import sys
import time
from typing import TYPE_CHECKING

from ament_index_python.packages import get_package_share_directory
from mcap.writer import CompressionType, Writer
from rclpy.duration import Duration, Infinite
from rclpy.qos import HistoryPolicy, QoSProfile
import yaml

from zeus_ros.ros.loop_spin import create_loop_subscription

if TYPE_CHECKING:
    from dm_control.mujoco import Physics
    import PIL.Image
    from rclpy.node import Node

_SEPARATOR = '=' * 80
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16',
               'uint16', 'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'}
METADATA_VERSION = 9       # rosbag2 in ROS 2 Jazzy
ROS_DISTRO = 'jazzy'
# The recorder's own queue: deep enough that a recorder thread stalled on a
# loaded machine loses nothing (DDS fills it while Python is away), 2-3 s of
# the loop at full speed.
RECORD_DEPTH = 1000
_NS = 1_000_000_000


def message_class(type_name: str) -> type:
    """Import the Python class of `pkg/msg/Type`."""
    package, kind, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def _interface_file(type_name: str, suffix: str) -> Path:
    package, kind, name = type_name.split('/')
    return Path(get_package_share_directory(package)) / kind / f'{name}{suffix}'


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
    text = _interface_file(type_name, '.msg').read_text()
    parts, seen = [text.rstrip('\n')], {type_name}
    queue = _field_types(text, type_name.split('/')[0])
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dep_text = _interface_file(dep, '.msg').read_text()
        package, _, name = dep.split('/')
        parts.append(f'{_SEPARATOR}\nMSG: {package}/{name}\n{dep_text.rstrip()}')
        queue.extend(_field_types(dep_text, package))
    return '\n'.join(parts) + '\n'


def type_description_hash(type_name: str) -> str:
    """Return the type's RIHS01 hash, as rosidl generated it beside the `.msg` (or '')."""
    try:
        hashes = json.loads(_interface_file(type_name, '.json').read_text())['type_hashes']
    except (OSError, KeyError, ValueError):
        return ''
    return next((h['hash_string'] for h in hashes if h['type_name'] == type_name), '')


# -- QoS as rosbag2 >= version 9 writes it (rosbag2_storage/qos.cpp) ---------------------
def _rmw_time(duration: Duration) -> dict:
    ns = duration.nanoseconds
    return {'sec': ns // _NS, 'nsec': ns % _NS}


def qos_entry(profile: QoSProfile) -> dict:
    """One `offered_qos_profiles` entry: policies by their rmw names, durations as sec/nsec."""
    return {'history': profile.history.name.lower(), 'depth': int(profile.depth),
            'reliability': profile.reliability.name.lower(),
            'durability': profile.durability.name.lower(),
            'deadline': _rmw_time(profile.deadline), 'lifespan': _rmw_time(profile.lifespan),
            'liveliness': profile.liveliness.name.lower(),
            'liveliness_lease_duration': _rmw_time(profile.liveliness_lease_duration),
            'avoid_ros_namespace_conventions': bool(profile.avoid_ros_namespace_conventions)}


def offered_profiles(node: Node, topic: str, declared: QoSProfile) -> list[QoSProfile]:
    """QoS of each publisher of `topic` the graph knows, as `ros2 bag record` stores them.

    DDS discovery carries reliability, durability, deadline, lifespan and
    liveliness, not history and depth (rmw reports UNKNOWN, 0): those come
    from `declared`, the profile the project's publishers are created with,
    so that `ros2 bag play` republishes with the same queue. With no
    publisher known, `declared` alone.
    """
    profiles = []
    for info in node.get_publishers_info_by_topic(topic):
        found = info.qos_profile
        if found.history in (HistoryPolicy.UNKNOWN, HistoryPolicy.SYSTEM_DEFAULT):
            found.history, found.depth = declared.history, declared.depth
        profiles.append(found)
    return profiles or [declared]


def _infinite_if_default(profile: QoSProfile) -> QoSProfile:
    # rclpy's 0 means "the rmw default", which for these three is infinite; a
    # recorder reading the graph sees (and stores) them as infinite.
    profile = copy.copy(profile)   # never the caller's (LOOP_QOS is shared)
    for name in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        if getattr(profile, name).nanoseconds == 0:
            setattr(profile, name, Infinite)
    return profile


@dataclass(frozen=True)
class TopicSpec:
    """A topic to record: its type and the QoS its publishers are created with."""

    type_name: str
    qos: QoSProfile


@dataclass
class _Topic:
    name: str
    type_name: str
    profiles: list[QoSProfile]
    channel: int
    count: int = 0


@dataclass
class _Span:
    """Receive times of the messages written so far (ns since the epoch)."""

    first: int | None = None
    last: int | None = None

    def add(self, t: int) -> None:
        self.first = t if self.first is None else min(self.first, t)
        self.last = t if self.last is None else max(self.last, t)

    def metadata(self) -> tuple[dict, dict]:
        """(starting_time, duration), new dicts each call (no YAML anchors between uses)."""
        start = self.first or 0
        return ({'nanoseconds_since_epoch': start},
                {'nanoseconds': (self.last or start) - start})


class BagWriter:
    """A rosbag2 bag with MCAP storage: `<dir>/<dir name>_0.mcap` + `metadata.yaml`.

    Writing is single-threaded: call `write` from one thread, `close` after it.
    """

    def __init__(self, bag_dir: Path):
        self.bag_dir = Path(bag_dir)
        if self.bag_dir.exists():   # as `ros2 bag record -o`: never append to a bag
            raise FileExistsError(f'{self.bag_dir} exists: a bag is written once')
        self.bag_dir.mkdir(parents=True)
        self.file_name = f'{self.bag_dir.name}_0.mcap'
        self._file = open(self.bag_dir / self.file_name, 'wb')
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile='ros2', library='zeus_ros')
        self.topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._span = _Span()

    @property
    def counts(self) -> dict[str, int]:
        return {name: topic.count for name, topic in self.topics.items()}

    def add_topic(self, name: str, type_name: str, profiles: list[QoSProfile]) -> None:
        """Create the topic's channel (schema once per type), with its offered QoS."""
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding='ros2msg',
                data=message_definition(type_name).encode())
        profiles = [_infinite_if_default(p) for p in profiles]
        channel = self._writer.register_channel(
            topic=name, message_encoding='cdr', schema_id=self._schemas[type_name],
            metadata={'offered_qos_profiles': yaml.safe_dump(
                          [qos_entry(p) for p in profiles], sort_keys=False),
                      'topic_type_hash': type_description_hash(type_name)})
        self.topics[name] = _Topic(name, type_name, profiles, channel)

    def write(self, name: str, data: bytes, log_time_ns: int) -> None:
        topic = self.topics[name]
        self._writer.add_message(channel_id=topic.channel, log_time=log_time_ns,
                                 publish_time=log_time_ns, sequence=topic.count, data=data)
        topic.count += 1
        self._span.add(log_time_ns)

    def metadata(self) -> dict:
        """Return the bag's metadata, as rosbag2's BagMetadata encodes it (version 9)."""
        starting_time, duration = self._span.metadata()
        file_start, file_duration = self._span.metadata()   # one file holds everything
        total = sum(t.count for t in self.topics.values())
        return {
            'version': METADATA_VERSION, 'storage_identifier': 'mcap',
            'duration': duration, 'starting_time': starting_time, 'message_count': total,
            'topics_with_message_count': [
                {'topic_metadata': {
                    'name': t.name, 'type': t.type_name, 'serialization_format': 'cdr',
                    'offered_qos_profiles': [qos_entry(p) for p in t.profiles],
                    'type_description_hash': type_description_hash(t.type_name)},
                 'message_count': t.count} for t in self.topics.values()],
            # rosbag2's own message/file compression: none (the MCAP chunks are zstd).
            'compression_format': '', 'compression_mode': '',
            'relative_file_paths': [self.file_name],
            'files': [{'path': self.file_name, 'starting_time': file_start,
                       'duration': file_duration, 'message_count': total}],
            'custom_data': None, 'ros_distro': ROS_DISTRO}

    def close(self) -> None:
        """Finish the MCAP (with rosbag2's metadata record) and write metadata.yaml."""
        metadata = self.metadata()
        self._writer.add_metadata('rosbag2', {
            'serialized_metadata': yaml.safe_dump(metadata, sort_keys=False)})
        self._writer.finish()
        self._file.close()
        (self.bag_dir / 'metadata.yaml').write_text(yaml.safe_dump(
            {'rosbag2_bagfile_information': metadata}, sort_keys=False))


class BagRecorder:
    """Subscribe to topics (raw CDR) on an existing node and record them into a bag.

    The subscriptions are loop subscriptions (taken by `spin_loop` in its
    thread, which keeps up where rclpy's executor drops messages), with a
    RECORD_DEPTH queue. A topic's channel is created at its first
    message, when its publishers are known (as rosbag2 creates a topic at
    discovery); topics that never sent one are added, empty, at close.
    """

    def __init__(self, node: Node, bag_dir: Path, topics: dict[str, TopicSpec],
                 depth: int = RECORD_DEPTH):
        self.node, self.specs = node, topics
        self.bag = BagWriter(bag_dir)
        for topic, spec in topics.items():
            # The publishers' reliability (a reliable reader would not match a
            # best-effort writer), a deeper queue than theirs.
            qos = QoSProfile(depth=depth, reliability=spec.qos.reliability)
            create_loop_subscription(node, message_class(spec.type_name), topic,
                                     self._writer_for(topic), qos, raw=True)

    @property
    def counts(self) -> dict[str, int]:
        return {topic: self.bag.counts.get(topic, 0) for topic in self.specs}

    def _add(self, topic: str) -> None:
        spec = self.specs[topic]
        # After shutdown (close) the graph cannot be asked: the declared profile.
        profiles = (offered_profiles(self.node, topic, spec.qos) if self.node.context.ok()
                    else [spec.qos])
        self.bag.add_topic(topic, spec.type_name, profiles)

    def _writer_for(self, topic: str):
        def write(data: bytes) -> None:
            now = time.time_ns()
            if topic not in self.bag.topics:
                self._add(topic)
            self.bag.write(topic, data, now)
        return write

    def close(self) -> None:
        """Call once the receiving thread has ended."""
        for topic in self.specs:
            if topic not in self.bag.topics:
                self._add(topic)
        self.bag.close()


# -- the robot of a recorded episode, as a GIF ----------------------------------------------
@dataclass
class EpisodeFrames:
    """What a video of one recorded episode needs, by stamp (read back from its bag)."""

    family: str = ''
    param_name: str = ''
    positions: dict[int, tuple[list[str], list[float]]] = field(default_factory=dict)
    steps: dict[int, tuple[int, int, float]] = field(default_factory=dict)  # episode, step, true
    estimates: dict[int, float] = field(default_factory=dict)


def read_episode(bag_dir: Path, episode: int | None = None) -> EpisodeFrames:
    """Joint states, true and decoded parameter of one episode of a bag (default: the last)."""
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from zeus_msgs.msg import Context, StepInfo

    kinds = {'/joint_states': JointState, '/zeus/step': StepInfo, '/zeus/context': Context}
    frames = EpisodeFrames()
    with open(Path(bag_dir) / f'{Path(bag_dir).name}_0.mcap', 'rb') as file:
        for _, channel, message in make_reader(file).iter_messages(topics=list(kinds)):
            msg = deserialize_message(message.data, kinds[channel.topic])
            stamp = msg.header.stamp.sec * _NS + msg.header.stamp.nanosec
            if channel.topic == '/joint_states':
                frames.positions[stamp] = (list(msg.name), list(msg.position))
            elif channel.topic == '/zeus/step':
                frames.family, frames.param_name = msg.family, msg.param_names[0]
                frames.steps[stamp] = (msg.episode, msg.step, msg.param_values[0])
            elif len(msg.param_estimates):
                frames.estimates[stamp] = float(msg.param_estimates[0])
    if episode is None:   # the longest one (a bag may also hold a next episode's start)
        lengths: dict[int, int] = {}
        for e, _, _ in frames.steps.values():
            lengths[e] = lengths.get(e, 0) + 1
        episode = max(lengths, key=lengths.get, default=0)
    frames.steps = {s: v for s, v in frames.steps.items() if v[0] == episode}
    return frames


def _caption(frames: EpisodeFrames, stamp: int) -> str:
    _, step, true = frames.steps[stamp]
    estimate = frames.estimates.get(stamp, float('nan'))
    decoded = 'none' if estimate != estimate else f'{estimate:.2f}'
    return f'step {step:4d}   {frames.param_name}: true {true:.2f}   decoded {decoded}'


_SCENE_COLOURS = 62   # + black and white for the caption: 64, GIF's 256 are not needed


def _gif_frame(image: PIL.Image.Image, text: str):
    """Return the rendered frame in 62 colours, the caption in black and white on top.

    Fewer colours make the GIF 40 % smaller and quicker to write with no loss
    to see; the caption's two colours are kept out of the quantisation, which
    could merge a few hundred white pixels into the scene's greys.
    """
    from PIL import Image, ImageDraw, ImageFont
    frame = image.quantize(colors=_SCENE_COLOURS, method=Image.Quantize.MEDIANCUT)
    palette = frame.getpalette()[:3 * _SCENE_COLOURS]
    frame.putpalette(palette + [0] * (3 * _SCENE_COLOURS - len(palette))
                     + [0, 0, 0, 255, 255, 255])
    # At the bottom, over the floor: the side camera puts the torso at the top.
    draw = ImageDraw.Draw(frame)
    draw.rectangle((0, frame.height - 20, frame.width, frame.height), fill=_SCENE_COLOURS)
    draw.text((6, frame.height - 17), text, fill=_SCENE_COLOURS + 1,
              font=ImageFont.load_default(size=13))
    return frame


class NoOffscreenGL(RuntimeError):
    """MuJoCo cannot render off-screen here (no GL backend, or MUJOCO_GL names a bad one)."""


def _gl_physics(family: str, value: float):
    """Physics of `family` at `value` that has rendered once off-screen.

    Each GL backend fails its own way, at dm_control's import, at the context
    or at MuJoCo's first render call (RuntimeError, AttributeError,
    mujoco.FatalError...): all of them become NoOffscreenGL, naming the cause.
    """
    try:
        from sim_node.env import build_physics
        from sim_node.families import get_family
        physics = build_physics(get_family(family), value)
        # No mirror image in the floor: in software GL it costs a third of
        # each frame and shows nothing of the robot that the frame does not.
        physics.model.mat_reflectance[:] = 0.0
        physics.render(8, 8, camera_id=0)
    except Exception as error:  # noqa: BLE001 (each GL backend fails its own way, above)
        raise NoOffscreenGL(f'MUJOCO_GL={os.environ.get("MUJOCO_GL", "")!r}: '
                            f'{type(error).__name__}: {error}') from None
    return physics


def _frame(physics: Physics, names: list[str], positions: list[float], size: tuple[int, int]):
    from PIL import Image
    for name, position in zip(names, positions, strict=True):
        physics.named.data.qpos[name] = position
    physics.forward()
    return Image.fromarray(physics.render(size[1], size[0], camera_id=0))


def render_video(bag_dir: Path, out: Path, every: int = 4, size: tuple[int, int] = (320, 240),
                 episode: int | None = None) -> int:
    """Render every `every`-th step of a recorded episode to a GIF; return the frame count.

    Off-screen MuJoCo rendering from the recorded joint positions (qpos in
    joint order, as the sim publishes them), with the physics of the true
    parameter of each step (a length changes the model) and the true and
    decoded parameter written on each frame. The GIF plays at real time.
    Needs MUJOCO_GL set before dm_control is imported (egl here).
    """
    frames = read_episode(bag_dir, episode)
    stamps = [s for s in sorted(frames.steps) if frames.steps[s][1] % every == 0
              and s in frames.positions]
    if not stamps:
        raise ValueError(f'{bag_dir}: no recorded joint states to render')
    images, physics, value = [], None, None
    for stamp in stamps:
        true = frames.steps[stamp][2]
        if physics is None or true != value:
            physics, value = _gl_physics(frames.family, true), true
        images.append(_gif_frame(_frame(physics, *frames.positions[stamp], size),
                                 _caption(frames, stamp)))
    # Stamps advance one control period per step, so this plays at real time
    # (GIF players treat less than 20 ms as 100 ms).
    gaps = [b - a for a, b in zip(stamps[:-1], stamps[1:], strict=True)]
    period_ms = max(int(round(min(gaps, default=100_000_000) / 1e6)), 20)
    images[0].save(out, save_all=True, append_images=images[1:], duration=period_ms, loop=0)
    return len(images)


def _video_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog='python -m zeus_ros.ros_tools.recording video',
                                     description=render_video.__doc__.split('\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory')
    parser.add_argument('out', type=Path, help='GIF to write')
    parser.add_argument('--every', type=int, default=4, help='render every Nth step')
    parser.add_argument('--episode', type=int, help='episode to render (default: the longest)')
    parser.add_argument('--png', type=Path, help='also save the middle frame as a PNG')
    args = parser.parse_args(argv)
    try:
        count = render_video(args.bag, args.out, args.every, episode=args.episode)
    except NoOffscreenGL as error:
        print(f'no off-screen OpenGL for MuJoCo ({error})', file=sys.stderr)
        return 3
    if args.png:
        from PIL import Image
        with Image.open(args.out) as gif:
            gif.seek(count // 2)
            gif.convert('RGB').save(args.png)
    print(f'{count} frames to {args.out}')
    return 0


def bag_summary(bag: Path) -> str:
    """Return what `ros2 bag info` prints of a bag, read with rosbags (no ros2cli needed)."""
    from rosbags.rosbag2 import Reader
    with Reader(bag) as reader:
        lines = [f'bag: {bag}', f'ros distro: {reader.ros_distro}',
                 f'duration: {reader.duration / 1e9:.3f} s',
                 f'messages: {reader.message_count}', 'topics:']
        for connection in sorted(reader.connections, key=lambda c: c.topic):
            lines.append(f'  {connection.topic} | {connection.msgtype} | '
                         f'{connection.msgcount} messages')
    return '\n'.join(lines)


def _info_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog='python -m zeus_ros.ros_tools.recording info',
                                     description=bag_summary.__doc__.split('\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory')
    args = parser.parse_args(argv)
    print(bag_summary(args.bag))
    return 0


if __name__ == '__main__':
    commands = {'video': _video_main, 'info': _info_main}
    if sys.argv[1:2] not in ([name] for name in commands):
        sys.exit('usage: python -m zeus_ros.ros_tools.recording video <bag> <out.gif> '
                 '[--every N]\n'
                 '       python -m zeus_ros.ros_tools.recording info <bag>')
    sys.exit(commands[sys.argv[1]](sys.argv[2:]))
