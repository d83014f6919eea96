"""The live server: the Foxglove SDK's WebSocket server behind its front door
(`apps.foxglove.front_door`: Host, Origin, the operator's token, the connections), its
channels, and the feeds started as clients subscribe (`apps.foxglove.feeds`); with an operator,
its services and the wind parameter (`apps.foxglove.operator`)."""

from __future__ import annotations

import functools
import logging
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

from archery.apps.foxglove.channels import open_channels
from archery.apps.foxglove.feeds import Feeds
from archery.apps.foxglove.front_door import MAX_CONNECTIONS, FrontDoor
from archery.apps.foxglove.inner_tls import INNER_HOST, inner_tls
from archery.apps.foxglove.operator import WIND, Operator
from archery.apps.foxglove.upgrade import UpgradeRules, normal_origin
from archery.apps.topics.robot_frames import RobotFrames
from archery.mesh.node import Node
from archery.protocol.text import shown

__all__ = ["MAX_PARAMETERS", "Bridge", "asset"]

log = logging.getLogger("archery.foxglove")

#: Messages the SDK's server queues per client before it drops the oldest: a client that reads
#: slower than the camera sends holds at most this many frames (2.8 MB each when raw) in the
#: server. The SDK sizes its control queue alike, and drops a client whose queue of replies
#: fills: the assets (the 3D panel asks for all 39 meshes at once) are therefore answered by the
#: front door, one at a time per client, and never queue there (a backlog sized for them would
#: hold as many raw frames per client: 39 + the streams' ≈ 150 MB for each slow reader).
BACKLOG = 4
MAX_PARAMETERS = 16  # parameters one get/set message may name (the bridge has one: the wind)
SERVER_STOP_WAIT = 0.5  # s: the longest the bridge waits for the SDK's server to stop
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
            is read-only and its name says so. An operator's upgrades need `token`.
        token: the operator's secret a client gives in the URL (`?token=…`).
        origins: page origins accepted beside the Foxglove app's and this machine's.
        max_clients: connections served at once.
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
        token: str | None = None,
        origins: tuple[str, ...] = (),
        max_clients: int = MAX_CONNECTIONS,
    ) -> None:
        if operator and not token:
            raise ValueError("an operator's server needs a token")
        self.context = foxglove.Context()
        self.channels = open_channels(self.context, node.keys.robot, jpeg=jpeg)
        self._topics = {channel.id(): topic for topic, channel in self.channels.items()}
        self.feeds = Feeds(node, self.channels, frames, urdf, jpeg=jpeg)
        self.operator = Operator(node) if operator else None
        self.token = token if operator else None
        self._lock = threading.Lock()
        self._watchers: dict[str, set[int]] = {}  # topic -> ids of the clients watching it
        self._newcomers: set[str] = set()  # static topics a new watcher wants sent again
        self._changed = threading.Event()  # the watchers changed since the follower looked
        self._closing = False
        self._stops: dict[str, Callable[[], None]] = {}  # the follower thread's only
        self._thread = threading.Thread(target=self._follow, name="foxglove watchers", daemon=True)
        self._thread.start()
        capabilities = [Capability.Services, Capability.Parameters] if operator else []
        mode = "operator" if operator else "read-only"
        tls = inner_tls()
        self.server = foxglove.start_server(
            name=f"archery {node.keys.robot} ({mode})",
            host=INNER_HOST,
            port=0,
            capabilities=capabilities,
            server_listener=self,
            supported_encodings=["json"],
            services=self.operator.services() if self.operator else None,
            asset_handler=lambda uri: asset(meshes, uri),
            context=self.context,
            message_backlog_size=BACKLOG,
            tls_cert=tls.cert,
            tls_key=tls.key,
        )
        accepted = frozenset(normal_origin(origin) for origin in origins)
        try:
            self.door = FrontDoor(
                host,
                port,
                (INNER_HOST, self.server.port),
                tls.client,
                lambda bound: UpgradeRules(*bound, origins=accepted, token=self.token).refusal,
                max_connections=max_clients,
                assets=lambda uri: asset(meshes, uri),
            )
        except BaseException:
            self._stop_server()
            raise

    @property
    def port(self) -> int:
        """The port the server listens on (its front door's)."""
        return self.door.bound[1]

    def watched(self) -> dict[str, int]:
        """{topic: clients watching it} of the topics someone watches."""
        with self._lock:
            return {topic: len(ids) for topic, ids in self._watchers.items() if ids}

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._watch(True, client.id, channel.id)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._watch(False, client.id, channel.id)

    def _watch(self, subscribed: bool, client: int, channel: int) -> None:
        """Note a change of a topic's watchers; the follower thread acts on the latest state
        (the SDK calls the listener with its own locks held, and starting a feed takes time),
        so a client that subscribes and unsubscribes 3,000 times costs at most a few starts."""
        topic = self._topics.get(channel)
        if topic is None:
            return
        with self._lock:
            watchers = self._watchers.setdefault(topic, set())
            if subscribed:
                if client not in watchers and topic in ("/robot_description", "/scene"):
                    self._newcomers.add(topic)  # sent once per client: again for the newcomer
                watchers.add(client)
            else:
                watchers.discard(client)
        self._changed.set()

    def _follow(self) -> None:
        """Run the feed of each topic someone watches, and only those (the follower thread),
        until `close()`; then stop every feed."""
        try:
            while True:
                self._changed.wait()
                self._changed.clear()
                with self._lock:
                    if self._closing:
                        return
                    wanted = {topic for topic, ids in self._watchers.items() if ids}
                    newcomers, self._newcomers = self._newcomers, set()
                for topic in sorted(set(self._stops) - wanted):
                    self._act(topic, self._stops.pop(topic))
                for topic in sorted(wanted - set(self._stops)):
                    self._act(topic, functools.partial(self._start, topic))
                for topic in newcomers & set(self._stops):
                    self.feeds.resend(topic)
        finally:
            for topic in sorted(self._stops):
                self._act(topic, self._stops.pop(topic))

    def _start(self, topic: str) -> None:
        self._stops[topic] = self.feeds.start(topic)

    def _act(self, topic: str, action: Callable[[], None]) -> None:
        try:
            action()
        except Exception:
            log.exception("%s: could not follow the change of its watchers", topic)

    def on_get_parameters(
        self, client: Client, param_names: list[str], request_id: str | None = None
    ) -> list[Parameter]:
        if self.operator is None:
            return []
        if len(param_names) > MAX_PARAMETERS:
            self._refuse(
                f"getParameters names {len(param_names)} parameters (at most {MAX_PARAMETERS})"
            )
            return []
        if param_names and WIND not in param_names:
            return []
        wind = self.operator.wind()
        if wind is None:
            return []
        return [_wind(wind)]

    def on_set_parameters(
        self, client: Client, parameters: list[Parameter], request_id: str | None = None
    ) -> list[Parameter]:
        """Set the wind: one message sets at most `MAX_PARAMETERS` parameters, each name once
        (a repeated one: its last value), so the robot is asked at most once per message."""
        if self.operator is None:
            return []
        if len(parameters) > MAX_PARAMETERS:
            self._refuse(
                f"setParameters names {len(parameters)} parameters (at most {MAX_PARAMETERS}): "
                "nothing set"
            )
            return []
        latest = {parameter.name: parameter for parameter in parameters}
        unknown = [name for name in latest if name != WIND]
        if unknown:
            self._refuse(f"no parameter {shown(unknown)}: the bridge has only {WIND!r}")
        if WIND not in latest:
            return []
        try:
            wind: list[float] | None = self.operator.set_wind(latest[WIND].get_value())
        except Exception as exc:
            self._refuse(str(exc))
            wind = self.operator.wind()
        return [] if wind is None else [_wind(wind)]

    def _refuse(self, message: str) -> None:
        log.warning("refused: %s", message)
        self.server.publish_status(message, foxglove.StatusLevel.Error)

    def _stop_server(self) -> None:
        """Stop the SDK's server, waiting at most `SERVER_STOP_WAIT` s (its stop waits for
        every connection's task; the process exits after this either way), then the feeds."""
        stopping = threading.Thread(target=self.server.stop, name="foxglove stop", daemon=True)
        stopping.start()
        stopping.join(SERVER_STOP_WAIT)
        if stopping.is_alive():
            log.warning("the Foxglove server did not stop within %g s", SERVER_STOP_WAIT)
        with self._lock:
            self._closing = True
            self._newcomers.clear()
        self._changed.set()
        self._thread.join(5)

    def close(self) -> None:
        """Close the front door and every connection, stop the server and every feed (what
        the watchers' changes still asked is dropped)."""
        self.door.close()
        self._stop_server()
