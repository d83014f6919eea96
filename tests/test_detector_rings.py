"""Ring geometry and white balance: robust ellipse fits (notches, bulges, the image border),
the centre extrapolated from nested ellipses, the frame's white and the model's record of it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from archery.services.detector.colour_model import ColourModel
from archery.services.detector.errors import ModelFileError
from archery.services.detector.rings import Ellipse, fit_disc, nested_centre, radial_position
from archery.services.detector.whitebalance import apply_gains, estimate_white, white_gains


def _disc(
    shape: tuple[int, int], centre: tuple[float, float], axes: tuple[float, float], angle: float
) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    cv2.ellipse(mask, (centre, axes, angle), 1, thickness=cv2.FILLED)
    return mask


def test_a_clean_ellipse_is_fitted_to_a_fraction_of_a_pixel() -> None:
    fit = fit_disc(_disc((300, 400), (201.3, 148.6), (180, 120), 30))
    assert fit is not None and fit.support == 1.0
    assert math.dist(fit.centre, (201.3, 148.6)) < 0.5
    assert sorted(fit.axes) == pytest.approx([120, 180], abs=1.5)


def test_notches_and_a_bulge_do_not_move_the_centre() -> None:
    disc = _disc((300, 400), (200, 150), (160, 160), 0)
    cv2.line(disc, (200, 150), (300, 60), 0, 9)  # a shaft cut through the rim
    cv2.rectangle(disc, (120, 140), (135, 165), 0, -1)  # a bite out of the edge
    cv2.circle(disc, (200, 235), 14, 1, -1)  # a fletching bulging out
    fit = fit_disc(disc)
    assert fit is not None and math.dist(fit.centre, (200, 150)) < 1.5
    assert fit.radius == pytest.approx(80, abs=2)


def test_a_face_cut_by_the_border_has_partial_support() -> None:
    disc = _disc((300, 400), (40, 150), (200, 200), 0)  # 60 px of 100 beyond the left edge
    fit = fit_disc(disc)
    assert fit is not None and 0.4 < fit.support < 0.8
    assert math.dist(fit.centre, (40, 150)) < 3


def test_nothing_to_fit_gives_none() -> None:
    assert fit_disc(np.zeros((50, 50), np.uint8)) is None
    tiny = np.zeros((50, 50), np.uint8)
    tiny[20:22, 20:22] = 1
    assert fit_disc(tiny) is None


def test_radial_position_is_one_on_the_ellipse() -> None:
    ring = Ellipse((10.0, 20.0), (40.0, 20.0), 90.0)
    points = np.array([[10.0, 40.0], [20.0, 20.0], [10.0, 20.0]])
    assert radial_position(ring, points) == pytest.approx([1.0, 1.0, 0.0])


def test_the_centre_is_extrapolated_to_radius_zero() -> None:
    """Perspective shifts each ring's centre by d·r²: three rings give back c₀."""
    c0, d = np.array([100.0, 50.0]), np.array([3e-3, -1e-3])
    rings = [Ellipse(tuple(c0 + d * r * r), (2 * r, 1.6 * r), 0.0) for r in (20.0, 40.0, 60.0)]
    assert nested_centre(rings) == pytest.approx(tuple(c0), abs=1e-6)
    assert nested_centre(rings[:2]) == rings[0].centre  # two: the inner one's
    outlier = [*rings[:2], Ellipse((400.0, 50.0), (120, 96), 0.0)]
    assert math.dist(nested_centre(outlier), rings[0].centre) < 1e-9  # not beyond the inner ring


def test_the_white_of_a_tinted_frame_and_the_gains_that_undo_it() -> None:
    rng = np.random.default_rng(0)
    frame = np.concatenate(
        [
            np.full((40, 100, 3), (200, 170, 120), np.uint8),
            rng.integers(0, 90, (60, 100, 3), dtype=np.uint8),
        ]
    )
    white = estimate_white(frame)
    assert white is not None and white == pytest.approx([200, 170, 120], abs=2)
    gains = white_gains(np.array([180.0, 180.0, 180.0]), white)
    assert gains is not None
    assert apply_gains(frame, gains)[0, 0] == pytest.approx([180, 180, 180], abs=1)
    assert white_gains(None, white) is None and white_gains(white, None) is None


def test_a_frame_of_pure_colours_has_no_white() -> None:
    frame = np.zeros((60, 60, 3), np.uint8)
    frame[:, :30] = (250, 20, 20)
    frame[:, 30:] = (20, 20, 250)
    assert estimate_white(frame) is None


def test_the_model_file_keeps_the_white_and_refuses_a_bad_one(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    pixels = np.clip(rng.normal((250, 210, 30), 4, (60, 3)), 0, 255).astype(np.uint8)
    model = ColourModel.fit(pixels, white_rgb=np.array([230.0, 210.0, 190.0]))
    path = tmp_path / "m.json"
    model.save(path)
    assert ColourModel.load(path).white_rgb == (230.0, 210.0, 190.0)
    data = json.loads(path.read_text())
    data["white_rgb"] = [230, 0, 190]
    path.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match="white_rgb must be three numbers"):
        ColourModel.load(path)
    data["white_rgb"] = None  # a model from before white balance: read, no balance
    path.write_text(json.dumps(data))
    assert ColourModel.load(path).white_rgb is None


def test_two_rings_farther_apart_than_perspective_allows_meet_halfway() -> None:
    inner = Ellipse((100.0, 50.0), (20.0, 16.0), 0.0)
    outer = Ellipse((103.0, 50.0), (30.0, 24.0), 0.0)  # 3 px apart, radius 13.4 px
    assert nested_centre([inner, outer]) == inner.centre  # no image size: the inner one's
    near = outer.radius**2 / 640  # the most a 640 px image's perspective shifts it: 0.28 px
    centre = nested_centre([inner, outer], 640)
    assert centre[1] == 50.0 and centre[0] == pytest.approx(100.0 + 0.5 * (3.0 - near))
    # a face filling a quarter of the image: 3 px is what perspective does, the inner one's
    large = [
        Ellipse((100.0, 50.0), (160.0, 128.0), 0.0),
        Ellipse((103.0, 50.0), (240.0, 192.0), 0.0),
    ]
    assert nested_centre(large, 640) == (100.0, 50.0)
