"""The project's learners (ARCHER, PoWER and every learner of the registry) as agents of any
environment with the archery task's interface (`apps.gym.spaces`): θ from the learner's `ask`,
one `step` per shot, `tell(θ shot, r measured)` from the step's `info`.

The details: `run_learner`'s docstring."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from archery.protocol.theta import ThetaBox
from archery.services.learner.abort_policy import NO_ARROW, after_abort
from archery.services.learner.algorithms.base import Learner
from archery.services.learner.algorithms.registry import make_learner

__all__ = ["Episode", "bounds_of", "learner_rng", "run_learner", "start_theta"]

StepHook = Callable[[int, dict[str, Any]], None]


@dataclass(frozen=True)
class Episode:
    """One episode's shots, in order.

    Attributes:
        thetas: (n, 3) θ shot (m).
        r: (n, 2) r measured (m); NaN for a shot that was not measured.
        r_true: (n, 2) the world's ground truth r (m); NaN where the world does not give it.
        rewards: (n,) the environment's rewards.
        hit_at: 1-based shot of the first hit (None: no hit).
        terminated: the episode ended at a hit (else at its budget, or the learner gave up).
    """

    thetas: np.ndarray
    r: np.ndarray
    r_true: np.ndarray
    rewards: np.ndarray
    hit_at: int | None
    terminated: bool


def bounds_of(space: gym.Space[Any]) -> ThetaBox:
    """The θ box (m) of an action `Box`.

    Raises:
        ValueError: not a `Box` of 3 θ components, or not a valid θ box (named).
    """
    if not isinstance(space, gym.spaces.Box) or space.shape != (3,):
        raise ValueError(f"the action space must be a Box of 3 θ components (m), got {space}")
    return ThetaBox(low=space.low.tolist(), high=space.high.tolist())


def start_theta(observation: np.ndarray) -> np.ndarray:
    """The start θ (m) in a reset observation `[r_y, r_z, θ_x, θ_y, θ_z]`."""
    return np.asarray(observation, dtype=float)[2:5].copy()


def learner_rng(seed: int, session: int = 0) -> np.random.Generator:
    """The generator `archery experiment --seed SEED` gives its session `session`'s learner."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(session, 1)))


def _vector(info: Mapping[str, Any], key: str, size: int) -> np.ndarray:
    value = info.get(key)
    return np.full(size, np.nan) if value is None else np.asarray(value, dtype=float)


def run_learner(
    env: gym.Env[Any, Any],
    name: str,
    *,
    seed: int,
    session: int = 0,
    rng: np.random.Generator | None = None,
    options: Mapping[str, Any] | None = None,
    on_step: StepHook | None = None,
) -> Episode:
    """One episode of learner `name` (`services.learner.algorithms.registry`) on `env`, from
    `reset(seed=seed, options={"session": session})` to `terminated` or `truncated`;
    `on_step(shot, info)` after each shot.

    Raises:
        LearnerError: unknown learner or bad options; whatever `env.step` raises.

    Seeds: `run_learner(env, name, seed=S, session=K)` resets the environment with `seed=S,
    options={"session": K}` and gives the learner the generator `archery experiment --seed S` gives
    session K, so on `archery/Aim-v0` it shoots exactly that session's rollouts. Pass `rng` for
    another convention (`archery learn --seed S` seeds its learner with `default_rng(S)`).

    A shot the environment could not measure (`info["r"]` None: no arrow on the target face) is
    handled as a learning session does (`services.learner.abort_policy`): the learner is not told,
    and the next shot backs off halfway towards the best θ so far (or the learner's own redraw).

    """
    observation, _ = env.reset(seed=seed, options={"session": session})
    bounds = bounds_of(env.action_space)
    theta0 = start_theta(observation)
    learner: Learner = make_learner(
        name,
        theta0,
        rng=learner_rng(seed, session) if rng is None else rng,
        bounds=bounds,
        **dict(options or {}),
    )
    thetas: list[np.ndarray] = []
    rs: list[np.ndarray] = []
    truths: list[np.ndarray] = []
    rewards: list[float] = []
    hit_at: int | None = None
    retry: np.ndarray | None = None
    terminated = truncated = False
    while not (terminated or truncated):
        proposal = learner.ask()  # asked even when a retry θ runs, as a session does
        theta = proposal if retry is None else retry
        _, reward, terminated, truncated, info = env.step(theta)
        shot = len(thetas) + 1
        sent = np.asarray(info.get("theta", theta), dtype=float)
        thetas.append(sent)
        rewards.append(float(reward))
        rs.append(_vector(info, "r", 2))
        truths.append(_vector(info, "r_true", 2))
        if on_step is not None:
            on_step(shot, dict(info))
        if hit_at is None and info.get("hit"):
            hit_at = shot
        retry = None
        if info.get("r") is None:  # no arrow on the face: back off, as a session does
            best = learner.best()[0] if learner.n_rollouts else None
            decision = after_abort(
                NO_ARROW,
                sent,
                best_theta=None if best is None else best.tolist(),
                theta0=theta0.tolist(),
                bounds=bounds,
                redraw=learner.redraw((seed, shot)),
            )
            if decision.failure is not None:
                break
            retry = np.array(decision.retry_theta)
        else:
            learner.tell(sent, rs[-1])
    return Episode(
        thetas=np.array(thetas).reshape(-1, 3),
        r=np.array(rs).reshape(-1, 2),
        r_true=np.array(truths).reshape(-1, 2),
        rewards=np.array(rewards),
        hit_at=hit_at,
        terminated=bool(terminated),
    )
