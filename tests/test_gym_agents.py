"""The project's learners as agents of `archery/Aim-v0` shoot exactly the rollouts of
`archery experiment` for the same seed: θ, r observed and r true, rollout by rollout."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from archery.apps.experiment.config import DEFAULT_ALGORITHMS, ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.apps.gym.agent import run_learner
from archery.sim.ballistic import Scenario

AIM = "archery.apps.gym:archery/Aim-v0"
SCENARIOS = ({}, {"noise": 0.01, "drag": 0.05, "wind": (0.0, 2.0, 0.0), "distance": 3.0})


@pytest.mark.parametrize("scenario", SCENARIOS, ids=("paper", "windy-noisy"))
@pytest.mark.parametrize("name", [*DEFAULT_ALGORITHMS, "archer-prior"])
def test_a_learner_through_the_environment_is_the_experiments_session(
    name: str, scenario: dict[str, object]
) -> None:
    config = ExperimentConfig(
        algorithms=(name,), sessions=2, rollouts=40, seed=5, scenario=Scenario(**scenario)
    )
    run = run_algorithm(config, name)
    env = gym.make(AIM, budget=40, until_hit=False, **scenario)
    for session in range(config.sessions):
        episode = run_learner(env, name, seed=5, session=session)
        assert np.array_equal(episode.thetas, run.thetas[session])
        assert np.array_equal(episode.r, run.r_observed[session])
        assert np.array_equal(episode.r_true, run.r_true[session])
        to_hit = run.rollouts_to_hit()[session]
        assert episode.hit_at == (None if to_hit > config.rollouts else to_hit)


def test_the_episode_ends_at_the_experiments_first_hit() -> None:
    config = ExperimentConfig(algorithms=("archer",), sessions=1, rollouts=60, seed=2)
    run = run_algorithm(config, "archer")
    episode = run_learner(gym.make(AIM), "archer", seed=2)
    hit_at = int(run.rollouts_to_hit()[0])
    assert episode.terminated and episode.hit_at == hit_at == len(episode.thetas)
    assert np.array_equal(episode.thetas, run.thetas[0, :hit_at])
