"""Tests of archer-prior's fitted physics: the range, drag and side wind that explain its misses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from archery.services.learner.algorithms import (
    ArcherPrior,
    BallisticModel,
    PhysicalModel,
    RestoreError,
    restore_learner,
)
from archery.services.learner.algorithms.model_fit import fit_parameters
from archery.sim.ballistic import BallisticWorld, Scenario
from archery.sim.geometry import INNER_RING_RADIUS
from tests.test_learner_prior import THETA0, _play, _prior


@pytest.mark.parametrize("distance", [1.5, 3.4, 5.0])
def test_hits_on_the_second_rollout_from_1_5_to_5_m_with_drag_and_side_wind(
    distance: float,
) -> None:
    world = BallisticWorld(Scenario(distance=distance, drag=0.05, wind=(0.0, 3.0, 0.0)))
    learner = _prior()
    distances = _play(learner, world, 4)
    assert distances[1] < INNER_RING_RADIUS
    assert np.all(distances[2:] < 0.01)
    assert learner.changes == []


def test_the_fit_finds_the_world_that_explains_the_misses() -> None:
    world = BallisticWorld(Scenario(distance=4.0, drag=0.05, wind=(0.0, 3.0, 0.0)))
    learner = _prior()
    assert learner.params is not None
    assert np.array_equal(learner.params, [2.2, 0.0, 0.0, 300.0])  # the nominal world first
    _play(learner, world, 3)
    # Two numbers per shot: the range is found, the air and the bow as a mix that lands alike.
    assert learner.params is not None
    assert learner.params[0] == pytest.approx(4.0, rel=0.02)
    assert learner.params[1] > 0.02 and learner.params[2] > 2.0  # drag, and wind to the right
    aim = learner.thetas[-1]
    near = aim + 0.005 * np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    fitted = learner.model.impacts_at(near, learner.params)
    assert np.abs(fitted - world.impacts(near).r).max() < 0.005  # it lands where the world does
    c, _ = learner.correction()
    assert np.linalg.norm(c) < 0.005  # the physics explains it: the residual is left ~0


def test_held_parameters_are_not_fitted() -> None:
    learner = _prior(model_drag_std=0.0, model_wind_std=0.0, model_stiffness_std=0.0)
    _play(learner, BallisticWorld(Scenario(distance=3.0)), 3)
    assert learner.params is not None
    assert learner.params[0] == pytest.approx(3.0, abs=0.01)
    assert learner.params[1:].tolist() == [0.0, 0.0, 300.0]


def test_fit_without_data_or_freedom_is_the_prior_mean() -> None:
    model = BallisticModel()
    mean = np.array([2.5, 0.01, 1.0, 320.0])
    assert isinstance(model, PhysicalModel)
    none = fit_parameters(
        model,
        np.empty((0, 3)),
        np.empty((0, 2)),
        np.empty(0),
        noise_std=0.005,
        mean=mean,
        start=mean,
    )
    assert np.array_equal(none, mean)
    fixed = BallisticModel(distance_std=0.0, drag_std=0.0, wind_std=0.0, stiffness_std=0.0)
    theta = THETA0[None]
    held = fit_parameters(
        fixed, theta, np.array([[0.3, 0.3]]), np.ones(1), noise_std=0.005, mean=mean, start=mean
    )
    assert np.array_equal(held, mean)


def test_the_model_at_its_nominal_parameters_is_the_nominal_model() -> None:
    model = BallisticModel(distance=3.0, drag=0.02)
    thetas = np.array([THETA0, THETA0 + np.array([0.01, 0.005, -0.01])])
    assert np.array_equal(model.impacts_at(thetas, model.nominal()), model.impacts(thetas))
    with pytest.raises(ValueError, match="distance"):
        model.impacts_at(thetas, np.array([0.0, 0.0, 0.0, 300.0]))  # a target behind the bow hand


def test_a_restored_learner_keeps_its_fit() -> None:
    world = BallisticWorld(Scenario(distance=3.4, drag=0.05, wind=(0.0, 3.0, 0.0), noise=0.01))
    world.reset(2)
    learner = _prior()
    _play(learner, world, 2)
    restored = restore_learner(json.loads(json.dumps(learner.state_dict())))
    assert isinstance(restored, ArcherPrior)
    assert np.array_equal(restored.params, learner.params)
    for _ in range(3):
        a, b = learner.ask(), restored.ask()
        assert np.array_equal(a, b)
        r = world.step(a).r
        learner.tell(a, r)
        restored.tell(b, r)


def test_a_state_saved_before_the_fit_restores_with_fixed_parameters() -> None:
    world = BallisticWorld(Scenario(distance=3.0))
    learner = _prior()
    _play(learner, world, 1)
    state = learner.state_dict()
    for name in BallisticModel.STD_OPTIONS:
        del state["options"][name]
    del state["extra"]["params"], state["extra"]["params_mean"]
    restored = restore_learner(state)
    assert isinstance(restored, ArcherPrior)
    assert restored.model == BallisticModel(
        distance_std=0.0, drag_std=0.0, wind_std=0.0, stiffness_std=0.0
    )
    _play(restored, world, 2)
    assert np.array_equal(restored.params, [2.2, 0.0, 0.0, 300.0])  # never fitted


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ([2.2, 0.0, 0.0], "4 finite numbers"),
        ([2.2, float("nan"), 0.0, 300.0], "4 finite"),
        ("far", "numbers"),
    ],
)
def test_bad_saved_parameters_are_refused(params: object, message: str) -> None:
    learner = _prior()
    _play(learner, BallisticWorld(), 1)
    state = learner.state_dict()
    state["extra"]["params"] = params
    with pytest.raises(RestoreError, match=message):
        restore_learner(state)
