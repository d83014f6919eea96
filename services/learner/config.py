"""Settings of the learner service (flags) and of one learning session (the `start` request)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import msgspec
from msgspec import UnsetType

from archery.mesh.cliargs import check_writable_dir
from archery.mesh.configflags import add_config_args, check_bounds, config_from_args, flag
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import BadRequest, ConfigError
from archery.protocol.journal_records import HeaderRecord
from archery.protocol.robotspec import HIT_RADIUS, RPC_TIMEOUT, THETA0
from archery.protocol.text import shown
from archery.protocol.theta import ThetaBox
from archery.protocol.vectors import finite_vector
from archery.protocol.verbs.learner import MAX_ROLLOUTS, Scenario, StartArgs
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.services.learner.operator_desk import OPERATOR_LIMIT

__all__ = [
    "DEFAULT_THETA0",
    "ROBOT_OPTIONS",
    "START_ARGS",
    "LearnerServiceConfig",
    "SessionConfig",
    "add_arguments",
    "make_config",
]

# θ (m) where sessions start (protocol.robotspec.THETA0).
DEFAULT_THETA0 = THETA0

# Learner options for the MuJoCo robot, under the caller's own. Its hands move the arrow about
# 11 m on the target per m of θ (aim) and 1-2 m per m of draw, so the analytic model's 10-20 mm
# of exploration would scatter the first arrows off the 25 cm face: 3 mm scatters them ~3.5 cm.
# ARCHER explores the aim 5 mm (~5.5 cm on the target, about 9 times the bow's shot noise, so
# its regression of Eq. 5 is not led by the noise), the draw 3 mm; its trust radius starts at
# 2 cm (22 cm on the target) and never exceeds 4 cm.
_EXPLORE = {"explore_std": 0.003}
_ARCHER = {
    "explore_std": (0.003, 0.005, 0.005),
    "trust_radius": 0.02,
    "max_step": 0.04,
    "fallback_std": 0.002,
}
ROBOT_OPTIONS: Mapping[str, Mapping[str, Any]] = MappingProxyType(
    {
        "archer": _ARCHER,
        "archer-plain": _ARCHER,
        "archer-iso": _ARCHER,
        "archer-plain-iso": _ARCHER,
        "archer-ridge": _ARCHER,
        "power": _EXPLORE,
        "power-metre": _EXPLORE,
        "hill": _EXPLORE,
        "cma": {"sigma0": 0.003},
    }
)

START_ARGS = (
    "algo",
    "rollouts",
    "seed",
    "until_hit",
    "scenario",
    "options",
    "resume",
    "session",
    "from_journal",
)
SCENARIO_KEYS = ("theta0", "bounds", "hit_radius", "reset")


def _integer(name: str, value: Any, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise BadRequest(f"{name} must be an integer in [{low}, {high}], got {shown(value)}")
    return value


def _theta(name: str, value: Any) -> tuple[float, ...]:
    """A θ of plain data (a journal's header, a request built from flags) as a tuple (m), or
    BadRequest naming `name`: the check of a θ that no decoding checked."""
    return tuple(finite_vector(name, value, BadRequest, unit="m").tolist())


def _box(name: str, value: Mapping[str, Any]) -> ThetaBox:
    """A θ box of plain data ({"low", "high"}, m) as a `ThetaBox`, or BadRequest naming
    `name`."""
    try:
        return ThetaBox(low=value["low"], high=value["high"])
    except ValueError as exc:
        raise BadRequest(f"{name}: {exc}") from None


@dataclass(frozen=True)
class SessionConfig:
    """One learning session, validated (what `start` asks for, or a journal's header).

    θ0 and the box come typed: a decoded `start` request checked them (`from_start`), and
    `from_request` and `from_header` check the plain data they read.

    Attributes:
        algorithm: a name of `services.learner.algorithms.registry.ALGORITHMS`.
        rollouts: budget of done rollouts (aborted attempts are not counted).
        seed: seeds the learner's generator, and the robot's shot noise at the start.
        until_hit: end the session at the first rollout within `hit_radius` of the centre.
        theta0: θ (m) the learner starts from, 3 finite numbers.
        bounds: θ box of the learner; None: the controller's box. Must lie inside it, and
            hold θ0 (`services.learner.session_setup` checks both against the controller's).
        hit_radius: a rollout hits when the measured ‖r‖ is below this (m).
        reset: reset the robot (home posture, shot noise seeded with `seed`) when the session
            starts (not when it resumes).
        options: learner options on top of `ROBOT_OPTIONS` and the algorithm's defaults.
        max_aborts: the session fails after this many aborted attempts in a row.
    """

    algorithm: str = "archer"
    rollouts: int = 30
    seed: int = 0
    until_hit: bool = True
    theta0: tuple[float, ...] = DEFAULT_THETA0
    bounds: ThetaBox | None = None
    hit_radius: float = HIT_RADIUS
    reset: bool = True
    options: Mapping[str, Any] = field(default_factory=dict)
    max_aborts: int = 8

    def __post_init__(self) -> None:
        if self.algorithm not in ALGORITHMS:
            raise BadRequest(
                f"unknown algorithm {shown(self.algorithm)}; valid algorithms: "
                f"{', '.join(ALGORITHMS)}"
            )
        _integer("rollouts", self.rollouts, 1, MAX_ROLLOUTS)
        _integer("seed", self.seed, 0, 2**32 - 1)
        _integer("max_aborts", self.max_aborts, 1, 1000)
        for name in ("until_hit", "reset"):
            if not isinstance(getattr(self, name), bool):
                raise BadRequest(f"{name} must be true or false, got {shown(getattr(self, name))}")
        object.__setattr__(self, "theta0", tuple(float(v) for v in self.theta0))
        radius = self.hit_radius
        if isinstance(radius, bool) or not isinstance(radius, int | float):
            raise BadRequest(f"scenario.hit_radius must be a number (m), got {shown(radius)}")
        if not (math.isfinite(radius) and 0.001 <= radius <= 0.25):
            raise BadRequest(f"scenario.hit_radius must be in [0.001, 0.25] m, got {shown(radius)}")
        object.__setattr__(self, "hit_radius", float(radius))
        if not isinstance(self.options, Mapping):
            raise BadRequest(f"options must be a map of learner options, got {shown(self.options)}")

    def learner_options(self) -> dict[str, Any]:
        """`ROBOT_OPTIONS` for the algorithm, overridden by `options`."""
        return {**ROBOT_OPTIONS.get(self.algorithm, {}), **dict(self.options)}

    def to_dict(self) -> dict[str, Any]:
        """Plain values for the journal's header (`from_dict` reads them back)."""
        return {
            "until_hit": self.until_hit,
            "theta0": list(self.theta0),
            "bounds": None if self.bounds is None else msgspec.to_builtins(self.bounds),
            "hit_radius_m": self.hit_radius,
            "reset": self.reset,
            "max_aborts": self.max_aborts,
        }

    @classmethod
    def from_start(cls, start: StartArgs) -> SessionConfig:
        """The session a `start` request asks for (without `resume`; its `from_journal` is the
        caller's, `services.learner.transfer`): fields left unset take the defaults.

        Raises:
            BadRequest: an invalid value; the message names it and what is valid.
        """
        defaults = cls()
        scenario = start.scenario if not isinstance(start.scenario, UnsetType) else Scenario()

        def given(value: Any, default: Any) -> Any:
            return default if isinstance(value, UnsetType) else value

        return cls(
            algorithm=given(start.algo, defaults.algorithm),
            rollouts=given(start.rollouts, defaults.rollouts),
            seed=given(start.seed, defaults.seed),
            until_hit=given(start.until_hit, defaults.until_hit),
            theta0=given(scenario.theta0, defaults.theta0),
            bounds=given(scenario.bounds, None),
            hit_radius=given(scenario.hit_radius, defaults.hit_radius),
            reset=given(scenario.reset, defaults.reset),
            options=given(start.options, {}),
        )

    @classmethod
    def from_request(cls, args: Mapping[str, Any]) -> SessionConfig:
        """The session a `start` request given as plain data asks for (what `archery learn`
        builds from its flags, checked before anything is sent): its keys and shape checked
        here, its values by `from_start`, with the same messages the learner gives.

        Raises:
            BadRequest: an unknown argument or scenario key, or an invalid value; the message
                names it and what is valid.
        """
        unknown = sorted(set(args) - set(START_ARGS))
        if unknown:
            raise BadRequest(
                f"start has no argument {shown(unknown[0])}; arguments: {', '.join(START_ARGS)}"
            )
        scenario = args.get("scenario", {})
        if not isinstance(scenario, Mapping):
            raise BadRequest(f"scenario must be a map with keys {', '.join(SCENARIO_KEYS)}")
        unknown = sorted(set(scenario) - set(SCENARIO_KEYS))
        if unknown:
            raise BadRequest(
                f"scenario has no key {shown(unknown[0])}; scenario keys: "
                f"{', '.join(SCENARIO_KEYS)}"
            )
        raw = scenario.get("bounds")
        if raw is not None and (not isinstance(raw, Mapping) or set(raw) != {"low", "high"}):
            raise BadRequest(
                f"scenario.bounds must be {{low: [x,y,z], high: [x,y,z]}} (m), got {shown(raw)}"
            )
        # Built without msgspec's checks, so that the values meet the same checks (and
        # messages) as on the learner: `from_start` and the config's own; θ0 and the box,
        # which the learner's decoding checks, are checked here.
        fields = {k: v for k, v in args.items() if k != "scenario"}
        if scenario:
            given = {k: v for k, v in scenario.items() if k not in ("theta0", "bounds")}
            if "theta0" in scenario:
                given["theta0"] = list(_theta("scenario.theta0", scenario["theta0"]))
            if "bounds" in scenario:
                given["bounds"] = None if raw is None else _box("scenario.bounds", raw)
            fields["scenario"] = Scenario(**given)
        return cls.from_start(StartArgs(**fields))

    @classmethod
    def from_header(cls, header: HeaderRecord) -> SessionConfig:
        """The session a journal's header describes (the learner itself comes from its state)."""
        config = header.config
        bounds = None if config.get("bounds") is None else _box("bounds", config["bounds"])
        return cls(
            algorithm=header.algorithm,
            rollouts=header.rollouts,
            seed=header.seed,
            until_hit=config["until_hit"],
            theta0=_theta("theta0", config["theta0"]),
            bounds=bounds,
            hit_radius=config["hit_radius_m"],
            reset=config["reset"],
            options=header.options,
            max_aborts=config["max_aborts"],
        )


@dataclass(frozen=True)
class LearnerServiceConfig:
    """Everything `archery learner` needs.

    Attributes:
        net: network settings (the common flags).
        runs: directory of the session directories (`runs/<session>/journal.jsonl`, report).
        service_wait: how long a session waits for a vanished service before it fails (wall s).
        start_wait: how long `start` waits for the other services to be alive (wall s).
        rpc_timeout: longest wait for a reply from another service (wall s).
        operator_wait: how long a session waits for the operator to confirm what a real robot
            cannot do by itself (a nock by hand: `operator_desk`) before it stops (wall s).
        report: write `report.png` and the hit frame when a session ends.
        fleet: more robot prefixes served by this one learner (a session on each at once).
    """

    net: NetConfig = field(default_factory=NetConfig)
    runs: Path = flag("runs", "directory of session journals and reports")
    service_wait: float = flag(
        120.0,
        "wait this long for a vanished service before failing the session",
        unit="s",
        low=0.1,
        high=86400,
    )
    start_wait: float = flag(
        5.0, "`start` waits this long for the other services", unit="s", low=0, high=600
    )
    rpc_timeout: float = flag(
        RPC_TIMEOUT, "longest wait for another service's reply", unit="s", low=0.5, high=600
    )
    operator_wait: float = flag(
        OPERATOR_LIMIT,
        "wait this long for the operator to confirm a nock or reset done by hand, then stop "
        "the session (resumable)",
        unit="s",
        low=1,
        high=86400,
    )
    report: bool = flag(True, "write no report figures", name="--no-report")
    fleet: tuple[str, ...] = flag(
        (),
        "also run sessions on these robots (one learner for a fleet): it serves "
        "PREFIX/learner/rpc:i for each, one session per robot at a time",
        parse=lambda text: tuple(p.strip() for p in text.split(",") if p.strip()),
        metavar="PREFIX,PREFIX",
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        for prefix in self.fleet:
            try:
                NetConfig(robot=prefix)
            except ConfigError as exc:
                raise ConfigError(f"--fleet {prefix!r}: {exc}") from None
        robots = self.robots()
        if len(set(robots)) != len(robots):
            raise ConfigError(f"--fleet {','.join(self.fleet)}: a robot is listed twice")

    def robots(self) -> tuple[str, ...]:
        """Every robot prefix this learner serves: its own (`--robot`), then `--fleet`'s."""
        return (self.net.robot, *self.fleet)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the learner service's own flags."""
    add_config_args(parser, LearnerServiceConfig)


def make_config(args: argparse.Namespace, net: NetConfig) -> LearnerServiceConfig:
    """Build the config from parsed flags.

    Raises:
        ConfigError: an invalid value; the message names the flag and its valid range.
    """
    check_writable_dir(Path(args.runs), "--runs", create=True)
    result: LearnerServiceConfig = config_from_args(LearnerServiceConfig, args, net=net)
    return result
