"""The launch description of `archery up`: which services, for which robots, with which
arguments and restart policies, and the router's endpoint.

`archery up --config mesh.toml` reads it from a TOML file: the repository's `mesh.toml`, which
equals the built-in default (`default_mesh()`), shows every table and key with its meaning, as
does docs/mesh-up.md. Every error (an unknown key, a bad policy, an unknown
service, a bad endpoint or robot prefix) is a `ConfigError` of one line naming the key.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from archery.apps.up.restart_policy import RestartPolicy
from archery.mesh.netflags import DEFAULT_ROUTER, NetConfig
from archery.protocol.errors import ConfigError
from archery.protocol.keys import DEFAULT_ROBOT

__all__ = [
    "SERVICES",
    "ChildSpec",
    "MeshConfig",
    "RobotSpec",
    "RouterSpec",
    "ServiceSpec",
    "default_mesh",
    "fleet_prefixes",
    "load_mesh",
    "parse_mesh",
]

SERVICES = ("robot", "controller", "camera", "detector", "learner")
DEFAULT_POLICY = RestartPolicy()
_POLICY_KEYS = tuple(f.name for f in dataclasses.fields(RestartPolicy))


@dataclass(frozen=True)
class ServiceSpec:
    """One service's arguments (after `--connect ENDPOINT --robot PREFIX`) and restart policy."""

    args: tuple[str, ...] = ()
    restart: RestartPolicy = DEFAULT_POLICY


@dataclass(frozen=True)
class RobotSpec:
    """One robot prefix, the services started for it, and extra arguments per service."""

    prefix: str = DEFAULT_ROBOT
    services: tuple[str, ...] = SERVICES
    args: Mapping[str, tuple[str, ...]] = field(default_factory=dict)


@dataclass(frozen=True)
class RouterSpec:
    """The router: its endpoint, whether `up` starts it, and its restart policy."""

    endpoint: str = DEFAULT_ROUTER
    start: bool = True
    restart: RestartPolicy = DEFAULT_POLICY


@dataclass(frozen=True)
class ChildSpec:
    """One service process of the mesh.

    Attributes:
        id: its name in `up` (the service's name; `SERVICE@PREFIX` when there are several
            robots); its log is `LOGS/<id>.log`.
        service: the service's name (also its liveliness name).
        robot: its robot prefix.
        args: its arguments after `--connect ENDPOINT --robot PREFIX`.
        restart: its restart policy.
    """

    id: str
    service: str
    robot: str
    args: tuple[str, ...]
    restart: RestartPolicy


@dataclass(frozen=True)
class MeshConfig:
    """A whole mesh: the router, the robots and the services' settings."""

    router: RouterSpec = RouterSpec()
    robots: tuple[RobotSpec, ...] = (RobotSpec(),)
    services: Mapping[str, ServiceSpec] = field(default_factory=dict)

    def __post_init__(self) -> None:
        NetConfig(connect=(self.router.endpoint,))  # a Zenoh endpoint, or ConfigError
        if not self.robots:
            raise ConfigError("robots: the mesh needs at least one robot")
        for name in self.services:
            _check_service(name, "services")
        prefixes = [r.prefix for r in self.robots]
        for robot in self.robots:
            NetConfig(robot=robot.prefix)  # a valid prefix, or ConfigError
            for name in (*robot.services, *robot.args):
                _check_service(name, f"robots.{robot.prefix}")
            if prefixes.count(robot.prefix) > 1:
                raise ConfigError(f"robots.{robot.prefix}: the robot is listed twice")

    def children(self) -> list[ChildSpec]:
        """The service processes, robot by robot, each robot's in `SERVICES` order."""
        several = len(self.robots) > 1
        out = []
        for robot in self.robots:
            for name in SERVICES:
                if name not in robot.services:
                    continue
                spec = self.services.get(name, ServiceSpec())
                out.append(
                    ChildSpec(
                        f"{name}@{robot.prefix}" if several else name,
                        name,
                        robot.prefix,
                        spec.args + robot.args.get(name, ()),
                        spec.restart,
                    )
                )
        return out

    def with_policy(self, mode: str | None = None, budget: int | None = None) -> MeshConfig:
        """This mesh with every restart policy's mode and/or budget replaced."""
        changes: dict[str, Any] = {
            k: v for k, v in (("mode", mode), ("budget", budget)) if v is not None
        }
        if not changes:
            return self

        def change(policy: RestartPolicy) -> RestartPolicy:
            return dataclasses.replace(policy, **changes)

        router = dataclasses.replace(self.router, restart=change(self.router.restart))
        services = {
            name: dataclasses.replace(spec, restart=change(spec.restart))
            for name, spec in self.services_or_defaults().items()
        }
        return dataclasses.replace(self, router=router, services=services)

    def services_or_defaults(self) -> dict[str, ServiceSpec]:
        """Every service's settings (the defaults for those not configured)."""
        return {name: self.services.get(name, ServiceSpec()) for name in SERVICES}


