"""The ask/tell protocol shared by every learner: state, determinism, bounds, errors."""

from __future__ import annotations

import json
import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.algorithms import (
    ALGORITHMS,
    Archer,
    CmaEs,
    HillClimber,
    Learner,
    LearnerConfigError,
    LearnerError,
    ObservationError,
    RandomSearch,
    RestoreError,
    make_learner,
    restore_learner,
    scalar_return,
)
from archery.services.learner.algorithms.base import rng_from_state, rng_state
from archery.sim.ballistic import BallisticWorld, Scenario
from archery.sim.geometry import START_THETA

NAMES = list(ALGORITHMS)


def _learner(name: str, seed: int = 0) -> Learner:
    return make_learner(name, np.array(START_THETA), rng=np.random.default_rng(seed))


def _play(learner: Learner, world: BallisticWorld, rollouts: int) -> list[np.ndarray]:
    proposals = []
    for _ in range(rollouts):
        theta = learner.ask()
        proposals.append(theta)
        learner.tell(theta, world.step(theta).r)
    return proposals


def _world() -> BallisticWorld:
    world = BallisticWorld(Scenario(noise=0.005))
    world.reset(11)
    return world


def test_scalar_return_is_equation_1() -> None:
    assert scalar_return(np.array([0.3, 0.4])) == pytest.approx(math.exp(-0.5), abs=1e-16)
    assert scalar_return(np.zeros(2)) == 1.0


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("rollouts", [0, 2, 5, 9])
@pytest.mark.parametrize("codec", ["json", "msgpack"])
def test_restored_learner_makes_the_identical_next_proposals(
    name: str, rollouts: int, codec: str
) -> None:
    world = _world()
    original = _learner(name, seed=5)
    _play(original, world, rollouts)
    state = original.state_dict()
    if codec == "json":
        stored = json.loads(json.dumps(state, allow_nan=False))
    else:
        stored = msgpack.unpackb(msgpack.packb(state), raw=False)
    restored = restore_learner(stored)
    for _ in range(6):  # the same future, bit for bit
        a, b = original.ask(), restored.ask()
        assert np.array_equal(a, b)
        r = world.step(a).r
        assert original.tell(a, r) == restored.tell(b, r)


@pytest.mark.parametrize("name", NAMES)
def test_a_pending_proposal_survives_a_restore(name: str) -> None:
    learner = _learner(name, seed=2)
    _play(learner, _world(), 4)
    pending = learner.ask()
    restored = restore_learner(json.loads(json.dumps(learner.state_dict())))
    assert np.array_equal(restored.ask(), pending)


# archer-prior aims with a deterministic model: its seed only drives the safeguards' exploration
# (tests/test_learner_prior.py checks that).
@pytest.mark.parametrize("name", NAMES)
def test_same_seed_same_proposals_other_seed_other_proposals(name: str) -> None:
    runs = [_play(_learner(name, seed), _world(), 12) for seed in (3, 3, 4)]
    assert all(np.array_equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))
    if name != "archer-prior":
        assert not all(np.array_equal(a, b) for a, b in zip(runs[0], runs[2], strict=True))


@pytest.mark.parametrize("name", NAMES)
def test_ask_is_idempotent_until_tell(name: str) -> None:
    learner = _learner(name)
    first = learner.ask()
    assert np.array_equal(learner.ask(), first)
    learner.tell(first, [0.1, 0.1])
    assert learner.n_rollouts == 1


@settings(max_examples=15, deadline=None)
@given(
    name=st.sampled_from(NAMES),
    rewards=st.lists(
        st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)), min_size=1, max_size=16
    ),
    repeat=st.booleans(),
)
def test_proposals_are_finite_and_inside_the_bounds(
    name: str, rewards: list[tuple[float, float]], repeat: bool
) -> None:
    # Arbitrary, even absurd or repeated, results never push θ out of the box or to NaN.
    learner = _learner(name)
    for r in rewards:
        theta = learner.ask()
        assert np.all(np.isfinite(theta)) and THETA_BOX.contains(theta)
        learner.tell(theta, rewards[0] if repeat else r)
    theta = learner.ask()
    assert np.all(np.isfinite(theta)) and THETA_BOX.contains(theta)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(
    ("theta", "r", "named"),
    [
        ([0.2, 0.0, 0.0], [float("nan"), 0.0], "r must be a finite 2-vector"),
        ([0.2, 0.0, 0.0], [float("inf"), 0.0], "r must be a finite 2-vector"),
        ([0.2, 0.0, 0.0], [0.1, 0.2, 0.3], "r must be a finite 2-vector"),
        (["left", "up", "back"], [0.1, 0.2], "must be numeric vectors"),
    ],
)
def test_bad_observations_are_refused_and_change_nothing(
    name: str, theta: list, r: list, named: str
) -> None:
    learner = _learner(name)
    before = learner.state_dict()
    with pytest.raises(ObservationError, match=named):
        learner.tell(theta, r)
    assert learner.state_dict() == before


