"""A lean offscreen renderer of the archery scene from qpos alone, and the simulated camera's
calibration marks.

The target camera sees the target, its stand, the floor and, after a shot, the arrow; the robot
is behind it, so the lean renderer (`SceneRenderer`) leaves out what changes no pixel of that
view. `calibration_frame` plays the paper's user for the simulated camera: it places an arrow
on the face, renders the frame and returns the pixels a user would mark.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import mujoco
import numpy as np

from archery.protocol.errors import ConfigError
from archery.sim.arrow import arrow_quat
from archery.sim.gl_backend import renderer_ready
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import (
    ARROW_BODY,
    RING_COLOURS,
    TARGET_CAMERA,
    TARGET_CENTRE_SITE,
    SceneConfig,
)
from archery.sim.view_key import ViewKey

__all__ = [
    "CALIBRATION_ARROW_R",
    "LEAN_FLAGS",
    "ROBOT_GEOM_GROUP",
    "SceneRenderer",
    "calibration_frame",
    "focal_length",
    "project",
]

ROBOT_GEOM_GROUP = 1
LEAN_FLAGS = (
    mujoco.mjtRndFlag.mjRND_SHADOW,
    mujoco.mjtRndFlag.mjRND_REFLECTION,
    mujoco.mjtRndFlag.mjRND_SKYBOX,
)
CALIBRATION_ARROW_R = (0.06, 0.19)  # m, where the calibration arrow sits (right, up): black ring


class SceneRenderer:
    """Renders `camera` of the scene built from `config`, for any qpos.

    With `lean` (the default), it builds the scene without the robot's meshes (they change no
    qpos), hides the robot's geom group, and turns off shadows, reflections, the skybox and
    multisampling: a 1280×720 frame then costs a fraction of the default settings on a
    software GL (Mesa llvmpipe with EGL). One renderer (one GL context) is reused for every
    frame; use it from the thread that created it.

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
        renderer_ready()  # MuJoCo opens its context with the backend sim.gl_backend picked
        self._renderer = mujoco.Renderer(self.model, height=height, width=width)
        self._option = mujoco.MjvOption()
        if lean:
            self._option.geomgroup[ROBOT_GEOM_GROUP] = 0
        self._lean = lean
        self._view = ViewKey(self.model, camera, width, height, self._option, lean=lean)

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def nq(self) -> int:
        """Length of the qpos vectors this renderer accepts."""
        return int(self.model.nq)

    def view_key(self, qpos: np.ndarray) -> bytes:
        """What the camera sees of `qpos`, as bytes: equal keys render equal images
        (`sim.view_key`)."""
        return self._view.key(qpos)

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
        mujoco.mj_fwdPosition(self.model, self.data)  # poses, tendons, cameras and lights
        self._renderer.update_scene(self.data, camera=self.camera, scene_option=self._option)
        if self._lean:  # update_scene restores the model's flags: switch them off each frame
            for flag in LEAN_FLAGS:
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
        """Free the GL context (idempotent)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def focal_length(height: int, fovy: float) -> float:
    """The focal length (px) of a pinhole camera `height` px high with a vertical field of view
    of `fovy` degrees."""
    return 0.5 * height / math.tan(0.5 * math.radians(fovy))


def project(renderer: SceneRenderer, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (column, row) of world points (N, 3, m) in the renderer's camera.

    Pixel (i, j) is centred on column i, row j (the image's top-left pixel is (0, 0)); the
    camera pose is the one of the renderer's data (as of its last `render`).
    """
    model, data = renderer.model, renderer.data
    cam = model.camera(renderer.camera).id
    pos = data.cam_xpos[cam]
    rot = data.cam_xmat[cam].reshape(3, 3)  # columns: camera x (right), y (up), z (backwards)
    local = (np.asarray(points, dtype=float) - pos) @ rot
    focal = focal_length(renderer.height, float(model.cam_fovy[cam]))
    column = 0.5 * renderer.width + focal * local[:, 0] / -local[:, 2] - 0.5
    row = 0.5 * renderer.height - focal * local[:, 1] / -local[:, 2] - 0.5
    return np.stack([column, row], axis=1)


def calibration_frame(
    renderer: SceneRenderer, qpos: np.ndarray, coloured_rings: int = 3, seed: int = 0
) -> tuple[np.ndarray, dict[str, list[list[float]]]]:
    """A frame with an arrow on the face, and marks {"target": [[x, y]…], "arrow": [[x, y]…]}.

    Target marks lie inside the first `coloured_rings` rings (yellow, red, blue), away from ring
    borders; arrow marks on the visible rim of the tip's disc: points of the scene projected
    through the camera (`project`), kept only where the segmentation shows that object. The
    renderer's data is left at the calibration state.

    Raises:
        ConfigError: qpos of the wrong length, or `coloured_rings` outside 1..5.
    """
    if not 1 <= coloured_rings <= len(RING_COLOURS):
        raise ConfigError(f"coloured_rings must be in 1..{len(RING_COLOURS)}, got {coloured_rings}")
    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.shape != (renderer.nq,):
        raise ConfigError(f"qpos has {qpos.size} values; this scene has nq = {renderer.nq}")
    physics = ScenePhysics(renderer.model, renderer.data)
    renderer.data.qpos[:] = qpos
    mujoco.mj_fwdPosition(renderer.model, renderer.data)
    centre = physics.site_position(TARGET_CENTRE_SITE)
    right, up = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    tip = centre + CALIBRATION_ARROW_R[0] * right + CALIBRATION_ARROW_R[1] * up
    direction = np.array([-1.0, 0.0, -0.05])
    physics.set_arrow_pose(tip, arrow_quat(direction))
    frame = renderer.render(renderer.data.qpos.copy())
    rng = np.random.default_rng(seed)
    radii = [0.0] + [r for r, _ in RING_COLOURS[:coloured_rings]]
    target_points = []
    for inner, outer in itertools.pairwise(radii):
        rho = rng.uniform(inner + 0.008, outer - 0.008, 40)
        phi = rng.uniform(0, 2 * math.pi, 40)
        target_points += [
            centre + r * (math.cos(p) * right + math.sin(p) * up)
            for r, p in zip(rho, phi, strict=True)
        ]
    axis = direction / np.linalg.norm(direction)
    side = np.cross(axis, up)
    side /= np.linalg.norm(side)
    lift = np.cross(side, axis)
    back = tip - 0.012 * axis
    phi = np.linspace(0, 2 * math.pi, 24, endpoint=False)
    arrow_points = [back + 0.011 * (math.cos(p) * side + math.sin(p) * lift) for p in phi]
    # keep only the marks where the camera really sees the object (not an occluding shaft)
    seen = renderer.segment(renderer.data.qpos.copy())
    model = renderer.model
    tip_geom = int(model.body_geomadr[model.body(ARROW_BODY).id])  # the tip's disc comes first
    ring_geoms = {model.geom(f"target_ring_{i}").id for i in range(coloured_rings)}

    def visible(points: list[np.ndarray], geoms: set[int]) -> list[list[float]]:
        pixels = project(renderer, np.array(points))
        keep = []
        for x, y in pixels:
            col, row = round(x), round(y)
            if 0 <= row < seen.shape[0] and 0 <= col < seen.shape[1] and seen[row, col] in geoms:
                keep.append([round(float(x), 1), round(float(y), 1)])
        return keep

    marks = {
        "target": visible(target_points, ring_geoms),
        "arrow": visible(arrow_points, {tip_geom}),
    }
    return frame, marks
