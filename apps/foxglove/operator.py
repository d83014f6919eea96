"""What a Foxglove client may do with `--operator`: call the learner's `status`, `start` and
`stop` and the robot's `reset` as Foxglove services, and set the wind as a parameter. Every call
goes through the verb tables (the same decoding and checks as any caller's), the robot's through
its one client (`RobotClient`); a refused call answers that client with the service's reason."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from typing import Any

import foxglove
import msgspec

from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import ArcheryError
from archery.protocol.robotspec import CALL_TIMEOUT
from archery.protocol.text import shown
from archery.protocol.verbs import learner as lv
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import Verb

__all__ = ["WIND", "Operator"]

log = logging.getLogger("archery.foxglove")

WIND = "wind"  # the parameter: the robot's constant wind [x, y, z] (m/s, root frame)


def _schema(name: str, schema: dict[str, Any]) -> foxglove.MessageSchema:
    data = json.dumps(schema).encode()
    return foxglove.MessageSchema(
        encoding="json",
        schema=foxglove.Schema(name=name, encoding="jsonschema", data=data),
    )


class Operator:
    """The operator's services and the wind parameter over `node` (its robot's keys)."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.robot = RobotClient(node, timeout=CALL_TIMEOUT)
        learner, robot = self._learner, self.robot.call
        self._verbs: dict[str, tuple[Callable[..., Any], Verb[Any, Any]]] = {
            "/learner/status": (learner, lv.STATUS),
            "/learner/start": (learner, lv.START),
            "/learner/stop": (learner, lv.STOP),
            "/robot/reset": (robot, rv.RESET),
        }

    def _learner(self, verb: Verb[Any, Any], args: Any, timeout: float) -> Any:
        return self.node.call_typed(self.node.keys.learner_rpc(), verb, args, timeout=timeout)

    def services(self) -> list[foxglove.Service]:
        """One Foxglove service per verb, JSON in and out, schemas from the verb's contract."""
        services = []
        for name, (_, verb) in self._verbs.items():
            schemas = verb.schema()
            schema = foxglove.ServiceSchema(
                f"archery.{verb.name}",
                request=_schema(f"archery.{verb.args.__name__}", schemas["args"]),
                response=_schema(f"archery.{verb.reply.__name__}", schemas["reply"]),
            )
            services.append(foxglove.Service(name, schema=schema, handler=self.call))
        return services

    def call(self, request: foxglove.ServiceRequest) -> bytes:
        """Run one service call; raises (the client gets the message) when it is refused."""
        call, verb = self._verbs[request.service_name]
        if request.encoding != "json":
            raise ValueError(f"{request.service_name}: send JSON, not {request.encoding!r}")
        try:
            args = msgspec.json.decode(request.payload or b"{}", type=verb.args)
        except msgspec.ValidationError as exc:
            raise ValueError(f"{request.service_name}: invalid request: {exc}") from None
        except msgspec.DecodeError as exc:
            raise ValueError(f"{request.service_name}: the request is not JSON: {exc}") from None
        try:
            reply = call(verb, args, timeout=CALL_TIMEOUT)
        except ArcheryError as exc:
            raise RuntimeError(f"{request.service_name}: {exc}") from None
        return msgspec.json.encode(reply)

    def wind(self) -> list[float] | None:
        """The wind in force (m/s), from the robot's status; None when the robot is silent."""
        try:
            status = self.robot.status()
        except ArcheryError as exc:
            log.warning("the wind: %s", exc)
            return None
        wind = status.world.get("wind")
        return [float(v) for v in wind] if isinstance(wind, list) else None

    def set_wind(self, value: Any) -> list[float]:
        """Set the wind to `value` ([x, y, z] m/s, each within ±`MAX_WIND`); the wind now in
        force. Raises ValueError naming what is wrong."""
        if (
            not isinstance(value, list)
            or len(value) != 3
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        ):
            raise ValueError(f"{WIND} must be 3 numbers [x, y, z] (m/s), got {shown(value)}")
        if not all(math.isfinite(v) and abs(v) <= rv.MAX_WIND for v in value):
            raise ValueError(f"{WIND} components must lie within ±{rv.MAX_WIND:g} m/s")
        reply = self.robot.call(rv.SET_WIND, rv.SetWindArgs(wind=[float(v) for v in value]))
        return list(reply.wind)
