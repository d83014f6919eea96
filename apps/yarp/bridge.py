"""The YARP bridge on a running mesh (`archery yarp`): each part's control board, the camera,
the detector's measurements, the world's events and the archery verbs as YARP ports named as
the mesh names them (`<prefix>/<part>/state:o` for `ROBOT/<part>/state:o`), each stream fed by a
subscription of the bridge's node at the rate the mesh publishes it. The mesh's callback
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
from collections.abc import Callable
from typing import Any

from archery.apps.follow import Stop, follow_events, follow_latest
from archery.apps.yarp.controlboard import ControlBoard, Output, PartLink
from archery.apps.yarp.ports import ArcheryPort, event_bottle, image_to, reward_bottle
from archery.mesh.node import Node
from archery.protocol.messages import Detection, Image, JointState, WorldEvent
from archery.protocol.parts import PARTS

__all__ = ["CLOSE_WITHIN", "EVENTS_QUEUED", "MEMORY_BOUND", "STATES_QUEUED", "Outbox", "YarpBridge"]

log = logging.getLogger("archery.yarp")

#: bytes of data (heap, anonymous mappings, thread stacks: RLIMIT_DATA) the bridge may hold
MEMORY_BOUND = 2 << 30
STATES_QUEUED = 4  # joint states a part's writer holds at most (latest-wins)
EVENTS_QUEUED = 64  # measurements or events a writer holds at most (then the oldest go)
CLOSE_WITHIN = 1.0  # s from the start of `close` to the end of the process, at most


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
        timeout: wall s for each call to the mesh.
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
        keys = node.keys
        try:
            for part in PARTS:
                board = ControlBoard(yarp, PartLink(node, part, timeout), prefix, operator=operator)
                self.boards[part] = board
                states = self._outbox(f"{board.name}/state:o", board.publish, STATES_QUEUED)
                self._stops.append(follow_events(node, keys.state(part), JointState, states.put))
            self.archery = ArcheryPort(yarp, node, prefix, operator=operator, timeout=timeout)
            frames = self._output(yarp.BufferedPortImageRgb, "cam/target:o")
            hits = self._output(yarp.BufferedPortBottle, "detector/hit:o")
            events = self._output(yarp.BufferedPortBottle, "world/events:o")
            write_hit = self._outbox(hits.name, self._writer(hits, reward_bottle), EVENTS_QUEUED)
            write_event = self._outbox(
                events.name, self._writer(events, event_bottle), EVENTS_QUEUED
            )
            self._stops += [
                follow_latest(  # a thread of its own, the newest frame only
                    node, keys.cam_frames(), Image, "frames", self._writer(frames, image_to), log
                ),
                follow_events(node, keys.detector_hits(), Detection, write_hit.put),
                follow_events(node, keys.world_events(), WorldEvent, write_event.put),
            ]
        except BaseException:
            self._close()
            raise

    def _output(self, kind: Any, leaf: str) -> Output:
        output = Output(self.yarp, kind, f"{self.prefix}/{leaf}")
        self._outputs.append(output)
        return output

    def _outbox(self, name: str, write: Callable[[Any], None], size: int) -> Outbox:
        outbox = Outbox(name, write, size, events=size == EVENTS_QUEUED)
        self._outboxes.append(outbox)
        return outbox

    def _writer(self, output: Output, fill: Callable[..., None]) -> Callable[[Any], None]:
        """Write each message on `output` (its stamp the envelope), never waiting on a slow
        reader (`Output.send`)."""
        counter = {image_to: "frames", reward_bottle: "hits", event_bottle: "events"}[fill]
        count = [0]
        port = output.port

        def write(message: Any) -> None:
            if fill is image_to:
                fill(self.yarp, port.prepare(), message)
            else:
                fill(port.prepare(), message)
            count[0] += 1
            port.setEnvelope(self.yarp.Stamp(count[0], message.stamp))
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