def _check_service(name: str, where: str) -> None:
    if name not in SERVICES:
        raise ConfigError(f"{where}: no service {name!r}; services: {', '.join(SERVICES)}")


def fleet_prefixes(robot: str, robots: int) -> tuple[str, ...]:
    """The robot prefixes of a fleet of `robots` stacks: `robot` itself for one, else
    `robot1` … `robotN`.

    Raises:
        ConfigError: `robots` is below 1, or a prefix is not a valid robot prefix.
    """
    if isinstance(robots, bool) or not isinstance(robots, int) or robots < 1:
        raise ConfigError(f"--robots must be an integer >= 1, got {robots!r}")
    prefixes = (robot,) if robots == 1 else tuple(f"{robot}{i}" for i in range(1, robots + 1))
    for prefix in prefixes:
        NetConfig(robot=prefix)  # a valid prefix, or ConfigError
    return prefixes


def default_mesh(
    endpoint: str = DEFAULT_ROUTER,
    robot: str = DEFAULT_ROBOT,
    *,
    seed: int = 0,
    rtf: float = 0.0,
    runs: str = "runs",
    start_router: bool = True,
    restart: RestartPolicy = DEFAULT_POLICY,
    robots: int = 1,
    shot: str = "posture",
    body: tuple[str, ...] = (),
) -> MeshConfig:
    """The mesh of `archery up` without --config: a router and the five services of one robot;
    the robot gets `--seed`, `--rtf` and `--shot` (posture, or whole: the learner then plays
    the whole shot's movement in every rollout), the learner `--runs`.

    With `body` (a YARP robot's flags, e.g. `("--body", "yarp", "--remote", "/icubSim")`), the
    robot gets those instead of `--seed`, `--rtf` and `--shot` (a YARP body has no shot noise,
    no simulated time and no shot of its own); one robot only.

    With `robots` N > 1, a fleet: N robot stacks (robot, controller, camera, detector) under
    the prefixes `ROBOT1` … `ROBOTN` (robot i's shot noise seeded with `seed + i - 1`) and one
    learner, under the first prefix, that also serves the others (`--fleet`), so it can run a
    session on each robot at once.
    """
    prefixes = fleet_prefixes(robot, robots)
    if body and robots != 1:
        raise ConfigError(f"--robots {robots}: a YARP body is one robot (--remote)")
    robot_args = ("--rtf", f"{rtf:g}", *(() if shot == "posture" else ("--shot", shot)))
    args: dict[str, tuple[str, ...]] = {"robot": robot_args, "learner": ("--runs", runs)}
    if robots == 1:
        args["robot"] = body or ("--seed", str(seed), *args["robot"])
        specs: tuple[RobotSpec, ...] = (RobotSpec(robot),)
    else:
        stack = tuple(s for s in SERVICES if s != "learner")
        specs = tuple(
            RobotSpec(
                prefix,
                (*stack, "learner") if i == 0 else stack,
                {"robot": ("--seed", str(seed + i))}
                | ({"learner": ("--fleet", ",".join(prefixes[1:]))} if i == 0 else {}),
            )
            for i, prefix in enumerate(prefixes)
        )
    return MeshConfig(
        RouterSpec(endpoint, start_router, restart),
        specs,
        {name: ServiceSpec(args.get(name, ()), restart) for name in SERVICES},
    )


