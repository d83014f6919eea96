"""Where θ puts the arrow, as a learner's physics model predicts it.

`ImpactModel` is what `ArcherPrior` needs of a model: inject any (a test's linear model, a
lab's fitted one). A `PhysicalModel` also names physical parameters of the world (a range, the
air) that the learner fits to its rollouts. `BallisticModel` is the default: the analytic
ballistic model of `sim.ballistic` with nominal parameters, which the registry
(`registry.make_learner`, `registry.restore_learner`) builds from a learner's `model_*`
options. θ is in m, r in m on the target plane (right, up).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from archery.services.learner.algorithms.base import LearnerConfigError, _finite_option
from archery.sim.ballistic import MAX_WIND, BallisticError, BallisticWorld, Scenario
from archery.sim.bow import Bow
from archery.sim.geometry import BOW_HAND, TARGET_DISTANCE

__all__ = ["MODEL_DT", "BallisticModel", "ImpactModel", "PhysicalModel"]

MODEL_DT = 0.04  # s, RK4 step of the model's flights with drag (≈ 1 µm off a 2 ms step at 5 m)
_MAX_DRAG = 10.0  # 1/m, the ballistic world's own limit
_CACHED_WORLDS = 64  # worlds kept per model (the fitted one and a fit's trial parameters)


class ImpactModel(Protocol):
    """A model of where θ puts the arrow."""

    def impacts(self, thetas: np.ndarray) -> np.ndarray:
        """r (m) on the target plane, one row (right, up) per row θ (m) of `thetas` (n, 3).

        Raises:
            ValueError: a θ cannot be shot, or its arrow never reaches the target plane.
        """

    def options(self) -> dict[str, Any]:
        """The settings that rebuild this model, saved among the learner's options (plain
        values, named apart from the learner's own; {} for a model the registry cannot
        rebuild, which must then be passed again to restore the learner)."""


@runtime_checkable
class PhysicalModel(ImpactModel, Protocol):
    """An `ImpactModel` of a world described by physical parameters p, with a Gaussian prior
    on each (its nominal value and a std; a std of 0 holds it fixed), that a learner fits to
    where its arrows landed."""

    def nominal(self) -> np.ndarray:
        """The prior mean of p (the parameters `impacts` assumes)."""

    def parameter_std(self) -> np.ndarray:
        """The prior std of each entry of p, in its unit (0: held at its nominal value)."""

    def parameter_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of p: the values the model can shoot with."""

    def impacts_at(self, thetas: np.ndarray, params: np.ndarray) -> np.ndarray:
        """`impacts` of the world with the parameters `params` (p) instead of the nominal ones.

        Raises:
            ValueError: a θ cannot be shot, or its arrow never reaches the target plane.
        """


