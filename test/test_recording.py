"""The recording is a rosbag2 bag: checked with an independent reader, `rosbags` (PyPI).

The reading helpers live in bag_helpers.py (test_demo.py checks the demo's bags with them).
"""

import time

from bag_helpers import assert_consistent, assert_loop_qos, read_bag
from mcap.reader import make_reader
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.interfaces import QosHistory, QosReliability
from sensor_msgs.msg import JointState
import yaml
from zeus_msgs.msg import StepInfo
from zeus_ros.ros_tools.recording import bag_summary, BagRecorder, BagWriter, TopicSpec
from zeus_ros.ros.util import LOOP_QOS


def _step(i: int) -> StepInfo:
    msg = StepInfo(episode=3, step=i, reward=0.5 * i, applied_action=[0.1, -0.2],
                   family='walker-walk-v0', param_names=['friction'], param_values=[1.0 + i])
    msg.header.stamp.sec, msg.header.stamp.nanosec = i, 25_000_000
    return msg


def test_bag_directory_is_read_by_rosbags(tmp_path):
    bag_dir = tmp_path / 'demo'
    writer = BagWriter(bag_dir)
    writer.add_topic('/zeus/step', 'zeus_msgs/msg/StepInfo', [LOOP_QOS])
    writer.add_topic('/joint_states', 'sensor_msgs/msg/JointState', [LOOP_QOS, LOOP_QOS])
    writer.add_topic('/unused', 'sensor_msgs/msg/JointState', [LOOP_QOS])
    t0 = 1_700_000_000_000_000_000
    for i in range(7):
        writer.write('/zeus/step', serialize_message(_step(i)), t0 + 10 * i)
        # effort filled: rclpy's serialize_message pads an empty last float64
        # sequence with 4 bytes that rosbags refuses (DDS payloads carry none).
        joints = JointState(name=['a', 'b'], position=[float(i), 2.0], velocity=[0.0, 1.0],
                            effort=[0.0, 0.0])
        writer.write('/joint_states', serialize_message(joints), t0 + 10 * i + 3)
    writer.close()

    assert sorted(p.name for p in bag_dir.iterdir()) == ['demo_0.mcap', 'metadata.yaml']
    info = yaml.safe_load((bag_dir / 'metadata.yaml').read_text())
    assert info['rosbag2_bagfile_information']['version'] == 9
    assert info['rosbag2_bagfile_information']['storage_identifier'] == 'mcap'
    bag = read_bag(bag_dir)
    assert bag.types == {'/zeus/step': 'zeus_msgs/msg/StepInfo',
                         '/joint_states': 'sensor_msgs/msg/JointState',
                         '/unused': 'sensor_msgs/msg/JointState'}
    assert bag.counts == {'/zeus/step': 7, '/joint_states': 7, '/unused': 0}
    assert_consistent(bag)
    assert (bag.start_ns, bag.duration_ns) == (t0, 63 + 1)
    assert [m.step for m in bag.messages['/zeus/step']] == list(range(7))
    last = bag.messages['/zeus/step'][-1]
    assert (last.episode, last.reward, last.family) == (3, 3.0, 'walker-walk-v0')
    assert list(last.param_values) == [7.0] and last.header.stamp.sec == 6
    assert list(bag.messages['/joint_states'][4].position) == [4.0, 2.0]
    assert [len(bag.qos[t]) for t in bag.types] == [1, 2, 1]
    # the pip-only `ros2 bag info`
    summary = bag_summary(bag_dir)
    assert 'messages: 14' in summary and 'ros distro: jazzy' in summary
    assert '  /zeus/step | zeus_msgs/msg/StepInfo | 7 messages' in summary.splitlines()
    assert '  /unused | sensor_msgs/msg/JointState | 0 messages' in summary.splitlines()
    for profiles in bag.qos.values():
        assert_loop_qos(profiles)
    assert bag.hashes['/joint_states'].startswith('RIHS01_')
    assert bag.hashes['/zeus/step'].startswith('RIHS01_')


