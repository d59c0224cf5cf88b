"""Reading rosbag2 bags back with an independent reader (rosbags), for the tests."""

from dataclasses import dataclass

import numpy as np
from PIL import Image

from conftest import REPO
from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

INFINITE = (9223372036, 854775807)   # RMW_DURATION_INFINITE as sec, nsec


def zeus_typestore():
    """Return rosbags' Jazzy types plus zeus_msgs, registered from msg_defs/msg/*.msg."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted((REPO / 'msg_defs' / 'msg').glob('*.msg')):
        types.update(get_types_from_msg(path.read_text(), f'zeus_msgs/msg/{path.stem}'))
    store.register(types)
    return store


@dataclass
class BagContents:
    """What rosbags reads from a bag directory."""

    types: dict          # topic -> type, from the bag's connections
    counts: dict         # topic -> message count the metadata states
    qos: dict            # topic -> rosbags Qos list (offered_qos_profiles)
    hashes: dict         # topic -> type description hash
    messages: dict       # topic -> decoded messages, in log-time order
    times: dict          # topic -> log times (ns)
    start_ns: int
    duration_ns: int
    message_count: int
    ros_distro: str


def read_bag(bag_dir) -> BagContents:
    """Open a rosbag2 directory with rosbags and decode every message."""
    store = zeus_typestore()
    with Reader(bag_dir) as reader:
        conns = reader.connections
        contents = BagContents(
            types={c.topic: c.msgtype for c in conns},
            counts={c.topic: c.msgcount for c in conns},
            qos={c.topic: c.ext.offered_qos_profiles for c in conns},
            hashes={c.topic: c.digest for c in conns},
            messages={c.topic: [] for c in conns}, times={c.topic: [] for c in conns},
            start_ns=reader.start_time, duration_ns=reader.duration,
            message_count=reader.message_count, ros_distro=reader.ros_distro)
        for conn, timestamp, raw in reader.messages():
            contents.messages[conn.topic].append(store.deserialize_cdr(raw, conn.msgtype))
            contents.times[conn.topic].append(timestamp)
    return contents


def assert_consistent(bag: BagContents) -> None:
    """Check that the counts and times the metadata states are those of the messages."""
    assert bag.counts == {t: len(m) for t, m in bag.messages.items()}
    assert bag.message_count == sum(bag.counts.values())
    times = [t for ts in bag.times.values() for t in ts]
    assert bag.start_ns == min(times)
    # rosbags reports duration as last - first + 1 ns (its end time is exclusive).
    assert bag.duration_ns in (max(times) - min(times), max(times) - min(times) + 1)
    assert bag.ros_distro == 'jazzy'


def assert_loop_qos(profiles) -> None:
    """Reliable, keep-last 10, volatile (LOOP_QOS), infinite deadline and lifespan."""
    assert profiles, 'no offered_qos_profiles'
    for qos in profiles:
        assert qos.reliability == QosReliability.RELIABLE
        assert (qos.history, qos.depth) == (QosHistory.KEEP_LAST, 10)
        assert qos.durability == QosDurability.VOLATILE
        assert (qos.deadline.sec, qos.deadline.nsec) == INFINITE
        assert (qos.lifespan.sec, qos.lifespan.nsec) == INFINITE


def robot_pixels(image: Image.Image) -> int:
    """Pixels of the walker's orange body (floor and sky are blue and dark)."""
    rgb = np.asarray(image.convert('RGB')).astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return int(np.sum((r > 150) & (r > g + 30) & (g > b + 20)))
