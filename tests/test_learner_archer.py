"""Tests of ARCHER's update (Eq. 5-6), its ridge option and its safeguards."""

from __future__ import annotations

import numpy as np
import pytest

from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.protocol.theta import ThetaBox
from archery.services.learner.algorithms import Archer, LearnerConfigError

WIDE = ThetaBox(low=(-5.0, -5.0, -5.0), high=(5.0, 5.0, 5.0))


def _archer(**options: object) -> Archer:
    options.setdefault("bounds", WIDE)
    return Archer(np.zeros(3), rng=np.random.default_rng(0), **options)


def _tell_hand_case(learner: Archer) -> None:
    # Best first by ‖r‖: rollout 1 (0.1), rollout 2 (0.3), rollout 3 (≈0.41).
    learner.tell([0.0, 0.0, 0.0], [0.1, 0.0])
    learner.tell([1.0, 0.0, 0.0], [0.3, 0.0])
    learner.tell([0.0, 1.0, 0.0], [0.1, 0.4])


@pytest.mark.parametrize("safeguard", [False, True])
def test_hand_computed_regression(safeguard: bool) -> None:
    # U = [[0.2, 0], [0, 0.4]], r_1T = (−0.1, 0)  →  W = r_1T U⁻¹ = (−0.5, 0)
    # θ̂_1T = −0.5·(1, 0, 0)  →  θ_4 = (−0.5, 0, 0).
    learner = _archer(safeguard=safeguard, trust_radius=1.0, max_step=1.0)
    _tell_hand_case(learner)
    assert learner.ask() == pytest.approx([-0.5, 0.0, 0.0], abs=1e-15)


def test_ridge_regression_follows_the_footnote() -> None:
    # W = r_1T Uᵀ (U Uᵀ + λI)⁻¹ with λ = 0.04: w_1 = −0.1·0.2/(0.04 + 0.04) = −0.25.
    learner = _archer(safeguard=False, ridge=0.04)
    _tell_hand_case(learner)
    assert learner.ask() == pytest.approx([-0.25, 0.0, 0.0], abs=1e-15)


def test_sorting_uses_the_return_not_the_order_of_arrival() -> None:
    learner = _archer(safeguard=False)
    learner.tell([0.0, 1.0, 0.0], [0.1, 0.4])
    learner.tell([1.0, 0.0, 0.0], [0.3, 0.0])
    learner.tell([0.0, 0.0, 0.0], [0.1, 0.0])
    assert learner.ask() == pytest.approx([-0.5, 0.0, 0.0], abs=1e-15)


