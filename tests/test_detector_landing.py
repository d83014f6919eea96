"""The landing from the camera alone (`services.detector.landing`, `landing_wait`) on real
frames: rendered frames of the scene with an older arrow already in the face and a new one, and
a real target photograph with arrow tips pasted on: camera noise is no change, a moving
picture is not still, the newest arrow is measured and never the older one, and the wait ends
on the first frame that has been still long enough, or says why it saw no landing."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import mujoco
import numpy as np
import pytest

from archery.protocol.errors import ConfigError, RpcError
from archery.protocol.messages import Image
from archery.protocol.verbs.detector import LANDING_STILL_S
from archery.services.detector.calibration import load_pixels, sample_pixels
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import Detector, DetectorSettings
from archery.services.detector.errors import ImageError, NoLanding
from archery.services.detector.landing import (
    LandingThresholds,
    compare,
    grey_frame,
    moved_fraction,
    search_region,
)
from archery.services.detector.landing_wait import wait_for_landing
from archery.sim.arrow import arrow_quat
from archery.sim.model_build import build_scene
from archery.sim.render import SceneRenderer, calibration_frame
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import TARGET_CENTRE_SITE, SceneConfig

SCENE = SceneConfig(meshes=False)
THRESHOLDS = LandingThresholds()
MIN_ARROW = DetectorSettings().min_arrow_pixels
OLD_R, NEW_R = (-0.10, 0.05), (0.08, -0.06)  # m on the face: right, up
PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-targets"
GREEN = (30, 250, 30)  # RGB of the pasted tips


def _noisy(rgb: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """`rgb` with Gaussian noise of `sigma` grey levels per pixel and channel (a camera's)."""
    noise = np.random.default_rng(seed).normal(0.0, sigma, rgb.shape)
    return np.clip(rgb + noise, 0, 255).astype(np.uint8)


@dataclass
class Rendered:
    """Frames of the scene: `empty` (no arrow in view), one arrow at `OLD_R` (`old`), the
    new arrow at `NEW_R` beside it (`both`, the two renders joined where the new arrow is),
    the new arrow 3 cm on (`moved`), and the colour model calibrated on the scene."""

    empty: np.ndarray
    old: np.ndarray
    both: np.ndarray
    moved: np.ndarray
    new_px: tuple[float, float]  # the new arrow's tip in `both`, as its render shows it
    old_px: tuple[float, float]
    detector: Detector


def _tip_px(render: np.ndarray, empty: np.ndarray) -> tuple[float, float]:
    """The centre (px) of the green tip a render adds to the empty scene."""
    added = np.any(render != empty, axis=2) & (render[:, :, 1] > 150) & (render[:, :, 0] < 120)
    rows, cols = np.nonzero(added)
    return float(cols.mean()), float(rows.mean())


def render_scenes() -> Rendered:
    """The frames of `Rendered`, rendered, and the colour model calibrated on the scene's
    calibration frame and marks."""
    model = build_scene(SCENE)
    with SceneRenderer(SCENE) as renderer:
        qpos = model.qpos0.copy()
        calibration, marks = calibration_frame(renderer, qpos)
        colours = ColourModel.fit(
            sample_pixels(calibration, marks["target"], "target"),
            sample_pixels(calibration, marks["arrow"], "arrow"),
        )
        physics = ScenePhysics(renderer.model, renderer.data)

        def arrow_at(right: float, up: float) -> np.ndarray:
            renderer.data.qpos[:] = qpos
            mujoco.mj_fwdPosition(renderer.model, renderer.data)
            centre = physics.site_position(TARGET_CENTRE_SITE)
            tip = centre + right * np.array([0.0, 1.0, 0.0]) + up * np.array([0.0, 0.0, 1.0])
            physics.set_arrow_pose(tip, arrow_quat(np.array([-1.0, 0.0, -0.05])))
            return renderer.render(renderer.data.qpos.copy())

        empty = renderer.render(qpos)
        old, new = arrow_at(*OLD_R), arrow_at(*NEW_R)
        moved = arrow_at(NEW_R[0] + 0.03, NEW_R[1])
        both = np.where(np.any(new != empty, axis=2)[:, :, None], new, old)
        moved_both = np.where(np.any(moved != empty, axis=2)[:, :, None], moved, old)
        return Rendered(
            empty,
            old,
            both,
            moved_both,
            _tip_px(new, empty),
            _tip_px(old, empty),
            Detector(colours),
        )


@pytest.fixture(scope="module")
def rendered() -> Rendered:
    return render_scenes()


def _paste_arrow(rgb: np.ndarray, tip: tuple[int, int]) -> np.ndarray:
    """`rgb` with an arrow stuck at `tip` (px): a dark shaft up and to the left, a green tip."""
    out = rgb.copy()
    cv2.line(out, tip, (tip[0] - 70, tip[1] - 45), (40, 40, 45), 5, cv2.LINE_AA)
    cv2.circle(out, tip, 9, GREEN, -1, cv2.LINE_AA)
    return out


def test_camera_noise_is_neither_a_new_object_nor_motion(rendered: Rendered) -> None:
    for scene in (rendered.empty, rendered.both):
        before = grey_frame(_noisy(scene, 8.0, 1), THRESHOLDS)
        for seed in (2, 3):
            frame = grey_frame(_noisy(scene, 8.0, seed), THRESHOLDS)
            change = compare(before, frame, THRESHOLDS, MIN_ARROW)
            assert not change.new_object and change.largest < change.needed, change.largest
            assert moved_fraction(before, frame, THRESHOLDS) < THRESHOLDS.still_fraction


def test_a_new_arrow_is_a_new_object_and_its_region_holds_it_not_the_older_one(
    rendered: Rendered,
) -> None:
    before = grey_frame(_noisy(rendered.old, 5.0, 1), THRESHOLDS)
    after = grey_frame(_noisy(rendered.both, 5.0, 2), THRESHOLDS)
    change = compare(before, after, THRESHOLDS, MIN_ARROW)
    assert change.new_object and change.largest > 4 * change.needed
    region = search_region(change, after, THRESHOLDS)
    assert region.shape == rendered.both.shape[:2] and region.dtype == bool
    new_x, new_y = (round(v) for v in rendered.new_px)
    old_x, old_y = (round(v) for v in rendered.old_px)
    assert (
        region[new_y, new_x] and not region[old_y - 20 : old_y + 21, old_x - 20 : old_x + 21].any()
    )


@pytest.mark.parametrize("older_first", [True, False])
def test_the_newest_arrow_is_measured_not_the_older_one(
    rendered: Rendered, older_first: bool
) -> None:
    """Either arrow the newest: the one measured is the one that appeared since the baseline,
    at its true place within a centimetre."""
    if older_first:
        before, after, truth = rendered.old, rendered.both, NEW_R
    else:  # the same two arrows, the other one the newer: the baseline shows only NEW_R's
        only_new = np.where(
            np.any(rendered.old != rendered.empty, axis=2)[:, :, None],
            rendered.empty,
            rendered.both,
        )
        before, after, truth = only_new, rendered.both, OLD_R
    baseline = grey_frame(_noisy(before, 5.0, 1), THRESHOLDS)
    frame = _noisy(after, 5.0, 2)
    change = compare(baseline, grey_frame(frame, THRESHOLDS), THRESHOLDS, MIN_ARROW)
    region = search_region(change, grey_frame(frame, THRESHOLDS), THRESHOLDS)
    found = rendered.detector.detect(frame, region)
    assert found.status == "ok" and found.r_m is not None
    assert math.dist(found.r_m, truth) < 0.01, (found.r_m, truth)
    # the whole frame holds both: the older arrow is evidence the region leaves out
    everywhere = rendered.detector.detect(frame)
    assert everywhere.arrow is not None and found.arrow is not None
    assert everywhere.arrow.confidence < found.arrow.confidence


def test_a_region_of_another_size_is_refused(rendered: Rendered) -> None:
    with pytest.raises(ImageError, match="search region"):
        rendered.detector.detect(rendered.both, np.ones((10, 10), bool))


def test_a_moving_picture_is_not_still(rendered: Rendered) -> None:
    """An arrow that moves 3 cm between two frames, or appears, is motion; noise is not."""
    landed = grey_frame(_noisy(rendered.both, 5.0, 1), THRESHOLDS)
    for other in (rendered.moved, rendered.old):
        frame = grey_frame(_noisy(other, 5.0, 2), THRESHOLDS)
        assert moved_fraction(landed, frame, THRESHOLDS) >= THRESHOLDS.still_fraction


def test_frames_of_another_size_are_refused_naming_both(rendered: Rendered) -> None:
    small = np.ascontiguousarray(cv2.resize(rendered.both, (640, 360)))
    with pytest.raises(ImageError, match=r"1280x720 px before, 640x360 px now"):
        compare(grey_frame(rendered.old, THRESHOLDS), grey_frame(small, THRESHOLDS), THRESHOLDS, 6)


def test_thresholds_outside_their_range_are_refused() -> None:
    with pytest.raises(ConfigError, match="grey_levels"):
        LandingThresholds(grey_levels=0)
    with pytest.raises(ConfigError, match="still_fraction"):
        LandingThresholds(still_fraction=float("nan"))


@pytest.mark.skipif(
    not (PHOTOS / "target-2.json").is_file(),
    reason=f"the real target photographs are not at {PHOTOS} (clone the repo beside shared/)",
)
def test_the_newest_arrow_on_a_real_photograph() -> None:
    """A real face with its arrow holes and ring lines: an older arrow in the red, the new one
    in the blue; camera noise on every frame."""
    bgr = cv2.imread(str(PHOTOS / "target-2.jpg"), cv2.IMREAD_COLOR)
    assert bgr is not None
    photo = bgr[:, :, ::-1]
    old_tip, new_tip = (545, 631), (375, 761)
    before = _paste_arrow(np.ascontiguousarray(photo), old_tip)
    after = _paste_arrow(before, new_tip)
    target = sample_pixels(photo, load_pixels(PHOTOS / "target-2.json")["target"], "target")
    tip = [[new_tip[0] + dx, new_tip[1] + dy] for dx, dy in itertools.product((-3, 0, 3), repeat=2)]
    detector = Detector(ColourModel.fit(target, sample_pixels(after, tip, "arrow")))
    baseline = grey_frame(_noisy(before, 6.0, 1), THRESHOLDS)
    frame = _noisy(after, 6.0, 2)
    # the noise of a still camera is neither
    assert not compare(
        baseline, grey_frame(_noisy(before, 6.0, 3), THRESHOLDS), THRESHOLDS, 6
    ).new_object
    grey = grey_frame(frame, THRESHOLDS)
    change = compare(baseline, grey, THRESHOLDS, MIN_ARROW)
    assert change.new_object
    found = detector.detect(frame, search_region(change, grey, THRESHOLDS))
    assert found.status == "ok" and found.arrow is not None
    assert math.dist(found.arrow.px, new_tip) < 1.5, found.arrow.px


# -- the wait: frames one after another, stamps from the frames ------------------------------


class Camera:
    """A camera that serves `frames` (RGB, capture stamp wall s) one per grab, each the first
    captured at or after the grab's `after_stamp`; the last is served again and again, each
    time `period` s later. It records the grabs' `after_stamp`s."""

    def __init__(self, frames: list[tuple[np.ndarray, float]], period: float = 0.1) -> None:
        self.frames = frames
        self.period = period
        self.asked: list[float | None] = []
        self.served = 0

    def grab(
        self, after_sim_time: float | None, after_stamp: float | None, timeout: float
    ) -> Image:
        self.asked.append(after_stamp)
        index = next(
            (i for i, (_, s) in enumerate(self.frames) if after_stamp is None or s >= after_stamp),
            None,
        )
        if index is None:  # past the list: the last picture, captured again
            assert after_stamp is not None
            pixels, last = self.frames[-1]
            stamp = last + self.period * math.ceil((after_stamp - last) / self.period + 1e-9)
        else:
            pixels, stamp = self.frames[index]
        self.served += 1
        return Image.from_numpy(pixels, stamp=stamp, frame=self.served)


def _wait(
    camera: Camera, baseline: np.ndarray, timeout: float = 5.0, still_s: float = LANDING_STILL_S
):
    return wait_for_landing(
        camera.grab,
        grey_frame(baseline, THRESHOLDS),
        name="baseline 1",
        after_sim_time=None,
        after_stamp=None,
        timeout=timeout,
        still_s=still_s,
        thresholds=THRESHOLDS,
        min_arrow_pixels=MIN_ARROW,
        interval=0.0,
    )


def test_the_wait_ends_on_the_first_frame_still_for_the_window(rendered: Rendered) -> None:
    """Nothing new until 0.3 s, the arrow 3 cm off at 0.3 s, in its place from 0.4 s: the
    landing is the frame of 0.9 s, the first after 0.5 s of still pairs."""
    old, both, moved = rendered.old, rendered.both, rendered.moved
    pictures = [old, old, old, moved, both] + [both] * 8
    frames = [(_noisy(p, 5.0, i), round(0.1 * i, 3)) for i, p in enumerate(pictures)]
    camera = Camera(frames)
    landed = _wait(camera, _noisy(old, 5.0, 99))
    assert landed.image.stamp == pytest.approx(0.4 + LANDING_STILL_S)
    assert landed.frames == 10 and landed.change.new_object
    # each frame asked for after the previous one
    assert camera.asked[0] is None
    assert all(b is not None and b > 0.1 * i for i, b in enumerate(camera.asked[1:]))
    found = rendered.detector.detect(landed.rgb, landed.region)
    assert found.r_m is not None and math.dist(found.r_m, NEW_R) < 0.01


def test_no_new_object_ends_in_no_landing_saying_what_was_seen(rendered: Rendered) -> None:
    camera = Camera([(_noisy(rendered.old, 5.0, 1), 0.0)])
    with pytest.raises(NoLanding, match=r"frames compared with baseline 1.*largest change") as no:
        _wait(camera, rendered.old, timeout=0.3)
    assert no.value.code == "no_landing" and "picture was still" in no.value.message
    assert camera.served > 2


def test_a_picture_that_never_rests_ends_in_no_landing_saying_it_moved(rendered: Rendered) -> None:
    frames = [(p, 0.1 * i) for i, p in enumerate([rendered.both, rendered.moved] * 200)]
    with pytest.raises(NoLanding, match=r"picture was moving .*of the 0.5 s needed"):
        _wait(Camera(frames), rendered.old, timeout=0.3)


def test_a_camera_that_sends_nothing_ends_in_no_landing_with_its_reason(rendered: Rendered) -> None:
    def silent(after_sim_time: float | None, after_stamp: float | None, timeout: float) -> Image:
        raise RpcError("grab: no frame with capture ≥ 5 within 0.2 s", code="timeout")

    with pytest.raises(NoLanding, match=r"camera sent no frame.*no frame with capture"):
        wait_for_landing(
            silent,
            grey_frame(rendered.old, THRESHOLDS),
            name="baseline 1",
            after_sim_time=None,
            after_stamp=None,
            timeout=0.2,
            still_s=0.5,
            thresholds=THRESHOLDS,
            min_arrow_pixels=MIN_ARROW,
        )


def test_a_busy_camera_is_asked_again(rendered: Rendered) -> None:
    frames = [(rendered.both, 0.1 * i) for i in range(12)]
    camera = Camera(frames)
    refusals = iter(range(2))

    def busy_twice(
        after_sim_time: float | None, after_stamp: float | None, timeout: float
    ) -> Image:
        if next(refusals, None) is not None:
            raise RpcError("grab: past the rate", code="busy")
        return camera.grab(after_sim_time, after_stamp, timeout)

    landed = wait_for_landing(
        busy_twice,
        grey_frame(rendered.old, THRESHOLDS),
        name="baseline 1",
        after_sim_time=None,
        after_stamp=None,
        timeout=5.0,
        still_s=0.2,
        thresholds=THRESHOLDS,
        min_arrow_pixels=MIN_ARROW,
        interval=0.0,
    )
    assert landed.image.stamp == pytest.approx(0.2) and landed.frames == 3
