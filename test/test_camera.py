"""The sim camera: off-screen frames of the robot, their messages, and a publisher over DDS.

Run as a script, this file is the tiny camera node of the process tests (a
ParamEnv stepped on a timer, a CameraPublisher over it, a step counter topic).
"""

import argparse
import os
from pathlib import Path
import sys
import threading
import time

import numpy as np
import pytest

# Not `from conftest import ...` at the top: run as the node, this file must not
# claim a ROS_DOMAIN_ID of its own (conftest does on import); the tests import it.
REPO = Path(__file__).resolve().parents[1]
STEPS_TOPIC = '/camera_test/steps'


def robot_mask(frame: np.ndarray) -> np.ndarray:
    """Pixels of the robots' orange 'self' material (the floor and sky are blue/grey)."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return (r - b > 60) & (r > g)


@pytest.fixture(scope='module', autouse=True)
def _keep_pyopengl_platform():
    # mujoco.egl sets PYOPENGL_PLATFORM=egl in os.environ when it loads: keep it
    # out of the processes later tests of this session start.
    before = os.environ.get('PYOPENGL_PLATFORM')
    yield
    if before is None:
        os.environ.pop('PYOPENGL_PLATFORM', None)
    else:
        os.environ['PYOPENGL_PLATFORM'] = before


@pytest.fixture(scope='module')
def camera():
    from sim_node.camera import SimCamera
    cam = SimCamera(320, 240)
    yield cam
    cam.close()


@pytest.mark.parametrize('family', ['walker-walk-v0', 'cheetah-run-v0', 'finger-spin-v0'])
def test_frame_shows_the_robot(camera, family, tmp_path):
    from PIL import Image as PILImage
    from sim_node.env import ParamEnv
    env = ParamEnv(family)
    frame = camera.render(env.physics)
    assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
    assert frame.std() > 10  # not blank
    assert robot_mask(frame).mean() > 0.01, 'no robot-coloured pixels'
    PILImage.fromarray(frame).save(tmp_path / f'{family}.png')
    for _ in range(20):
        env.step(np.ones(env.action_dim))
    moved = camera.render(env.physics)
    assert np.abs(moved.astype(int) - frame).mean() > 1.0, 'another state, the same picture'


def test_the_camera_follows_the_walker(camera):
    from sim_node.env import ParamEnv
    env = ParamEnv('walker-walk-v0')
    near = robot_mask(camera.render(env.physics)).mean()
    qpos = env.physics.data.qpos.copy()
    qpos[env.joint_names.index('rootx')] += 20.0  # far beyond a fixed camera's view
    far = robot_mask(camera.render_state(env.physics.model.ptr, qpos)).mean()
    assert far > 0.5 * near > 0


def test_messages_match_the_frame_and_project_the_torso(camera):
    from sim_node.env import ParamEnv
    from zeus_ros.ros.camera import camera_info, image_message
    env = ParamEnv('walker-walk-v0')
    frame = camera.render(env.physics)
    stamp = 12 * 1_000_000_000 + 345
    image, info = image_message(frame, stamp), camera_info(camera, stamp)
    assert (image.height, image.width, image.encoding, image.is_bigendian) == (240, 320, 'rgb8', 0)
    assert image.step == 3 * 320 and bytes(image.data) == frame.tobytes()
    assert (image.header.stamp.sec, image.header.stamp.nanosec) == (12, 345)
    assert info.header == image.header and (info.height, info.width) == (240, 320)
    fx, _, cx, _, fy, cy, *_ = info.k
    assert fx == fy > 0 and (cx, cy) == (160, 120) and list(info.d) == [0.0] * 5
    assert list(info.p) == [fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0]
    # K and the image orientation together: the torso, projected, lands on the robot.
    u, v = _project(env.physics, 'torso', fx, cx, cy)
    assert 0 <= u < 320 and 0 <= v < 240
    assert robot_mask(frame)[int(v) - 3:int(v) + 4, int(u) - 3:int(u) + 4].any()


def _project(physics, body: str, f: float, cx: float, cy: float) -> tuple[float, float]:
    """Pixel of a body's origin through MuJoCo camera 0 (it looks along its -z, y up)."""
    data = physics.data
    offset = data.xpos[physics.model.name2id(body, 'body')] - data.cam_xpos[0]
    x, y, z = data.cam_xmat[0].reshape(3, 3).T @ offset
    return cx + f * x / -z, cy - f * y / -z