# -- reading a file --------------------------------------------------------------------------------
def _table(value: Any, key: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ConfigError(f"{key}: expected a table, got {value!r}")
    return value


def _only(table: Mapping[str, Any], allowed: Sequence[str], key: str) -> None:
    for name in table:
        if name not in allowed:
            where = f"{key}.{name}" if key else name
            raise ConfigError(f"{where}: unknown key; known here: {', '.join(allowed)}")


def _strings(value: Any, key: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{key}: expected a list of strings, got {value!r}")
    return tuple(value)


def _policy(value: Any, base: RestartPolicy, key: str) -> RestartPolicy:
    """A policy from a mode string or a table of RestartPolicy fields, over `base`."""
    if isinstance(value, str):
        value = {"mode": value}
    table = _table(value, key)
    _only(table, _POLICY_KEYS, key)
    try:
        return dataclasses.replace(base, **table)
    except ConfigError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def parse_mesh(data: Mapping[str, Any]) -> MeshConfig:
    """A mesh from a parsed TOML document.

    Raises:
        ConfigError: one line naming the key that is wrong.
    """
    _only(data, ("router", "restart", "robots", "services"), "")
    restart = _policy(data.get("restart", {}), RestartPolicy(), "restart")
    router = _table(data.get("router", {}), "router")
    _only(router, ("endpoint", "start", "restart"), "router")
    endpoint = router.get("endpoint", DEFAULT_ROUTER)
    if not isinstance(endpoint, str):
        raise ConfigError(f"router.endpoint: expected a string, got {endpoint!r}")
    try:
        NetConfig(connect=(endpoint,))
    except ConfigError as exc:
        raise ConfigError(f"router.endpoint: {exc}") from None
    start = router.get("start", True)
    if not isinstance(start, bool):
        raise ConfigError(f"router.start: expected true or false, got {start!r}")
    router_spec = RouterSpec(
        endpoint, start, _policy(router.get("restart", {}), restart, "router.restart")
    )
    services = {}
    for name, value in _table(data.get("services", {}), "services").items():
        key = f"services.{name}"
        _check_service(name, key)
        table = _table(value, key)
        _only(table, ("args", "restart"), key)
        services[name] = ServiceSpec(
            _strings(table.get("args", []), f"{key}.args"),
            _policy(table.get("restart", {}), restart, f"{key}.restart"),
        )
    for name in SERVICES:
        services.setdefault(name, ServiceSpec(restart=restart))
    robots = []
    for prefix, value in _table(data.get("robots", {DEFAULT_ROBOT: {}}), "robots").items():
        key = f"robots.{prefix}"
        table = _table(value, key)
        _only(table, ("services", "args"), key)
        chosen = _strings(table.get("services", list(SERVICES)), f"{key}.services")
        for name in chosen:
            _check_service(name, f"{key}.services")
        extra = {}
        for name, args in _table(table.get("args", {}), f"{key}.args").items():
            _check_service(name, f"{key}.args")
            extra[name] = _strings(args, f"{key}.args.{name}")
        try:
            NetConfig(robot=prefix)
        except ConfigError as exc:
            raise ConfigError(f"{key}: {exc}") from None
        robots.append(RobotSpec(prefix, chosen, extra))
    return MeshConfig(router_spec, tuple(robots), services)


def load_mesh(path: Path) -> MeshConfig:
    """Read a launch description (TOML).

    Raises:
        ConfigError: the file is missing, not TOML, or wrong; one line naming the file and key.
    """
    try:
        data = tomllib.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"--config {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"--config {path}: not valid TOML: {exc}") from None
    try:
        return parse_mesh(data)
    except ConfigError as exc:
        raise ConfigError(f"--config {path}: {exc}") from None
