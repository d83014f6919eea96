"""Detection on rendered frames with ground-truth impacts, on synthetic frames, and bad input."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from archery.protocol.errors import ConfigError
from archery.services.detector.calibration import sample_pixels
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import Detector, DetectorSettings
from archery.services.detector.errors import ImageError
from archery.sim.arrow import arrow_quat
from archery.sim.bow import Bow
from archery.sim.geometry import BOW_HAND, TARGET_DISTANCE
from archery.sim.model_build import build_scene
from archery.sim.render import SceneRenderer, calibration_frame, project
from archery.sim.scene_config import ARROW_TIP_SITE, TARGET_CENTRE_SITE, SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig
from tests.detector_reference import exact_memberships, locate
from tests.postures import archery_posture
from tests.world_steps import move_until_done

SCENE = SceneConfig(meshes=False)
# a noisy bow, so the shots spread over the face
NOISY = {"direction_noise": 0.04, "speed_noise": 0.02}


def _aim_theta(length: float = 0.17) -> np.ndarray:
    """θ whose drag-free arrow from the nominal bow hand meets the target centre."""
    speed = Bow().launch_speed(np.array([length, 0.0, 0.0]))
    distance = BOW_HAND[0] + TARGET_DISTANCE
    elevation = math.atan2(0.5 * 9.81 * (distance / speed) ** 2, distance)
    return length * np.array([math.cos(elevation), 0.0, -math.sin(elevation)])


@dataclass
class Rig:
    renderer: SceneRenderer
    world: ArcheryWorld
    posture: dict[str, np.ndarray]
    model: ColourModel
    detector: Detector


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    model = build_scene(SCENE)
    world = ArcheryWorld(WorldConfig(scene=SCENE, **NOISY), model=model)  # type: ignore[arg-type]  # float noise fields
    posture = archery_posture(model, BOW_HAND, BOW_HAND + _aim_theta(), tolerance=5e-3)
    with SceneRenderer(SCENE) as renderer:
        frame, marks = calibration_frame(renderer, world.qpos())
        colours = ColourModel.fit(
            sample_pixels(frame, marks["target"], "target"),
            sample_pixels(frame, marks["arrow"], "arrow"),
        )
        yield Rig(renderer, world, posture, colours, Detector(colours))


def _shoot(rig: Rig, seed: int):
    world = rig.world
    world.reset(seed)
    for part, values in rig.posture.items():
        world.set_joint_targets(part, values)
    assert move_until_done(world, 15.0)
    world.nock()
    return world.release()


def test_rendered_landings_are_measured_within_a_centimetre(rig: Rig) -> None:
    errors = []
    for seed in range(8):
        landing = _shoot(rig, seed)
        if not landing.hit:
            continue
        found = rig.detector.detect(rig.renderer.render(rig.world.qpos()))
        assert found.status == "ok", (seed, found)
        assert found.target.confidence > 0.9 and found.arrow.confidence > 0.5
        error = np.linalg.norm(np.asarray(found.r_m) - landing.r)
        errors.append(error)
        assert error <= 0.010, (seed, landing.r, found.r_m)  # m, at 2.2 m
    assert len(errors) >= 6
    assert float(np.mean(errors)) < 0.006


@pytest.mark.parametrize("r", [(0.10, 0.0), (0.0, 0.10), (-0.08, -0.12), (0.2, 0.1)])
def test_r_follows_the_mesh_convention_right_and_up(rig: Rig, r: tuple[float, float]) -> None:
    """An arrow placed at a known offset (m, right, up) is measured there: image columns are the
    robot's right, image rows point down."""
    world = rig.world
    world.reset(0)
    physics = world.physics
    centre = physics.site_position(TARGET_CENTRE_SITE)
    physics.set_arrow_pose(
        centre + np.array([0.0, r[0], r[1]]), arrow_quat(np.array([-1, 0, -0.05]))
    )
    found = rig.detector.detect(rig.renderer.render(physics.qpos()))
    assert found.status == "ok"
    np.testing.assert_allclose(found.r_m, r, atol=0.01)
    # the paper's r = m_T − m_A in pixels points the other way, with rows downwards
    m_t, m_a = np.asarray(found.target.px), np.asarray(found.arrow.px)
    assert np.sign(m_a[0] - m_t[0]) == np.sign(r[0]) or r[0] == 0
    assert np.sign(m_t[1] - m_a[1]) == np.sign(r[1]) or r[1] == 0


