"""The YARP bridge on a running mesh (`archery yarp`): each part's control board, the camera,
the detector's measurements, the world's events and the archery verbs as YARP ports named as
the mesh names them (`<prefix>/<part>/state:o` for `ROBOT/<part>/state:o`). The streams are the
rows of the declared table YARP shows (`protocol/streams.py`: `shown_by("yarp")`), each followed
as its row says (`follow_stream`) by the bridge's node at the rate the mesh publishes it and
written by its conversion (`CONVERSIONS`); the moves and the verbs go through the one robot
client (`RobotClient`). The mesh's callback
threads never wait on YARP: each output port is written by a thread of its own behind a small
queue (`Outbox`: latest-wins for states, bounded for events; frames: the newest only), and no
reader can block a write (`controlboard.Output`). The process's memory is bounded
(`MEMORY_BOUND`), so that a flood of input ends in a restart, not in the host's OOM killer."""

from __future__ import annotations

import collections
import logging
import os
import resource
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from archery.apps.follow import Stop, follow_stream
from archery.apps.yarp.controlboard import ControlBoard, Output
from archery.apps.yarp.ports import (
    ArcheryPort,
    SeenClock,
    event_bottle,
    image_to,
    reward_bottle,
)
from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.protocol.messages import Image, JointState, WorldState
from archery.protocol.parts import PARTS
from archery.protocol.streams import Stream, shown_by

__all__ = [
    "CLOSE_WITHIN",
    "CONVERSIONS",
    "EVENTS_QUEUED",
    "MEMORY_BOUND",
    "STATES_QUEUED",
    "Conversion",
    "Outbox",
    "YarpBridge",
]

log = logging.getLogger("archery.yarp")

#: bytes of data (heap, anonymous mappings, thread stacks: RLIMIT_DATA) the bridge may hold
MEMORY_BOUND = 2 << 30
STATES_QUEUED = 4  # joint states a part's writer holds at most (latest-wins)
EVENTS_QUEUED = 64  # measurements or events a writer holds at most (then the oldest go)
CLOSE_WITHIN = 1.0  # s from the start of `close` to the end of the process, at most


@dataclass(frozen=True)
class Conversion:
    """How the bridge shows one row of the stream table on its YARP channel
    (`row.channels["yarp"]`).

    Attributes:
        port: the `yarp` module's port class of the channel; "" for the joints, which each
            part's control board writes (`ControlBoard.publish`, routed by the state's `part`).
        fill: `fill(yarp, prepared, message)` writes a message into the port's prepared one.
        queued: how many messages its writer's `Outbox` holds; 0: no outbox, the newest only,
            written on the follower's own thread (a "latest" row).
        counter: its count in `YarpBridge.counts`.
    """

    port: str
    fill: Callable[[Any, Any, Any], None] | None
    queued: int
    counter: str = ""


#: {row name: its conversion}, exactly the rows YARP shows (`shown_by("yarp")`)
CONVERSIONS: Mapping[str, Conversion] = MappingProxyType(
    {
        "joints": Conversion("", None, STATES_QUEUED),
        "events": Conversion(
            "BufferedPortBottle", lambda _, out, m: event_bottle(out, m), EVENTS_QUEUED, "events"
        ),
        "camera": Conversion("BufferedPortImageRgb", image_to, 0, "frames"),
        "detections": Conversion(
            "BufferedPortBottle", lambda _, out, m: reward_bottle(out, m), EVENTS_QUEUED, "hits"
        ),
    }
)


def _end_now() -> None:
    log.warning("the bridge did not close within %g s: it ends now", CLOSE_WITHIN)
    logging.shutdown()
    os._exit(0)


def bound_memory(limit: int = MEMORY_BOUND) -> None:
    """Bound this process's data (`RLIMIT_DATA`) to `limit` bytes (or its hard limit): past it
    an allocation fails and the bridge ends, to be restarted."""
    _, hard = resource.getrlimit(resource.RLIMIT_DATA)
    soft = limit if hard == resource.RLIM_INFINITY else min(limit, hard)
    resource.setrlimit(resource.RLIMIT_DATA, (soft, hard))


class Outbox:
    """Messages for one writer, handed over without waiting: `put` never blocks, a thread of
    its own calls `write(message)` for each, in order. Full (`size` waiting), the oldest goes:
    latest-wins for a state stream; for events (`events=True`) the first loss is logged."""

    def __init__(
        self, name: str, write: Callable[[Any], None], size: int, *, events: bool = False
    ) -> None:
        self.name, self._write, self._events = name, write, events
        self._queue: collections.deque[Any] = collections.deque(maxlen=size)
        self._cond = threading.Condition()
        self._closing = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=f"yarp {name}", daemon=True)
        self._thread.start()

    def put(self, message: Any) -> None:
        """Hand `message` over (on the mesh's callback thread): never waits on YARP."""
        with self._cond:
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
                if self._events and self.dropped == 1:
                    log.warning("%s: a reader is too slow: the oldest events dropped", self.name)
            self._queue.append(message)
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if self._closing:
                    return
                message = self._queue.popleft()
            try:
                self._write(message)
            except Exception:
                log.exception("%s: could not write a message", self.name)

    def close(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout=5)


