"""The development set: each scene calibrated once, then every change of light, camera, angle,
arrows and border; the centre within 5 % of the blue ring's diameter wherever the face is
visible, and never a wrong centre with confidence ≥ 0.5. Drawn faces always; the shared
photographs when they are beside the clone."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from archery.services.detector.detect import Detector
from tests.devset import (
    CHANGES,
    Scene,
    calibrate,
    cases,
    drawn_scenes,
    judge,
    photo_scenes,
    white_balance,
)

# known limits, reported as not seen (never wrong): drawn faces of flat colours at exposure ×2.5
# clip to white and cyan until only one calibrated colour (the red ring) is left; on the 110 px
# face (its yellow 22 px across), six arrows seen at 40° in warm light cover most of the yellow
# and red
KNOWN_MISSES = {
    ("drawn-110", "combined", "warm, tilted, arrows, JPEG"),
    ("drawn-350", "exposure", "2.5"),
    ("drawn-650", "exposure", "2.5"),
    ("drawn-1300", "exposure", "2.5"),
}
# a 100 px face in a 2400×1800 frame is found by looking again at a finer scale, but its
# calibration (120 marks on a 60 px disc, ring lines and blends included) is poor: of its 32
# visible cases at most this many are missed (never wrong); the plain frame is always found
MISSES_ALLOWED = {"drawn-100-in-2400": 2}
# issue 28's four harder kinds (cut and steep with arrows, filling a small frame with a shaft
# across the gold, sunlit and angled with many arrows, a dark boss from above): never wrong,
# and of a scene's 12 such cases at most this many missed (reported as not seen). The faces
# 110 and 100 px across are too small for the steepest cut views and for a dark boss in warm
# light; twenty arrows at 50° in sun leave too little of the inner rings of the 100 and 350 px
# faces
HARD_KINDS = {"cut, steep, arrows", "fills the frame", "sunlit, angled, arrows",
              "dark boss, from above"}  # fmt: skip
HARD_MISSES_ALLOWED = {
    "drawn-110": 3,
    "drawn-350": 1,
    "drawn-650": 0,
    "drawn-1300": 0,
    "drawn-100-in-2400": 5,
    "target-1": 0,
    "target-2": 0,
    "target-3": 0,
    "target-4": 0,
}
PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-targets"
DRAWN = {scene.name: scene for scene in drawn_scenes()}
REAL = {scene.name: scene for scene in photo_scenes(PHOTOS)} if PHOTOS.is_dir() else {}


def _run(scene: Scene) -> list[str]:
    """Problems found on every case of one scene (empty: all as required)."""
    detector = Detector(calibrate(scene))
    problems = []
    for case in cases(scene):
        found = detector.detect(case.rgb)
        px = found.target.px if found.target else None
        confidence = found.target.confidence if found.target else 0.0
        verdict = judge(case, px, confidence)
        error = "not seen" if px is None else f"{math.dist(px, case.centre) / case.diameter:.1%}"
        what = f"{case.kind} {case.level}: {error}, confidence {confidence:.2f}"
        if verdict == "wrong":
            problems.append(f"wrong and confident: {what}")
        elif (case.scene, case.kind, case.level) in KNOWN_MISSES:
            if px is not None:
                problems.append(f"a known miss is now seen (update KNOWN_MISSES): {what}")
        elif case.expect == "visible" and verdict != "right":
            problems.append(
                f"{'hard case missed' if case.kind in HARD_KINDS else 'missed'}: {what}"
            )
        elif verdict == "right" and found.rings:
            # the scale too (it maps pixels to metres): the outer ring is the blue one
            size = 2 * found.rings[-1].radius / case.diameter
            if not 0.9 < size < 1.1:
                problems.append(f"outer ring {size:.2f} of the blue ring's size: {what}")
        elif case.expect == "hidden" and px is not None:
            problems.append(f"seen though mostly outside the image: {what}")
    return problems


def _beyond_allowed(name: str, problems: list[str]) -> list[str]:
    """The problems left once a scene's allowed misses are taken out."""
    missed = [p for p in problems if p.startswith("missed: ") and not p.startswith("missed: none")]
    hard = [p for p in problems if p.startswith("hard case missed: ")]
    allowed = missed[: MISSES_ALLOWED.get(name, 0)] + hard[: HARD_MISSES_ALLOWED[name]]
    return [p for p in problems if p not in allowed]