def test_mcap_channels_carry_the_qos_and_rosbag2_metadata(tmp_path):
    """`ros2 bag play` of the .mcap alone reads the QoS from the channel, as rosbag2 stores it."""
    writer = BagWriter(tmp_path / 'bag')
    writer.add_topic('/zeus/step', 'zeus_msgs/msg/StepInfo', [LOOP_QOS])
    writer.write('/zeus/step', serialize_message(_step(0)), 5)
    writer.close()
    with open(tmp_path / 'bag' / 'bag_0.mcap', 'rb') as file:
        reader = make_reader(file)
        summary = reader.get_summary()
        channel = next(iter(summary.channels.values()))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert summary.schemas[channel.schema_id].encoding == 'ros2msg'
    assert channel.message_encoding == 'cdr'
    (profile,) = yaml.safe_load(channel.metadata['offered_qos_profiles'])
    assert (profile['history'], profile['depth'], profile['reliability'],
            profile['durability']) == ('keep_last', 10, 'reliable', 'volatile')
    stored = yaml.safe_load(metadata['rosbag2']['serialized_metadata'])
    assert stored['version'] == 9 and stored['message_count'] == 1


def test_a_bag_is_written_once(tmp_path):
    BagWriter(tmp_path / 'bag').close()
    with pytest.raises(FileExistsError):
        BagWriter(tmp_path / 'bag')


def test_recorder_stores_what_the_publishers_offer(ros_node, tmp_path):
    """Over DDS: every message recorded, and the QoS discovery reports (a best-effort one too)."""
    import rclpy
    from zeus_ros.ros.loop_spin import spin_in_background
    context = rclpy.Context()
    rclpy.init(context=context)
    recorder_node = rclpy.create_node('test_recorder', context=context)
    best_effort = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    recorder = BagRecorder(recorder_node, tmp_path / 'rec', {
        '/test_rec/step': TopicSpec('zeus_msgs/msg/StepInfo', LOOP_QOS),
        '/test_rec/joints': TopicSpec('sensor_msgs/msg/JointState', best_effort)})
    spinner = spin_in_background(recorder_node)
    steps = ros_node.create_publisher(StepInfo, '/test_rec/step', LOOP_QOS)
    joints = ros_node.create_publisher(JointState, '/test_rec/joints', best_effort)
    deadline = time.monotonic() + 20

    def until(done):
        while not done() and time.monotonic() < deadline:
            time.sleep(0.05)
    # Episode 0 until the recorder hears it: a writer may see the reader before
    # the reader has matched it, and keeps only its last 10 meanwhile.
    probe = StepInfo(episode=0)
    until(lambda: steps.publish(probe) or recorder.counts['/test_rec/step'] > 0)
    time.sleep(0.3)               # the probes in flight land
    probes = recorder.counts['/test_rec/step']
    for i in range(200):
        steps.publish(_step(i))   # episode 3, at about the loop's rate
        time.sleep(0.001)
    until(lambda: joints.publish(JointState(name=['a'], position=[1.0])) or (
        recorder.counts['/test_rec/joints'] > 0
        and recorder.counts['/test_rec/step'] >= probes + 200))
    time.sleep(0.2)
    rclpy.try_shutdown(context=context)
    spinner.join(timeout=5)
    recorder.close()
    recorder_node.destroy_node()

    bag = read_bag(tmp_path / 'rec')
    recorded = [m.step for m in bag.messages['/test_rec/step'] if m.episode == 3]
    assert recorded == list(range(200))
    assert_consistent(bag)
    assert_loop_qos(bag.qos['/test_rec/step'])
    (joints_qos,) = bag.qos['/test_rec/joints']
    assert joints_qos.reliability == QosReliability.BEST_EFFORT
    assert (joints_qos.history, joints_qos.depth) == (QosHistory.KEEP_LAST, 5)
