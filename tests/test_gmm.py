"""The colour model: UV conversion, GMM fits sized by BIC, the 256×256 tables, model files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.services.detector.colour_model import (
    MIN_PIXELS,
    MODEL_VERSION,
    ColourModel,
    Gmm,
    fit_gmm,
    rgb_to_uv,
    rgb_to_uv_exact,
)
from archery.services.detector.errors import CalibrationError, ModelFileError

YELLOW, RED, BLUE, GREEN = (250, 215, 20), (225, 25, 25), (30, 90, 225), (30, 250, 30)


def _cluster(rgb: tuple[int, int, int], n: int, rng: np.random.Generator, spread: float = 6.0):
    """`n` pixels around one colour, with sensor-like noise (RGB uint8)."""
    pixels = np.asarray(rgb, float) + spread * rng.standard_normal((n, 3))
    return np.clip(np.round(pixels), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def model() -> ColourModel:
    rng = np.random.default_rng(0)
    target = np.concatenate([_cluster(c, 150, rng) for c in (YELLOW, RED, BLUE)])
    return ColourModel.fit(target, _cluster(GREEN, 80, rng))


@given(st.lists(st.integers(0, 255), min_size=3, max_size=3))
@settings(max_examples=200, deadline=None)
def test_exact_uv_matches_opencv_within_rounding(rgb: list[int]) -> None:
    pixel = np.array([rgb], np.uint8)
    np.testing.assert_allclose(rgb_to_uv_exact(pixel), rgb_to_uv(pixel), atol=1.0)


def test_grey_has_neutral_chroma_and_brightness_does_not_move_uv() -> None:
    greys = np.array([[0, 0, 0], [128, 128, 128], [255, 255, 255]], np.uint8)
    np.testing.assert_allclose(rgb_to_uv(greys), 128.0, atol=1.0)
    dark, bright = np.array([[120, 30, 30]], np.uint8), np.array([[240, 60, 60]], np.uint8)
    # the same hue twice as bright moves U and V only in proportion to the chroma (Y is gone)
    assert np.linalg.norm(rgb_to_uv(dark) - 128) < np.linalg.norm(rgb_to_uv(bright) - 128)


def test_bic_picks_more_components_for_a_multicoloured_target_than_a_single_coloured_tip(
    model: ColourModel,
) -> None:
    assert model.arrow is not None
    assert model.target.n_components >= 3
    assert model.arrow.n_components == 1
    assert model.target.n_components > model.arrow.n_components
    # the chosen K is the BIC minimum of those tried
    assert min(model.target.bic, key=model.target.bic.get) == model.target.n_components
    assert abs(model.target.weights.sum() - 1) < 1e-9


def test_each_colour_goes_to_its_own_model_and_grey_to_neither(model: ColourModel) -> None:
    target, arrow = model.tables()
    assert target.shape == arrow.shape == (256, 256) and target.dtype == np.uint8

    def at(rgb: tuple[int, int, int]) -> tuple[int, int]:
        u, v = (int(c) for c in rgb_to_uv(np.array([rgb], np.uint8))[0])
        return int(target[u, v]), int(arrow[u, v])

    for colour in (YELLOW, RED, BLUE):
        assert at(colour) == (255, 0), colour
    assert at(GREEN) == (0, 255)
    for neutral in ((128, 128, 128), (20, 20, 20), (245, 245, 245), (140, 120, 100)):
        assert at(neutral) == (0, 0), neutral
    # no colour belongs to both
    assert not np.any((target > 0) & (arrow > 0))


@given(st.integers(0, 255), st.integers(0, 255))
@settings(max_examples=100, deadline=None)
def test_tables_equal_the_exact_memberships_at_integer_uv(u: int, v: int) -> None:
    rng = np.random.default_rng(0)
    target = np.concatenate([_cluster(c, 150, rng) for c in (YELLOW, RED, BLUE)])
    model = _cached_model(target, _cluster(GREEN, 80, rng))
    t_table, a_table = model.tables()
    t_exact, a_exact = model.memberships(np.array([[float(u), float(v)]]))
    assert abs(int(t_table[u, v]) - 255 * t_exact[0]) <= 0.5 + 1e-9
    assert abs(int(a_table[u, v]) - 255 * a_exact[0]) <= 0.5 + 1e-9


_MODELS: dict[bytes, ColourModel] = {}


def _cached_model(target: np.ndarray, arrow: np.ndarray) -> ColourModel:
    key = target.tobytes() + arrow.tobytes()
    if key not in _MODELS:
        _MODELS[key] = ColourModel.fit(target, arrow)
    return _MODELS[key]


def test_a_single_colour_gives_one_gaussian_at_the_noise_floor() -> None:
    model = ColourModel.fit(np.tile(np.array(RED, np.uint8), (50, 1)))
    assert model.target.n_components == 1
    cov = model.target.covariances[0]
    np.testing.assert_allclose(cov, np.eye(2) * cov[0, 0], atol=1e-9)
    assert 1.0 <= cov[0, 0] <= 10.0  # (UV levels)²: the regularisation, not a singular matrix
    target, _ = model.tables()
    u, v = (int(c) for c in rgb_to_uv(np.array([RED], np.uint8))[0])
    assert target[u, v] == 255 and target[128, 128] == 0


def test_calibration_sets_that_cannot_make_a_model_are_refused() -> None:
    rng = np.random.default_rng(1)
    with pytest.raises(CalibrationError, match="at least 8"):
        ColourModel.fit(np.zeros((0, 3), np.uint8))
    with pytest.raises(CalibrationError, match=f"{MIN_PIXELS - 1} calibration pixels"):
        ColourModel.fit(_cluster(RED, MIN_PIXELS - 1, rng))
    with pytest.raises(CalibrationError, match="grey, white or black"):
        ColourModel.fit(_cluster((200, 200, 200), 100, rng, spread=3))
    with pytest.raises(CalibrationError, match="arrow: 3 calibration pixels"):
        ColourModel.fit(_cluster(RED, 50, rng), _cluster(GREEN, 3, rng))
    with pytest.raises(CalibrationError, match="look more like the target"):
        ColourModel.fit(_cluster(RED, 100, rng), _cluster(RED, 100, rng))
    with pytest.raises(CalibrationError, match="finite"):
        fit_gmm(np.array([[np.nan, 1.0]] * 20))
    with pytest.raises(CalibrationError, match="max_components"):
        fit_gmm(rgb_to_uv(_cluster(RED, 50, rng)), max_components=0)


def test_model_file_round_trip(model: ColourModel, tmp_path: Path) -> None:
    path = tmp_path / "model.json"
    model.save(path)
    loaded = ColourModel.load(path)
    for a, b in zip(model.tables(), loaded.tables(), strict=True):
        np.testing.assert_array_equal(a, b)
    assert loaded.summary() == model.summary()
    data = json.loads(path.read_text())
    assert data["version"] == MODEL_VERSION and data["format"] == "archery-colour-model"


def test_target_only_model_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    model = ColourModel.fit(_cluster(BLUE, 60, rng))
    model.save(tmp_path / "m.json")
    loaded = ColourModel.load(tmp_path / "m.json")
    assert loaded.arrow is None
    assert not loaded.tables()[1].any()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.update(version=MODEL_VERSION + 1), "version 2 is not supported"),
        (lambda d: d.update(format="something-else"), "not an archery colour model"),
        (lambda d: d.pop("target"), 'no "target"'),
        (lambda d: d["target"].update(covariances=[[[1, 0], [0, -1]]] * 3), "positive-definite"),
        (lambda d: d["target"].update(weights=[0.5, 0.5, 0.5]), "sum to 1"),
        (lambda d: d["target"].pop("means"), "malformed"),
        (lambda d: d.update(density_floor=-1), "density_floor"),
    ],
)
def test_bad_model_files_are_refused_with_a_reason(
    model: ColourModel, tmp_path: Path, change, message: str
) -> None:
    data = model.to_dict()
    data["target"] = {**data["target"]}
    change(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match=message):
        ColourModel.load(path)


def test_unreadable_model_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ModelFileError, match="cannot read"):
        ColourModel.load(tmp_path / "missing.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(ModelFileError, match="cannot read"):
        ColourModel.load(tmp_path / "x.json")


def test_density_is_the_mixture_of_eq_8() -> None:
    gmm = Gmm(
        weights=np.array([0.25, 0.75]),
        means=np.array([[100.0, 150.0], [60.0, 170.0]]),
        covariances=np.array([[[16.0, 4.0], [4.0, 9.0]], [[25.0, 0.0], [0.0, 25.0]]]),
        bic={},
    )
    point = np.array([97.0, 152.0])
    expected = 0.0
    for w, mu, cov in zip(gmm.weights, gmm.means, gmm.covariances, strict=True):
        d = point - mu
        expected += (
            w
            * np.exp(-0.5 * d @ np.linalg.solve(cov, d))
            / (2 * np.pi * np.sqrt(np.linalg.det(cov)))
        )
    assert gmm.density(point) == pytest.approx(expected, rel=1e-12)
    assert gmm.density(np.tile(point, (4, 3, 1))).shape == (4, 3)


def test_a_few_mis_clicked_grey_pixels_do_not_make_grey_a_target_colour() -> None:
    rng = np.random.default_rng(3)
    clicks = np.concatenate(
        [_cluster(c, 60, rng) for c in (YELLOW, RED, BLUE)] + [_cluster((90, 90, 95), 12, rng)]
    )
    model = ColourModel.fit(clicks)
    chroma = np.hypot(*(model.target.means - 128.0).T)
    assert np.all(chroma >= 10.0)
    assert model.target.weights.sum() == pytest.approx(1.0)
    target, _ = model.tables()
    u, v = (int(c) for c in rgb_to_uv(np.array([(90, 90, 95)], np.uint8))[0])
    assert target[u, v] == 0 and target[128, 128] == 0
