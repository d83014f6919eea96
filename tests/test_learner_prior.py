"""Tests of archer-prior: the ballistic model's aim, corrected by a Bayesian residual."""

from __future__ import annotations

import json

import numpy as np
import pytest

from archery.protocol.theta import ThetaBox
from archery.services.learner.algorithms import (
    ArcherPrior,
    BallisticModel,
    LearnerConfigError,
    RestoreError,
    make_learner,
    restore_learner,
)
from archery.sim.ballistic import BallisticWorld, Scenario
from archery.sim.geometry import INNER_RING_RADIUS, START_THETA

THETA0 = np.array(START_THETA)

# Worlds whose physics differ from the learner's nominal model (2.2 m, 300 N/m, no drag).
MISMATCHED = {
    "drag 0.1/m + wind 0,6,0 m/s": Scenario(drag=0.1, wind=(0.0, 6.0, 0.0)),
    "drag 0.05/m + wind 1,3,0 m/s": Scenario(drag=0.05, wind=(1.0, 3.0, 0.0)),
    "target at 3 m": Scenario(distance=3.0),
    "stiffer bow 420 N/m": Scenario(bow_stiffness=420.0),
    "softer bow 220 N/m": Scenario(bow_stiffness=220.0),
}
# The model's physical parameters (range, drag, side wind) held at the nominal ones.
FIXED_PHYSICS = {
    "model_distance_std": 0.0,
    "model_drag_std": 0.0,
    "model_wind_std": 0.0,
    "model_stiffness_std": 0.0,
}


def _prior(seed: int = 0, **options: object) -> ArcherPrior:
    learner = make_learner("archer-prior", THETA0, rng=np.random.default_rng(seed), **options)
    assert isinstance(learner, ArcherPrior)
    return learner


def _play(learner: ArcherPrior, world: BallisticWorld, rollouts: int) -> np.ndarray:
    """Distances (m) of `rollouts` true impacts to the centre."""
    distances = []
    for _ in range(rollouts):
        theta = learner.ask()
        shot = world.step(theta)
        learner.tell(theta, shot.r)
        distances.append(float(np.linalg.norm(shot.r_true)))
    return np.array(distances)


def test_the_first_proposal_is_the_models_aim() -> None:
    learner = _prior()
    theta = learner.ask()
    assert not np.allclose(theta, THETA0)  # θ0 itself misses the centre by ~36 cm
    assert np.linalg.norm(BallisticWorld().impacts(theta[None]).r[0]) < 1e-6
    assert np.linalg.norm(learner.predict(theta)) < 1e-6


@pytest.mark.parametrize("name", list(MISMATCHED))
def test_converges_on_worlds_the_model_gets_wrong(name: str) -> None:
    world = BallisticWorld(MISMATCHED[name])
    learner = _prior()
    distances = _play(learner, world, 8)
    assert distances[0] > INNER_RING_RADIUS / 2  # the model alone is visibly wrong there
    assert np.any(distances[:2] < INNER_RING_RADIUS)  # hit within two rollouts
    assert np.all(distances[3:] < 0.01)  # and keeps hitting, close to the centre
    assert learner.changes == []  # a wrong model is not a changed world


def test_a_far_wrong_model_still_converges() -> None:
    # At 5 m the nominal 2.2 m model misses by 65 cm and its Jacobian is 2x too small: the
    # fitted range mends both, and with the range held fixed the residual still converges.
    distances = _play(_prior(), BallisticWorld(Scenario(distance=5.0)), 10)
    assert distances[0] > 0.5
    assert distances[1] < INNER_RING_RADIUS
    assert np.all(distances[2:] < 0.01)
    distances = _play(_prior(**FIXED_PHYSICS), BallisticWorld(Scenario(distance=5.0)), 10)
    assert np.any(distances[:4] < INNER_RING_RADIUS)
    assert np.all(distances[5:] < 0.01)