def test_rate_zero_creates_nothing(ros_node):
    from zeus_ros.ros.camera import CameraPublisher
    threads = threading.active_count()
    camera = CameraPublisher(ros_node, lambda: pytest.fail('physics read'), 0)
    assert camera.image_pub is None and camera.info_pub is None and not camera.active
    topics = [pub.topic_name for pub in ros_node.publishers]
    assert not any(topic.startswith('/camera') for topic in topics)
    assert threading.active_count() == threads
    camera.close()


class TimedLock:
    """A lock that records how long each holder kept it."""

    def __init__(self):
        self._lock, self.holds, self._since = threading.Lock(), [], 0.0

    def __enter__(self):
        self._lock.acquire()
        self._since = time.monotonic()

    def __exit__(self, *exc):
        self.holds.append(time.monotonic() - self._since)
        self._lock.release()


def test_publisher_reads_under_the_lock_and_never_holds_it_while_drawing(ros_node):
    from zeus_ros.ros.camera import CameraPublisher
    from sim_node.env import ParamEnv
    env, lock = ParamEnv('walker-walk-v0'), TimedLock()
    camera = CameraPublisher(ros_node, lambda: env.physics, 20, lock=lock,
                             get_stamp_ns=lambda: env.step_count)
    try:
        assert _wait(lambda: camera.frames >= 3, 30), 'no frames'
        with lock:  # the stepping thread "steps": the camera must wait for it
            held_at = camera.frames
            time.sleep(0.5)
            assert camera.frames <= held_at + 1  # at most the frame already past the lock
        assert _wait(lambda: camera.frames >= held_at + 3, 30)
    finally:
        camera.close()
    assert not camera.active
    # A frame takes 20-150 ms to draw here; the camera holds the lock for a copy
    # (a GIL hand-over, 5 ms, at worst), never for a frame.
    camera_holds = [hold for hold in lock.holds if hold < 0.4]
    assert camera_holds and max(camera_holds) < 0.015 and np.median(camera_holds) < 0.001


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _camera_node_env(**extra) -> dict:
    # The node under test imports this checkout's sim_node, not an older install.
    path = os.pathsep.join([str(REPO), os.environ.get('PYTHONPATH', '')])
    return dict(os.environ, PYTHONPATH=path, **extra)


def camera_node_command(rate: float, **env) -> tuple[list, str, dict]:
    """Arguments of `spawn` for the camera node (this file run as a script)."""
    return [sys.executable, __file__, '--rate', str(rate)], 'camera_node', _camera_node_env(**env)


def _subscribe(node, received: dict) -> None:
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import UInt64
    for topic, msg_type in (('/camera/image_raw', Image), ('/camera/camera_info', CameraInfo),
                            (STEPS_TOPIC, UInt64)):
        node.create_subscription(
            msg_type, topic, lambda msg, t=topic: received[t].append((time.monotonic(), msg)),
            10)


def test_camera_node_publishes_frames_over_dds_at_the_rate(ros_node, spawn):
    from conftest import spin_until
    rate = 5.0
    received = {'/camera/image_raw': [], '/camera/camera_info': [], STEPS_TOPIC: []}
    _subscribe(ros_node, received)
    proc = spawn(*camera_node_command(rate))
    images = received['/camera/image_raw']
    assert spin_until(ros_node, lambda: len(images) >= 1, 60), proc.output()
    first = len(images)
    spin_until(ros_node, lambda: False, 4.0)
    times = [t for t, _ in images[first - 1:]]
    measured = (len(times) - 1) / (times[-1] - times[0])
    assert 0.6 * rate <= measured <= 1.3 * rate, f'{measured:.2f} Hz for {rate} Hz'
    msgs = [msg for _, msg in images]
    frames = [np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.width, 3) for m in msgs]
    assert all(m.encoding == 'rgb8' and (m.width, m.height) == (320, 240) for m in msgs)
    assert all(robot_mask(frame).mean() > 0.01 for frame in frames)
    assert np.abs(frames[-1].astype(int) - frames[0]).mean() > 1.0  # the walker moved
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs]
    assert stamps == sorted(stamps) and stamps[-1] > stamps[0]
    infos = {(i.header.stamp.sec, i.header.stamp.nanosec): i for _, i in
             received['/camera/camera_info']}
    matched = [infos[(m.header.stamp.sec, m.header.stamp.nanosec)] for m in msgs
               if (m.header.stamp.sec, m.header.stamp.nanosec) in infos]
    assert matched and all((i.width, i.height) == (320, 240) for i in matched)
    assert proc.alive() and 'camera off' not in proc.output()


