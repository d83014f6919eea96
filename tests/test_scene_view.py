"""The third-person view: the whole robot, bow and target seen from the side camera."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from archery.protocol.errors import ConfigError
from archery.sim.render import SceneRenderer, project
from archery.sim.scene_config import SIDE_CAMERA, SceneConfig
from archery.sim.scene_view import SceneView


@pytest.fixture(scope="module")
def view() -> Iterator[SceneView]:
    with SceneView(SceneConfig(meshes=False), width=320, height=180) as v:
        yield v


def test_the_view_draws_the_robot_meshes_the_lean_renderer_drops(view: SceneView) -> None:
    qpos = np.zeros(view.nq)
    with SceneRenderer(SceneConfig(), width=320, height=180, camera=SIDE_CAMERA) as lean:
        qpos = lean.model.qpos0.copy()
        bare = lean.render(qpos)
        root = project(lean, np.array([[0.0, 0.0, 0.0]]))[0]
    full = view.render(qpos)
    assert full.shape == (180, 320, 3) and full.dtype == np.uint8
    np.testing.assert_array_equal(view.render(qpos), full)
    # around the robot's root (its red torso) the view differs from the scene without meshes
    col, row = round(root[0]), round(root[1])
    patch = (slice(row - 6, row + 6), slice(col - 4, col + 4))
    diff = np.abs(full[patch].astype(int) - bare[patch].astype(int)).sum(axis=2)
    assert (diff > 60).mean() > 0.5
    red = full[patch][..., 0].astype(int) - full[patch][..., 1:].max(axis=2)
    assert (red > 60).mean() > 0.3


def test_a_qpos_of_another_scene_is_refused(view: SceneView) -> None:
    with pytest.raises(ConfigError, match=f"nq = {view.nq}"):
        view.render(np.zeros(view.nq + 1))


def test_an_unknown_camera_is_refused() -> None:
    with pytest.raises(ConfigError, match="no camera 'nowhere'"):
        SceneView(camera="nowhere")