@pytest.mark.parametrize("options", [FIXED_PHYSICS, {}], ids=["fixed physics", "fitted physics"])
def test_the_data_override_the_prior_offset(options: dict) -> None:
    # A world that is the model plus a constant offset: with the physics held fixed the
    # posterior offset c finds it; fitted, the physics explains part of it and c the rest.
    offset = np.array([0.2, -0.15])
    model = BallisticWorld()
    learner = _prior(**options)
    for _ in range(6):
        theta = learner.ask()
        learner.tell(theta, model.impacts(theta[None]).r[0] + offset)
    c, _ = learner.correction()
    if options:
        assert c == pytest.approx(offset, abs=2e-3)
    assert np.linalg.norm(model.impacts(learner.ask()[None]).r[0] + offset) < 1e-3


def test_same_seed_same_proposals_in_a_noisy_world() -> None:
    runs = []
    for _ in range(2):
        world = BallisticWorld(Scenario(noise=0.02, distance=3.0))
        world.reset(7)
        learner = _prior(seed=3)
        proposals = []
        for _ in range(10):
            theta = learner.ask()
            proposals.append(theta)
            learner.tell(theta, world.step(theta).r)
        runs.append(np.array(proposals))
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.parametrize("rollouts", [0, 1, 3, 7])
def test_a_restored_learner_proposes_the_same_next_theta(rollouts: int) -> None:
    world = BallisticWorld(Scenario(drag=0.05, wind=(0.0, 3.0, 0.0), noise=0.01))
    world.reset(5)
    learner = _prior(seed=9, half_life=3.0)
    _play(learner, world, rollouts)
    restored = restore_learner(json.loads(json.dumps(learner.state_dict(), allow_nan=False)))
    assert isinstance(restored, ArcherPrior)
    for _ in range(5):
        a, b = learner.ask(), restored.ask()
        assert np.array_equal(a, b)
        r = world.step(a).r
        learner.tell(a, r)
        restored.tell(b, r)
    assert restored.forget_before == learner.forget_before
    assert restored.changes == learner.changes


def _constant_world(learner: ArcherPrior, rollouts: int) -> np.ndarray:
    """Tell `rollouts` results that do not depend on θ at all (r = (0.1, 0.1) m)."""
    proposals = []
    for _ in range(rollouts):
        theta = learner.ask()
        proposals.append(theta)
        learner.tell(theta, [0.1, 0.1])
    return np.array(proposals)


def test_safeguards_on_data_that_do_not_depend_on_theta() -> None:
    # The data say dr/dθ = 0: J_model + D turns singular, the trust radius shrinks to its
    # minimum and the learner explores instead of stepping far or failing.
    learner = _prior(seed=1)
    proposals = _constant_world(learner, 25)
    assert np.all(np.isfinite(proposals))
    assert all(learner.bounds.contains(t) for t in proposals)
    assert learner.trust_radius == learner.min_step
    steps = np.linalg.norm(np.diff(proposals[5:], axis=0), axis=1)
    assert np.all(steps < 0.03)
    assert np.all(steps > 0)  # it keeps exploring
    other = _constant_world(_prior(seed=2), 25)
    assert not np.array_equal(proposals, other)  # the exploration comes from the seed


def test_repeated_theta_with_conflicting_results_is_safe() -> None:
    learner = _prior()
    theta = THETA0.copy()
    for r in ([0.3, 0.0], [-0.3, 0.0], [0.0, 0.3], [0.0, -0.3]):
        learner.tell(theta, r)
    proposal = learner.ask()
    assert np.all(np.isfinite(proposal)) and learner.bounds.contains(proposal)
    assert np.linalg.norm(proposal - theta) <= learner.trust_radius + 1e-12


def test_a_wind_change_is_detected_and_the_learner_hits_again() -> None:
    before = BallisticWorld(Scenario(drag=0.05, wind=(0.0, 3.0, 0.0)))
    after = BallisticWorld(Scenario(drag=0.05, wind=(0.0, -6.0, 0.0)))
    learner = _prior()
    assert np.all(_play(learner, before, 6)[1:] < 0.01)
    distances = _play(learner, after, 4)
    assert distances[0] > INNER_RING_RADIUS  # the change itself
    assert learner.changes == [6] and learner.forget_before == 6
    assert distances[1] < INNER_RING_RADIUS  # hit again on the next rollout
    assert np.all(distances[2:] < 0.01)