def test_without_gl_one_warning_and_the_node_goes_on(ros_node, spawn):
    from conftest import spin_until
    received = {'/camera/image_raw': [], '/camera/camera_info': [], STEPS_TOPIC: []}
    _subscribe(ros_node, received)
    # EGL with a device this machine does not have: making the context raises.
    proc = spawn(*camera_node_command(10.0, MUJOCO_EGL_DEVICE_ID='99'))
    assert spin_until(ros_node, lambda: 'camera off' in proc.output(), 60), proc.output()
    steps = received[STEPS_TOPIC]
    before = len(steps)
    assert spin_until(ros_node, lambda: len(steps) >= before + 20, 20), 'the node stopped'
    output = proc.output()
    assert output.count('no off-screen OpenGL') == 1 and 'MUJOCO_EGL_DEVICE_ID' in output, output
    assert 'Traceback' not in output and proc.alive()
    assert received['/camera/image_raw'] == []


def camera_node(rate: float, family: str) -> None:
    """Step a ParamEnv at its control rate and publish its camera: the node under test."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from std_msgs.msg import UInt64

    from zeus_ros.ros.camera import CameraPublisher
    from sim_node.env import ParamEnv
    rclpy.init()
    node, env, lock = Node('camera_test_node'), ParamEnv(family), threading.Lock()
    steps_pub = node.create_publisher(UInt64, STEPS_TOPIC, 10)
    rng, period_ns = np.random.default_rng(0), int(env.control_timestep * 1e9)
    ticks = [0]  # states since start: the stamp, as sim_node's clock

    def step():
        with lock:
            if env.step(rng.uniform(-1, 1, env.action_dim)).truncated:
                env.reset()
            ticks[0] += 1
        steps_pub.publish(UInt64(data=ticks[0]))

    node.create_timer(env.control_timestep, step)
    camera = CameraPublisher(node, lambda: env.physics, rate, lock=lock,
                             get_stamp_ns=lambda: ticks[0] * period_ns)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        camera.close()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    parser = argparse.ArgumentParser(description=camera_node.__doc__)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--family', default='walker-walk-v0')
    cli = parser.parse_args()
    camera_node(cli.rate, cli.family)


def test_sim_node_serves_its_camera_when_asked_and_nothing_by_default(ros_node, spawn):
    """`camera_rate` on the real sim node: frames of the robot while it steps in realtime."""
    from conftest import installed_exe, spin_until
    from zeus_msgs.msg import StepInfo
    received = {'/camera/image_raw': [], '/camera/camera_info': [], STEPS_TOPIC: []}
    _subscribe(ros_node, received)
    steps = []
    ros_node.create_subscription(StepInfo, '/zeus/step', steps.append, 100)
    proc = spawn([installed_exe('sim_node'), '--ros-args', '-p', 'mode:=realtime',
                  '-p', 'camera_rate:=4.0'], 'sim_node_camera')
    images = received['/camera/image_raw']
    assert spin_until(ros_node, lambda: len(images) >= 3, 90), proc.output()
    msg = images[-1][1]
    frame = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, 3)
    assert robot_mask(frame).mean() > 0.01
    # The loop keeps stepping while it renders. Waited for, not read at once: on a
    # loaded machine the states can arrive well after the frames.
    assert spin_until(ros_node, lambda: len(steps) > 10, 60), proc.output()
    proc.stop()
    plain = spawn([installed_exe('sim_node'), '--ros-args', '-p', 'mode:=realtime'],
                  'sim_node_plain')
    mark = len(steps)
    assert spin_until(ros_node, lambda: len(steps) > mark + 20, 60), plain.output()
    publishers = ros_node.get_publishers_info_by_topic('/camera/image_raw')
    assert not [p for p in publishers if p.node_name == 'sim_node'], publishers


def test_an_in_place_swap_is_drawn_at_its_new_size():
    """A swap edits the live model in place: the camera draws the new torso, not the old."""
    from sim_node.camera import geometry_of, SimCamera
    from sim_node.env import ParamEnv
    env = ParamEnv('cheetah-run-v0', 0.6, seed=0)
    env.reset(seed=0)
    model = env.physics.model.ptr
    cam = SimCamera(320, 240)
    qpos, qvel = env.physics.data.qpos.copy(), env.physics.data.qvel.copy()
    short = cam.render_state(model, qpos, qvel, geometry_of(model))
    env.apply_prepared(env.prepare_values((1.5,)))
    assert env.physics.model.ptr is model             # the same model object, edited
    stale = cam.render_state(model, qpos, qvel)       # without the copied geometry
    long = cam.render_state(model, qpos, qvel, geometry_of(model))
    assert np.array_equal(stale, short)
    assert robot_mask(long).sum() > 1.2 * robot_mask(short).sum()
