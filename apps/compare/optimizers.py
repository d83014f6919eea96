"""The field's optimizers pointed at the archery task through its Gymnasium environment, as any
user of theirs would: pycma's CMA-ES and nevergrad's default optimizer (NGOpt), both by
ask/tell, minimising ‖r‖ = −reward (m), one shot per evaluation.

Each runs one episode: `reset(seed=SEED, options={"session": K})`, then shots until the
episode is truncated (or terminated). Their own seeds come from (SEED, K) as the project's
learners' do (`apps.gym.agent.learner_rng`), so a run is reproducible.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from archery.apps.gym.agent import Episode, StepHook, bounds_of, start_theta

__all__ = ["CMA_SIGMA0", "OPTIMIZERS", "run_optimizer"]

CMA_SIGMA0 = 0.01  # m, pycma's initial step: the project's CMA-ES baseline's


class _Shots:
    """The shots of one episode: step the environment and keep what it returned."""

    def __init__(self, env: gym.Env[Any, Any], on_step: StepHook | None) -> None:
        self.env = env
        self.on_step = on_step
        self.thetas: list[np.ndarray] = []
        self.r: list[np.ndarray] = []
        self.r_true: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.hit_at: int | None = None
        self.done = False
        self.terminated = False

    def shoot(self, theta: np.ndarray) -> float:
        """Shoot θ (m); the distance to minimise (m)."""
        _, reward, terminated, truncated, info = self.env.step(np.asarray(theta, dtype=float))
        self.thetas.append(np.asarray(info["theta"], dtype=float))
        self.r.append(np.full(2, np.nan) if info["r"] is None else np.asarray(info["r"]))
        truth = info.get("r_true")
        self.r_true.append(np.full(2, np.nan) if truth is None else np.asarray(truth))
        self.rewards.append(float(reward))
        if self.hit_at is None and info["hit"]:
            self.hit_at = len(self.thetas)
        self.done = bool(terminated or truncated)
        self.terminated = bool(terminated)
        if self.on_step is not None:
            self.on_step(len(self.thetas), dict(info))
        return -float(reward)

    def episode(self) -> Episode:
        return Episode(
            thetas=np.array(self.thetas).reshape(-1, 3),
            r=np.array(self.r).reshape(-1, 2),
            r_true=np.array(self.r_true).reshape(-1, 2),
            rewards=np.array(self.rewards),
            hit_at=self.hit_at,
            terminated=self.terminated,
        )


def _seed(seed: int, session: int) -> int:
    """A 31-bit seed (> 0) for an optimizer's own generator, from (seed, session)."""
    state = np.random.SeedSequence(seed, spawn_key=(session, 1)).generate_state(1)[0]
    return int(state) % (2**31 - 1) + 1


def _pycma(shots: _Shots, theta0: np.ndarray, low: np.ndarray, high: np.ndarray, seed: int) -> None:
    import cma

    options = {"bounds": [low.tolist(), high.tolist()], "seed": seed, "verbose": -9}
    es = cma.CMAEvolutionStrategy(theta0.tolist(), CMA_SIGMA0, options)
    while not shots.done:
        candidates = es.ask()
        values = []
        for x in candidates:
            values.append(shots.shoot(np.asarray(x)))
            if shots.done:
                break
        if len(values) == len(candidates):
            es.tell(candidates, values)


def _ngopt(shots: _Shots, theta0: np.ndarray, low: np.ndarray, high: np.ndarray, seed: int) -> None:
    import nevergrad as ng

    parameter = ng.p.Array(init=theta0, lower=low, upper=high)
    parameter.random_state = np.random.RandomState(seed)
    budget = getattr(shots.env.unwrapped, "budget", None)
    optimizer = ng.optimizers.NGOpt(parametrization=parameter, budget=budget, num_workers=1)
    while not shots.done:
        candidate = optimizer.ask()
        optimizer.tell(candidate, shots.shoot(candidate.value))


Method = Callable[[_Shots, np.ndarray, np.ndarray, np.ndarray, int], None]
#: name -> (label, the optimizer's episode)
OPTIMIZERS: dict[str, tuple[str, Method]] = {
    "pycma": (f"CMA-ES (pycma, σ0 = {100 * CMA_SIGMA0:g} cm)", _pycma),
    "ngopt": ("NGOpt (nevergrad)", _ngopt),
}


def run_optimizer(
    env: gym.Env[Any, Any],
    name: str,
    *,
    seed: int,
    session: int = 0,
    on_step: StepHook | None = None,
) -> Episode:
    """One episode of the optimizer `name` (`OPTIMIZERS`) on `env`.

    Raises:
        KeyError: unknown name; whatever `env.step` raises.
    """
    _, method = OPTIMIZERS[name]
    observation, _ = env.reset(seed=seed, options={"session": session})
    bounds = bounds_of(env.action_space)
    shots = _Shots(env, on_step)
    with warnings.catch_warnings():  # the optimizers' chatter about their own settings
        warnings.simplefilter("ignore")
        method(
            shots,
            start_theta(observation),
            np.array(bounds.low),
            np.array(bounds.high),
            _seed(seed, session),
        )
    return shots.episode()
