"""The third-person view of the whole archery scene: the iCub with its meshes, the bow and its
string, the arrow and the target, seen from the scene's side camera (`sim.props`).

`SceneView` is the full-quality counterpart of the lean target-camera renderer of `sim.render`:
it loads the robot's meshes and keeps shadows, the skybox and multisampling, because a person
watches it. Like that renderer it reproduces any state of a robot running the same
`SceneConfig` from the qpos alone, and holds one GL context: use it from the thread that made it.

    with SceneView(config, width=960, height=540) as view:
        frame = view.render(qpos)  # (540, 960, 3) uint8 RGB
"""

from __future__ import annotations

import dataclasses

import numpy as np

from sim.render import SceneRenderer
from sim.scene_config import SIDE_CAMERA, SceneConfig

__all__ = ["SceneView"]


class SceneView:
    """Renders the full scene, robot meshes included, from `camera` for any qpos.

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

    def __enter__(self) -> SceneView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def nq(self) -> int:
        """Length of the qpos vectors this view accepts."""
        return self._renderer.nq

    def render(self, qpos: np.ndarray) -> np.ndarray:
        """An RGB uint8 image (height, width, 3) of the scene at `qpos`.

        Raises:
            ConfigError: qpos of the wrong length (another scene configuration).
        """
        return self._renderer.render(qpos)

    def close(self) -> None:
        """Free the GL context (idempotent)."""
        self._renderer.close()
