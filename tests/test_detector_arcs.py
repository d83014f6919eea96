"""Faces the detector used to miss in sun (issue 28): an inner ring cut up by arrows, fitted from
the arcs of its edge; a region opened by a shaft's shadow; a lone ring of the wrong size; a
face washed out in places by a sheen."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from archery.services.detector.arcs import ring_from_arcs
from archery.services.detector.detect import Detector
from archery.services.detector.rings import Ellipse, fit_disc
from archery.services.detector.target import find_face
from tests.devset import Case, Scene, _encode, _linear, calibrate, drawn_scenes, judge

OUTER = Ellipse((200.0, 150.0), (180.0, 120.0), 20.0)
KERNEL = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))


def _mask(ellipse: Ellipse, shape: tuple[int, int] = (300, 400)) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    cv2.ellipse(mask, ellipse.cv_box(), 1, thickness=cv2.FILLED)
    return mask


def _shafts(mask: np.ndarray, centre: tuple[float, float], angles: list[float]) -> None:
    """Arrow shafts and their shadows from near the centre outwards, 7 px thick (in place)."""
    for angle in angles:
        end = (centre[0] + 150 * math.cos(math.radians(angle)),
               centre[1] + 150 * math.sin(math.radians(angle)))  # fmt: skip
        cv2.line(mask, (round(centre[0]), round(centre[1])), (round(end[0]), round(end[1])), 0, 7)


def test_a_ring_cut_up_by_arrows_is_fitted_from_its_arcs() -> None:
    inner = Ellipse((201.5, 149.0), (120.0, 80.0), 20.0)  # 2/3 of the outer, shifted
    face = _mask(OUTER)
    disc = _mask(inner)
    cv2.ellipse(disc, ((200.0, 150.0), (70.0, 45.0), 20.0), 0, thickness=cv2.FILLED)  # gold hidden
    _shafts(disc, inner.centre, [10, 55, 100, 150, 200, 250, 300, 340])
    rest = face & ~_mask(inner)
    _shafts(rest, inner.centre, [10, 55, 100, 150, 200, 250, 300, 340])
    cv2.circle(rest, (168, 203), 5, 0, -1)  # a fletching in the ring's colour on the next ring
    cv2.circle(disc, (168, 203), 5, 1, -1)
    largest = fit_disc(disc)  # no piece, nor the largest's hull, is the ring
    assert largest is None or math.dist(largest.centre, inner.centre) > 3
    ring = ring_from_arcs(OUTER, disc, rest, KERNEL)
    assert ring is not None and math.dist(ring.centre, inner.centre) < 0.8
    assert ring.radius == pytest.approx(inner.radius, abs=1.0)
    assert ring.angle == OUTER.angle and ring.ratio == pytest.approx(OUTER.ratio)
    assert 0.6 < ring.support < 1.0  # the shafts leave gaps


def test_colours_that_never_meet_give_no_ring() -> None:
    disc = _mask(Ellipse((200.0, 150.0), (60.0, 40.0), 20.0))
    rest = _mask(OUTER) & ~_mask(Ellipse((200.0, 150.0), (120.0, 80.0), 20.0))  # 30 px apart
    assert ring_from_arcs(OUTER, disc, rest, KERNEL) is None
    assert ring_from_arcs(OUTER, np.zeros_like(disc), rest, KERNEL) is None


def _ring_map(gap: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Membership and components of a face whose gold is hidden (no target colour), its red
    and blue rings crossed by a shadow from the gold to the edge when `gap`."""
    member = np.zeros((240, 320), np.uint8)
    components = np.zeros((240, 320), np.uint8)
    centre, radius = (160, 120), 60
    for k, fraction in ((2, 1.0), (1, 2 / 3)):
        cv2.circle(components, centre, round(radius * fraction), k, -1)
    cv2.circle(member, centre, radius, 255, -1)
    cv2.circle(member, centre, radius // 3, 0, -1)
    if gap:
        cv2.line(member, centre, (160 + 90, 120 - 30), 0, 4)
    return member, components, np.array([0, 1, 2])


def test_a_region_opened_by_a_shadow_is_still_elliptic() -> None:
    closed = find_face(*_ring_map(gap=False))
    opened = find_face(*_ring_map(gap=True))
    assert closed is not None and opened is not None
    assert opened.factors["elliptic"] == pytest.approx(closed.factors["elliptic"], abs=0.05)
    assert opened.factors["elliptic"] > 0.9


def test_a_lone_ring_of_the_wrong_size_is_not_trusted() -> None:
    member = np.zeros((240, 320), np.uint8)
    components = np.zeros((240, 320), np.uint8)
    groups = np.array([0, 1, 2])
    cv2.circle(member, (160, 120), 60, 255, -1)
    cv2.circle(components, (160, 120), 60, 2, -1)
    for red, trusted in ((40, True), (48, False)):  # 2/3 of the outer ring, then 4/5
        cv2.circle(components, (160, 120), red, 1, -1)
        cv2.circle(components, (160, 120), 6, 0, -1)  # a speck of gold: no ring of its own
        fit = find_face(member, components, groups)
        assert fit is not None and len(fit.ellipses) == 2
        assert (fit.factors["rings"] > 0.5) is trusted


def _washed(scene: Scene, strength: float) -> Case:
    """The scene with a sheen over one side of the face, washing its colours towards white."""
    height, width = scene.rgb.shape[:2]
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    radius = scene.diameter / 2
    spot = np.exp(-((x - scene.centre[0] - radius) ** 2 + (y - scene.centre[1]) ** 2) / radius**2)
    linear = _linear(scene.rgb)
    image = _encode(linear + strength * spot[:, :, None] * (1.0 - linear))
    return Case(scene.name, "sheen", f"{strength}", image, scene.centre, scene.diameter, "visible")


def test_a_face_washed_out_on_one_side_is_found() -> None:
    scene = next(s for s in drawn_scenes() if s.name == "drawn-350")
    detector = Detector(calibrate(scene))
    case = _washed(scene, 0.4)  # none of the chroma scales alone finds it
    found = detector.detect(case.rgb)
    target = found.target
    assert target is not None and judge(case, target.px, target.confidence) == "right"
    assert len(found.rings) == 3