def test_without_change_detection_the_stale_rollouts_slow_it_down() -> None:
    after = BallisticWorld(Scenario(drag=0.05, wind=(0.0, -6.0, 0.0)))
    learner = _prior(change_threshold=0.0)
    _play(learner, BallisticWorld(Scenario(drag=0.05, wind=(0.0, 3.0, 0.0))), 6)
    distances = _play(learner, after, 2)
    assert learner.changes == []
    assert distances[1] > INNER_RING_RADIUS  # the old rollouts still pull it back


@pytest.mark.parametrize(
    "options",
    [
        {"prior_gain_std": 0.0},
        {"noise_std": -1.0},
        {"draw_weight": 0.5},
        {"half_life": float("nan")},
        {"trust_radius": 0.5},
        {"model_stiffness": 0.0},
        {"model_distance": 0.1},
        {"model_distance_std": -1.0},
        {"model_drag_std": float("nan")},
        {"model_wind_std": float("inf")},
    ],
)
def test_invalid_options_are_refused(options: dict) -> None:
    with pytest.raises(LearnerConfigError):
        _prior(**options)  # the model's options build the registry's default model


def test_every_proposal_stays_inside_narrow_bounds() -> None:
    bounds = ThetaBox(low=(0.16, -0.01, -0.01), high=(0.18, 0.01, 0.01))
    learner = ArcherPrior(
        np.array([0.17, 0.0, 0.0]),
        rng=np.random.default_rng(0),
        model=BallisticModel(),
        bounds=bounds,
    )
    world = BallisticWorld(Scenario(distance=5.0))
    for _ in range(6):
        theta = learner.ask()
        assert bounds.contains(theta)
        learner.tell(theta, world.step(theta).r)


# -- an injected model -----------------------------------------------------------------------------
GAIN = np.array([[-1.0, -11.0, -1.1], [2.3, -4.0, -11.8]])  # m of r per m of θ


class LinearModel:
    """A linear world's exact model: r = GAIN (θ − aim) (m); counts its calls."""

    def __init__(self, aim: np.ndarray) -> None:
        self.aim = aim
        self.calls = 0

    def impacts(self, thetas: np.ndarray) -> np.ndarray:
        self.calls += 1
        return (np.atleast_2d(thetas) - self.aim) @ GAIN.T

    def options(self) -> dict[str, float]:
        return {}


def test_an_injected_model_is_the_one_it_aims_with() -> None:
    model = LinearModel(THETA0 + np.array([0.004, 0.003, -0.002]))
    learner = make_learner("archer-prior", THETA0, rng=np.random.default_rng(0), model=model)
    assert isinstance(learner, ArcherPrior) and learner.model is model
    theta = learner.ask()
    assert model.calls > 0
    assert np.linalg.norm(model.impacts(theta)[0]) < 1e-9  # the model's own aim: its centre
    assert np.linalg.norm(learner.predict(theta)) < 1e-9
    assert "model_distance" not in learner.options()  # not the nominal ballistic model
    built = ArcherPrior(THETA0, rng=np.random.default_rng(0), model=model)
    assert np.array_equal(built.ask(), theta)  # the same as the registry builds it
    learner.tell(theta, model.impacts(theta)[0] + 0.01)  # the world is 1 cm off the model
    # The state does not describe this model: restoring it needs the model again.
    with pytest.raises(RestoreError, match="model of its own"):
        restore_learner(learner.state_dict())
    restored = restore_learner(learner.state_dict(), model=model)
    assert np.array_equal(restored.ask(), learner.ask())
    with pytest.raises(LearnerConfigError, match="not both"):
        make_learner(
            "archer-prior", THETA0, rng=np.random.default_rng(0), model=model, model_drag=0.1
        )
    with pytest.raises(LearnerConfigError, match="no physics model"):
        make_learner("archer", THETA0, rng=np.random.default_rng(0), model=model)


def test_the_registry_builds_the_nominal_ballistic_model_by_default() -> None:
    learner = _prior(model_distance=3.0)
    assert learner.model == BallisticModel(distance=3.0)
    assert learner.options()["model_distance"] == 3.0 and learner.options()["model_drag"] == 0.0
    restored = restore_learner(learner.state_dict())
    assert isinstance(restored, ArcherPrior) and restored.model == learner.model
