"""The YARP bridge on a running mesh (`archery yarp`): each part's control board, the camera,
the detector's measurements, the world's events and the archery verbs as YARP ports named as
the mesh names them (`<prefix>/<part>/state:o` for `ROBOT/<part>/state:o`), each stream fed by a
subscription of the bridge's node at the rate the mesh publishes it."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from archery.apps.follow import Stop, follow_events, follow_latest
from archery.apps.yarp.controlboard import ControlBoard, PartLink, close_port, open_port
from archery.apps.yarp.ports import ArcheryPort, event_bottle, image_to, reward_bottle
from archery.mesh.node import Node
from archery.protocol.messages import Detection, Image, JointState, WorldEvent
from archery.protocol.parts import PARTS

__all__ = ["YarpBridge"]

log = logging.getLogger("archery.yarp")


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
        self.yarp, self.node, self.prefix = yarp, node, prefix
        self.boards: dict[str, ControlBoard] = {}
        self._ports: list[Any] = []
        self._stops: list[Stop] = []
        self.counts = {"frames": 0, "hits": 0, "events": 0}
        keys = node.keys
        try:
            for part in PARTS:
                board = ControlBoard(yarp, PartLink(node, part, timeout), prefix, operator=operator)
                self.boards[part] = board
                self._stops.append(follow_events(node, keys.state(part), JointState, board.publish))
            self.archery = ArcheryPort(yarp, node, prefix, operator=operator, timeout=timeout)
            frames = self._port(yarp.BufferedPortImageRgb(), "cam/target:o")
            hits = self._port(yarp.BufferedPortBottle(), "detector/hit:o")
            events = self._port(yarp.BufferedPortBottle(), "world/events:o")
            self._stops += [
                follow_latest(
                    node, keys.cam_frames(), Image, "frames", self._writer(frames, image_to), log
                ),
                follow_events(
                    node, keys.detector_hits(), Detection, self._writer(hits, reward_bottle)
                ),
                follow_events(
                    node, keys.world_events(), WorldEvent, self._writer(events, event_bottle)
                ),
            ]
        except BaseException:
            self.close()
            raise

    def _port(self, port: Any, leaf: str) -> Any:
        self._ports.append(open_port(self.yarp, port, f"{self.prefix}/{leaf}"))
        return port

    def _writer(self, port: Any, fill: Callable[..., None]) -> Callable[[Any], None]:
        """Write each message on `port` (its stamp the envelope): every measurement and event
        (a busy connection waits for them), the newest frame (a busy reader skips one)."""
        counter = {image_to: "frames", reward_bottle: "hits", event_bottle: "events"}[fill]
        count = [0]

        def write(message: Any) -> None:
            if fill is image_to:
                fill(self.yarp, port.prepare(), message)
            else:
                fill(port.prepare(), message)
            count[0] += 1
            port.setEnvelope(self.yarp.Stamp(count[0], message.stamp))
            port.write(fill is not image_to)  # events strictly; a frame skips a busy reader
            self.counts[counter] += 1

        return write

    def ports(self) -> list[str]:
        """The names of every port the bridge serves."""
        names = [
            f"{board.name}/{leaf}"
            for board in self.boards.values()
            for leaf in ("rpc:i", "command:i", "state:o", "stateExt:o")
        ]
        return [*names, self.archery.name, *(port.getName() for port in self._ports)]

    def close(self) -> None:
        for stop in self._stops:
            stop()
        self._stops = []
        for board in self.boards.values():
            board.close()
        if hasattr(self, "archery"):
            self.archery.close()
        for port in self._ports:
            port.interrupt()
            close_port(self.yarp, port)
        self._ports = []
