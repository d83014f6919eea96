"""`archery/Aim-v0`: the analytic world through Gymnasium's own API and checker."""

from __future__ import annotations

import importlib
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from archery.apps.gym.agent import run_learner
from archery.apps.gym.registration import AIM_ID, AIM_ROBOT_ID
from archery.protocol.theta import THETA_BOX
from archery.sim.ballistic import BallisticWorld, Scenario, ScenarioError

ROOT = Path(__file__).resolve().parents[1]
AIM = f"archery.apps.gym:{AIM_ID}"


def _checked(env: gym.Env) -> None:
    """Gymnasium's checker passes; its only remarks are those on a box in metres that is
    neither symmetric nor bounded for r (the task's units, on purpose)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    remarks = {str(w.message) for w in caught}
    assert all("symmetric and normalized" in m or "infinity" in m for m in remarks), remarks


def test_gymnasiums_checker_passes_on_the_paper_world_and_a_windy_noisy_one() -> None:
    _checked(gym.make(AIM).unwrapped)
    _checked(gym.make(AIM, drag=0.05, wind=(0, 3, 0), noise=0.01, distance=3.0).unwrapped)


def test_the_ids_resolve_in_a_fresh_interpreter_with_nothing_imported_first() -> None:
    code = (
        "import gymnasium as g; e = g.make('archery.apps.gym:archery/Aim-v0'); "
        "o, _ = e.reset(seed=1); "
        "print(e.spec.id, e.observation_space.shape, e.action_space.shape)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split()[0] == AIM_ID


def test_the_declared_plugin_entry_point_registers_both_ids() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    target = project["project"]["entry-points"]["gymnasium.envs"]["archery"]
    module, function = target.split(":")
    getattr(importlib.import_module(module), function)()
    assert AIM_ID in gym.registry and AIM_ROBOT_ID in gym.registry


def test_the_spaces_are_the_experiments_theta_box_and_r_with_theta_in_metres() -> None:
    env = gym.make(AIM)
    assert env.action_space.low.tolist() == THETA_BOX.low
    assert env.action_space.high.tolist() == THETA_BOX.high
    assert env.action_space.dtype == np.float64
    assert env.observation_space.shape == (5,)
    obs, info = env.reset(seed=0)
    assert obs.tolist() == [0.0, 0.0, *Scenario().start] and info["shots"] == 0


def test_one_step_is_one_shot_of_the_ballistic_world_with_reward_minus_distance() -> None:
    env = gym.make(AIM, noise=0.0)
    env.reset(seed=3)
    theta = np.array([0.2, 0.01, -0.02])
    obs, reward, terminated, truncated, info = env.step(theta)
    shot = BallisticWorld(Scenario()).step(theta)
    assert info["r"].tolist() == shot.r.tolist() == obs[:2].tolist()
    assert obs[2:].tolist() == theta.tolist() == info["theta"].tolist()
    assert reward == -info["distance"] == -float(np.hypot(*shot.r))
    assert info["hit"] is shot.hit and info["confidence"] == 1.0 and not info["clipped"]
    assert not terminated and not truncated


def test_the_same_seed_gives_the_same_episode_bit_for_bit() -> None:
    def episode(seed: int) -> list[list[float]]:
        env = gym.make(AIM, noise=0.02, drag=0.05, wind=(0, 2, 0))
        env.reset(seed=seed)
        env.action_space.seed(seed)
        rows = []
        for _ in range(8):
            obs, reward, *_ = env.step(env.action_space.sample())
            rows.append([*obs.tolist(), reward])
        return rows

    assert episode(11) == episode(11)
    assert episode(11) != episode(12)


def test_an_episode_ends_at_a_hit_or_at_its_budget() -> None:
    env = gym.make(AIM, budget=3)
    env.reset(seed=0)
    assert env.step(np.array([0.2, 0.0, 0.0]))[2:4] == (False, False)
    assert env.step(np.array([0.2, 0.0, 0.0]))[2:4] == (False, False)
    assert env.step(np.array([0.2, 0.0, 0.0]))[2:4] == (False, True)
    episode = run_learner(gym.make(AIM), "archer", seed=0)  # ARCHER hits within 60 shots
    assert episode.terminated and episode.hit_at == len(episode.thetas)
    theta = episode.thetas[-1]
    env = gym.make(AIM, until_hit=False, budget=2)
    env.reset(seed=0)
    assert env.step(theta)[2] is False


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_action_is_refused_naming_it_before_anything_moves(bad: float) -> None:
    env = gym.make(AIM).unwrapped
    env.reset(seed=0)
    obs = env.step(np.array([0.2, 0.0, 0.0]))[0]
    with pytest.raises(ValueError, match=f"{bad!r} at index 1"):
        env.step(np.array([0.2, bad, 0.0]))
    assert env._shots == 1 and env._obs.tolist() == obs.tolist()
    with pytest.raises(ValueError, match="3 numbers"):
        env.step(np.array([0.2, 0.0]))


def test_an_action_outside_the_box_is_clipped_and_flagged_never_shot_raw() -> None:
    env = gym.make(AIM)
    env.reset(seed=0)
    obs, _, _, _, info = env.step(np.array([0.9, -0.5, 0.0]))
    clipped = [THETA_BOX.high[0], THETA_BOX.low[1], 0.0]
    assert info["clipped"] and info["theta"].tolist() == clipped == obs[2:].tolist()
    shot = BallisticWorld(Scenario()).step(np.array(clipped))
    assert info["r"].tolist() == shot.r.tolist()


def test_every_scenario_option_of_the_experiment_is_a_keyword_and_checked() -> None:
    theta = np.array([0.2, 0.01, 0.0])
    base = gym.make(AIM)
    base.reset(seed=0)
    r0 = base.step(theta)[4]["r_true"]
    for keyword in (
        {"distance": 3.0},
        {"drag": 0.05},
        {"drag": 0.05, "wind": (0.0, 3.0, 0.0)},
        {"bow_stiffness": 400.0},
    ):
        env = gym.make(AIM, **keyword)
        env.reset(seed=0)
        assert env.step(theta)[4]["r_true"].tolist() != r0.tolist(), keyword
    noisy = gym.make(AIM, noise=0.01)
    noisy.reset(seed=0)
    info = noisy.step(theta)[4]
    assert info["r_true"].tolist() == r0.tolist() and info["r"].tolist() != r0.tolist()
    assert gym.make(AIM, start=(0.2, 0.0, 0.0)).reset(seed=0)[0][2:].tolist() == [0.2, 0, 0]
    changed = gym.make(AIM, drag=0.05, wind_change="2:0,5,0")
    changed.reset(seed=0)
    first, second = (changed.step(theta)[4]["r_true"] for _ in range(2))
    assert first.tolist() != second.tolist()
    for keyword, named in (
        ({"distance": -1.0}, "distance"),
        ({"drag": -1.0}, "drag"),
        ({"wind": (0.0, 3.0, 0.0)}, "wind"),
        ({"noise": float("nan")}, "noise"),
        ({"start": (0.5, 0.0, 0.0)}, "start"),
        ({"wind_change": "1:0,1,0", "drag": 0.05}, "wind_change"),
        ({"budget": 0}, "budget"),
    ):
        with pytest.raises(ValueError, match=named):
            gym.make(AIM, **keyword)
    with pytest.raises(ScenarioError):
        gym.make(AIM, bow_stiffness=0.0)


def test_make_vec_runs_the_analytic_world_in_processes() -> None:
    envs = gym.make_vec(AIM, num_envs=2, vectorization_mode="async", noise=0.01)
    try:
        obs, _ = envs.reset(seed=[5, 6])
        actions = np.array([[0.2, 0.0, 0.0], [0.21, 0.01, -0.01]])
        obs, rewards, *_ = envs.step(actions)
    finally:
        envs.close()
    for i, seed in enumerate((5, 6)):
        single = gym.make(AIM, noise=0.01)
        single.reset(seed=seed)
        expected, reward, *_ = single.step(actions[i])
        assert obs[i].tolist() == expected.tolist() and rewards[i] == reward
