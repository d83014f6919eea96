"""The live server: the Foxglove SDK's WebSocket server, its channels, and the feeds started as
clients subscribe (`apps.foxglove.feeds`); with an operator, its services and the wind
parameter (`apps.foxglove.operator`)."""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from pathlib import Path

import foxglove
from foxglove.websocket import (
    Capability,
    ChannelView,
    Client,
    Parameter,
    ParameterType,
    ServerListener,
)

from apps.foxglove.channels import open_channels
from apps.foxglove.feeds import Feeds
from apps.foxglove.operator import WIND, Operator
from apps.topics.robot_frames import RobotFrames
from mesh.node import Node

__all__ = ["Bridge", "asset"]

log = logging.getLogger("archery.foxglove")

#: Messages the server queues per client before it drops the oldest: a client that reads slower
#: than the camera sends holds at most this many frames (2.8 MB each when raw) in the
#: server. The SDK sizes its control queue alike: a client whose queue of replies fills is dropped.
BACKLOG = 16
MAX_ASSET_BYTES = 64 << 20  # a mesh file the client may fetch (the iCub's largest: ~2 MB)


def asset(root: Path, uri: str) -> bytes | None:
    """The file a `package://iCub/…` URI of the robot description names, read from `root`
    (icub-models' `iCub` folder); None for any other URI, a path leaving `root` or a file
    over `MAX_ASSET_BYTES`."""
    prefix = "package://iCub/"
    if not uri.startswith(prefix):
        return None
    path = (root / uri[len(prefix) :]).resolve()
    if not path.is_relative_to(root.resolve()) or not path.is_file():
        return None
    if path.stat().st_size > MAX_ASSET_BYTES:
        return None
    return path.read_bytes()


def _wind(wind: list[float]) -> Parameter:
    value: list[foxglove.AnyInnerParameterValue] = [*wind]
    return Parameter(WIND, value=value, type=ParameterType.Float64Array)


class Bridge(ServerListener):
    """Serves one robot's mesh to Foxglove clients until `close()`.

    Args:
        node: a node on the mesh, for the robot to follow (its keys).
        frames: the robot's 3D records (`RobotFrames`, built for the scene it runs).
        urdf: the robot description's text; `meshes` the folder its `package://iCub/` URIs
            name.
        host, port: where the server listens (port 0: a free one).
        jpeg: the camera's frames as JPEG.
        operator: serve the operator's services and the wind parameter; without it the server
            is read-only and its name says so.
    """

    def __init__(
        self,
        node: Node,
        frames: RobotFrames,
        urdf: str,
        meshes: Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        jpeg: bool = False,
        operator: bool = False,
    ) -> None:
        self.context = foxglove.Context()
        self.channels = open_channels(self.context, node.keys.robot, jpeg=jpeg)
        self._topics = {channel.id(): topic for topic, channel in self.channels.items()}
        self.feeds = Feeds(node, self.channels, frames, urdf, jpeg=jpeg)
        self.operator = Operator(node) if operator else None
        self._lock = threading.Lock()
        self._watchers: dict[str, set[int]] = {}  # topic -> ids of the clients watching it
        self._stops: dict[str, Callable[[], None]] = {}  # the bridge's thread's only
        self._changes: queue.SimpleQueue[tuple[bool, int, str] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._follow, name="foxglove watchers", daemon=True)
        self._thread.start()
        capabilities = [Capability.Services, Capability.Parameters] if operator else []
        mode = "operator" if operator else "read-only"
        self.server = foxglove.start_server(
            name=f"archery {node.keys.robot} ({mode})",
            host=host,
            port=port,
            capabilities=capabilities,
            server_listener=self,
            supported_encodings=["json"],
            services=self.operator.services() if self.operator else None,
            asset_handler=lambda uri: asset(meshes, uri),
            context=self.context,
            message_backlog_size=BACKLOG,
        )

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return self.server.port

    def watched(self) -> dict[str, int]:
        """{topic: clients watching it} of the topics someone watches."""
        with self._lock:
            return {topic: len(ids) for topic, ids in self._watchers.items() if ids}

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        topic = self._topics.get(channel.id)
        if topic is not None:  # handled on the bridge's thread: the SDK's own waits for nothing
            self._changes.put((True, client.id, topic))

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        topic = self._topics.get(channel.id)
        if topic is not None:
            self._changes.put((False, client.id, topic))

    def _follow(self) -> None:
        """Start a topic's feed at its first watcher, stop it after its last (the bridge's
        thread: the SDK calls the listener with its own locks held, and a feed logs)."""
        while True:
            change = self._changes.get()
            if change is None:
                return
            subscribed, client, topic = change
            with self._lock:
                watchers = self._watchers.setdefault(topic, set())
                before = len(watchers)
                (watchers.add if subscribed else watchers.discard)(client)
                after = len(watchers)
            try:
                if before == 0 and after == 1:
                    self._stops[topic] = self.feeds.start(topic)
                elif after == 0 and before == 1:
                    self._stops.pop(topic)()
                elif subscribed and after > before and topic in ("/robot_description", "/scene"):
                    self.feeds.resend(topic)  # sent once per client: again for the newcomer
            except Exception:
                log.exception("%s: could not follow the change of its watchers", topic)

    def on_get_parameters(
        self, client: Client, param_names: list[str], request_id: str | None = None
    ) -> list[Parameter]:
        if self.operator is None or (param_names and WIND not in param_names):
            return []
        wind = self.operator.wind()
        if wind is None:
            return []
        return [_wind(wind)]

    def on_set_parameters(
        self, client: Client, parameters: list[Parameter], request_id: str | None = None
    ) -> list[Parameter]:
        if self.operator is None:
            return []
        out = []
        for parameter in parameters:
            if parameter.name != WIND:
                self._refuse(f"no parameter {parameter.name!r}: the bridge has only {WIND!r}")
                continue
            try:
                wind: list[float] | None = self.operator.set_wind(parameter.get_value())
            except Exception as exc:
                self._refuse(str(exc))
                wind = self.operator.wind()
            if wind is not None:
                out.append(_wind(wind))
        return out

    def _refuse(self, message: str) -> None:
        log.warning("refused: %s", message)
        self.server.publish_status(message, foxglove.StatusLevel.Error)

    def close(self) -> None:
        """Stop the server and every feed."""
        self.server.stop()
        self._changes.put(None)
        self._thread.join(10)
        for stop in self._stops.values():
            stop()
        self._stops.clear()