@dataclass(frozen=True)
class BallisticModel:
    """The analytic ballistic model (`sim.ballistic`) of a nominal world: the target at
    `distance` (m), a bow of `stiffness` (N/m), air drag `drag` (1/m), no wind, no noise.

    Its physical parameters p (a `PhysicalModel`) are (range (m), drag (1/m), side wind (m/s),
    bow stiffness (N/m)), the causes of a miss: vertical ones (how far the target is, how much
    the air slows the arrow, how fast the bow shoots) and a lateral one (a wind across the range,
    which acts through the drag). Their prior, centred on (distance, drag, 0, stiffness) with
    the stds `distance_std`, `drag_std`, `wind_std` and `stiffness_std` (a std of 0 holds that
    parameter fixed), is the range of worlds the learner is built for; by default targets at
    about 1 to 6 m, drag up to about 0.1/m, winds of a few m/s and a bow within about ±20 %.
    One shot tells two numbers, so where several causes explain a miss alike the prior picks
    the mix, and the second shot is as good as that mix is near the world's.

    Raises:
        LearnerConfigError: a parameter is not finite, out of range, or gives no world.
    """

    distance: float = TARGET_DISTANCE
    stiffness: float = Bow().stiffness
    drag: float = 0.0
    distance_std: float = 2.0
    drag_std: float = 0.05
    wind_std: float = 5.0
    stiffness_std: float = 60.0
    _world: BallisticWorld = field(init=False, repr=False, compare=False)
    _worlds: dict[tuple[float, ...], BallisticWorld] = field(
        init=False, repr=False, compare=False, default_factory=dict
    )

    #: The learner options that name the parameters (what `options` gives, `from_options` takes).
    OPTIONS = (
        "model_distance",
        "model_stiffness",
        "model_drag",
        "model_distance_std",
        "model_drag_std",
        "model_wind_std",
        "model_stiffness_std",
    )
    #: The options every saved learner has; learners saved before the fitted parameters had
    #: no std options, and their parameters stay fixed.
    NOMINAL_OPTIONS = OPTIONS[:3]
    STD_OPTIONS = OPTIONS[3:]

    def __post_init__(self) -> None:
        for name, low, unit in (
            ("distance", 0.0, "m"),
            ("stiffness", 1e-6, "N/m"),
            ("drag", 0.0, "1/m"),
            ("distance_std", 0.0, "m"),
            ("drag_std", 0.0, "1/m"),
            ("wind_std", 0.0, "m/s"),
            ("stiffness_std", 0.0, "N/m"),
        ):
            value = _finite_option(f"model_{name} ({unit})", getattr(self, name), low=low)
            object.__setattr__(self, name, value)
        try:
            world = self._world_at(self.nominal())
        except BallisticError as exc:
            raise LearnerConfigError(f"invalid nominal model: {exc}") from exc
        object.__setattr__(self, "_world", world)

    @classmethod
    def from_options(cls, **options: float) -> BallisticModel:
        """The model of the learner options `model_distance` (m), `model_stiffness` (N/m),
        `model_drag` (1/m) and the prior stds `model_distance_std` (m), `model_drag_std` (1/m),
        `model_wind_std` (m/s), `model_stiffness_std` (N/m); a missing one keeps its default."""
        names = {k: k.removeprefix("model_") for k in cls.OPTIONS}
        return cls(**{names[k]: v for k, v in options.items()})

    def impacts(self, thetas: np.ndarray) -> np.ndarray:
        """r (m) of each θ row (m); raises `sim.ballistic.BallisticError` (a ValueError) where
        a θ cannot be shot."""
        return self._world.impacts(thetas).r

    def nominal(self) -> np.ndarray:
        """p of the nominal world: (distance (m), drag (1/m), 0 m/s of side wind, stiffness
        (N/m))."""
        return np.array([self.distance, self.drag, 0.0, self.stiffness])

    def parameter_std(self) -> np.ndarray:
        """(distance_std (m), drag_std (1/m), wind_std (m/s), stiffness_std (N/m))."""
        return np.array([self.distance_std, self.drag_std, self.wind_std, self.stiffness_std])

    def parameter_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The ballistic world's limits: the target beyond the bow hand, drag ≤ 10/m, wind ≤
        50 m/s, a bow of 1 to 1e5 N/m."""
        nearest = -float(BOW_HAND[0]) + 0.1
        return np.array([nearest, 0.0, -MAX_WIND, 1.0]), np.array([100.0, _MAX_DRAG, MAX_WIND, 1e5])

    def impacts_at(self, thetas: np.ndarray, params: np.ndarray) -> np.ndarray:
        """r (m) of each θ row (m) in the world of p = `params`; raises a ValueError where a θ
        cannot be shot or p gives no world."""
        return self._world_at(np.asarray(params, dtype=float)).impacts(thetas).r

    def options(self) -> dict[str, Any]:
        """{model_distance (m), model_stiffness (N/m), model_drag (1/m), model_distance_std (m),
        model_drag_std (1/m), model_wind_std (m/s), model_stiffness_std (N/m)}."""
        values = (
            self.distance,
            self.stiffness,
            self.drag,
            self.distance_std,
            self.drag_std,
            self.wind_std,
            self.stiffness_std,
        )
        return dict(zip(self.OPTIONS, values, strict=True))

    def _world_at(self, params: np.ndarray) -> BallisticWorld:
        key = tuple(float(v) for v in params)
        world = self._worlds.get(key)
        if world is None:
            if len(self._worlds) >= _CACHED_WORLDS:
                self._worlds.clear()
            world = self._worlds[key] = self._new_world(*key)
        return world

    def _new_world(
        self, distance: float, drag: float, wind: float, stiffness: float
    ) -> BallisticWorld:
        scenario = Scenario(
            distance=distance,
            bow_stiffness=stiffness,
            drag=drag,
            wind=(0.0, wind if drag > 0 else 0.0, 0.0),
        )
        return BallisticWorld(scenario, dt=MODEL_DT)
