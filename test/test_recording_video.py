"""The demo's video: the robot rendered off-screen from a bag's joint states, or a clear skip."""

import os
import subprocess
import sys
from types import SimpleNamespace

from bag_helpers import robot_pixels
from conftest import REPO
import numpy as np
from PIL import Image
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from zeus_msgs.msg import Context, StepInfo
from zeus_ros.ros_tools import demo
from zeus_ros.ros_tools.recording import BagWriter, read_episode
from zeus_ros.ros.util import LOOP_QOS

pytestmark = pytest.mark.ros   # starts processes of its own

STEP_NS = 25_000_000


def _stamped(msg, step: int):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod((step + 1) * STEP_NS, 10**9)
    return msg


def make_episode_bag(bag_dir, steps: int = 40):
    """Write a walker-walk-v0 episode stepped in process, friction 1.0, 0.4 from step 20."""
    from sim_node.env import ParamEnv
    env = ParamEnv('walker-walk-v0', 1.0, seed=0)
    writer = BagWriter(bag_dir)
    for topic, kind in (('/joint_states', 'sensor_msgs/msg/JointState'),
                        ('/zeus/step', 'zeus_msgs/msg/StepInfo'),
                        ('/zeus/context', 'zeus_msgs/msg/Context')):
        writer.add_topic(topic, kind, [LOOP_QOS])
    for step in range(steps + 1):
        friction = 1.0 if step < 20 else 0.4
        if step:
            env.set_values((friction,))
            env.step(np.full(env.action_dim, 0.5 * np.sin(step / 3)))
        state = JointState(name=list(env.joint_names), position=env.joint_positions().tolist(),
                           velocity=env.joint_velocities().tolist())
        info = StepInfo(episode=1, step=step, family='walker-walk-v0',
                        param_names=['friction'], param_values=[friction])
        context = Context(param_names=['friction'], param_estimates=[0.9])
        for topic, msg in (('/zeus/step', info), ('/joint_states', state),
                           ('/zeus/context', context)):
            writer.write(topic, serialize_message(_stamped(msg, step)), step * 1000)
    writer.close()


@pytest.fixture(scope='module')
def episode_bag(tmp_path_factory):
    bag_dir = tmp_path_factory.mktemp('video') / 'bag'
    make_episode_bag(bag_dir)
    return bag_dir


def render(bag_dir, out, gl: str, *extra):
    return subprocess.run(
        [sys.executable, '-m', 'zeus_ros.ros_tools.recording', 'video', str(bag_dir), str(out),
         *extra],
        cwd=REPO, env=dict(os.environ, MUJOCO_GL=gl), capture_output=True, text=True,
        timeout=180)


def test_read_episode_pairs_states_parameters_and_estimates(episode_bag):
    frames = read_episode(episode_bag)
    assert (frames.family, frames.param_name) == ('walker-walk-v0', 'friction')
    assert sorted(step for _, step, _ in frames.steps.values()) == list(range(41))
    assert set(frames.steps) == set(frames.positions) == set(frames.estimates)
    assert {true for _, _, true in frames.steps.values()} == {1.0, 0.4}
    assert list(frames.estimates.values()) == [pytest.approx(0.9)] * 41


def test_video_shows_the_robot_with_true_and_decoded_parameter(episode_bag, tmp_path):
    result = render(episode_bag, tmp_path / 'v.gif', 'egl', '--every', '10',
                    '--png', tmp_path / 'mid.png')
    # EGL (Mesa) is part of these machines: no off-screen GL is a failure, not a skip.
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith('5 frames')        # steps 0, 10, 20, 30, 40
    with Image.open(tmp_path / 'v.gif') as gif:
        assert (gif.n_frames, gif.size) == (5, (320, 240))
        assert gif.info['duration'] == 250             # 10 steps of 25 ms: real time
        first = np.asarray(gif.convert('RGB')).copy()
        gif.seek(4)
        last = np.asarray(gif.convert('RGB'))
        assert np.abs(first.astype(int) - last).mean() > 1.0   # the robot moved
    middle = Image.open(tmp_path / 'mid.png')
    assert robot_pixels(middle) > 500
    caption = np.asarray(middle.convert('L'))[-20:]
    assert np.sum(caption > 200) > 100                  # white text on the black band


def test_no_gl_is_one_clear_line_from_the_renderer_and_a_skip_in_the_demo(
        episode_bag, tmp_path, monkeypatch):
    result = render(episode_bag, tmp_path / 'v.gif', 'not-a-backend')
    assert result.returncode == 3
    assert result.stderr.startswith('no off-screen OpenGL for MuJoCo')
    assert 'Traceback' not in result.stderr and not (tmp_path / 'v.gif').exists()

    monkeypatch.setattr(demo, 'VIDEO_GL', 'not-a-backend')
    line = demo.render_video(SimpleNamespace(bag=episode_bag, episode=1),
                             tmp_path / 'd.gif', every=10)
    assert line.startswith('video skipped: no off-screen OpenGL for MuJoCo'), line
