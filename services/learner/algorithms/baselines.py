"""Baselines under the same ask/tell protocol: CMA-ES (the `cma` package), a hill climber and
uniform random search."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from archery.protocol.text import shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.algorithms.base import (
    MAX_STD,
    Learner,
    RestoreError,
    _count_option,
    _finite_option,
    _std_option,
    in_range,
    rng_from_state,
    rng_state,
)

__all__ = ["HILL_STATE_MARK", "CmaEs", "HillClimber", "RandomSearch"]

# The extra state key only the hill climber saves: how a state it saved is told apart, also one
# saved when the hill climber was called "random" (see `registry.restore_learner`).
HILL_STATE_MARK = "std"


class CmaEs(Learner):
    """CMA-ES from the `cma` package, minimising −R = −exp(−‖r‖), one θ at a time.

    A generation of `popsize` candidates is asked from `cma` at once and handed out one per
    `ask()`; `cma` is told when `popsize` rollouts have been told. Its normal samples come from
    the injected generator. The state is the generator's initial state plus the sequence of
    proposals and updates: `load_state_dict` replays the history through a fresh `cma` instance,
    which reproduces its internal state exactly.

    Args:
        theta0: initial mean (m).
        rng: the random generator for sampling.
        bounds: θ box (m), also given to `cma`.
        sigma0: initial step size (m).
        popsize: candidates per generation; None for `cma`'s default 4 + ⌊3 ln d⌋.
    """

    algorithm = "cma"

    def __init__(
        self,
        theta0: np.ndarray,
        *,
        rng: np.random.Generator,
        bounds: ThetaBox = THETA_BOX,
        sigma0: float = 0.01,
        popsize: int | None = None,
    ) -> None:
        super().__init__(theta0, rng=rng, bounds=bounds)
        self.sigma0 = _finite_option("sigma0 (m)", sigma0, low=1e-9, high=MAX_STD)
        self.popsize = (
            4 + int(3 * np.log(self.theta0.size))
            if popsize is None
            else _count_option("popsize", popsize, low=2)
        )
        self.exploration_rollouts = self.popsize
        self._rng0 = rng_state(rng)
        self._build()

    def _build(self) -> None:
        import cma  # imported here: the package takes a second to import

        low, high = list(self.bounds.low), list(self.bounds.high)
        options = {
            "bounds": [low, high],
            "popsize": self.popsize,
            "randn": self._randn,
            "seed": float("nan"),  # no global seeding: samples come from self.rng
            "verbose": -9,
            "verb_disp": 0,
            "verb_log": 0,
            "tolfun": 0.0,
            "tolx": 0.0,
            "tolfunhist": 0.0,
            "tolflatfitness": 10**9,
            "tolstagnation": 10**9,
        }
        self._es = cma.CMAEvolutionStrategy(self.theta0.tolist(), self.sigma0, options)
        self._queue: list[np.ndarray] = []
        self._told_x: list[np.ndarray] = []
        self._told_f: list[float] = []
        self._events: list[str] = []

    def _randn(self, *shape: int) -> np.ndarray:
        """Standard normal samples of `shape` from the injected generator (for `cma`)."""
        return self.rng.standard_normal(shape)

    def options(self) -> dict[str, Any]:
        """Constructor options as plain values."""
        return {"sigma0": self.sigma0, "popsize": self.popsize}

    def _propose(self) -> np.ndarray:
        self._events.append("p")
        if not self._queue:
            self._queue = [np.array(x, dtype=float) for x in self._es.ask()]
        return self._queue.pop(0)

    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        self._events.append("u")
        self._told_x.append(theta)
        self._told_f.append(-big_return)  # cma minimises
        if len(self._told_x) == self.popsize:
            self._es.tell(self._told_x, self._told_f)
            self._told_x, self._told_f, self._queue = [], [], []

    def _extra_state(self) -> dict[str, Any]:
        return {"rng0": self._rng0, "events": "".join(self._events)}

    def _load_extra_state(self, extra: dict[str, Any]) -> None:
        try:
            rng0, events = extra["rng0"], str(extra["events"])
        except (KeyError, TypeError) as exc:
            raise RestoreError(f"CMA-ES state needs 'rng0' and 'events': {exc}") from exc
        # One 'p' per proposal: at most one per told rollout, and the pending one.
        if (
            set(events) - {"p", "u"}
            or events.count("u") != self.n_rollouts
            or events.count("p") > self.n_rollouts + 1
        ):
            raise RestoreError(
                f"CMA-ES events must be 'p'/'u' letters, one 'u' per told rollout "
                f"({self.n_rollouts}) and at most one 'p' more, got {shown(events, 60)}"
            )
        saved_final, pending = rng_state(self.rng), self._pending
        self.rng, self._rng0 = rng_from_state(rng0), rng0
        self._build()
        told = iter(zip(self._thetas, self._rewards, self._returns, strict=True))
        for event in events:
            if event == "p":
                self._propose()
            else:
                self._update(*next(told))
        if rng_state(self.rng) != saved_final:
            raise RestoreError(
                "replaying the CMA-ES history did not reproduce the saved generator state "
                "(was it saved by another version of the cma package?)"
            )
        self._pending = pending


class HillClimber(Learner):
    """A stochastic hill climber: each θ is the best θ so far plus N(0, std²) noise per component.

    Earlier versions called it "random"; that name is now the uniform `RandomSearch`.

    Args:
        theta0: the starting point, used until a rollout has been told (m).
        rng: the random generator.
        bounds: θ box (m).
        explore_std: initial std of the perturbation (m), one for all θ components or one each.
        decay: factor applied to the variance after each rollout (1 keeps it fixed).
    """

    algorithm = "hill"

    def __init__(
        self,
        theta0: np.ndarray,
        *,
        rng: np.random.Generator,
        bounds: ThetaBox = THETA_BOX,
        explore_std: float | Sequence[float] = 0.0075,
        decay: float = 1.0,
    ) -> None:
        super().__init__(theta0, rng=rng, bounds=bounds)
        self.explore_std = _std_option("explore_std (m)", explore_std, self.theta0.size)
        self.decay = _finite_option("decay", decay, low=1e-6, high=1.0)
        self.std = self.explore_std.copy()

    def options(self) -> dict[str, Any]:
        """Constructor options as plain values."""
        return {"explore_std": self.explore_std.tolist(), "decay": self.decay}

    def _propose(self) -> np.ndarray:
        centre = self.best()[0] if self.n_rollouts else self.theta0
        return centre + self.std * self.rng.standard_normal(centre.size)

    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        self.std = self.std * np.sqrt(self.decay)

    def _extra_state(self) -> dict[str, Any]:
        return {HILL_STATE_MARK: self.std.tolist()}

    def _load_extra_state(self, extra: dict[str, Any]) -> None:
        try:
            std = np.array(extra[HILL_STATE_MARK], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise RestoreError(f"hill-climber state needs 'std' (m): {exc}") from exc
        if std.shape != self.theta0.shape:
            raise RestoreError(f"hill-climber 'std' must have {self.theta0.size} components")
        if not in_range(std, 0.0, MAX_STD):
            raise RestoreError(
                f"hill-climber 'std' {shown(extra[HILL_STATE_MARK])} m is outside [0, {MAX_STD}]"
            )
        self.std = std


class RandomSearch(Learner):
    """Uniform random search: every θ is drawn uniformly in the θ bounds, independent of the
    rewards (a floor that any learner must beat; it ignores θ0).

    The state is the history and the generator: a restored learner draws the same θ next.

    Args:
        theta0: the start θ (m); only checked against the bounds, never proposed.
        rng: the random generator.
        bounds: θ box (m) that θ is drawn from.
    """

    algorithm = "random"

    def options(self) -> dict[str, Any]:
        """Constructor options as plain values (none beyond θ0, the generator and the bounds)."""
        return {}

    def _propose(self) -> np.ndarray:
        return self.rng.uniform(self.bounds.low, self.bounds.high)

    def redraw(self, key: Sequence[int]) -> np.ndarray:
        """After a θ that missed the target, another uniform draw in the bounds (m), from a
        generator seeded by `key`: backing off towards the best θ, as the other learners do,
        would make this baseline a local search."""
        return np.random.default_rng(list(key)).uniform(self.bounds.low, self.bounds.high)

    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        """Nothing to learn: the next θ does not depend on the rewards."""
