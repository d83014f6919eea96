"""The learners by name: what `--algo` accepts, building a learner and restoring a saved one."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import msgspec
import numpy as np

from archery.protocol.text import cut, shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.algorithms.archer import Archer
from archery.services.learner.algorithms.base import (
    Learner,
    LearnerConfigError,
    RestoreError,
)
from archery.services.learner.algorithms.baselines import (
    HILL_STATE_MARK,
    CmaEs,
    HillClimber,
    RandomSearch,
)
from archery.services.learner.algorithms.impact_model import BallisticModel, ImpactModel
from archery.services.learner.algorithms.power import Power
from archery.services.learner.algorithms.prior import ArcherPrior

__all__ = [
    "ALGORITHMS",
    "LEARNER_CLASSES",
    "TRANSFER_ALGORITHMS",
    "Algorithm",
    "check_transfer",
    "make_learner",
    "restore_learner",
    "transferred_learner",
]


@dataclass(frozen=True)
class Algorithm:
    """A named learner configuration.

    Attributes:
        name: the name `--algo` accepts.
        cls: the learner class.
        options: constructor options on top of the class defaults.
        label: a short label for tables and figures.
    """

    name: str
    cls: type[Learner]
    label: str
    options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))


# archer: the default, safeguarded, exploring the draw (θ_x) 4x less than the aim (5 vs 20 mm);
# archer-plain: the paper's algorithm with the same exploration; the -iso variants explore 20 mm
# on every component; archer-ridge: the footnote's ridge regression. power: the paper's Eq. 1-4
# with the authors' σ = 3 and decay 0.965, importance weights exp(−‖r‖/5 cm) (why: `Power`);
# power-metre: the same with ‖r‖ in metres, exp(−‖r‖/1 m). hill: best θ so far + noise (called
# "random" before); random: uniform in the θ box.
# archer-recent: ARCHER regressing on the N best of the 4 most recent rollouts (forgets a changed
# world); archer-prior: the ballistic model, its range, air and bow fitted to the rollouts, aims
# and a Bayesian residual corrects it.
ALGORITHMS: Mapping[str, Algorithm] = MappingProxyType(
    {
        a.name: a
        for a in (
            Algorithm("archer", Archer, "ARCHER (safeguarded)"),
            Algorithm(
                "archer-plain", Archer, "ARCHER (paper)", MappingProxyType({"safeguard": False})
            ),
            Algorithm(
                "archer-iso",
                Archer,
                "ARCHER (safeguarded, isotropic exploration)",
                MappingProxyType({"explore_std": 0.02}),
            ),
            Algorithm(
                "archer-plain-iso",
                Archer,
                "ARCHER (paper, isotropic exploration)",
                MappingProxyType({"safeguard": False, "explore_std": 0.02}),
            ),
            Algorithm(
                "archer-ridge",
                Archer,
                "ARCHER (ridge λ=1e-3 m²)",
                MappingProxyType({"safeguard": False, "ridge": 1e-3}),
            ),
            Algorithm(
                "archer-recent",
                Archer,
                "ARCHER (safeguarded, N best of the 4 most recent)",
                MappingProxyType({"window": 4}),
            ),
            Algorithm("archer-prior", ArcherPrior, "ARCHER with the ballistic prior"),
            Algorithm("power", Power, "PoWER"),
            Algorithm(
                "power-metre",
                Power,
                "PoWER (R = exp(−‖r‖/1 m))",
                MappingProxyType({"return_scale": 1.0}),
            ),
            Algorithm("cma", CmaEs, "CMA-ES"),
            Algorithm("hill", HillClimber, "hill climber (best θ + noise)"),
            Algorithm("random", RandomSearch, "random search (uniform in the θ box)"),
        )
    }
)

LEARNER_CLASSES: Mapping[str, type[Learner]] = MappingProxyType(
    {cls.algorithm: cls for cls in (Archer, ArcherPrior, Power, CmaEs, HillClimber, RandomSearch)}
)

# The algorithms that can start from another session's learned model (`Learner.seed_from`).
TRANSFER_ALGORITHMS = tuple(name for name, a in ALGORITHMS.items() if a.cls.transferable)


def check_transfer(name: str, flag: str = "--from") -> None:
    """Refuse, in one line, to start `name` from another session if it cannot.

    Raises:
        LearnerConfigError: `name` cannot transfer.
    """
    if name not in TRANSFER_ALGORITHMS:
        raise LearnerConfigError(
            f"{flag}: {name} cannot start from another session; the algorithms that can: "
            f"{', '.join(TRANSFER_ALGORITHMS)}"
        )


def _build(
    cls: type[Learner],
    theta0: np.ndarray,
    rng: np.random.Generator,
    bounds: ThetaBox,
    options: Mapping[str, Any],
    model: ImpactModel | None,
    *,
    saved: bool = False,
) -> Learner:
    """`cls` built with `options`. A learner that aims with a physics model (`ArcherPrior`) gets
    `model`, or by default the nominal ballistic model its `model_*` options describe
    (`BallisticModel`); restoring a `saved` learner whose options do not describe one needs
    its `model` again.

    Raises:
        LearnerConfigError: an invalid option or model, a model with its options, a model for a
            learner without one, or a saved learner's own model missing.
        TypeError: an option `cls` does not take.
    """
    options = dict(options)
    if issubclass(cls, ArcherPrior):
        described = {k: options.pop(k) for k in BallisticModel.OPTIONS if k in options}
        if model is not None and described:
            raise LearnerConfigError(
                f"give {cls.algorithm} a model or the options {', '.join(described)}, not both"
            )
        if model is None and saved:
            if any(k not in described for k in BallisticModel.NOMINAL_OPTIONS):
                raise LearnerConfigError(
                    f"this {cls.algorithm} learner aimed with a model of its own (its options do "
                    f"not describe the nominal one): pass that model to restore it"
                )
            # Saved before the model's physical parameters were fitted: they stay fixed.
            described = {k: 0.0 for k in BallisticModel.STD_OPTIONS} | described
        options["model"] = BallisticModel.from_options(**described) if model is None else model
    elif model is not None:
        raise LearnerConfigError(f"{cls.algorithm} aims with no physics model")
    return cls(theta0, rng=rng, bounds=bounds, **options)


def make_learner(
    name: str,
    theta0: np.ndarray,
    *,
    rng: np.random.Generator,
    bounds: ThetaBox = THETA_BOX,
    model: ImpactModel | None = None,
    **options: Any,
) -> Learner:
    """Build the learner `name` (a key of ALGORITHMS); `options` override its settings.

    `model` is the physics an `archer-prior` learner aims with; by default the registry builds
    the nominal ballistic model (`impact_model.BallisticModel`) from its `model_distance` (m),
    `model_stiffness` (N/m) and `model_drag` (1/m) options, with the prior stds of the fitted
    range, drag, side wind and bow `model_distance_std` (m), `model_drag_std` (1/m),
    `model_wind_std` (m/s) and `model_stiffness_std` (N/m).

    Raises:
        LearnerConfigError: unknown name, invalid option or model.
    """
    if name not in ALGORITHMS:
        raise LearnerConfigError(
            f"unknown algorithm {shown(name)}; valid algorithms: {', '.join(ALGORITHMS)}"
        )
    algorithm = ALGORITHMS[name]
    merged = {**algorithm.options, **options}
    try:
        return _build(algorithm.cls, theta0, rng, bounds, merged, model)
    except TypeError as exc:
        raise LearnerConfigError(f"invalid option for {name!r}: {cut(str(exc))}") from exc


def _check_not_old_random(state: Mapping[str, Any]) -> None:
    """Refuse a state saved when "random" named the hill climber (now `hill`).

    Such a state (algorithm "random" with the hill climber's step size in its extra state) is
    not mapped to `hill`: its journal's header and options also say "random", so a resumed
    session would run under a name that now means another algorithm. The error says so, and
    that the earlier version that wrote it can finish it.

    Raises:
        RestoreError: it is such a state.
    """
    extra = state.get("extra")
    hill_extra = isinstance(extra, Mapping) and HILL_STATE_MARK in extra
    if state.get("algorithm") == "random" and hill_extra:
        raise RestoreError(
            "this learner state was saved when 'random' named the hill climber (best θ so far "
            "+ noise), which is now 'hill'; 'random' is now uniform search, so it is not resumed "
            "as either: finish it with the version that wrote it, or start a new 'hill' session"
        )


def restore_learner(state: Mapping[str, Any], *, model: ImpactModel | None = None) -> Learner:
    """Rebuild a learner from `Learner.state_dict()`; its next proposal equals the saved one's.

    `model`: the physics model an `archer-prior` learner aimed with, when it was not the nominal
    one its options describe (which is rebuilt by default). A state of the old "random" (the
    hill climber before it was renamed `hill`) is refused with a clear error, never restored as
    another algorithm (`_check_not_old_random`).

    Raises:
        RestoreError: the state is malformed, names an unknown algorithm, or is an old "random".
    """
    if not isinstance(state, Mapping):
        raise RestoreError(f"a learner state must be a dict, got {type(state).__name__}")
    _check_not_old_random(state)
    algorithm = state.get("algorithm")
    if algorithm not in LEARNER_CLASSES:
        raise RestoreError(
            f"learner state names algorithm {algorithm!r}; known: {', '.join(LEARNER_CLASSES)}"
        )
    assert isinstance(algorithm, str)  # one of LEARNER_CLASSES' names
    try:
        learner = _build(
            LEARNER_CLASSES[algorithm],
            np.asarray(state["theta0"], dtype=float),
            np.random.default_rng(0),  # replaced by the saved generator below
            msgspec.convert(state["bounds"], ThetaBox),
            dict(state["options"]),
            model,
            saved=True,
        )
    except (KeyError, TypeError, msgspec.ValidationError, LearnerConfigError) as exc:
        raise RestoreError(f"learner state cannot rebuild a {algorithm!r} learner: {exc}") from exc
    learner.load_state_dict(dict(state))
    return learner


def transferred_learner(learner: Learner, source_state: Mapping[str, Any]) -> Learner:
    """`learner` (fresh) seeded with what the saved learner `source_state` learned.

    Raises:
        RestoreError: the source state is malformed, of another algorithm, or cannot seed it.
    """
    if source_state.get("algorithm") != learner.algorithm:
        raise RestoreError(
            f"the source learner is {source_state.get('algorithm')!r}, not {learner.algorithm!r}"
        )
    source = restore_learner(source_state)
    try:
        learner.seed_from(source)
    except LearnerConfigError as exc:
        raise RestoreError(f"cannot start from the source learner: {exc}") from None
    return learner
