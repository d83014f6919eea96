"""The film frames the shot: measured on the frames `archery film` shoots (its states and
cameras, rendered as MuJoCo's segmentation: the geom at each pixel), the robot's upper body
fills at least a third of the frame's height while it moves, and the flying arrow stays in the
middle of the frame until it lands; the camera moves without a jump."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest

from archery.apps.film.framing import ShotCamera, framed
from archery.apps.film.replay import FilmFrame, ShotReplay, load_rollout
from archery.sim.geometry import target_centre
from archery.sim.scene_config import ARROW_BODY, SceneConfig
from archery.sim.scene_view import SceneView

JOURNAL = Path(__file__).parent / "journals" / "old_format.jsonl"
WIDTH, HEIGHT = 320, 180  # px
FPS = 30
MIDDLE = 0.8  # of the frame's width and height, centred: where the flying arrow must be


@dataclass(frozen=True)
class Shown:
    """One rendered frame of the film: its state, its camera (look-at point m, distance m,
    azimuth and elevation degrees) and the geom seen at each pixel."""

    frame: FilmFrame
    lookat: np.ndarray
    distance: float
    azimuth: float
    elevation: float
    geoms: np.ndarray


def _upper_body(model: mujoco.MjModel) -> np.ndarray:
    """The robot's geoms from the torso up, both arms with it: its visual meshes (group 1) on
    the bodies that hang from the torso's first link."""
    torso = model.body("torso_1").id
    return np.flatnonzero((model.geom_group == 1) & (model.body_rootid[model.geom_bodyid] == torso))


def _extent(geoms: np.ndarray, wanted: np.ndarray) -> tuple[int, int, int, int] | None:
    """(top row, bottom row, left column, right column) of the pixels showing `wanted` geoms,
    None if none shows."""
    seen = np.isin(geoms, wanted)
    rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
    if rows.size == 0:
        return None
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


@pytest.fixture(scope="module")
def film() -> Iterator[tuple[list[Shown], SceneView]]:
    """The session's first hit as `archery film` shoots it (`film_session`'s frames and
    cameras, at its default frame rate), each frame segmented from its camera."""
    replay = ShotReplay(load_rollout(JOURNAL, None))
    shown = []
    with SceneView(replay.world.config.scene, width=WIDTH, height=HEIGHT) as view:
        for frame, camera in framed(replay.frames(FPS), view.model, WIDTH, HEIGHT):
            shown.append(
                Shown(
                    frame,
                    np.array(camera.lookat),
                    float(camera.distance),
                    float(camera.azimuth),
                    float(camera.elevation),
                    view.segment(frame.qpos, camera),
                )
            )
        yield shown, view


def test_the_robot_fills_a_third_of_the_frame_while_it_moves(
    film: tuple[list[Shown], SceneView],
) -> None:
    shown, view = film
    upper = _upper_body(view.model)
    moving = [s for s in shown if not s.frame.released]
    assert len(moving) >= 10  # the posture move and the nock
    fractions = []
    for s in moving:
        extent = _extent(s.geoms, upper)
        assert extent is not None, s.frame.phase
        top, bottom, left, right = extent
        fractions.append((bottom - top + 1) / HEIGHT)
        # the whole upper body in view: the head under the top edge, both arms within the sides
        assert top > 0 and left > 0 and right < WIDTH - 1, (s.frame.phase, extent)
    assert min(fractions) >= 1 / 3, min(fractions)


def test_the_camera_follows_the_arrow_from_the_release_to_the_landing(
    film: tuple[list[Shown], SceneView],
) -> None:
    shown, view = film
    model = view.model
    arrow = np.flatnonzero(model.geom_bodyid == model.body(ARROW_BODY).id)
    flying = [s for s in shown if s.frame.phase.startswith(("release", "flight", "impact"))]
    assert flying and all(s.frame.released for s in flying)
    assert sum(s.frame.phase.startswith("flight") for s in flying) >= 20
    margin_x, margin_y = (1 - MIDDLE) / 2 * WIDTH, (1 - MIDDLE) / 2 * HEIGHT
    for s in flying:
        extent = _extent(s.geoms, arrow)
        assert extent is not None, s.frame.phase  # never out of the frame nor hidden
        top, bottom, left, right = extent
        assert margin_y <= top and bottom < HEIGHT - margin_y, (s.frame.phase, extent)
        assert margin_x <= left and right < WIDTH - margin_x, (s.frame.phase, extent)
    # the camera went with it: from the robot at the release to the target at the landing
    centre = target_centre(view.config.target_distance)
    assert np.linalg.norm(flying[0].lookat - centre) > 1.5
    assert np.linalg.norm(flying[-1].lookat - centre) < 0.05


def test_the_camera_moves_without_a_jump(film: tuple[list[Shown], SceneView]) -> None:
    shown, view = film
    tan_x = math.tan(math.radians(view.model.vis.global_.fovy) / 2) * WIDTH / HEIGHT
    for before, after in itertools.pairwise(shown):
        width = 2 * before.distance * tan_x  # m seen across the frame at the look-at point
        step = float(np.linalg.norm(after.lookat - before.lookat))
        assert step <= 0.06 * width, (after.frame.phase, step, width)
        assert abs(after.distance - before.distance) <= 0.02 * before.distance
        assert abs(after.azimuth - before.azimuth) <= 3.0
        assert abs(after.elevation - before.elevation) <= 1.0


def test_the_whole_shot_is_framed_with_the_arrow_in_its_holder() -> None:
    """The whole shot's robot framing (from a recording: the same camera) shows the robot at
    its start, arms down, and the arrow it reaches for in its holder."""
    with SceneView(SceneConfig(shot="whole"), width=WIDTH, height=HEIGHT) as view:
        model = view.model
        camera = ShotCamera(model, WIDTH, HEIGHT)
        qpos = model.qpos0.copy()
        geoms = view.segment(qpos, camera.aim(qpos, released=False))
    body = _extent(geoms, _upper_body(model))
    held = _extent(geoms, np.flatnonzero(model.geom_bodyid == model.body(ARROW_BODY).id))
    assert body is not None and held is not None
    assert (body[1] - body[0] + 1) / HEIGHT >= 1 / 3 and body[0] > 0, body
    assert held[0] > 0 and held[1] < HEIGHT - 1 and held[2] > 0 and held[3] < WIDTH - 1, held
