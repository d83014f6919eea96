"""Where θ puts the arrow, as a learner's physics model predicts it.

`ImpactModel` is what `ArcherPrior` needs of a model: inject any (a test's linear model, a
lab's fitted one). `BallisticModel` is the default: the analytic ballistic model of
`sim.ballistic` with nominal parameters, which the registry (`registry.make_learner`,
`registry.restore_learner`) builds from a learner's `model_*` options. θ is in m, r in m on the
target plane (right, up).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from services.learner.algorithms.base import LearnerConfigError, _finite_option
from sim.ballistic import BallisticError, BallisticWorld, Scenario
from sim.bow import Bow
from sim.geometry import TARGET_DISTANCE

__all__ = ["BallisticModel", "ImpactModel"]


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


@dataclass(frozen=True)
class BallisticModel:
    """The analytic ballistic model (`sim.ballistic`) of a nominal world: the target at
    `distance` (m), a bow of `stiffness` (N/m), air drag `drag` (1/m), no wind, no noise.

    Raises:
        LearnerConfigError: a parameter is not finite, out of range, or gives no world.
    """

    distance: float = TARGET_DISTANCE
    stiffness: float = Bow().stiffness
    drag: float = 0.0
    _world: BallisticWorld = field(init=False, repr=False, compare=False)

    #: The learner options that name the parameters (what `options` gives, `from_options` takes).
    OPTIONS = ("model_distance", "model_stiffness", "model_drag")

    def __post_init__(self) -> None:
        for name, low, unit in (
            ("distance", 0.0, "m"),
            ("stiffness", 1e-6, "N/m"),
            ("drag", 0.0, "1/m"),
        ):
            value = _finite_option(f"model_{name} ({unit})", getattr(self, name), low=low)
            object.__setattr__(self, name, value)
        try:
            world = BallisticWorld(
                Scenario(distance=self.distance, bow_stiffness=self.stiffness, drag=self.drag)
            )
        except BallisticError as exc:
            raise LearnerConfigError(f"invalid nominal model: {exc}") from exc
        object.__setattr__(self, "_world", world)

    @classmethod
    def from_options(cls, **options: float) -> BallisticModel:
        """The model of the learner options `model_distance` (m), `model_stiffness` (N/m) and
        `model_drag` (1/m); a missing one keeps its nominal value."""
        names = dict(zip(cls.OPTIONS, ("distance", "stiffness", "drag"), strict=True))
        return cls(**{names[k]: v for k, v in options.items()})

    def impacts(self, thetas: np.ndarray) -> np.ndarray:
        """r (m) of each θ row (m); raises `sim.ballistic.BallisticError` (a ValueError) where
        a θ cannot be shot."""
        return self._world.impacts(thetas).r

    def options(self) -> dict[str, Any]:
        """{model_distance (m), model_stiffness (N/m), model_drag (1/m)}."""
        return dict(zip(self.OPTIONS, (self.distance, self.stiffness, self.drag), strict=True))
