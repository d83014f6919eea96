"""Calibration marks for the simulated camera: what a user would click on a frame, from geometry.

The paper's user marks pixels inside the target and on the arrow's tip in one camera image.
For the simulated scene the marks come from the scene itself: an arrow is placed on the face,
the frame is rendered, and points inside the coloured rings and on the tip's disc are projected
through the camera model into pixel coordinates (column, row).
"""

from __future__ import annotations

import itertools
import math

import mujoco
import numpy as np

from sim.arrow import arrow_quat
from sim.render import SceneRenderer
from sim.scene import RING_COLOURS, TARGET_CENTRE_SITE, ScenePhysics

__all__ = ["calibration_frame", "project"]

CALIBRATION_ARROW_R = (0.06, 0.19)  # m, where the arrow sits on the face (right, up): black ring


def project(renderer: SceneRenderer, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (column, row) of world points (N, 3) in the renderer's camera."""
    model, data = renderer.model, renderer.data
    cam = model.camera(renderer.camera).id
    pos = data.cam_xpos[cam]
    rot = data.cam_xmat[cam].reshape(3, 3)  # columns: camera x (right), y (up), z (backwards)
    local = (np.asarray(points, dtype=float) - pos) @ rot
    fovy = math.radians(float(model.cam_fovy[cam]))
    focal = 0.5 * renderer.height / math.tan(0.5 * fovy)
    column = 0.5 * renderer.width + focal * local[:, 0] / -local[:, 2]
    row = 0.5 * renderer.height - focal * local[:, 1] / -local[:, 2]
    return np.stack([column, row], axis=1)


def calibration_frame(
    renderer: SceneRenderer, qpos: np.ndarray, coloured_rings: int = 3, seed: int = 0
) -> tuple[np.ndarray, dict[str, list[list[float]]]]:
    """A frame with an arrow on the face, and marks {"target": [[x, y]…], "arrow": [[x, y]…]}.

    Target marks lie inside the first `coloured_rings` rings (yellow, red, blue), away from ring
    borders; arrow marks on the visible rim of the tip's disc.
    """
    physics = ScenePhysics(renderer.model, renderer.data)
    renderer.data.qpos[:] = qpos
    mujoco.mj_kinematics(renderer.model, renderer.data)
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
    tip_geom = int(model.body_geomadr[model.body("arrow").id])  # the tip's disc comes first
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
