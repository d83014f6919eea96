"""`archery/Aim-v0`: the paper's analytic world (`sim.ballistic`) as a Gymnasium environment.

The details: `AimEnv`'s docstring."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, cast

import gymnasium as gym
import numpy as np

from archery.apps.experiment.config import WindChange
from archery.apps.gym.keywords import (
    flag,
    keyword_errors,
    make_keywords,
    number,
    refuse_unknown,
    reset_options,
)
from archery.apps.gym.registration import AIM_ID
from archery.apps.gym.spaces import action_space, checked_action, observation, observation_space
from archery.protocol.text import cut, shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.protocol.vectors import finite_vector
from archery.sim.ballistic import BallisticWorld, Scenario, ScenarioError
from archery.sim.geometry import INNER_RING_RADIUS

__all__ = ["DEFAULT_BUDGET", "KEYWORDS", "AimEnv", "episode_budget", "session_of", "wind_change_of"]

DEFAULT_BUDGET = 60  # shots per episode, as the paper's sessions


def _bounds(bounds: object) -> ThetaBox:
    """The `bounds` keyword: None (`THETA_BOX`), a `ThetaBox` or (low, high) in m.

    Raises:
        ValueError: anything else, named.
    """
    if bounds is None:
        return THETA_BOX
    if isinstance(bounds, ThetaBox):
        return bounds
    try:
        low, high = cast(tuple[Sequence[float], Sequence[float]], bounds)
        return ThetaBox(low=list(low), high=list(high))
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"bounds must be (low, high) θ vectors (m) or a ThetaBox, got {shown(bounds)}: "
            f"{cut(str(exc))}"
        ) from None


def episode_budget(budget: object) -> int:
    """`budget` (shots per episode) checked: an integer >= 1.

    Raises:
        ValueError: it is not one.
    """
    if isinstance(budget, bool) or not isinstance(budget, int | np.integer) or budget < 1:
        raise ValueError(f"budget must be an integer >= 1 (shots per episode), got {shown(budget)}")
    return int(budget)


def session_of(options: dict[str, Any] | None) -> int:
    """The session K of `reset(options={"session": K})` (0 without one).

    Raises:
        ValueError: K is not an integer >= 0.
    """
    session = (options or {}).get("session", 0)
    if isinstance(session, bool) or not isinstance(session, int | np.integer) or session < 0:
        raise ValueError(f"options['session'] must be an integer >= 0, got {shown(session)}")
    return int(session)


def wind_change_of(value: object, budget: int) -> WindChange | None:
    """A `wind_change` keyword (`"AT:VX,VY,VZ"`, `(AT, (VX, VY, VZ))`, a `WindChange` or None)
    checked against the episode's budget: AT in [2, budget], the wind in m/s.

    Raises:
        ValueError: malformed, or AT outside the budget.
    """
    if value is None or isinstance(value, WindChange):
        change = value
    elif isinstance(value, str):
        change = WindChange.parse(value)
    else:
        try:
            at, wind = cast(tuple[int, Sequence[float]], value)
            vx, vy, vz = (float(w) for w in wind)
            change = WindChange(int(at), (vx, vy, vz))
        except (TypeError, ValueError):
            raise ValueError(
                f"wind_change must be 'AT:VX,VY,VZ' or (AT, (VX, VY, VZ)), got {shown(value)}"
            ) from None
    if change is not None and not 2 <= change.at <= budget:
        raise ValueError(f"wind_change shot {change.at} must be in [2, {budget}] (the budget)")
    return change


class AimEnv(gym.Env[np.ndarray, np.ndarray]):
    """The analytic archery range: shoot θ (m), observe r (m).

    Args:
        distance, wind, drag, noise, bow_stiffness, start: the scenario (`sim.ballistic.Scenario`,
            the units of `archery experiment`'s flags); None keeps its default.
        wind_change: the wind from a shot of the episode on (None: no change).
        budget: shots per episode before it is truncated.
        until_hit: end the episode at the first hit (`terminated`).
        bounds: the θ box (m, `(low, high)` or a `protocol.theta.ThetaBox`); default
            `protocol.theta.THETA_BOX`, the controller's, as `archery experiment`'s.
        render_mode: None (nothing to render).

    Raises:
        ValueError (`sim.ballistic.ScenarioError` for the scenario's ranges): a bad or unknown
            keyword, named, in at most `apps.gym.keywords.MESSAGE_LIMIT` characters.

    One step is one shot: the action θ (m, `apps.gym.spaces`) is shot at the target and the
    observation is where it landed (r, m) and the θ shot; the reward is −‖r‖ (m). Every scenario
    option of `archery experiment` is a `make` keyword of the same name and unit: `distance` (m),
    `wind` (m/s, root frame), `drag` (1/m), `noise` (m, the std of the observation noise on r),
    `bow_stiffness` (N/m), `start` (θ at the start of an episode, m) and `wind_change`
    (`"AT:VX,VY,VZ"` or `(AT, (VX, VY, VZ))`: the wind from the episode's shot AT on, m/s).

    An episode ends at a hit, the true ‖r‖ under the innermost ring's 5 cm as `archery experiment`
    counts it (`terminated`; `until_hit=False`: never), or after `budget` shots (`truncated`,
    default 60). `reset(seed=S, options={"session": K})` seeds the observation noise exactly as
    `archery experiment --seed S` seeds its session K (K defaults to 0), so an episode is
    reproduced bit for bit and the project's learners given the experiment's learner seed
    (`apps.gym.agent`) shoot exactly the rollouts of the experiment.

    `info` after a step: `r` (m, observed), `distance` (‖r‖, m), `hit`, `theta` (the θ shot, m),
    `theta_measured` (the same here: the analytic world has no arms), `confidence` (1.0: r needs no
    detection here), `clipped` (the action lay outside the box and was clipped), `shots` (this
    episode's), and the ground truth `r_true` and `true_distance` (m).

    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (Gymnasium's class attribute)

    def __init__(
        self,
        *,
        distance: float | None = None,
        wind: Sequence[float] | None = None,
        drag: float | None = None,
        noise: float | None = None,
        bow_stiffness: float | None = None,
        start: Sequence[float] | None = None,
        wind_change: object = None,
        budget: int = DEFAULT_BUDGET,
        until_hit: bool = True,
        bounds: ThetaBox | tuple[Sequence[float], Sequence[float]] | None = None,
        render_mode: str | None = None,
        **unknown: object,
    ) -> None:
        with keyword_errors():
            refuse_unknown(AIM_ID, unknown, KEYWORDS)
            if render_mode is not None:
                raise ValueError(
                    f"{AIM_ID} renders nothing: render_mode must be None, got {shown(render_mode)}"
                )
            self._check(distance, wind, drag, noise, bow_stiffness, start, budget, until_hit)
            self.wind_change = wind_change_of(wind_change, self.budget)
            self.bounds = _bounds(bounds)
        if not self.bounds.contains(self.scenario.start):
            raise ScenarioError(self.bounds.outside("start θ", self.scenario.start), "start")
        self.world = BallisticWorld(self.scenario)
        changed = self.world
        if self.wind_change is not None:
            changed = BallisticWorld(replace(self.scenario, wind=self.wind_change.wind))
        self._changed = changed
        self.action_space: gym.spaces.Box = action_space(self.bounds)
        self.observation_space: gym.spaces.Box = observation_space(self.bounds)
        self.render_mode = render_mode
        self._start = np.array(self.scenario.start, dtype=np.float64)
        self._shots = 0
        self._seeded = False
        self._obs = observation(np.zeros(2), self._start)

    def _check(
        self,
        distance: object,
        wind: object,
        drag: object,
        noise: object,
        bow_stiffness: object,
        start: object,
        budget: object,
        until_hit: object,
    ) -> None:
        """The scenario's keywords checked (named, bounded messages), `scenario`, `budget` and
        `until_hit` set."""
        given = {
            name: number(name, value, unit)
            for name, value, unit in (
                ("distance", distance, "m"),
                ("drag", drag, "1/m"),
                ("noise", noise, "m"),
                ("bow_stiffness", bow_stiffness, "N/m"),
            )
            if value is not None
        }
        vectors = {
            name: tuple(finite_vector(name, value, ValueError, unit=unit).tolist())
            for name, value, unit in (("wind", wind, "m/s"), ("start", start, "m"))
            if value is not None
        }
        self.scenario = Scenario(**given, **vectors)  # type: ignore[arg-type]
        self.budget = episode_budget(budget)
        self.until_hit = flag("until_hit", until_hit)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode: no shot yet, θ at the start; with `seed` (and `options["session"]`),
        the observation noise of `archery experiment --seed SEED`'s session.

        Raises:
            ValueError: options other than None or `{"session": K}`, K an integer >= 0.
        """
        session = session_of(reset_options(AIM_ID, options, ("session",)))
        super().reset(seed=seed)
        if seed is not None or not self._seeded:
            master = seed if seed is not None else int(self.np_random.integers(2**63))
            self.world.reset(np.random.SeedSequence(master, spawn_key=(session, 0)))
            self._seeded = True
        self._shots = 0
        self._obs = observation(np.zeros(2), self._start)
        return self._obs.copy(), {"shots": 0, "theta": self._start.copy()}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Shoot θ = `action` (m, clipped into the box).

        Raises:
            BadAction: the action holds a NaN or an infinity, or is not 3 numbers (Gymnasium's
                `InvalidAction`, a ValueError).
        """
        theta, clipped = checked_action(action, self.action_space)
        self._shots += 1
        changed = self.wind_change is not None and self._shots >= self.wind_change.at
        impacts = (self._changed if changed else self.world).impacts(theta.reshape(1, -1))
        r_true = impacts.r[0]
        r = self.world.observe(r_true)
        distance = math.hypot(float(r[0]), float(r[1]))
        true_distance = math.hypot(float(r_true[0]), float(r_true[1]))
        hit = true_distance < INNER_RING_RADIUS
        self._obs = observation(r, theta)
        info = {
            "r": r.copy(),
            "distance": distance,
            "hit": hit,
            "theta": theta.copy(),
            "theta_measured": theta.copy(),
            "confidence": 1.0,
            "clipped": clipped,
            "shots": self._shots,
            "r_true": r_true.copy(),
            "true_distance": true_distance,
        }
        terminated = self.until_hit and hit
        truncated = not terminated and self._shots >= self.budget
        return self._obs.copy(), -distance, terminated, truncated, info


#: `AimEnv`'s `make` keywords: its constructor's.
KEYWORDS = make_keywords(AimEnv)
