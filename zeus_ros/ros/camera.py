"""The sim node's camera on ROS: frames as sensor_msgs/Image at a fixed rate.

`CameraPublisher` is what the sim node owns to publish `/camera/image_raw` and
`/camera/camera_info` at a fixed rate. It renders (`sim_node.camera.SimCamera`,
MuJoCo, no ROS) on a thread of its own: the only thing it does in the stepping
thread's way is copy qpos/qvel under the node's lock; the frame is drawn from a
private copy of the model and data, so a control step never waits for a frame
(software rendering took 60-140 ms a 320x240 frame here, the machine loaded).
Without off-screen OpenGL it logs one warning and stops; the node carries on.

`image_message` and `camera_info` turn a frame and the camera that drew it
into the rgb8 `Image` and the matching pinhole `CameraInfo`. The only module
of the plumbing that reaches MuJoCo (through the simulation's renderer): the
controller nodes never import it.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Protocol, TYPE_CHECKING

from builtin_interfaces.msg import Time
import numpy as np
from sensor_msgs.msg import CameraInfo, Image

from sim_node.camera import geometry_of, NoOffscreenGL, SimCamera

if TYPE_CHECKING:
    from rclpy.node import Node

IMAGE_TOPIC = '/camera/image_raw'
INFO_TOPIC = '/camera/camera_info'
FRAME_ID = 'sim_camera_optical'
CAMERA_QOS_DEPTH = 2
# The longest `close()` waits for a frame being drawn (one takes < 0.2 s here).
CLOSE_TIMEOUT_S = 2.0


class CameraPhysics(Protocol):
    """What the camera copies of the physics in force: sim_node.family_env.EnvPhysics.

    A protocol of its own: the plumbing imports no simulation module but the
    renderer (test_layers), not even for a type.
    """

    @property
    def model(self) -> Any: ...    # has `ptr`, the mujoco.MjModel

    @property
    def data(self) -> Any: ...     # has qpos and qvel


def to_time(stamp: int | Time) -> Time:
    """Return a builtin_interfaces/Time for integer nanoseconds (a Time as it is)."""
    if isinstance(stamp, Time):
        return stamp
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)



def image_message(frame: np.ndarray, stamp: int | Time, frame_id: str = FRAME_ID) -> Image:
    """sensor_msgs/Image (rgb8) of a frame; `stamp` in nanoseconds or a Time."""
    height, width, channels = frame.shape
    if channels != 3 or frame.dtype != np.uint8:
        raise ValueError(f'expected an (h, w, 3) uint8 frame, got {frame.shape} {frame.dtype}')
    image = Image(height=height, width=width, encoding='rgb8', is_bigendian=0,
                  step=3 * width, data=np.ascontiguousarray(frame).tobytes())
    image.header.stamp, image.header.frame_id = to_time(stamp), frame_id
    return image


def camera_info(camera: SimCamera, stamp: int | Time, frame_id: str = FRAME_ID) -> CameraInfo:
    """CameraInfo of the pinhole camera that made the frames (no distortion)."""
    f = camera.focal_length()
    cx, cy = camera.width / 2, camera.height / 2
    info = CameraInfo(height=camera.height, width=camera.width, distortion_model='plumb_bob',
                      d=[0.0] * 5, k=[f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
                      r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                      p=[f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    info.header.stamp, info.header.frame_id = to_time(stamp), frame_id
    return info


class CameraPublisher:
    """Publish frames of the node's physics on /camera/image_raw and /camera/camera_info.

    `get_physics()` returns the dm_control Physics in force (called under
    `lock`, so a parameter swap that replaces it is seen); `lock` is the lock
    the node holds while it steps or resets that physics; `get_stamp_ns()`
    (also under the lock) gives the stamp of the state in it, by default the
    node's clock. Without a lock the copy is unsynchronised: only for a
    physics that nothing steps meanwhile. `rate_hz` 0 creates nothing at all.
    With `start` False the publishers exist but no frame is drawn before
    `start()` (a node that may still refuse to run draws nothing).
    """

    def __init__(self, node: Node, get_physics: Callable[[], CameraPhysics], rate_hz: float,
                 lock: threading.Lock | None = None,
                 get_stamp_ns: Callable[[], int] | None = None, width: int = 320,
                 height: int = 240, camera: int | str | None = None, start: bool = True):
        self.rate_hz = float(rate_hz)
        self.frames = 0
        self.image_pub = self.info_pub = self._thread = None
        if not self.rate_hz > 0:
            return
        self._node, self._get_physics = node, get_physics
        self._lock = lock if lock is not None else threading.Lock()
        self._get_stamp_ns = get_stamp_ns or (lambda: node.get_clock().now().nanoseconds)
        self._camera_args = (width, height, camera)
        # A depth is rclpy's reliable keep-last profile: a reliable and a best-effort reader
        # (ros2 topic hz, Foxglove) both match, and a slow one never holds the writer.
        self.image_pub = node.create_publisher(Image, IMAGE_TOPIC, CAMERA_QOS_DEPTH)
        self.info_pub = node.create_publisher(CameraInfo, INFO_TOPIC, CAMERA_QOS_DEPTH)
        self._stop = threading.Event()
        node.context.on_shutdown(self.close)  # stop drawing before rclpy goes away
        self._thread = threading.Thread(target=self._run, name='camera', daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        """Start drawing (idempotent; nothing with `rate_hz` 0 or once closed)."""
        if self._thread is None or self._thread.ident is not None or self._stop.is_set():
            return
        self._thread.start()

    @property
    def active(self) -> bool:
        """True while the render thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def close(self) -> None:
        """Stop rendering and wait for the frame in progress (idempotent)."""
        if self._thread is None:
            return
        self._stop.set()
        if self._thread.ident is not None and self._thread is not threading.current_thread():
            self._thread.join(CLOSE_TIMEOUT_S)   # started (a thread never started cannot join)

    def _run(self) -> None:
        camera = SimCamera(*self._camera_args)
        try:
            self._publish_at_rate(camera)
        except NoOffscreenGL as error:
            self._node.get_logger().warning(
                f'camera off, no frames on {IMAGE_TOPIC}: no off-screen OpenGL with {error}. '
                'EGL (the default) works headless with Mesa; a rate of 0 turns the camera off.')
        except Exception as error:  # noqa: BLE001 (the node must not go down with its camera)
            if not self._stop.is_set() and self._node.context.ok():
                self._node.get_logger().warning(f'camera stopped: {type(error).__name__}: '
                                                f'{error}')
        finally:
            camera.close()

    def _publish_at_rate(self, camera: SimCamera) -> None:
        period = 1.0 / self.rate_hz
        next_frame = time.monotonic()
        while not self._stop.wait(max(0.0, next_frame - time.monotonic())):
            self._publish_frame(camera)
            # An absolute schedule; a frame that overran does not cause a burst.
            next_frame = max(next_frame + period, time.monotonic())

    def _publish_frame(self, camera: SimCamera) -> None:
        with self._lock:  # only copies: the stepping thread waits microseconds at most
            physics = self._get_physics()
            model = physics.model.ptr
            qpos, qvel = physics.data.qpos.copy(), physics.data.qvel.copy()
            geometry = geometry_of(model)   # an in-place swap keeps the model object
            stamp = self._get_stamp_ns()
        frame = camera.render_state(model, qpos, qvel, geometry)
        if self._stop.is_set():
            return
        self.image_pub.publish(image_message(frame, stamp))
        self.info_pub.publish(camera_info(camera, stamp))
        self.frames += 1
