"""Tests of PoWER's update (Eq. 2-4), its exploration and its decay."""

from __future__ import annotations

import math

import numpy as np
import pytest

from archery.protocol.theta import ThetaBox
from archery.services.learner.algorithms import LearnerConfigError, Power, make_learner
from archery.services.learner.algorithms.power import DEFAULT_RETURN_SCALE
from archery.sim.geometry import INNER_RING_RADIUS

WIDE = ThetaBox(low=(-5.0, -5.0, -5.0), high=(5.0, 5.0, 5.0))


def test_update_is_the_return_weighted_mean_of_the_top_sigma() -> None:
    learner = Power(
        np.zeros(3), rng=np.random.default_rng(0), bounds=WIDE, n_best=3, return_scale=1.0
    )
    told = [
        ([1.0, 0.0, 0.0], [0.3, 0.4]),  # ‖r‖ = 0.5
        ([0.0, 2.0, 0.0], [0.0, 0.1]),  # 0.1  (best)
        ([0.0, 0.0, 3.0], [2.0, 0.0]),  # 2.0  (worst: left out with σ = 3)
        ([1.0, 1.0, 1.0], [0.0, 0.2]),  # 0.2
    ]
    for theta, r in told:
        learner.tell(theta, r)
    weights = {0.1: math.exp(-0.1), 0.2: math.exp(-0.2), 0.5: math.exp(-0.5)}
    expected = (
        weights[0.1] * np.array([0.0, 2.0, 0.0])
        + weights[0.2] * np.array([1.0, 1.0, 1.0])
        + weights[0.5] * np.array([1.0, 0.0, 0.0])
    ) / sum(weights.values())
    assert learner.mean == pytest.approx(expected, abs=1e-15)


def test_with_sigma_one_the_policy_jumps_to_the_best_rollout() -> None:
    learner = Power(np.zeros(3), rng=np.random.default_rng(0), bounds=WIDE, n_best=1)
    learner.tell([1.0, 0.0, 0.0], [0.5, 0.0])
    learner.tell([0.0, 1.0, 0.0], [0.1, 0.0])
    learner.tell([0.0, 0.0, 1.0], [0.7, 0.0])
    assert np.array_equal(learner.mean, [0.0, 1.0, 0.0])


def test_weights_survive_returns_that_underflow() -> None:
    # exp(−1000) is 0 in floating point; the ratio in Eq. 2 is still well defined.
    learner = Power(
        np.zeros(3), rng=np.random.default_rng(0), bounds=WIDE, n_best=2, return_scale=1.0
    )
    learner.tell([1.0, 0.0, 0.0], [1000.0, 0.0])
    learner.tell([0.0, 1.0, 0.0], [1001.0, 0.0])
    e = math.exp(-1.0)
    assert learner.mean == pytest.approx([1 / (1 + e), e / (1 + e), 0.0], abs=1e-12)


def test_exploration_is_gaussian_around_the_mean_and_decays() -> None:
    learner = Power(
        np.zeros(3), rng=np.random.default_rng(7), bounds=WIDE, explore_std=0.1, decay=0.9
    )
    reference = np.random.default_rng(7)
    first = learner.ask()
    assert first == pytest.approx(0.1 * reference.standard_normal(3), abs=1e-15)
    learner.tell(first, [0.2, 0.0])
    assert learner.variance == pytest.approx(np.full(3, 0.9 * 0.01))
    second = learner.ask()
    expected = learner.mean + math.sqrt(0.9 * 0.01) * reference.standard_normal(3)
    assert second == pytest.approx(expected, abs=1e-15)


def test_per_component_exploration() -> None:
    learner = Power(
        np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(1), explore_std=(0.0, 0.01, 0.02)
    )
    samples = []
    for _ in range(400):
        samples.append(learner.ask())
        learner.tell(samples[-1], [1.0, 1.0])  # all equal: the mean barely moves
    spread = np.array(samples).std(axis=0)
    assert spread[0] < 1e-12 and spread[2] > spread[1] > 0.0


def test_return_scale_sharpens_the_weights() -> None:
    plain = Power(np.zeros(3), rng=np.random.default_rng(0), bounds=WIDE, n_best=2, return_scale=1)
    sharp = Power(
        np.zeros(3), rng=np.random.default_rng(0), bounds=WIDE, n_best=2, return_scale=0.01
    )
    for learner in (plain, sharp):
        learner.tell([1.0, 0.0, 0.0], [0.1, 0.0])
        learner.tell([0.0, 1.0, 0.0], [0.2, 0.0])
    e = math.exp(-0.1)
    assert plain.mean == pytest.approx([1 / (1 + e), e / (1 + e), 0.0])
    e10 = math.exp(-10.0)  # r in centimetres: weights 1 and exp(−10)
    assert sharp.mean == pytest.approx([1 / (1 + e10), e10 / (1 + e10), 0.0], abs=1e-15)


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"n_best": 0}, "n_best"),
        ({"explore_std": float("inf")}, "explore_std"),
        ({"decay": 1.5}, "decay"),
        ({"decay": 0.0}, "decay"),
        ({"return_scale": 0.0}, "return_scale"),
    ],
)
def test_bad_options_are_named(options: dict, named: str) -> None:
    with pytest.raises(LearnerConfigError, match=named):
        Power(np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(0), **options)


def test_default_scale_is_the_5_cm_ring_and_power_metre_reads_r_in_metres() -> None:
    default = make_learner("power", np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(0))
    metre = make_learner("power-metre", np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(0))
    assert default.return_scale == DEFAULT_RETURN_SCALE == INNER_RING_RADIUS
    assert metre.return_scale == 1.0
    for learner in (default, metre):
        learner.tell([0.20, 0.0, 0.0], [0.05, 0.0])  # on the ring: weight e^−1 at 5 cm
        learner.tell([0.22, 0.0, 0.0], [0.0, 0.0])
    assert default.mean[0] == pytest.approx((0.22 + 0.20 * math.exp(-1)) / (1 + math.exp(-1)))
    e = math.exp(-0.05)
    assert metre.mean[0] == pytest.approx((0.22 + 0.20 * e) / (1 + e))
    # The scale is PoWER's alone: the return every learner is told stays exp(−‖r‖ in m), Eq. 1.
    assert default.returns[0] == metre.returns[0] == pytest.approx(math.exp(-0.05))