@pytest.mark.parametrize("name", sorted(DRAWN))
def test_drawn_faces_under_every_change(name: str) -> None:
    assert _beyond_allowed(name, _run(DRAWN[name])) == []


@pytest.mark.skipif(not REAL, reason=f"the real target photographs are not at {PHOTOS}")
@pytest.mark.parametrize("name", ["target-1", "target-2", "target-3", "target-4"])
def test_photographs_under_every_change(name: str) -> None:
    assert _beyond_allowed(name, _run(REAL[name])) == []


def test_the_set_covers_the_issue_s_ranges() -> None:
    assert min(CHANGES["exposure"]) <= 0.4 and max(CHANGES["exposure"]) >= 2.5
    assert min(CHANGES["white balance"]) <= 3000 and max(CHANGES["white balance"]) >= 7500
    assert min(CHANGES["jpeg"]) <= 30 and max(CHANGES["jpeg"]) >= 95
    assert max(abs(tilt) for _, tilt in CHANGES["perspective"]) >= 50
    sizes = [scene.diameter / 0.6 for scene in DRAWN.values()]  # the whole face, px
    assert min(sizes) <= 110 and max(sizes) >= 1300
    kinds = {case.expect for case in cases(DRAWN["drawn-350"], kinds=["border"])}
    assert kinds == {"visible", "either", "hidden"}


def test_the_set_is_deterministic() -> None:
    again = {scene.name: scene for scene in drawn_scenes()}
    for name, scene in DRAWN.items():
        assert np.array_equal(scene.rgb, again[name].rgb) and scene.centre == again[name].centre
    first = [c.rgb for c in cases(DRAWN["drawn-110"], seed=3, kinds=["noise", "arrows"])]
    second = [c.rgb for c in cases(DRAWN["drawn-110"], seed=3, kinds=["noise", "arrows"])]
    assert all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))


def test_warm_and_cold_light_tint_white_as_expected() -> None:
    grey = np.full((8, 8, 3), 180, np.uint8)
    warm, cold = white_balance(grey, 3000)[0, 0], white_balance(grey, 7500)[0, 0]
    assert warm[0] > warm[1] > warm[2] and cold[2] > cold[1] and cold[2] > cold[0]


def test_a_scene_without_its_face_reports_no_target() -> None:
    scene = DRAWN["drawn-350"]
    detector = Detector(calibrate(scene))
    x, y = (round(v) for v in scene.centre)
    blank = scene.rgb.copy()
    half = round(0.7 * scene.diameter / 0.6)
    blank[max(0, y - half) : y + half, max(0, x - half) : x + half] = scene.rgb[:2, :2].mean((0, 1))
    assert detector.detect(blank).status == "no_target"


def test_warm_light_is_balanced_against_the_calibration_s_white() -> None:
    scene = DRAWN["drawn-350"]
    detector = Detector(calibrate(scene))
    same = detector.gains(scene.rgb)
    assert same is not None and same == pytest.approx([1, 1, 1], abs=0.03)
    assert detector.detect(scene.rgb).gains is None  # the calibration's own light: as it is
    warm = next(c for c in cases(scene, kinds=["white balance"]) if c.level == "3000")
    gains = detector.gains(warm.rgb)
    assert gains is not None
    red, _, blue = gains
    assert blue > 1.2 > 1.0 > red  # warm light: blue boosted, red cut
    # the paper's own colours give the true gains (its red saturates at 255 in warm light)
    x, y = round(scene.centre[0] + 0.53 * scene.diameter / 0.6), round(scene.centre[1])
    true = scene.rgb[y, x] / warm.rgb[y, x].astype(float)
    assert gains == pytest.approx(true, abs=0.06)
    found = detector.detect(warm.rgb)
    assert found.target is not None and len(found.rings) == 3
    # the white is estimated on the detector's own downscaled copy: the same within 2 %
    assert found.gains is None or found.gains == pytest.approx(tuple(gains), abs=0.02)
    assert math.dist(found.target.px, warm.centre) < 0.05 * warm.diameter