def _linear_world(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A random, well-conditioned linear world r = A θ + b (singular values of A in [1, 2])."""
    rng = np.random.default_rng(100 + seed)
    left, _ = np.linalg.qr(rng.normal(size=(2, 2)))
    right, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    a = left @ np.diag(rng.uniform(1.0, 2.0, size=2)) @ right[:2]
    theta_goal = rng.normal(scale=0.02, size=3) + np.array([0.2, 0.0, 0.0])
    return a, -a @ theta_goal


@pytest.mark.parametrize("seed", range(8))
def test_exactly_linear_world_is_solved_by_the_first_aimed_rollout(seed: int) -> None:
    a, b = _linear_world(seed)
    learner = Archer(
        np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(seed), bounds=WIDE, safeguard=False
    )
    for _ in range(3):  # the exploratory phase: rollouts 1-3
        theta = learner.ask()
        learner.tell(theta, a @ theta + b)
    theta4 = learner.ask()
    assert np.linalg.norm(a @ theta4 + b) < 1e-9


def test_safeguards_leave_a_well_posed_step_alone() -> None:
    # Where U is well-conditioned and the step fits in the trust radius, the safeguarded
    # learner proposes exactly the paper's θ, which solves a linear world at rollout 4.
    checked = 0
    for seed in range(20):
        a, b = _linear_world(seed)
        guarded = Archer(np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(seed), bounds=WIDE)
        plain = Archer(
            np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(seed), bounds=WIDE, safeguard=False
        )
        for _ in range(3):
            theta = guarded.ask()
            guarded.tell(theta, a @ theta + b)
            plain.tell(theta, a @ theta + b)
        best = guarded.ranked()[:3]
        u = guarded.rewards[best[1:]] - guarded.rewards[best[0]]
        singular = np.linalg.svd(u, compute_uv=False)
        step = plain.ask() - guarded.thetas[best[0]]
        if singular[0] <= guarded.max_cond * singular[1] and np.linalg.norm(step) <= 0.06:
            assert np.array_equal(guarded.ask(), plain.ask())
            assert np.linalg.norm(a @ guarded.ask() + b) < 1e-9
            checked += 1
    assert checked >= 10


def test_exploration_phase_is_random_around_theta0() -> None:
    theta0 = np.array([0.2, 0.0, 0.0])
    learner = Archer(theta0, rng=np.random.default_rng(1), explore_std=0.02)
    proposals = []
    for _ in range(3):
        proposals.append(learner.ask())
        learner.tell(proposals[-1], [0.3, 0.3])
    expected = theta0 + 0.02 * np.random.default_rng(1).standard_normal((3, 3))
    assert np.array(proposals) == pytest.approx(expected, abs=1e-15)


def _collinear_case(learner: Archer) -> None:
    # Three results on one line that misses the centre: U is singular up to 1e-9.
    learner.tell([0.0, 0.0, 0.0], [0.1, 0.0])
    learner.tell([0.01, 0.0, 0.0], [0.2, 0.1])
    learner.tell([0.0, 0.01, 0.0], [0.3, 0.2 + 1e-9])


def test_plain_archer_jumps_far_on_collinear_results() -> None:
    learner = _archer(safeguard=False)
    _collinear_case(learner)
    assert np.linalg.norm(learner.ask()) > 1.0  # the pseudo-inverse amplifies 1e-9


def test_safeguarded_archer_takes_a_bounded_exploratory_step_instead() -> None:
    for seed in range(20):
        learner = Archer(np.zeros(3), rng=np.random.default_rng(seed), bounds=WIDE)
        _collinear_case(learner)
        step = learner.ask()
        # Truncated step (along the well-determined direction) plus N(0, fallback_std²) noise.
        assert np.linalg.norm(step) <= learner.trust_radius + 5 * learner.fallback_std
        assert np.all(np.isfinite(step))


def test_trust_radius_shrinks_after_a_failure_and_grows_after_a_success() -> None:
    learner = _archer(trust_radius=0.04, min_step=0.005, max_step=0.1)
    _tell_hand_case(learner)
    learner.tell(learner.ask(), [1.0, 1.0])  # worse than the best: shrink
    assert learner.trust_radius == pytest.approx(0.02)
    learner.tell(learner.ask(), [2.0, 2.0])
    learner.tell(learner.ask(), [3.0, 3.0])
    assert learner.trust_radius == pytest.approx(0.005)  # not below min_step
    learner.tell(learner.ask(), [0.01, 0.0])  # a new best: grow
    assert learner.trust_radius == pytest.approx(0.01)


def test_repeated_failures_do_not_repeat_the_same_proposal() -> None:
    # The plain algorithm proposes the same θ forever when its jump keeps missing.
    plain, guarded = _archer(safeguard=False), _archer()
    for learner in (plain, guarded):
        _tell_hand_case(learner)
        proposals = []
        for _ in range(4):
            proposals.append(learner.ask())
            learner.tell(proposals[-1], [5.0, 5.0])
        learner.proposals = proposals  # type: ignore[attr-defined]  # kept on the learner for the asserts below
    assert all(np.array_equal(p, plain.proposals[0]) for p in plain.proposals)  # type: ignore[attr-defined]  # set above
    distinct = {tuple(p) for p in guarded.proposals}  # type: ignore[attr-defined]  # set above
    assert len(distinct) == 4


def test_safeguarded_archer_hits_in_every_session_and_plain_archer_does_not() -> None:
    config = ExperimentConfig(algorithms=("archer", "archer-plain"), sessions=40, rollouts=60)
    guarded = run_algorithm(config, "archer").rollouts_to_hit()
    plain = run_algorithm(config, "archer-plain").rollouts_to_hit()
    assert np.all(guarded <= 60)
    assert np.median(guarded) <= 4
    assert np.any(plain > 60)


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"n_best": 1}, "n_best"),
        ({"n_explore": 2}, "n_explore"),
        ({"explore_std": -0.1}, "explore_std"),
        ({"explore_std": (0.1, 0.2)}, "explore_std"),
        ({"ridge": float("nan")}, "ridge"),
        ({"safeguard": "yes"}, "safeguard"),
        ({"trust_radius": 1.0}, "trust_radius"),
    ],
)
def test_bad_options_are_named(options: dict, named: str) -> None:
    with pytest.raises(LearnerConfigError, match=named):
        Archer(np.array([0.2, 0.0, 0.0]), rng=np.random.default_rng(0), **options)


def test_window_chooses_the_best_among_recent_rollouts_only() -> None:
    # The best rollout overall (r = 0.01) is older than the window of 3: the regression uses
    # the three most recent, as the hand case above with the stale best in front.
    windowed = _archer(safeguard=False, window=3)
    windowed.tell([5.0, 5.0, 5.0], [0.01, 0.0])
    _tell_hand_case(windowed)
    assert windowed.ask() == pytest.approx([-0.5, 0.0, 0.0], abs=1e-15)
    everything = _archer(safeguard=False)
    everything.tell([5.0, 5.0, 5.0], [0.01, 0.0])
    _tell_hand_case(everything)
    assert everything.ask() != pytest.approx([-0.5, 0.0, 0.0], abs=1e-3)


def test_window_must_hold_the_n_best() -> None:
    with pytest.raises(LearnerConfigError, match="window"):
        _archer(window=2)
