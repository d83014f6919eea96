"""Faces the detector used to miss (issue 28): a disc cut into pieces by a thick shaft, rings
that break the concentric model, a white face on a dark boss, a face cut by the border seen
through its inner rings."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from archery.services.detector.detect import Detector
from archery.services.detector.pieces import joined_hull
from archery.services.detector.rings import Ellipse, centre_spread, fit_disc
from archery.services.detector.whitebalance import estimate_white
from tests.devset import calibrate, cases, drawn_scenes, judge


def _pieces(mask: np.ndarray) -> tuple[list[np.ndarray], list[float]]:
    outlines, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return list(outlines), [cv2.contourArea(outline) for outline in outlines]


def test_a_disc_cut_by_a_thick_shaft_is_joined_into_its_hull() -> None:
    disc = np.zeros((300, 400), np.uint8)
    cv2.circle(disc, (200, 150), 80, 1, -1)
    cv2.line(disc, (60, 40), (340, 260), 0, 18)  # a shaft 18 px thick across the centre
    outlines, areas = _pieces(disc)
    assert len(outlines) == 2
    largest = fit_disc(disc)  # the larger half alone: a wrong centre
    assert largest is not None and math.dist(largest.centre, (200, 150)) > 8
    hull = joined_hull(outlines, areas, int(np.argmax(areas)))
    assert hull is not None
    filled = np.zeros_like(disc)
    cv2.drawContours(filled, [hull], -1, 1, cv2.FILLED)
    fit = fit_disc(filled)
    assert fit is not None and math.dist(fit.centre, (200, 150)) < 2
    assert fit.radius == pytest.approx(80, abs=3)


def test_pieces_farther_apart_than_the_gap_stay_apart() -> None:
    mask = np.zeros((200, 400), np.uint8)
    cv2.circle(mask, (100, 100), 50, 1, -1)
    cv2.circle(mask, (300, 100), 50, 1, -1)  # 100 px apart: more than 0.3 of 100 px
    outlines, areas = _pieces(mask)
    assert joined_hull(outlines, areas, 0) is None
    assert joined_hull(outlines, areas, 0, gap_fraction=1.1) is not None
    alone, one = _pieces(mask[:, :200].copy())
    assert joined_hull(alone, one, 0) is None  # a single piece: nothing to join


def test_pieces_are_joined_through_each_other() -> None:
    """Wedges of a disc cut by shafts from its centre: each reaches the next."""
    disc = np.zeros((300, 300), np.uint8)
    cv2.circle(disc, (150, 150), 100, 1, -1)
    for angle in (0, 70, 150, 230):
        end = (150 + 140 * math.cos(math.radians(angle)), 150 + 140 * math.sin(math.radians(angle)))
        cv2.line(disc, (150, 150), (round(end[0]), round(end[1])), 0, 9)
    cv2.circle(disc, (150, 150), 30, 0, -1)  # the gold hidden under the arrows
    outlines, areas = _pieces(disc)
    assert len(outlines) == 4
    hull = joined_hull(outlines, areas, int(np.argmax(areas)))
    assert hull is not None and cv2.contourArea(hull) == pytest.approx(math.pi * 100**2, rel=0.05)


def test_concentric_rings_under_perspective_have_no_spread_and_a_stray_one_has() -> None:
    c0, d = np.array([100.0, 50.0]), np.array([3e-3, -1e-3])
    rings = [Ellipse(tuple(c0 + d * r * r), (2 * r, 1.6 * r), 0.0) for r in (20.0, 40.0, 60.0)]
    assert centre_spread(rings) == pytest.approx(0.0, abs=1e-9)
    assert centre_spread(rings[:2]) == 0.0  # two ellipses always fit the model
    stray = [Ellipse((112.0, 40.0), (40.0, 32.0), 0.0), *rings[1:]]
    assert centre_spread(stray) > 0.05


def test_the_white_of_a_face_on_a_dark_boss_is_its_paper() -> None:
    """The boss fills most of the frame: the brighter 40 % of it is boss, not paper."""
    rng = np.random.default_rng(0)
    frame = np.repeat(rng.integers(22, 42, (200, 200, 1)), 3, axis=2).astype(np.uint8)
    frame[:, :, 0] += 4  # dark foam, nearly grey
    cv2.circle(frame, (100, 100), 40, (225, 210, 170), -1)  # warm-lit paper, 13 % of it
    white = estimate_white(frame)
    assert white is not None and white == pytest.approx([225, 210, 170], abs=3)


@pytest.mark.parametrize("kind", ["cut, steep, arrows", "fills the frame", "dark boss, from above"])
def test_issue_28_s_faces_are_found_on_a_drawn_face(kind: str) -> None:
    scene = next(s for s in drawn_scenes() if s.name == "drawn-650")
    detector = Detector(calibrate(scene))
    verdicts = []
    for case in cases(scene, kinds=[kind]):
        found = detector.detect(case.rgb)
        target = found.target
        verdicts.append(
            judge(case, target.px if target else None, target.confidence if target else 0.0)
        )
    assert "wrong" not in verdicts and verdicts.count("right") >= 2, verdicts
