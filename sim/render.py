"""A lean offscreen renderer of the archery scene from qpos alone (for the camera service).

The target camera sees the target, its stand, the floor and, after a shot, the arrow; the robot
is behind it. So the renderer builds the scene without the robot's meshes, hides the robot's
geom group, and turns off shadows, reflections, the skybox and multisampling: a 1280×720 frame
then costs a fraction of the default settings on a software GL (Mesa llvmpipe with EGL).
"""

from __future__ import annotations

import dataclasses
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

from sim.errors import ConfigError
from sim.scene import TARGET_CAMERA, SceneConfig, build_scene

__all__ = ["ROBOT_GEOM_GROUP", "SceneRenderer"]

ROBOT_GEOM_GROUP = 1


class SceneRenderer:
    """Renders `camera` of the scene built from `config`, for any qpos.

    Args:
        config: the robot's scene parameters (the same model, so the same qpos layout).
        width, height: image size (px).
        camera: a camera name of the scene.
        lean: drop robot meshes, shadows, reflections, skybox and multisampling.
    """

    def __init__(
        self,
        config: SceneConfig | None = None,
        *,
        width: int = 1280,
        height: int = 720,
        camera: str = TARGET_CAMERA,
        lean: bool = True,
    ) -> None:
        config = config or SceneConfig()
        if lean:
            config = dataclasses.replace(config, meshes=False)
        self.model = build_scene(config)
        if mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            raise ConfigError(f"the scene has no camera {camera!r}")
        if not (16 <= width <= 4096 and 16 <= height <= 4096):
            raise ConfigError(f"image size {width}x{height} is outside 16..4096 px")
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, width)
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, height)
        if lean:
            self.model.vis.quality.offsamples = 0
        self.data = mujoco.MjData(self.model)
        self.camera = camera
        self.width, self.height = width, height
        self._renderer = mujoco.Renderer(self.model, height=height, width=width)
        self._option = mujoco.MjvOption()
        if lean:
            self._option.geomgroup[ROBOT_GEOM_GROUP] = 0
            for flag in (
                mujoco.mjtRndFlag.mjRND_SHADOW,
                mujoco.mjtRndFlag.mjRND_REFLECTION,
                mujoco.mjtRndFlag.mjRND_SKYBOX,
            ):
                self._renderer.scene.flags[flag] = 0
        self._lean = lean

    @property
    def nq(self) -> int:
        """Length of the qpos vectors this renderer accepts."""
        return int(self.model.nq)

    def render(self, qpos: np.ndarray) -> np.ndarray:
        """An RGB uint8 image (height, width, 3) of the scene at `qpos`.

        Raises:
            ConfigError: qpos of the wrong length (a scene built with other parameters).
        """
        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.shape != (self.model.nq,):
            raise ConfigError(
                f"qpos has {qpos.size} values; this scene has nq = {self.model.nq} "
                f"(is the robot running a different scene configuration?)"
            )
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self._renderer.update_scene(self.data, camera=self.camera, scene_option=self._option)
        if self._lean:
            for flag in (
                mujoco.mjtRndFlag.mjRND_SHADOW,
                mujoco.mjtRndFlag.mjRND_REFLECTION,
                mujoco.mjtRndFlag.mjRND_SKYBOX,
            ):
                self._renderer.scene.flags[flag] = 0
        return self._renderer.render()

    def segment(self, qpos: np.ndarray) -> np.ndarray:
        """Geom id seen at each pixel (height, width) int32, −1 where no geom is seen."""
        self._renderer.enable_segmentation_rendering()
        try:
            ids = self.render(qpos)
        finally:
            self._renderer.disable_segmentation_rendering()
        geom = np.where(ids[:, :, 1] == int(mujoco.mjtObj.mjOBJ_GEOM), ids[:, :, 0], -1)
        return geom.astype(np.int32)

    def close(self) -> None:
        """Free the GL context."""
        self._renderer.close()