def test_learner_errors_form_one_hierarchy() -> None:
    for error in (LearnerConfigError, ObservationError, RestoreError):
        assert issubclass(error, LearnerError) and issubclass(error, ValueError)


def test_unknown_algorithm_is_named_with_the_valid_ones() -> None:
    with pytest.raises(LearnerConfigError, match=r"'powr'.*archer, archer-plain"):
        make_learner("powr", np.array(START_THETA), rng=np.random.default_rng(0))


def test_unknown_option_is_a_config_error() -> None:
    with pytest.raises(LearnerConfigError, match="invalid option for 'power'"):
        make_learner("power", np.array(START_THETA), rng=np.random.default_rng(0), sigma=3)


def test_constructor_checks_rng_theta0_and_bounds() -> None:
    with pytest.raises(LearnerConfigError, match=r"numpy\.random\.Generator"):
        Archer(np.array(START_THETA), rng=np.random.RandomState(0))  # type: ignore[arg-type]  # a legacy RandomState on purpose
    with pytest.raises(LearnerConfigError, match=r"theta0 \[0.5, 0.0, 0.0\] m lies outside the θ"):
        Archer(np.array([0.5, 0.0, 0.0]), rng=np.random.default_rng(0))
    with pytest.raises(LearnerConfigError, match="finite 3-vector"):
        Archer(np.array([0.2, 0.0]), rng=np.random.default_rng(0))
    with pytest.raises(LearnerConfigError, match="must be a ThetaBox"):
        Archer(np.array(START_THETA), rng=np.random.default_rng(0), bounds=(0.1, 0.3))  # type: ignore[arg-type]  # not a box on purpose


def test_a_theta_box_is_three_finite_numbers_a_side_low_below_high() -> None:
    # θ is 3-D in this project: a box of another dimension is refused, like a flat one.
    with pytest.raises(ValueError, match="low < high on every axis"):
        ThetaBox(low=(0.0, 0.0, 0.0), high=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match=r"θ box low must be 3 finite numbers \(m\), got \(0.0,\)"):
        ThetaBox(low=(0.0,), high=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="θ box high must be 3 finite numbers"):
        ThetaBox(low=(0.0, 0.0, 0.0), high=(1.0, math.inf, 1.0))
    box = ThetaBox(low=np.zeros(3), high=(1, 2, 3))
    assert box == ThetaBox(low=[0.0, 0.0, 0.0], high=[1.0, 2.0, 3.0])
    assert box.contains([1.0, 0.0, 3.0]) and not box.contains([1.0, -0.1, 3.0])
    np.testing.assert_array_equal(box.clip([2.0, -1.0, 1.5]), [1.0, 0.0, 1.5])


def test_restore_refuses_broken_states() -> None:
    learner = _learner("archer")
    _play(learner, _world(), 3)
    state = learner.state_dict()
    with pytest.raises(RestoreError, match="'nope'"):
        restore_learner({**state, "algorithm": "nope"})
    with pytest.raises(RestoreError, match="version 99"):
        restore_learner({**state, "version": 99})
    with pytest.raises(RestoreError, match="2-vectors r"):
        restore_learner({**state, "rewards": [[0.1, 0.2, 0.3]] * 3})
    with pytest.raises(RestoreError, match="random generator"):
        restore_learner({**state, "rng": {"bit_generator": "Nope"}})
    with pytest.raises(RestoreError, match="cannot be loaded into"):
        make_learner("power", np.array(START_THETA), rng=np.random.default_rng(0)).load_state_dict(
            state
        )
    cma = _learner("cma")
    _play(cma, _world(), 3)
    broken = cma.state_dict()
    broken["extra"]["events"] = "pu"
    with pytest.raises(RestoreError, match="one 'u' per told rollout"):
        restore_learner(broken)


