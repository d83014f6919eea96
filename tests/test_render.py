"""The lean renderer of the target camera: frames, projection, segmentation, calibration marks."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from archery.protocol.errors import ConfigError
from archery.sim.render import SceneRenderer, calibration_frame, project
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import ARROW_TIP_SITE, RING_COLOURS, TARGET_CENTRE_SITE, SceneConfig

SCENE = SceneConfig(meshes=False)


@pytest.fixture(scope="module")
def renderer() -> Iterator[SceneRenderer]:
    with SceneRenderer(SCENE) as r:
        yield r


def test_frames_are_rgb_of_the_asked_size_and_deterministic(renderer: SceneRenderer) -> None:
    qpos = renderer.model.qpos0.copy()
    first = renderer.render(qpos)
    assert first.shape == (720, 1280, 3) and first.dtype == np.uint8
    np.testing.assert_array_equal(renderer.render(qpos), first)
    assert renderer.model.vis.quality.offsamples == 0  # no multisampling


def test_a_qpos_of_another_scene_is_refused(renderer: SceneRenderer) -> None:
    with pytest.raises(ConfigError, match=f"nq = {renderer.nq}"):
        renderer.render(np.zeros(renderer.nq + 3))


def test_the_target_centre_projects_onto_the_yellow_disc(renderer: SceneRenderer) -> None:
    frame = renderer.render(renderer.model.qpos0.copy())
    physics = ScenePhysics(renderer.model, renderer.data)
    centre_px = project(renderer, physics.site_position(TARGET_CENTRE_SITE)[None])[0]
    yellow = np.array(RING_COLOURS[0][1][:3]) * 255
    close = np.linalg.norm(frame.astype(float) - yellow, axis=2) < 60
    rows, cols = np.nonzero(close)
    assert len(rows) > 500
    # the disc is small (5 cm at 2.3 m): its projected centroid is the centre's projection
    np.testing.assert_allclose([cols.mean(), rows.mean()], centre_px, atol=0.6)
    # image columns grow to the robot's right (+y), rows grow downwards (−z)
    right = project(
        renderer, (physics.site_position(TARGET_CENTRE_SITE) + np.array([0, 0.1, 0]))[None]
    )
    up = project(
        renderer, (physics.site_position(TARGET_CENTRE_SITE) + np.array([0, 0, 0.1]))[None]
    )
    assert right[0, 0] > centre_px[0] + 50 and abs(right[0, 1] - centre_px[1]) < 10
    assert up[0, 1] < centre_px[1] - 50 and abs(up[0, 0] - centre_px[0]) < 10


def test_segmentation_names_the_geoms_seen(renderer: SceneRenderer) -> None:
    qpos = renderer.model.qpos0.copy()
    seen = renderer.segment(qpos)
    assert seen.shape == (720, 1280) and seen.dtype == np.int32
    physics = ScenePhysics(renderer.model, renderer.data)
    col, row = np.round(project(renderer, physics.site_position(TARGET_CENTRE_SITE)[None])[0])
    assert seen[int(row), int(col)] == renderer.model.geom("target_ring_0").id
    # segmentation is switched off again afterwards
    assert renderer.render(qpos).std() > 10


def test_calibration_marks_lie_on_the_rings_and_on_the_tip(renderer: SceneRenderer) -> None:
    frame, marks = calibration_frame(renderer, renderer.model.qpos0.copy())
    assert len(marks["target"]) >= 100 and len(marks["arrow"]) >= 8
    rings = np.array([rgba[:3] for _, rgba in RING_COLOURS[:3]]) * 255
    for x, y in marks["target"]:
        colour = frame[round(y), round(x)].astype(float)
        assert np.min(np.linalg.norm(rings - colour, axis=1)) < 90, (x, y, colour)
    for x, y in marks["arrow"]:
        r, g, b = frame[round(y), round(x)].astype(int)
        assert g > 120 and g > r + 50 and g > b + 50, (x, y, (r, g, b))
    # the arrow sits where the marks are: its tip projects next to them
    physics = ScenePhysics(renderer.model, renderer.data)
    tip = project(renderer, physics.site_position(ARROW_TIP_SITE)[None])[0]
    assert np.linalg.norm(np.mean(marks["arrow"], axis=0) - tip) < 15


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ConfigError, match="no camera"):
        SceneRenderer(SCENE, camera="nope")
    with pytest.raises(ConfigError, match=r"16\.\.4096"):
        SceneRenderer(SCENE, width=8)


def test_a_view_key_changes_with_what_the_camera_sees_only(renderer: SceneRenderer) -> None:
    model = renderer.model
    rest = model.qpos0.copy()
    # the robot turns its torso and moves both arms (behind the camera): same key, same image
    moved = rest.copy()
    rng = np.random.default_rng(3)
    for j in range(model.njnt):
        name = model.joint(j).name
        if name.startswith(("torso_", "l_", "r_")):
            moved[model.jnt_qposadr[j]] += rng.uniform(-0.3, 0.3)
    assert not np.array_equal(moved, rest)
    assert renderer.view_key(moved) == renderer.view_key(rest)
    np.testing.assert_array_equal(renderer.render(moved), renderer.render(rest))
    # an arrow on the face: another key and another image; moved on the face: another again
    calibration_frame(renderer, rest)
    stuck = renderer.data.qpos.copy()
    assert renderer.view_key(stuck) != renderer.view_key(rest)
    assert not np.array_equal(renderer.render(stuck), renderer.render(rest))
    nudged = stuck.copy()
    nudged[model.jnt_qposadr[model.joint("arrow_free").id] + 1] += 1e-6
    assert renderer.view_key(nudged) != renderer.view_key(stuck)


def test_without_the_lean_settings_the_key_is_the_qpos() -> None:
    with SceneRenderer(SCENE, width=64, height=48, lean=False) as plain:
        qpos = plain.model.qpos0.copy()
        assert plain.view_key(qpos) == qpos.tobytes()