def test_the_arrow_tip_is_found_next_to_its_projection(rig: Rig) -> None:
    landing = _shoot(rig, 3)
    assert landing.hit
    found = rig.detector.detect(rig.renderer.render(rig.world.qpos()))
    tip = project(rig.renderer, rig.world.physics.site_position(ARROW_TIP_SITE)[None])[0]
    # the visible disc stands 12 mm proud of the face: a few pixels of parallax
    assert np.linalg.norm(np.asarray(found.arrow.px) - tip) < 4.0


def test_lut_matches_the_exact_gmm_within_a_pixel(rig: Rig) -> None:
    _shoot(rig, 1)
    frame = rig.renderer.render(rig.world.qpos())
    by_table = locate(rig.detector, *rig.detector.memberships(frame))
    exact = locate(rig.detector, *exact_memberships(rig.model, frame))
    assert by_table.status == exact.status == "ok"
    for a, b in ((by_table.target, exact.target), (by_table.arrow, exact.arrow)):
        assert np.linalg.norm(np.subtract(a.px, b.px)) <= 1.0


def test_bic_uses_more_gaussians_for_the_rings_than_for_the_tip(rig: Rig) -> None:
    assert rig.model.arrow is not None
    assert rig.model.target.n_components > rig.model.arrow.n_components


def test_a_frame_without_the_arrow_reports_no_arrow(rig: Rig) -> None:
    rig.world.reset(0)  # the arrow is stowed beside the robot, out of the camera's view
    found = rig.detector.detect(rig.renderer.render(rig.world.qpos()))
    assert found.status == "no_arrow" and found.arrow is None and found.r_m is None
    assert found.target is not None and found.target.confidence > 0.9


def test_frames_without_the_target_report_no_target(rig: Rig) -> None:
    rig.world.reset(0)
    frame = rig.renderer.render(rig.world.qpos())
    rng = np.random.default_rng(0)
    floor_only = np.ascontiguousarray(frame[400:, :400])
    half_target = np.ascontiguousarray(frame[:, :640])  # cut through the face's centre
    noise = rng.integers(0, 256, frame.shape, dtype=np.uint8)
    blotches = np.full_like(frame, 90)
    for _ in range(40):  # target-coloured specks scattered over the frame
        x, y = rng.integers(0, 1280), rng.integers(0, 720)
        colour = [(250, 215, 20), (225, 25, 25), (30, 90, 225)][int(rng.integers(3))]
        cv2.circle(blotches, (int(x), int(y)), int(rng.integers(3, 12)), colour, -1)
    for name, image in (
        ("floor", floor_only),
        ("half", half_target),
        ("noise", noise),
        ("blotches", blotches),
        ("black", np.zeros_like(frame)),
    ):
        found = rig.detector.detect(image)
        assert found.status == "no_target" and found.target is None and found.r_m is None, name


def test_images_of_the_wrong_type_or_size_are_refused(rig: Rig) -> None:
    frame = np.zeros((720, 1280, 3), np.uint8)
    for bad, message in (
        (frame[:, :, 0], "colour image"),
        (frame.astype(np.float32), "uint8"),
        (np.zeros((720, 1280, 4), np.uint8), "colour image"),
        (frame[:20], "32..8192"),
        ([[0, 0, 0]], "numpy array"),
    ):
        with pytest.raises(ImageError, match=message):
            rig.detector.detect(bad)  # type: ignore[arg-type]  # non-images on purpose


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ConfigError, match="coloured_fraction"):
        DetectorSettings(coloured_fraction=0.0)
    with pytest.raises(ConfigError, match="target_diameter_m"):
        DetectorSettings(target_diameter_m=float("nan"))


