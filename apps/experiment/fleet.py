"""A fleet of robots as one learner sees it: which robot stacks are alive on the mesh, and a
rig per robot over one shared Zenoh session.

A robot stack is alive when its robot, camera, detector and controller all hold their
liveliness tokens (`PREFIX/alive/NAME`); the stacks may hang off different routers that are
linked to each other, the learner sees them all through the router it connects to.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import zenoh

from archery.mesh.liveliness import OnWait
from archery.mesh.netflags import NetConfig, listens, open_session
from archery.mesh.node import Node
from archery.mesh.router import wait_for_endpoint
from archery.mesh.tokens import TokenSet
from archery.protocol.errors import ArcheryError, ConfigError
from archery.services.learner.rig import SERVICES, MeshRig
from archery.services.learner.rig_protocol import Measurement, Shot

__all__ = [
    "ExperimentRig",
    "FleetRobot",
    "NoRobot",
    "StackWatch",
    "alive_now",
    "open_fleet",
    "robot_stacks",
]

_ALIVE_ALL = "*/alive/*"  # every service's liveliness token, every robot prefix


class NoRobot(ArcheryError):
    """No robot stack is alive on the mesh (or none is left)."""

    code = "no_robot"


class ExperimentRig(MeshRig):
    """A `MeshRig` that takes no picture of a hit: the hit frame, PNG-encoded by the detector,
    would cost most rollouts of an experiment tens of ms."""

    def hit_frame(self, shot: Shot, measurement: Measurement) -> bytes | None:
        """No frame: None."""
        return None


@dataclass
class FleetRobot:
    """One robot stack of the fleet: its prefix, a node of that prefix and the rig over it."""

    prefix: str
    node: Node
    rig: ExperimentRig


def robot_stacks(tokens: set[str]) -> list[str]:
    """The robot prefixes whose robot, camera, detector and controller all appear among the
    liveliness keys `tokens` (`PREFIX/alive/NAME`), sorted."""
    by_robot: dict[str, set[str]] = {}
    for key in tokens:
        parts = key.split("/")
        if len(parts) == 3 and parts[1] == "alive":
            by_robot.setdefault(parts[0], set()).add(parts[2])
    return sorted(p for p, names in by_robot.items() if set(SERVICES) <= names)


class StackWatch:
    """The robot stacks alive on the mesh, kept current by liveliness events (a
    `mesh.tokens.TokenSet` of whole keys). Use as a context manager."""

    def __init__(self, session: zenoh.Session) -> None:
        self._tokens = TokenSet(session, _ALIVE_ALL, name=str)

    def robots(self) -> list[str]:
        """The prefixes of the robot stacks alive now, sorted."""
        return robot_stacks(self._tokens.present())

    def wait_for(self, predicate: Callable[[list[str]], bool], timeout: float) -> list[str]:
        """Wait up to `timeout` s until `predicate(robots)` holds; the robots alive then."""
        self._tokens.wait_for(lambda keys: predicate(robot_stacks(keys)), timeout)
        return self.robots()

    def __enter__(self) -> StackWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self._tokens.close()


def alive_now(session: zenoh.Session, timeout: float = 5.0) -> list[str]:
    """The robot stacks alive now, from one liveliness query (all routers' answers together)."""
    replies = session.liveliness().get(_ALIVE_ALL, timeout=timeout)
    return robot_stacks({str(r.ok.key_expr) for r in replies if r.ok is not None})


@contextmanager
def open_fleet(
    net: NetConfig,
    robots: Sequence[str] | None,
    timeout: float = 5.0,
    rpc_timeout: float = 20.0,
    on_wait: OnWait | None = None,
) -> Iterator[list[FleetRobot]]:
    """One Zenoh session to the mesh and a `FleetRobot` per robot: those named in `robots`
    (each must be alive within `timeout` s), or every robot stack alive (None).

    `on_wait(what, timeout)` is called once as each wait begins: while no router listens at the
    endpoint (up to `timeout` s), and when the robots wanted are not all alive at once
    (`mesh.liveliness.OnWait`).

    Raises:
        ConfigError: a named robot is not alive.
        NoRobot: no robot is named and none is alive.
    """
    endpoint = net.connect[0] if net.connect else None
    if endpoint is not None and not listens(endpoint):  # `archery up &` just started
        if on_wait is not None:
            on_wait(f"the router at {endpoint}", timeout)
        with contextlib.suppress(ConfigError):  # then the session says why
            wait_for_endpoint(endpoint, timeout)
    with open_session(net.with_identity("operator")) as session:
        wanted = set(robots or ())
        if on_wait is not None:  # asked before subscribing: the tokens stream in one by one
            now = set(alive_now(session, max(0.01, min(1.0, timeout))))
            if not now or not wanted <= now:
                names = ", ".join(sorted(wanted - now))
                on_wait(f"robots {names} to be alive" if wanted else "a robot on the mesh", timeout)
        with StackWatch(session) as watch:
            seen = watch.wait_for(lambda alive: bool(alive) and wanted <= set(alive), timeout)
            # The tokens stream in one by one: a query's answer is the whole set at once.
            found = sorted(set(seen) | set(alive_now(session, timeout)))
        if robots is None:
            chosen = found
            if not chosen:
                raise NoRobot(
                    f"no robot alive on the mesh at {', '.join(net.connect)} after {timeout:g} s "
                    f"(a robot needs its robot, camera, detector and controller); start some "
                    f"with `archery up --robots N`"
                )
        else:
            chosen = list(robots)
            absent = [p for p in chosen if p not in found]
            if absent:
                raise ConfigError(
                    f"--robots: no robot {absent[0]!r} alive after {timeout:g} s; alive: "
                    f"{', '.join(found) or 'none'}"
                )
        fleet = []
        try:
            for prefix in chosen:
                node = Node(None, dataclasses.replace(net, robot=prefix), session=session)
                fleet.append(FleetRobot(prefix, node, ExperimentRig(node, rpc_timeout)))
                # a whole-shot robot: every rollout is the controller's whole movement
                fleet[-1].rig.follow_shot()
            yield fleet
        finally:
            for robot in fleet:
                robot.rig.close()
                robot.node.close()
