"""The experiment's config and results, shared by both worlds (the ballistic model here, the
robots of a fleet in `apps.experiment.experiment_mesh`) and by the figures: which learners, how
many sessions and rollouts, the scenario, a wind change, a transfer, and what each run gave."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.protocol.vectors import parse_vector
from archery.protocol.verbs.learner import MAX_ROLLOUTS
from archery.services.learner.algorithms.base import Learner, LearnerError
from archery.services.learner.algorithms.power import Power
from archery.services.learner.algorithms.registry import (
    ALGORITHMS,
    check_transfer,
    make_learner,
    transferred_learner,
)
from archery.sim.ballistic import Scenario
from archery.sim.geometry import INNER_RING_RADIUS

__all__ = [
    "CURVE_COLUMNS",
    "DEFAULT_ALGORITHMS",
    "LEARNERS_NAME",
    "LEARNERS_VERSION",
    "WORLDS",
    "AlgorithmRun",
    "ExperimentConfig",
    "ExperimentError",
    "Transfer",
    "WindChange",
    "number",
]


DEFAULT_ALGORITHMS = ("archer", "power", "cma", "hill", "random")
# curves.csv: θ (m), the observed and the true reward vector (m), the true distance ‖r‖ (m).
CURVE_COLUMNS = (
    "algorithm",
    "session",
    "rollout",
    "theta_x",
    "theta_y",
    "theta_z",
    "r_x",
    "r_y",
    "r_true_x",
    "r_true_y",
    "distance",
)
WORLDS = ("ballistic", "mesh")  # mesh: the MuJoCo iCubs of a fleet (experiment_mesh)
LEARNERS_NAME = "learners.json"  # the final learner states of a run, what --from reads
LEARNERS_VERSION = 1


class ExperimentError(LearnerError):
    """An invalid experiment setting (world, algorithm list, budget, start θ)."""


@dataclass(frozen=True)
class WindChange:
    """The wind becomes `wind` (m/s, root frame) from rollout `at` (1-based) on."""

    at: int
    wind: tuple[float, float, float]

    @classmethod
    def parse(cls, text: str) -> WindChange:
        """`AT:VX,VY,VZ`, e.g. `20:0,-3,0`.

        Raises:
            ExperimentError: malformed text.
        """
        at, sep, wind = text.partition(":")
        try:
            rollout = int(at)
        except ValueError:
            rollout = -1
        if not sep or rollout < 0:
            raise ExperimentError(
                f"--wind-change needs AT:VX,VY,VZ (a rollout number, then the new wind in m/s), "
                f"got {text!r}"
            )
        vx, vy, vz = parse_vector("--wind-change wind", wind, ExperimentError, unit="m/s")
        return cls(rollout, (float(vx), float(vy), float(vz)))

    def to_dict(self) -> dict[str, Any]:
        """Plain values for summary.json."""
        return {"at": self.at, "wind": list(self.wind)}


@dataclass(frozen=True)
class Transfer:
    """Final learner states of an earlier run that seed the sessions of a new one.

    Attributes:
        source: where they come from (the earlier run's directory).
        states: per algorithm, one learner state per session of the earlier run.
    """

    source: str
    states: dict[str, tuple[dict[str, Any], ...]]

    @classmethod
    def load(cls, directory: Path) -> Transfer:
        """The states an experiment wrote into `directory`.

        Raises:
            ExperimentError: no readable `learners.json` of this version there.
        """
        path = directory / LEARNERS_NAME
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ExperimentError(
                f"--from {str(directory)!r}: cannot read {LEARNERS_NAME} of an earlier "
                f"`archery experiment --out DIR` ({getattr(exc, 'strerror', None) or exc})"
            ) from None
        if not isinstance(data, dict) or data.get("version") != LEARNERS_VERSION:
            raise ExperimentError(
                f"--from {str(directory)!r}: {path} is not a version {LEARNERS_VERSION} "
                f"learner-state file"
            )
        states = data.get("algorithms")
        if not isinstance(states, dict) or not all(
            isinstance(v, list) and v and all(isinstance(x, dict) for x in v)
            for v in states.values()
        ):
            raise ExperimentError(f"--from {str(directory)!r}: {path} holds no learner states")
        return cls(str(directory), {name: tuple(v) for name, v in states.items()})

    def state(self, name: str, session: int) -> dict[str, Any]:
        """The state that seeds `session` of algorithm `name`."""
        states = self.states[name]
        return states[session % len(states)]


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment: every algorithm runs `sessions` sessions of `rollouts` rollouts.

    Session s of every algorithm sees the same observation-noise stream and its learner gets the
    same seed, both derived from (seed, s); so results do not depend on which algorithms run.

    Attributes:
        algorithms: names from `services.learner.algorithms.registry.ALGORITHMS`.
        sessions: number of independent learning sessions per algorithm.
        rollouts: rollout budget per session.
        seed: master seed.
        scenario: the simulated range.
        bounds: θ box (m) given to every learner: by default the controller's,
            `protocol.theta.THETA_BOX` (a fleet's robots tell theirs).
        world: the simulator: "ballistic" (the paper's analytic model, here) or "mesh" (the
            MuJoCo robots of a fleet, `apps.experiment.experiment_mesh`).
        wind_change: the wind changes during the sessions (None: it does not).
        transfer: start each session from an earlier run's learner (None: from scratch).
        power_scale: s (m) in PoWER's importance weights R = exp(−‖r‖/s) for every PoWER
            algorithm of the run (None: each one's own, `Power`); no other learner has one.
    """

    algorithms: tuple[str, ...] = DEFAULT_ALGORITHMS
    sessions: int = 40
    rollouts: int = 60
    seed: int = 0
    scenario: Scenario = field(default_factory=Scenario)
    bounds: ThetaBox = THETA_BOX
    world: str = "ballistic"
    wind_change: WindChange | None = None
    transfer: Transfer | None = None
    power_scale: float | None = None

    def __post_init__(self) -> None:
        if self.world not in WORLDS:
            raise ExperimentError(
                f"unknown world {self.world!r}; valid worlds: {', '.join(WORLDS)}"
            )
        if not self.algorithms:
            raise ExperimentError(f"no algorithm given; valid algorithms: {', '.join(ALGORITHMS)}")
        for name in self.algorithms:
            if name not in ALGORITHMS:
                raise ExperimentError(
                    f"unknown algorithm {name!r}; valid algorithms: {', '.join(ALGORITHMS)}"
                )
        scale = self.power_scale
        if scale is not None and not (
            isinstance(scale, int | float) and math.isfinite(scale) and 1e-4 <= scale <= 10
        ):
            raise ExperimentError(f"--power-scale must be in [0.0001, 10] m, got {scale!r}")
        if len(set(self.algorithms)) != len(self.algorithms):
            raise ExperimentError(f"algorithm list {list(self.algorithms)} repeats a name")
        for name, low in (("sessions", 1), ("rollouts", 1), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ExperimentError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.rollouts > MAX_ROLLOUTS:
            raise ExperimentError(f"rollouts must be at most {MAX_ROLLOUTS}, got {self.rollouts}")
        if not self.bounds.contains(self.scenario.start):
            raise ExperimentError(self.bounds.outside("start θ", self.scenario.start))
        if self.wind_change is not None:
            at = self.wind_change.at
            if not 2 <= at <= self.rollouts:
                raise ExperimentError(
                    f"--wind-change rollout {at} must be in [2, {self.rollouts}] (the budget)"
                )
            self.changed_scenario()  # a wind without drag is rejected here
        if self.transfer is not None:
            for name in self.algorithms:
                check_transfer(name)
                if name not in self.transfer.states:
                    raise ExperimentError(
                        f"--from {self.transfer.source!r} has no {name} sessions; it has "
                        f"{', '.join(self.transfer.states) or 'none'}"
                    )
        for name in self.algorithms:
            probe = self.learner(name, 0)
            needed = probe.exploration_rollouts + 1
            if self.rollouts < needed:
                raise ExperimentError(
                    f"rollouts {self.rollouts} is below {name}'s exploration phase "
                    f"({probe.exploration_rollouts} rollouts) plus one learned rollout; "
                    f"use rollouts >= {needed}"
                )

    def seeds(self, session: int) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
        """(world noise seed, learner seed) of a session."""
        return (
            np.random.SeedSequence(self.seed, spawn_key=(session, 0)),
            np.random.SeedSequence(self.seed, spawn_key=(session, 1)),
        )

    def learner(self, name: str, session: int) -> Learner:
        """A fresh learner `name` for `session`, starting at the scenario's θ (and from the
        transferred learner of `session`, with `transfer`).

        Raises:
            RestoreError: the transferred state cannot seed it.
        """
        options: dict[str, Any] = {}
        if self.power_scale is not None and ALGORITHMS[name].cls is Power:
            options["return_scale"] = float(self.power_scale)
        learner = make_learner(
            name,
            np.array(self.scenario.start),
            rng=np.random.default_rng(self.seeds(session)[1]),
            bounds=self.bounds,
            **options,
        )
        if self.transfer is None:
            return learner
        return transferred_learner(learner, self.transfer.state(name, session))

    def changed_scenario(self) -> Scenario:
        """The range after the wind change (the scenario itself without one).

        Raises:
            ScenarioError: the new wind needs drag and the scenario has none.
        """
        if self.wind_change is None:
            return self.scenario
        return replace(self.scenario, wind=self.wind_change.wind)

    def to_dict(self) -> dict[str, Any]:
        """The run settings as plain values."""
        return {
            "sessions": self.sessions,
            "rollouts": self.rollouts,
            "seed": self.seed,
            "algorithms": list(self.algorithms),
            "bounds": msgspec.to_builtins(self.bounds),
            "from": None if self.transfer is None else self.transfer.source,
            "power_scale_m": self.power_scale,
        }


@dataclass(frozen=True)
class AlgorithmRun:
    """Everything one algorithm did in an experiment.

    Attributes:
        name: the algorithm's name.
        thetas: (sessions, rollouts, 3) θ of every rollout (m).
        r_observed: (sessions, rollouts, 2) reward vectors the learner was told (m).
        r_true: (sessions, rollouts, 2) true arrow − centre offsets (m).
        wall_time: seconds spent on this algorithm (learning and simulation).
        states: each session's final learner state.
    """

    name: str
    thetas: np.ndarray
    r_observed: np.ndarray
    r_true: np.ndarray
    wall_time: float
    states: tuple[dict[str, Any], ...] = ()

    @property
    def distances(self) -> np.ndarray:
        """(sessions, rollouts) true distance of each arrow to the centre (m)."""
        return np.hypot(self.r_true[..., 0], self.r_true[..., 1])

    def rollouts_to_hit(self) -> np.ndarray:
        """(sessions,) 1-based index of the first hit (‖r‖ < 5 cm); budget + 1 if none."""
        hits = self.distances < INNER_RING_RADIUS
        budget = hits.shape[1]
        return np.where(hits.any(axis=1), hits.argmax(axis=1) + 1, budget + 1)

    def rollouts_to_rehit(self, at: int) -> np.ndarray:
        """(sessions,) rollouts from `at` (1-based, counted as 1) to the first hit at or after it;
        budget − at + 2 if none."""
        hits = self.distances[:, at - 1 :] < INNER_RING_RADIUS
        return np.where(hits.any(axis=1), hits.argmax(axis=1) + 1, hits.shape[1] + 1)


def number(text: str, flag: str) -> float:
    """The finite number `text`, the value of `flag` (its vectors: `protocol.vectors`).

    Raises:
        ExperimentError: it is not one.
    """
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ExperimentError(f"{flag} needs a number, got {text!r}")
    return value