# -- synthetic faces: exact geometry ------------------------------------------------------


def _face(
    centre: tuple[float, float], axes: tuple[float, float], angle: float, arrow: np.ndarray | None
) -> np.ndarray:
    """A 1280×720 frame with yellow/red/blue elliptic rings (outer semi-axes `axes`, px) and a
    green tip at image offset `arrow` (px) from the centre."""
    image = np.full((720, 1280, 3), 70, np.uint8)
    shift = 4  # cv2's sub-pixel drawing: coordinates × 16
    for scale, colour in ((1.0, (30, 90, 225)), (2 / 3, (225, 25, 25)), (1 / 3, (250, 215, 20))):
        size = (round(2 * axes[0] * scale * 16), round(2 * axes[1] * scale * 16))
        c = (round(centre[0] * 16), round(centre[1] * 16))
        cv2.ellipse(
            image, c, (size[0] // 2, size[1] // 2), angle, 0, 360, colour, -1, cv2.LINE_AA, shift
        )
    if arrow is not None:
        tip = (round((centre[0] + arrow[0]) * 16), round((centre[1] + arrow[1]) * 16))
        cv2.circle(image, tip, 9 * 16, (30, 250, 30), -1, cv2.LINE_AA, shift)
    return image


@pytest.fixture(scope="module")
def synthetic() -> Detector:
    frame = _face((640, 360), (150, 150), 0, np.array([40.0, -20.0]))
    blue, green = frame[360, 640 - 130], frame[340, 680]
    rng = np.random.default_rng(0)
    target = np.concatenate([np.tile(frame[360, 640 + d], (30, 1)) for d in (0, 70, 130)]).astype(
        float
    ) + rng.normal(0, 2, (90, 3))
    arrow = np.tile(green, (30, 1)).astype(float) + rng.normal(0, 2, (30, 3))
    assert blue[2] > 200
    model = ColourModel.fit(
        np.clip(target, 0, 255).astype(np.uint8), np.clip(arrow, 0, 255).astype(np.uint8)
    )
    # the coloured rings' outer diameter is 0.30 m
    return Detector(model, DetectorSettings(target_diameter_m=0.5, coloured_fraction=0.6))


@pytest.mark.parametrize(
    ("axes", "angle"), [((150, 150), 0), ((150, 100), 0), ((160, 110), 35), ((90, 140), -20)]
)
def test_pixels_map_to_metres_through_the_imaged_ellipse(
    synthetic: Detector, axes: tuple[float, float], angle: float
) -> None:
    """A face seen obliquely is an ellipse; an offset on it maps back to the face by the
    ellipse's shape (M = D/4 · C^(-1/2))."""
    centre = (612.3, 371.8)
    rotation = np.array(
        [
            [math.cos(math.radians(angle)), -math.sin(math.radians(angle))],
            [math.sin(math.radians(angle)), math.cos(math.radians(angle))],
        ]
    )
    face = np.array([0.07, -0.04])  # m on the face: right, down (image axes before the tilt)
    pixels = rotation @ (face / 0.15 * np.asarray(axes, float))
    found = synthetic.detect(_face(centre, axes, angle, pixels))
    assert found.status == "ok"
    np.testing.assert_allclose(found.target.px, centre, atol=0.6)
    np.testing.assert_allclose(found.arrow.px, np.add(centre, pixels), atol=0.3)
    expected = (face[0], -face[1]) if angle == 0 else None
    if expected is not None:
        np.testing.assert_allclose(found.r_m, expected, atol=0.002)
    # whatever the tilt, the distance on the face is preserved
    assert np.hypot(*found.r_m) == pytest.approx(np.hypot(*face), abs=0.003)


def test_a_target_only_model_never_reports_an_arrow(synthetic: Detector) -> None:
    target_only = Detector(ColourModel(target=synthetic.model.target))
    found = target_only.detect(_face((640, 360), (150, 150), 0, np.array([40.0, -20.0])))
    assert found.status == "no_arrow" and found.arrow is None and found.target is not None
