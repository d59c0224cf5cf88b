"""An off-screen camera on the simulated robot: frames as RGB arrays (no ROS).

`SimCamera` renders a MuJoCo model in a given state to an RGB array through a
camera that follows the robot (the model's first tracking camera: walker and
cheetah have `side`, which tracks the centre of mass). The sim node publishes
its frames through `zeus_ros.ros.camera.CameraPublisher`.

The GL backend is chosen here, not through dm_control: dm_control picks its
backend once, when it is imported, and `sim_node` sets MUJOCO_GL=disable for
itself (nothing else in it renders). MUJOCO_GL=glfw or osmesa is honoured;
anything else (unset, 'disable', 'egl') means EGL, which runs headless on
Mesa's software renderer.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING

import mujoco
import numpy as np

if TYPE_CHECKING:
    from sim_node.family_env import EnvPhysics


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

    def __init__(self, source: mujoco.MjModel, width: int, height: int,
                 camera: int | str | None):
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

    def draw(self, qpos: np.ndarray, qvel: np.ndarray | None, width: int, height: int,
             geometry: dict[str, np.ndarray] | None = None) -> np.ndarray:
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

    def __init__(self, width: int = 320, height: int = 240, camera: int | str | None = None):
        if width <= 0 or height <= 0:
            raise ValueError(f'frame size {width}x{height} must be positive')
        self.width, self.height = int(width), int(height)
        self.camera = camera
        self._gl = None
        self._source = None      # the model the scene was made from
        self._scene: _GLScene | None = None

    def render(self, physics: EnvPhysics) -> np.ndarray:
        """Frame (height, width, 3) uint8 of a dm_control Physics in its current state."""
        return self.render_state(physics.model.ptr, physics.data.qpos, physics.data.qvel)

    def render_state(self, model: mujoco.MjModel, qpos: np.ndarray,
                     qvel: np.ndarray | None = None,
                     geometry: dict[str, np.ndarray] | None = None) -> np.ndarray:
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

    def close(self) -> None:
        """Free the GL resources (in the thread that rendered)."""
        if self._scene is not None:
            self._scene.free()
        if self._gl is not None:
            self._gl.free()
        self._gl, self._scene, self._source = None, None, None
