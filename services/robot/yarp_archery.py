"""A YARP robot's own archery verbs and world events, for `archery robot --body yarp
--archery-rpc PORT`: `ArcheryLink` asks the robot's text RPC port (as `archery yarp
--operator` serves it at `/icubSim/archery/rpc:i`) for `status`, `reset`, `nock`, `release`
and `grasp` in its lossless form, `json VERB` → `ok TEXT` (TEXT the verb's typed reply of
`protocol.verbs.robot` as JSON) or `fail code message`, and decodes each answer as the
contract's typed reply: nothing is invented, an answer that does not decode is refused
(`bad_reply`). The robot's world events (bottles `kind shot (x y) reason` on
`<remote>/world/events:o`, when that port exists) are read on a thread of their own and handed
to the sink as the mesh's `WorldEvent`s (no simulated time: a bottle carries none). `yarp`
is never imported here: the body (`yarp_parts.YarpBody.yarp`) holds it.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
from typing import Any, TypeVar

import msgspec

from archery.protocol.errors import ArcheryError
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv
from archery.services.robot.sink import Sink
from archery.services.robot.yarp_parts import BodyError

__all__ = ["ArcheryLink", "event_of"]

log = logging.getLogger("archery.robot")

R = TypeVar("R")

#: the world events' kinds a bottle may name (`WorldEvent.kind`)
EVENT_KINDS = ("grasped", "nocked", "released", "landed", "missed", "reset", "watchdog")
EVENTS_POLL = 0.05  # s between two looks at the events port once it is empty
_locals = itertools.count()


def event_of(bottle: Any) -> tuple[str, int, list[float] | None, str] | None:
    """`(kind, shot, impact_m, reason)` of a world event's bottle `kind shot (x y) reason`
    (the impact in m: on the target plane, 2 numbers, or a point, 3; no impact, no list; no
    reason, none), or None when the bottle is not one."""
    if bottle.size() < 2 or not bottle.get(0).isString() or not bottle.get(1).isInt32():
        return None
    kind = bottle.get(0).asString()
    if kind not in EVENT_KINDS:
        return None
    impact: list[float] | None = None
    reason = ""
    for k in range(2, bottle.size()):
        item = bottle.get(k)
        if item.isList() and impact is None:
            values = item.asList()
            if not 2 <= values.size() <= 3 or not all(
                values.get(i).isFloat64() or values.get(i).isInt32() for i in range(values.size())
            ):
                return None
            impact = [values.get(i).asFloat64() for i in range(values.size())]
        elif item.isString() and not reason:
            reason = item.asString()
        else:
            return None
    return kind, bottle.get(1).asInt32(), impact, reason


class ArcheryLink:
    """The YARP robot's archery RPC port `port` (and its world events, when `events` names a
    port that exists), through the YARP library `yarp` the body joined, until `close`.

    Args:
        yarp: YARP's module (its network joined).
        port: the robot's archery RPC port, e.g. /icubSim/archery/rpc:i.
        events: the robot's world events port, e.g. /icubSim/world/events:o ("" = none).
        sink: receives the events (`Sink.event`).
        timeout: how long a verb's answer may take (wall s; a release waits for the arrow's
            flight).

    Raises:
        BodyError: no such RPC port on the name server, or it does not connect.
    """

    def __init__(self, yarp: Any, port: str, events: str, sink: Sink, timeout: float) -> None:
        self.yarp, self.remote, self.timeout = yarp, port, timeout
        self._sink = sink
        self._lock = threading.Lock()  # one request at a time on the port
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._events: Any = None
        local = f"/archery/robot/{os.getpid()}/{next(_locals)}"
        if not yarp.Network.exists(port, True):
            raise BodyError(
                f"--archery-rpc {port}: no such port on the YARP name server (is the robot's "
                "archery RPC port up? `yarp name list` lists the ports)"
            )
        self._port = yarp.Port()
        self._port.setTimeout(timeout)
        if not self._port.open(f"{local}/archery:o"):
            raise BodyError(f"the port {local}/archery:o does not open")
        try:
            if not yarp.Network.connect(self._port.getName(), port):
                raise BodyError(f"YARP does not connect {self._port.getName()} to {port}")
            if events and yarp.Network.exists(events, True):
                self._open_events(events, f"{local}/events:i")
            elif events:
                log.warning("%s: no such port: the robot's world events are not forwarded", events)
        except BaseException:
            self.close()
            raise

    def _open_events(self, events: str, local: str) -> None:
        yarp = self.yarp
        self._events = yarp.BufferedPortBottle()
        self._events.setStrict(True)  # every event, in order
        if not self._events.open(local):
            raise BodyError(f"the port {local} does not open")
        if not yarp.Network.connect(events, local):
            raise BodyError(f"YARP does not connect {events} to {local}")
        self._thread = threading.Thread(target=self._forward, name="robot yarp events", daemon=True)
        self._thread.start()
        log.info("the robot's world events %s forwarded to the mesh", events)

    def _forward(self) -> None:
        """Each event bottle as a `WorldEvent` (`Sink.event`, sim time unknown: None), until
        `close`; a bottle that is no event is logged and dropped."""
        while not self._closing.is_set():
            bottle = self._events.read(False)
            if bottle is None:
                self._closing.wait(EVENTS_POLL)
                continue
            event = event_of(bottle)
            if event is None:
                log.warning("not a world event, dropped: %s", shown(bottle.toString()))
                continue
            kind, shot, impact, reason = event
            self._sink.event(kind, shot, None, impact, reason)

    def call(self, verb: str, reply: type[R], *words: int) -> R:
        """The robot's answer to `json VERB WORDS…`, decoded as `reply`.

        Raises:
            ArcheryError: the robot's `fail code message` (its code kept), no answer within
                `timeout` (`unreachable`), or an answer that is not a `reply` (`bad_reply`).
        """
        request, answer = self.yarp.Bottle(), self.yarp.Bottle()
        request.addString("json")
        request.addString(verb)
        for word in words:
            request.addInt64(word)
        with self._lock:
            answered = self._port.write(request, answer)
        if not answered or answer.size() == 0:
            raise ArcheryError(
                f"{self.remote} did not answer {verb} within {self.timeout:g} s",
                code="unreachable",
            )
        head = answer.get(0).toString()
        if head == "fail" and answer.size() >= 3:
            raise ArcheryError(
                f"{self.remote}: {answer.get(2).toString()}", code=answer.get(1).toString()
            )
        if head != "ok" or answer.size() != 2 or not answer.get(1).isString():
            raise ArcheryError(
                f"{self.remote} answered {verb} with {shown(answer.toString())}, not `ok JSON`",
                code="bad_reply",
            )
        try:
            return msgspec.json.decode(answer.get(1).asString(), type=reply)
        except msgspec.DecodeError as exc:
            raise ArcheryError(
                f"{self.remote}'s {verb} answer is not the contract's {reply.__name__}: {exc}",
                code="bad_reply",
            ) from None

    def status(self) -> rv.ArcheryStatusReply:
        return self.call("status", rv.ArcheryStatusReply)

    def reset(self, seed: int | None = None) -> rv.ResetReply:
        return self.call("reset", rv.ResetReply, *(() if seed is None else (seed,)))

    def nock(self) -> rv.NockReply:
        return self.call("nock", rv.NockReply)

    def release(self) -> rv.ReleaseReply:
        return self.call("release", rv.ReleaseReply)

    def grasp(self) -> rv.GraspReply:
        return self.call("grasp", rv.GraspReply)

    def close(self) -> None:
        """Stop forwarding, close the ports (before YARP's network ends)."""
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._events is not None:
            self._events.interrupt()
            self._events.close()
        self._port.interrupt()
        self._port.close()