def test_generator_state_is_plain_and_exact() -> None:
    for bit_generator in (np.random.PCG64(9), np.random.MT19937(9), np.random.Philox(9)):
        rng = np.random.Generator(bit_generator)
        rng.standard_normal(5)
        plain = json.loads(json.dumps(rng_state(rng)))
        msgpack.packb(plain)  # ints fit in 64 bits
        assert np.array_equal(rng_from_state(plain).random(4), rng.random(4))


def test_cma_draws_only_from_the_injected_generator() -> None:
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    learner = CmaEs(np.array(START_THETA), rng=np.random.default_rng(0))
    _play(learner, _world(), 10)
    assert np.array_equal(np.random.get_state()[1], before)
    assert learner.popsize == 7 and learner.exploration_rollouts == 7


def test_hill_climber_explores_around_the_best_so_far() -> None:
    wide = ThetaBox(low=(0.10, -0.12, -0.12), high=(0.30, 0.12, 0.12))  # around every θ told
    learner = HillClimber(
        np.array(START_THETA), rng=np.random.default_rng(0), explore_std=0.001, bounds=wide
    )
    learner.tell([0.2, 0.05, 0.0], [0.5, 0.5])
    learner.tell([0.25, -0.05, 0.0], [0.01, 0.0])
    learner.tell([0.15, 0.0, 0.05], [0.3, 0.0])
    samples = []
    for _ in range(200):
        samples.append(learner.ask())
        learner.tell(samples[-1], [1.0, 1.0])
    assert np.mean(samples, axis=0) == pytest.approx([0.25, -0.05, 0.0], abs=5e-4)


def test_random_search_draws_uniformly_in_the_bounds_whatever_the_rewards() -> None:
    bounds = ThetaBox(low=(0.1, -0.1, -0.05), high=(0.3, 0.1, 0.05))
    learner = RandomSearch(np.array(START_THETA), rng=np.random.default_rng(2), bounds=bounds)
    samples = []
    for _ in range(4000):
        samples.append(learner.ask())
        learner.tell(samples[-1], [0.0, 0.0] if len(samples) == 1 else [1.0, 1.0])
    samples = np.array(samples)
    low, high = np.array(bounds.low), np.array(bounds.high)
    assert np.all(samples >= low) and np.all(samples <= high)
    # Uniform: mean at the box centre, std (high − low)/√12, per component (4000 samples).
    width = high - low
    assert np.all(np.abs(samples.mean(axis=0) - (low + high) / 2) < 0.02 * width)
    assert np.all(np.abs(samples.std(axis=0) / (width / math.sqrt(12)) - 1) < 0.05)
    # The best rollout (the first) does not attract the search.
    assert np.linalg.norm(samples[1:] - samples[0], axis=1).min() > 1e-4


def test_random_search_is_reproducible_from_its_seed() -> None:
    a, b = _learner("random", seed=9), _learner("random", seed=9)
    world = _world()
    assert [t.tolist() for t in _play(a, world, 5)] == [t.tolist() for t in _play(b, world, 5)]
    assert not np.array_equal(_learner("random", seed=10).ask(), _learner("random", seed=9).ask())


def test_only_random_search_redraws_after_a_miss_and_leaves_its_generator_alone() -> None:
    learner = _learner("random", seed=9)
    before = learner.state_dict()
    draw = learner.redraw((9, 4))
    assert draw is not None and learner.bounds.contains(draw)
    np.testing.assert_array_equal(draw, learner.redraw((9, 4)))  # reproducible from the key
    assert not np.array_equal(draw, learner.redraw((9, 5)))
    assert learner.state_dict() == before
    for name in ("archer", "power", "cma", "hill"):
        assert _learner(name).redraw((9, 4)) is None  # these back off towards the best θ


def test_a_state_saved_when_random_named_the_hill_climber_is_refused() -> None:
    hill = _learner("hill", seed=1)
    _play(hill, _world(), 3)
    old = json.loads(json.dumps(hill.state_dict()))
    old["algorithm"] = "random"  # what the hill climber wrote under its former name
    with pytest.raises(RestoreError, match=r"'random' named the hill climber.*now 'hill'"):
        restore_learner(old)
    assert restore_learner(hill.state_dict()).algorithm == "hill"