class YarpBridge:
    """The robot of `node`'s mesh on YARP's network until `close`.

    Args:
        yarp: the `yarp` module, its network initialised (`network.YarpNetwork`).
        node: the bridge's node on the mesh (its identity: viewer, or operator).
        prefix: the robot's YARP name (e.g. "/icubSim").
        operator: take moves and the archery verbs (else read-only).
        timeout: wall s for each call to the robot (its client's).
    """

    def __init__(
        self, yarp: Any, node: Node, prefix: str, *, operator: bool, timeout: float
    ) -> None:
        bound_memory()
        self.yarp, self.node, self.prefix = yarp, node, prefix
        self.boards: dict[str, ControlBoard] = {}
        self._outputs: list[Output] = []
        self._outboxes: list[Outbox] = []
        self._stops: list[Stop] = []
        self.counts = {"frames": 0, "hits": 0, "events": 0}
        self.robot = RobotClient(node, timeout=timeout)
        #: when the world was in each rendered frame's state: the frames' envelope stamps
        self.seen = SeenClock()
        self._world = node.subscribe(
            node.keys.world_state(), WorldState, mode="fifo", callback=self.seen.state
        )
        try:
            for part in PARTS:
                self.boards[part] = ControlBoard(yarp, self.robot, part, prefix, operator=operator)
            self.archery = ArcheryPort(yarp, self.robot, prefix, operator=operator)
            rows = shown_by("yarp")
            writers = {row.name: self._writer_of(row, CONVERSIONS[row.name]) for row in rows}
            for row in rows:  # the ports all open before the first message comes
                self._stops.append(
                    follow_stream(node, row, writers[row.name], log, CONVERSIONS[row.name].counter)
                )
        except BaseException:
            self._close()
            raise

    def _writer_of(self, row: Stream, conversion: Conversion) -> Callable[[Any], None]:
        """The function the row's follower hands each message to: its writer's outbox's `put`
        (never waiting on YARP), or the writer itself for a row followed latest-wins."""
        if not conversion.port:  # the joints: each part's board, by the state's part
            states = {
                part: self._outbox(f"{board.name}/state:o", board.publish, conversion.queued)
                for part, board in self.boards.items()
            }

            def route(state: JointState) -> None:
                outbox = states.get(state.part)
                if outbox is not None:  # a part the contract does not name: nowhere to show it
                    outbox.put(state)

            return route
        (channel,) = row.channels["yarp"]
        output = Output(self.yarp, getattr(self.yarp, conversion.port), f"{self.prefix}{channel}")
        self._outputs.append(output)
        write = self._writer(output, conversion)
        if not conversion.queued:
            return write
        return self._outbox(output.name, write, conversion.queued).put

    def _outbox(self, name: str, write: Callable[[Any], None], size: int) -> Outbox:
        outbox = Outbox(name, write, size, events=size == EVENTS_QUEUED)
        self._outboxes.append(outbox)
        return outbox

    def _writer(self, output: Output, conversion: Conversion) -> Callable[[Any], None]:
        """Write each message on `output` (its stamp the envelope; a frame's, when the world
        was in the state it shows: `SeenClock`), never waiting on a slow reader
        (`Output.send`)."""
        fill, counter = conversion.fill, conversion.counter
        assert fill is not None
        count = [0]
        port = output.port

        def write(message: Any) -> None:
            fill(self.yarp, port.prepare(), message)
            count[0] += 1
            stamp = self.seen.seen(message) if isinstance(message, Image) else message.stamp
            port.setEnvelope(self.yarp.Stamp(count[0], stamp))
            output.send()
            self.counts[counter] += 1

        return write

    def ports(self) -> list[str]:
        """The names of every port the bridge serves."""
        names = [
            f"{board.name}/{leaf}"
            for board in self.boards.values()
            for leaf in ("rpc:i", "command:i", "state:o", "stateExt:o")
        ]
        return [*names, self.archery.name, *(output.name for output in self._outputs)]

    def close(self) -> None:
        """Close every port; a close that takes `CLOSE_WITHIN` s or more (YARP waiting on a
        connection) ends the process there, so that SIGTERM ends it within that time."""
        watchdog = threading.Timer(CLOSE_WITHIN, _end_now)
        watchdog.daemon = True
        watchdog.start()
        self._close()

    def _close(self) -> None:
        for stop in self._stops:
            stop()
        self._stops = []
        self.node.unsubscribe(self._world)
        for outbox in self._outboxes:
            outbox.close()
        self._outboxes = []
        for board in self.boards.values():
            board.close()
        if hasattr(self, "archery"):
            self.archery.close()
        for output in self._outputs:
            output.close()
        self._outputs = []
        if hasattr(self, "robot"):
            self.robot.close()
