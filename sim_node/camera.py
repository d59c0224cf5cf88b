"""An off-screen camera on the simulated robot: frames as sensor_msgs/Image.

`SimCamera` renders a MuJoCo model in a given state to an RGB array through a
camera that follows the robot (the model's first tracking camera: walker and
cheetah have `side`, which tracks the centre of mass), and turns a frame into
a `sensor_msgs/Image` (rgb8) and the matching `CameraInfo`. It needs no ROS
node.

`CameraPublisher` is what a node owns to publish `/camera/image_raw` and
`/camera/camera_info` at a fixed rate. It renders on a thread of its own: the
only thing it does in the stepping thread's way is copy qpos/qvel under the
node's lock; the frame is drawn from a private copy of the model and data, so
a control step never waits for a frame (software rendering took 60-140 ms
a 320x240 frame here, the machine loaded). Without off-screen OpenGL it
logs one warning and stops; the node carries on.

The GL backend is chosen here, not through dm_control: dm_control picks its
backend once, when it is imported, and `sim_node` sets MUJOCO_GL=disable for
itself (nothing else in it renders). MUJOCO_GL=glfw or osmesa is honoured;
anything else (unset, 'disable', 'egl') means EGL, which runs headless on
Mesa's software renderer.
"""

from __future__ import annotations

import math
import os
import threading
import time

from builtin_interfaces.msg import Time
import mujoco
import numpy as np
from sensor_msgs.msg import CameraInfo, Image

IMAGE_TOPIC = '/camera/image_raw'
INFO_TOPIC = '/camera/camera_info'
FRAME_ID = 'sim_camera_optical'
CAMERA_QOS_DEPTH = 2
# The longest `close()` waits for a frame being drawn (one takes < 0.2 s here).
CLOSE_TIMEOUT_S = 2.0


class NoOffscreenGL(RuntimeError):
    """No off-screen OpenGL context could be made (no backend, or MUJOCO_GL names a bad one)."""


def gl_backend() -> str:
    """Return the GL backend frames are drawn with: 'osmesa', 'glfw' or (default) 'egl'."""
    choice = os.environ.get('MUJOCO_GL', '').strip().lower()
    return {'osmesa': 'osmesa', 'glfw': 'glfw', 'glx': 'glfw'}.get(choice, 'egl')


def _no_gl(error: Exception) -> NoOffscreenGL:
    return NoOffscreenGL(f'{gl_backend()} (MUJOCO_GL={os.environ.get("MUJOCO_GL", "")!r}): '
                         f'{type(error).__name__}: {str(error).rstrip(".")}')


def _gl_context_class():
    backend = gl_backend()
    if backend == 'osmesa':
        from mujoco.osmesa import GLContext
    elif backend == 'glfw':
        from mujoco.glfw import GLContext
    else:
        from mujoco.egl import GLContext
    return GLContext


def pick_camera(model: mujoco.MjModel, camera: int | str | None = None) -> int:
    """Return the id of the camera to render through; -1 means MuJoCo's free camera.

    None picks the first camera that follows the robot (any mode but fixed),
    else the model's first camera (a robot that stays put, like the finger),
    else the free camera looking at the whole model.
    """
    if isinstance(camera, str):
        camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if camera_id < 0:
            raise ValueError(f'the model has no camera {camera!r}')
        return camera_id
    if camera is not None:
        if not -1 <= camera < model.ncam:
            raise ValueError(f'camera id {camera} outside [-1, {model.ncam - 1}]')
        return int(camera)
    for camera_id in range(model.ncam):
        if model.cam_mode[camera_id] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED:
            return camera_id
    return 0 if model.ncam else -1


def to_time(stamp) -> Time:
    """Return a builtin_interfaces/Time for integer nanoseconds (a Time as it is)."""
    if isinstance(stamp, Time):
        return stamp
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


# The model arrays a parameter swap may change in place (sizes, positions,
# masses: see ParamEnv.apply_prepared) and that decide what is drawn where.
# Copied from the live model under the node's lock with every frame (a few
# hundred bytes), so a swapped foot or torso is drawn at its new size.
GEOMETRY_FIELDS = ('body_pos', 'body_quat', 'body_ipos', 'body_iquat', 'body_mass',
                   'geom_pos', 'geom_quat', 'geom_size', 'geom_rbound', 'jnt_pos',
                   'site_pos', 'site_size', 'cam_pos', 'cam_quat', 'cam_pos0', 'cam_poscom0',
                   'cam_mat0')


