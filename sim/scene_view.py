"""The third-person view of the whole archery scene: the iCub with its meshes, the bow and its
string, the arrow and the target, from the scene's side camera (`sim.props`) or a free camera.

`SceneView` is the full-quality counterpart of the lean target-camera renderer of `sim.render`:
it loads the robot's meshes and keeps shadows, the skybox and multisampling, because a person
watches it. Like that renderer it reproduces any state of a robot running the same
`SceneConfig` from the qpos alone, and holds one GL context: use it from the thread that made it.

    with SceneView(config, width=960, height=540) as view:
        frame = view.render(qpos)  # (540, 960, 3) uint8 RGB, from the side camera
        close = view.render(qpos, free_camera(lookat, 1.2, -70.0, -8.0))  # m, m, deg, deg
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import mujoco
import numpy as np

from archery.sim.render import SceneRenderer
from archery.sim.scene_config import SIDE_CAMERA, SceneConfig

__all__ = ["SceneView", "free_camera"]


def free_camera(
    lookat: Sequence[float] | np.ndarray, distance: float, azimuth: float, elevation: float
) -> mujoco.MjvCamera:
    """A free MuJoCo camera looking at `lookat` (m, root frame) from `distance` (m), turned
    `azimuth` degrees about +z from +x (−90: looking along −y) and tilted `elevation` degrees
    (< 0: looking down); its vertical field of view is the model's `vis.global_.fovy`."""
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = np.asarray(lookat, dtype=float)
    camera.distance = float(distance)
    camera.azimuth = float(azimuth)
    camera.elevation = float(elevation)
    return camera


class SceneView:
    """Renders the full scene, robot meshes included, from `camera` or from a free camera, for
    any qpos.

    A free camera is given to the view's camera of the scene: MuJoCo places its free camera
    (`mjv_updateCamera`) and the view's camera takes that pose and field of view for the
    frame; a frame without a free camera is seen from the named camera's own pose.

    Args:
        config: the robot's scene parameters (the same model, so the same qpos layout); the
            view loads the meshes whatever `config.meshes` says.
        width, height: image size (px, 16..4096).
        camera: a camera name of the scene; the side camera sees robot, flight and target.

    Raises:
        ConfigError: an unknown camera or an image size out of range.
        sim.errors.SceneError: the robot's model files are missing.
    """

    def __init__(
        self,
        config: SceneConfig | None = None,
        *,
        width: int = 1280,
        height: int = 720,
        camera: str = SIDE_CAMERA,
    ) -> None:
        config = dataclasses.replace(config or SceneConfig(), meshes=True)
        self._renderer = SceneRenderer(
            config, width=width, height=height, camera=camera, lean=False
        )
        self.config = config
        self.width, self.height = width, height
        self.model = self._renderer.model
        self._camera = self.model.camera(camera).id
        self._own_pose = (
            self.model.cam_pos[self._camera].copy(),
            self.model.cam_quat[self._camera].copy(),
            float(self.model.cam_fovy[self._camera]),
        )
        self._free = mujoco.MjvScene(self.model, maxgeom=1)  # only its cameras are used

    def __enter__(self) -> SceneView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def nq(self) -> int:
        """Length of the qpos vectors this view accepts."""
        return self._renderer.nq

    def render(self, qpos: np.ndarray, camera: mujoco.MjvCamera | None = None) -> np.ndarray:
        """An RGB uint8 image (height, width, 3) of the scene at `qpos`, from the free `camera`
        (`free_camera`), or from the view's camera of the scene if None.

        Raises:
            ConfigError: qpos of the wrong length (another scene configuration).
        """
        self._aim(camera)
        return self._renderer.render(qpos)

    def segment(self, qpos: np.ndarray, camera: mujoco.MjvCamera | None = None) -> np.ndarray:
        """Geom id seen at each pixel (height, width) int32, −1 where no geom is seen, from the
        camera `render(qpos, camera)` sees from."""
        self._aim(camera)
        return self._renderer.segment(qpos)

    def _aim(self, camera: mujoco.MjvCamera | None) -> None:
        """Give the view's camera the pose and field of view of the free `camera` (None: its
        own)."""
        model, cam = self.model, self._camera
        if camera is None:
            pos, quat, fovy = self._own_pose
        else:
            mujoco.mjv_updateCamera(model, self._renderer.data, camera, self._free)
            left, right = self._free.camera[0], self._free.camera[1]
            pos = 0.5 * (np.asarray(left.pos) + np.asarray(right.pos))  # between the eyes
            forward, up = np.asarray(left.forward), np.asarray(left.up)
            frame = np.column_stack([np.cross(forward, up), up, -forward])  # x right, z back
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, frame.flatten())
            fovy = float(model.vis.global_.fovy)
        model.cam_pos[cam], model.cam_quat[cam], model.cam_fovy[cam] = pos, quat, fovy

    def close(self) -> None:
        """Free the GL context (idempotent)."""
        self._renderer.close()
