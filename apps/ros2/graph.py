"""The node on the ROS 2 graph: its topics (the table below, docs/ros2.md tells each beside its
YARP port), the feeds that follow the mesh's streams (the rows of `protocol/streams.py` the
node shows, each through its conversions: `CONVERSIONS`) while a ROS 2 subscriber matches, the
parts' commands (position targets, and trajectories the robot plays at their points' times)
and, with an operator, the archery services, all through one `RobotClient`. Bad input is
dropped and counted (`Ros2Node.counts`) or refused with a clear log line; nothing moves for
it."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import zenoh

from archery.apps.follow import Stop, follow_stream
from archery.apps.ros2 import convert, typestore
from archery.apps.ros2.endpoints import Counts, RosPublisher
from archery.apps.ros2.latest import LatestPerKey
from archery.apps.ros2.wire import (
    Attachment,
    AttachmentError,
    Endpoint,
    Kind,
    NodeId,
    Qos,
    check_name,
)
from archery.apps.topics.image_records import FRAME_ID
from archery.apps.topics.robot_frames import RobotFrames
from archery.mesh.acl import ROS2_COMMANDS
from archery.mesh.instances import zid_of
from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import ArcheryError
from archery.protocol.messages import Image, WorldState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import CALL_TIMEOUT, COMMAND_RATE, RPC_TIMEOUT
from archery.protocol.streams import Stream, shown_by
from archery.protocol.text import cut
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import Verb
from archery.sim.render import focal_length

__all__ = [
    "CONVERSIONS",
    "MAX_COMMAND_BYTES",
    "MAX_WAITING_CALLS",
    "NODE_NAME",
    "SERVICES",
    "TOPICS",
    "Ros2Node",
    "Topic",
]

log = logging.getLogger("archery.ros2")

NODE_NAME = "archery"
SERVICES: dict[str, Verb[Any, Any]] = {"reset": rv.RESET, "nock": rv.NOCK, "release": rv.RELEASE}
_STREAM = Qos(depth=10)
_LATCHED = Qos(depth=1, transient_local=True)
_SENSOR = Qos(depth=5, best_effort=True)
_COMMANDS = Qos(depth=1)  # KEEP_LAST 1: a newer command replaces the waiting one
#: The largest command payload decoded (bytes): a part's Float64MultiArray, or a JointTrajectory
#: of some hundreds of points (7 joints: 80 bytes a point, 136 with velocities), is under it; a
#: bigger one is dropped before any decoding.
MAX_COMMAND_BYTES = 64 * 1024
#: Service calls (reset, nock, release) waiting at once; one more is answered `success: false`.
MAX_WAITING_CALLS = 4
_LOG_LIMIT = 600  # characters of a reason in a log line (its received values quoted shorter)


@dataclass(frozen=True)
class Topic:
    """A published topic: its name (relative: under the namespace; absolute: as it is), type,
    QoS and the feed that fills it: the stream table's row that shows on it (None: sent once
    at the start, transient local)."""

    name: str
    ros_type: str
    qos: Qos
    feed: str | None


#: {topic: the name of the stream table's row it shows} (`channels["ros2"]` of each row)
_ROWS = {topic: row.name for row in shown_by("ros2") for topic in row.channels["ros2"]}


def _topic(name: str, ros_type: str, qos: Qos) -> Topic:
    return Topic(name, ros_type, qos, _ROWS.get(name))


TOPICS = (
    _topic("joint_states", "sensor_msgs/msg/JointState", _STREAM),
    _topic("/tf", "tf2_msgs/msg/TFMessage", _STREAM),
    _topic("/tf_static", "tf2_msgs/msg/TFMessage", _LATCHED),
    _topic("robot_description", "std_msgs/msg/String", _LATCHED),
    _topic("camera/image_raw", "sensor_msgs/msg/Image", _SENSOR),
    _topic("camera/camera_info", "sensor_msgs/msg/CameraInfo", _SENSOR),
    _topic("learner/rollout", convert.FLOAT_COMMAND, _STREAM),
    _topic("world/landing", "geometry_msgs/msg/PointStamped", _STREAM),
)
#: Each part's command topics (under `NAMESPACE/PART/`) and their types.
COMMANDS = dict(
    zip(ROS2_COMMANDS, (convert.FLOAT_COMMAND, convert.TRAJECTORY_COMMAND), strict=True)
)


class Ros2Node:
    """The robot of `node` on the ROS 2 graph of `domain`, until `close()`.

    Args:
        node: a node on the mesh (its session carries the ROS 2 entities; its robot's keys).
        frames: the robot's 3D records (`RobotFrames`, the recorder's own transforms).
        urdf: the robot description's text.
        camera_fovy: the target camera's vertical field of view (degrees).
        domain: the ROS 2 domain id (0…232).
        namespace: the node's namespace, e.g. `/icubSim`.
        operator: subscribe to the parts' commands and serve reset, nock and release;
            without it the node declares no command subscription and answers each service
            call `success: false`.
        rtf: the robot's real-time factor (its status' `rtf`; 0, as fast as it can, is taken
            as the wall clock's pace): how long a trajectory's call waits for the robot's reply
            at its end (wall s: `CALL_TIMEOUT` and twice its simulated duration ÷ rtf).

    A part's commands go through one keep-last slot per part (`LatestPerKey`), on a thread of
    their own for each part: while the robot plays a part's trajectory (it answers `busy` to
    anything else for that part until it ends) the part's newest command or trajectory waits
    in the slot, replacing an older one, and goes once the robot's reply has come.
    """

    def __init__(
        self,
        node: Node,
        frames: RobotFrames,
        urdf: str,
        camera_fovy: float,
        *,
        domain: int = 0,
        namespace: str = "/icubSim",
        operator: bool = False,
        rtf: float = 0.0,
    ) -> None:
        self.node = node
        self.keys = node.keys
        self.frames = frames
        self.camera_fovy = camera_fovy
        self.operator = operator
        self.rtf = rtf
        #: The robot's reply to each part's last trajectory, once it has ended.
        self.followed: dict[str, rv.TrajectoryReply] = {}
        self.namespace = check_name(namespace, "--namespace")
        self.ros = NodeId(domain, zid_of(node.session), 0, self.namespace, NODE_NAME)
        self.counts = Counts()
        self.robot = RobotClient(node)
        self._next_id = 0
        self._lock = threading.Lock()
        self._closables: list[Any] = []
        self._matched: dict[str, int] = {}  # feed (row) -> topics of it someone subscribes to
        self._stops: dict[str, Stop] = {}
        self._changes: queue.SimpleQueue[tuple[str, bool] | None] = queue.SimpleQueue()
        self._work: queue.Queue[Callable[[], None] | None] = queue.Queue(MAX_WAITING_CALLS + 1)
        self._commands = LatestPerKey(self._move, 1.0 / COMMAND_RATE, self.counts, log)
        self._rows = {row.name: row for row in shown_by("ros2")}
        self._threads = [
            threading.Thread(target=self._follow, name="ros2 feeds", daemon=True),
            threading.Thread(target=self._worker, name="ros2 calls", daemon=True),
            *(
                threading.Thread(target=self._commands.run, name="ros2 commands", daemon=True)
                for _ in PARTS
            ),
        ]
        for thread in self._threads:
            thread.start()
        session = node.session
        self._closables.append(session.liveliness().declare_token(self.ros.token()))
        self.publishers: dict[str, RosPublisher] = {}
        for topic in TOPICS:
            self.publishers[topic.name] = self._publisher(topic)
        self.publishers["/tf_static"].publish(self._static_tf())
        self.publishers["robot_description"].publish(convert.description(urdf))
        if operator:  # read-only: no command subscription at all (no subscriber, no token)
            for part in PARTS:
                for leaf, ros_type in COMMANDS.items():
                    self._subscribe(part, leaf, ros_type)
        for name in SERVICES:
            self._serve(name)

    # -- names and entities ---------------------------------------------------------------------
    def name(self, relative: str) -> str:
        """The fully qualified name of a topic or service (`/tf` stays as it is)."""
        if relative.startswith("/"):
            return relative
        return f"{self.namespace.rstrip('/')}/{relative}"

    def endpoint(self, kind: Kind, relative: str, ros_type: str, qos: Qos) -> Endpoint:
        """A new entity of this node (the next entity id)."""
        with self._lock:
            self._next_id += 1
            entity = self._next_id
        name = self.name(relative)
        hash_ = typestore.type_hash(ros_type)
        return Endpoint(self.ros, entity, kind, name, typestore.dds_type_name(ros_type), hash_, qos)

    def _publisher(self, topic: Topic) -> RosPublisher:
        endpoint = self.endpoint(Kind.PUBLISHER, topic.name, topic.ros_type, topic.qos)
        feed = topic.feed
        on_match = None if feed is None else (lambda on: self._changes.put((feed, on)))
        publisher = RosPublisher(self.node.session, endpoint, topic.ros_type, self.counts, on_match)
        self._closables.append(publisher)
        return publisher

    # -- feeds: started at a topic's first subscriber, stopped after its last -------------------
    def _follow(self) -> None:
        while True:
            change = self._changes.get()
            if change is None:
                return
            feed, on = change
            before = self._matched.get(feed, 0)
            after = max(0, before + (1 if on else -1))
            self._matched[feed] = after
            try:
                if before == 0 and after == 1:
                    self._stops[feed] = self._feed(self._rows[feed])
                    log.info("feed %s started (a ROS 2 subscriber matched)", feed)
                elif before == 1 and after == 0 and feed in self._stops:
                    self._stops.pop(feed)()
                    log.info("feed %s stopped (no ROS 2 subscriber left)", feed)
            except Exception:
                log.exception("feed %s: could not follow its subscribers' change", feed)

    def _feed(self, row: Stream) -> Stop:
        """Follow `row` of the stream table, each message sent on the row's topics through
        their conversions (`CONVERSIONS`; a None is not sent)."""
        conversions = CONVERSIONS[row.name]

        def each(message: Any) -> None:
            for topic, conversion in conversions.items():
                self._send(topic, conversion(self, message))

        return follow_stream(self.node, row, each, log, name=row.channels["ros2"][0])

    def _send(self, topic: str, message: Any) -> None:
        if message is not None:
            self.publishers[topic].publish(message)

    def _static_tf(self) -> Any:
        """`/tf_static`: the URDF's fixed joints (and `world` to its root), and the camera's
        optical frame in `world` (the image's `frame_id`)."""
        return convert.static_tf(self.frames, time.time())

    # -- commands ----------------------------------------------------------------------------
    def _subscribe(self, part: str, leaf: str, ros_type: str) -> None:
        """A part's command subscription (with the operator only): each good command replaces
        the part's waiting one (KEEP_LAST, depth 1: a stale command is dropped, never sent);
        the call to the robot runs on the commands' threads, never on Zenoh's."""
        endpoint = self.endpoint(Kind.SUBSCRIPTION, f"{part}/{leaf}", ros_type, _COMMANDS)
        session = self.node.session

        def each(sample: zenoh.Sample) -> None:
            message = self._received(endpoint.name, ros_type, sample)
            if message is None:
                return
            try:
                args = convert.command_args(part, ros_type, message)
            except convert.CommandError as exc:
                self._refuse(endpoint.name, str(exc))
                return
            self._commands.offer(part, (part, endpoint.name, args))

        self._closables.append(session.declare_subscriber(endpoint.key(), each))
        self._closables.append(session.liveliness().declare_token(endpoint.token()))

    def _received(self, name: str, ros_type: str, sample: zenoh.Sample) -> Any | None:
        """The message of a received sample, or None (dropped and counted): no rmw_zenoh
        attachment, more than `MAX_COMMAND_BYTES` (refused before decoding), not CDR."""
        try:
            attachment = sample.attachment
            Attachment.decode(None if attachment is None else attachment.to_bytes())
        except AttachmentError as exc:
            self._drop(name, "attachment", str(exc))
            return None
        size = len(sample.payload)
        if size > MAX_COMMAND_BYTES:
            self._drop(name, "size", f"{size} bytes, more than a command's {MAX_COMMAND_BYTES}")
            return None
        try:
            return typestore.deserialize(sample.payload.to_bytes(), ros_type)
        except Exception as exc:  # rosbags raises a few kinds for bytes that are no message
            self._drop(name, "cdr", f"not a CDR {ros_type}: {cut(str(exc))}")
            return None

    def _drop(self, name: str, reason: str, why: str) -> None:
        self.counts.add(f"dropped {reason}")
        log.warning("%s: dropped a sample: %s", name, cut(why, _LOG_LIMIT))

    def _refuse(self, name: str, why: str) -> None:
        self.counts.add("refused")
        log.error("%s: refused, nothing moves: %s", name, cut(why, _LOG_LIMIT))

    def _move(self, command: tuple[str, str, rv.PositionMoveArgs | rv.PartTrajectoryArgs]) -> None:
        part, name, args = command
        try:
            if isinstance(args, rv.PositionMoveArgs):
                self.robot.part_call(part, rv.POSITION_MOVE, args, timeout=CALL_TIMEOUT)
                self.counts.add("commands")
                return
            reply = self.robot.part_call(
                part, rv.FOLLOW_PART_TRAJECTORY, args, timeout=self._trajectory_timeout(args)
            )
        except ArcheryError as exc:
            self._refuse(name, f"the robot says: {exc}")
            return
        self.followed[part] = reply
        self.counts.add("trajectories")
        log.info(
            "%s: followed %d points from sim time %.3f s to %.3f s (path error %.4f rad, "
            "goal error %.4f rad)",
            name,
            len(args.times),
            reply.started,
            reply.ended,
            reply.path_error,
            reply.goal_error,
        )

    def _trajectory_timeout(self, args: rv.PartTrajectoryArgs) -> float:
        """How long (wall s) a trajectory's call waits for the robot's reply at its end: twice
        its simulated time (last point and goal time) at the robot's pace, and `CALL_TIMEOUT`."""
        pace = self.rtf if self.rtf > 0 else 1.0
        return CALL_TIMEOUT + 2.0 * (args.times[-1] + args.goal_time) / pace

    # -- services ------------------------------------------------------------------------------
    def _serve(self, name: str) -> None:
        """A Trigger service, declared always (its queryable and `SS` token): without the
        operator each call is answered `success: false` at once; with it the call waits on
        the services' own thread (never behind the commands), `MAX_WAITING_CALLS` at most."""
        endpoint = self.endpoint(Kind.SERVICE, name, typestore.TRIGGER, _STREAM)
        verb = SERVICES[name]
        session = self.node.session

        def each(query: zenoh.Query) -> None:
            attachment = query.attachment
            try:
                request = Attachment.decode(None if attachment is None else attachment.to_bytes())
            except AttachmentError as exc:
                self._drop(endpoint.name, "attachment", str(exc))
                query.reply_err(f"{endpoint.name}: {exc}".encode())
                return
            if not self.operator:
                why = f"{endpoint.name}: archery ros2 runs without --operator: nothing was done"
                self._refuse(endpoint.name, "a call without the operator")
                self._answer(query, request, endpoint.key(), False, why)
                return
            try:
                self._work.put_nowait(lambda: self._call(query, request, endpoint, verb))
            except queue.Full:
                why = f"{endpoint.name}: {MAX_WAITING_CALLS} calls wait already: nothing was done"
                self._refuse(endpoint.name, "too many calls waiting")
                self._answer(query, request, endpoint.key(), False, why)

        self._closables.append(session.declare_queryable(endpoint.key(), each, complete=True))
        self._closables.append(session.liveliness().declare_token(endpoint.token()))

    def _call(
        self, query: zenoh.Query, request: Attachment, endpoint: Endpoint, verb: Verb[Any, Any]
    ) -> None:
        try:
            reply = self.robot.call(verb, timeout=RPC_TIMEOUT)
        except ArcheryError as exc:
            self._refuse(endpoint.name, f"the robot says: {exc}")
            self._answer(query, request, endpoint.key(), False, f"{verb.name}: {exc}")
            return
        self.counts.add("services")
        text = msgspec.json.encode(reply).decode()
        self._answer(query, request, endpoint.key(), True, f"{verb.name}: {text}")

    def _answer(
        self, query: zenoh.Query, request: Attachment, key: str, ok: bool, text: str
    ) -> None:
        """Reply `Trigger_Response(ok, text)`, its attachment echoing the request's sequence
        number and GID with a new timestamp (as rmw_zenoh's services do)."""
        response = typestore.new(f"{typestore.TRIGGER}_Response", success=ok, message=text)
        data = typestore.serialize(response, f"{typestore.TRIGGER}_Response")
        attachment = Attachment(request.sequence, time.time_ns(), request.gid).encode()
        try:
            query.reply(key, data, attachment=attachment)
        finally:
            query.drop()

    def _worker(self) -> None:
        while True:
            job = self._work.get()
            if job is None:
                return
            try:
                job()
            except Exception:
                log.exception("a service call failed")

    def close(self) -> None:
        """Stop the feeds and undeclare every entity (tokens first)."""
        self._changes.put(None)
        self._commands.close()
        self._work.put(None)
        deadline = time.monotonic() + CALL_TIMEOUT  # a trajectory under way ends on its own
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        for stop in self._stops.values():
            stop()
        self._stops.clear()
        self.robot.close()
        tokens = [c for c in self._closables if isinstance(c, zenoh.LivelinessToken)]
        others = [c for c in self._closables if not isinstance(c, zenoh.LivelinessToken)]
        for item in [*tokens, *reversed(others)]:
            try:
                (item.close if isinstance(item, RosPublisher) else item.undeclare)()
            except Exception as exc:  # closing goes on whatever one part raises
                log.debug("%s not undeclared: %s", type(item).__name__, exc)


# -- the conversions: each row's messages as its topics' (None: nothing sent) -------------------


def _tf(ros: Ros2Node, state: WorldState) -> Any:
    poses = ros.frames.state_poses(state)
    return None if poses is None else convert.tf_message(state.stamp, ros.frames.links, *poses)


def _camera_info(ros: Ros2Node, frame: Image) -> Any:
    focal = focal_length(frame.height, ros.camera_fovy)
    return convert.camera_info(frame.stamp, FRAME_ID, frame.width, frame.height, focal)


Conversion = Callable[[Ros2Node, Any], Any]
#: {row of the stream table the node shows: {its topic: the conversion of a row's message to
#: the topic's message, or None}}, in the order they are sent (a frame's image before its info).
CONVERSIONS: dict[str, dict[str, Conversion]] = {
    "joints": {"joint_states": lambda ros, state: convert.joint_state(state)},
    "world": {"/tf": _tf},  # another scene's state (its poses unknown here) sends nothing
    "events": {"world/landing": lambda ros, event: convert.landing(event)},
    "camera": {
        "camera/image_raw": lambda ros, frame: convert.image(frame, FRAME_ID),
        "camera/camera_info": _camera_info,
    },
    "rollouts": {"learner/rollout": lambda ros, rollout: convert.rollout(rollout)},
}