def geometry_of(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Return copies of the model's swappable geometry arrays."""
    return {name: getattr(model, name).copy() for name in GEOMETRY_FIELDS}


class _GLScene:
    """What drawing one model takes: its private copy, a scene and a MuJoCo GL context."""

    def __init__(self, source: mujoco.MjModel, width: int, height: int, camera):
        # A copy, so that rendering reads nothing the stepping thread holds,
        # with an off-screen buffer at least as large as the frame.
        self.model = source.__copy__()
        self.model.vis.global_.offwidth = max(width, self.model.vis.global_.offwidth)
        self.model.vis.global_.offheight = max(height, self.model.vis.global_.offheight)
        self.data = mujoco.MjData(self.model)
        self.scene = mujoco.MjvScene(self.model, maxgeom=1000)
        self.context = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
        self.option = mujoco.MjvOption()
        self.camera = mujoco.MjvCamera()
        self.camera_id = pick_camera(self.model, camera)
        if self.camera_id >= 0:
            self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
            self.camera.fixedcamid = self.camera_id
        else:
            mujoco.mjv_defaultFreeCamera(self.model, self.camera)

    @property
    def fovy_deg(self) -> float:
        if self.camera_id >= 0:
            return float(self.model.cam_fovy[self.camera_id])
        return float(self.model.vis.global_.fovy)

    def draw(self, qpos, qvel, width: int, height: int, geometry=None) -> np.ndarray:
        for name, values in (geometry or {}).items():
            getattr(self.model, name)[:] = values
        self.data.qpos[:] = qpos
        if qvel is not None:
            self.data.qvel[:] = qvel
        mujoco.mj_forward(self.model, self.data)  # places bodies and the tracking camera
        viewport = mujoco.MjrRect(0, 0, width, height)
        mujoco.mjv_updateScene(self.model, self.data, self.option, None, self.camera,
                               mujoco.mjtCatBit.mjCAT_ALL, self.scene)
        mujoco.mjr_render(viewport, self.scene, self.context)
        pixels = np.empty((height, width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(pixels, None, viewport, self.context)
        return np.ascontiguousarray(pixels[::-1])  # OpenGL's rows run bottom-up

    def free(self) -> None:
        self.context.free()


class SimCamera:
    """Off-screen frames of a MuJoCo model through a camera that follows the robot.

    Everything GL happens in the thread that calls `render`/`render_state`
    (an OpenGL context belongs to one thread): create, render and `close` in
    the same one.
    """

    def __init__(self, width: int = 320, height: int = 240, camera: int | str | None = None,
                 frame_id: str = FRAME_ID):
        if width <= 0 or height <= 0:
            raise ValueError(f'frame size {width}x{height} must be positive')
        self.width, self.height = int(width), int(height)
        self.camera, self.frame_id = camera, frame_id
        self._gl = None
        self._source = None      # the model the scene was made from
        self._scene: _GLScene | None = None

    def render(self, physics) -> np.ndarray:
        """Frame (height, width, 3) uint8 of a dm_control Physics in its current state."""
        return self.render_state(physics.model.ptr, physics.data.qpos, physics.data.qvel)

    def render_state(self, model: mujoco.MjModel, qpos, qvel=None,
                     geometry: dict | None = None) -> np.ndarray:
        """Frame of `model` at joint positions `qpos` (velocities only matter to nothing drawn).

        Raises NoOffscreenGL when no GL context can be made.
        """
        self._use_model(model)
        self._gl.make_current()  # another camera in this thread may have taken it
        return self._scene.draw(qpos, qvel, self.width, self.height, geometry)

    def _use_model(self, model: mujoco.MjModel) -> None:
        if model is self._source:
            return
        if self._gl is None:
            self._gl = self._make_gl_context()
        self._gl.make_current()
        if self._scene is not None:
            self._scene.free()
        self._scene = None
        # A new model (a parameter swap rebuilds it): new copy, scene and textures.
        try:
            self._scene = _GLScene(model, self.width, self.height, self.camera)
        except mujoco.FatalError as error:  # mjr_makeContext: a GL context that does not work
            raise _no_gl(error) from error
        self._source = model

    def _make_gl_context(self):
        try:
            context = _gl_context_class()(self.width, self.height)
            context.make_current()
        except Exception as error:  # ImportError, OSError, RuntimeError, GLError...
            raise _no_gl(error) from error
        return context

    def focal_length(self) -> float:
        """Focal length in pixels (square pixels) of the camera last rendered through."""
        if self._scene is None:
            raise RuntimeError('nothing rendered yet: the camera is known at the first frame')
        return 0.5 * self.height / math.tan(math.radians(self._scene.fovy_deg) / 2)

    def image_message(self, frame: np.ndarray, stamp) -> Image:
        """sensor_msgs/Image (rgb8) of a frame; `stamp` in nanoseconds or a Time."""
        height, width, channels = frame.shape
        if channels != 3 or frame.dtype != np.uint8:
            raise ValueError(f'expected an (h, w, 3) uint8 frame, got {frame.shape} {frame.dtype}')
        image = Image(height=height, width=width, encoding='rgb8', is_bigendian=0,
                      step=3 * width, data=np.ascontiguousarray(frame).tobytes())
        image.header.stamp, image.header.frame_id = to_time(stamp), self.frame_id
        return image

    def camera_info(self, stamp) -> CameraInfo:
        """CameraInfo of the pinhole camera that made the frames (no distortion)."""
        f = self.focal_length()
        cx, cy = self.width / 2, self.height / 2
        info = CameraInfo(height=self.height, width=self.width, distortion_model='plumb_bob',
                          d=[0.0] * 5, k=[f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
                          r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                          p=[f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        info.header.stamp, info.header.frame_id = to_time(stamp), self.frame_id
        return info

    def close(self) -> None:
        """Free the GL resources (in the thread that rendered)."""
        if self._scene is not None:
            self._scene.free()
        if self._gl is not None:
            self._gl.free()
        self._gl, self._scene, self._source = None, None, None


class CameraPublisher:
    """Publish frames of the node's physics on /camera/image_raw and /camera/camera_info.

    `get_physics()` returns the dm_control Physics in force (called under
    `lock`, so a parameter swap that replaces it is seen); `lock` is the lock
    the node holds while it steps or resets that physics; `get_stamp_ns()`
    (also under the lock) gives the stamp of the state in it, by default the
    node's clock. Without a lock the copy is unsynchronised: only for a
    physics that nothing steps meanwhile. `rate_hz` 0 creates nothing at all.
    """

    def __init__(self, node, get_physics, rate_hz: float, lock=None, get_stamp_ns=None,
                 width: int = 320, height: int = 240, camera: int | str | None = None):
        self.rate_hz = float(rate_hz)
        self.frames = 0
        self.image_pub = self.info_pub = self._thread = None
        if not self.rate_hz > 0:
            return
        self._node, self._get_physics = node, get_physics
        self._lock = lock if lock is not None else threading.Lock()
        self._get_stamp_ns = get_stamp_ns or (lambda: node.get_clock().now().nanoseconds)
        self._camera_args = (width, height, camera)
        # A depth is rclpy's reliable keep-last profile (and no rclpy import, which
        # the simulation layer does without): a reliable and a best-effort reader
        # (ros2 topic hz, Foxglove) both match, and a slow one never holds the writer.
        self.image_pub = node.create_publisher(Image, IMAGE_TOPIC, CAMERA_QOS_DEPTH)
        self.info_pub = node.create_publisher(CameraInfo, INFO_TOPIC, CAMERA_QOS_DEPTH)
        self._stop = threading.Event()
        node.context.on_shutdown(self.close)  # stop drawing before rclpy goes away
        self._thread = threading.Thread(target=self._run, name='camera', daemon=True)
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
        if self._thread is not threading.current_thread():
            self._thread.join(CLOSE_TIMEOUT_S)

    def _run(self) -> None:
        camera = SimCamera(*self._camera_args)
        try:
            self._publish_at_rate(camera)
        except NoOffscreenGL as error:
            self._node.get_logger().warning(
                f'camera off, no frames on {IMAGE_TOPIC}: no off-screen OpenGL with {error}. '
                'EGL (the default) works headless with Mesa; a rate of 0 turns the camera off.')
        except Exception as error:  # the node must not go down with its camera
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
        self.image_pub.publish(camera.image_message(frame, stamp))
        self.info_pub.publish(camera.camera_info(stamp))
        self.frames += 1
