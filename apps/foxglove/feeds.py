"""The bridge's feeds: what each live topic follows of the mesh, started when a client first
subscribes to the topic and stopped when the last one leaves (a topic nobody watches costs the
mesh nothing: no subscription, so no publisher sends for it and the camera renders nothing).
A stream's topic follows its row of `protocol/streams.py` through its conversion (`CONVERSIONS`).

The camera is placed for the 3D panel: `/tf` carries its optical frame (`target_camera`, the
frames' `frame_id`: z forward, x right, y down) in `world`, from the scene's camera pose, and
`/camera/calibration` a `foxglove.CameraCalibration` per frame (its size; the focal length from
the camera's vertical field of view)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import foxglove

from archery.apps.follow import Stop, follow_stream
from archery.apps.foxglove.marks import event_log, image_marks, rollout_record
from archery.apps.port_rates import PortRates, stream_counts
from archery.apps.topics.foxglove_records import (
    camera_calibration,
    frame_transforms,
    joint_states,
)
from archery.apps.topics.image_records import FRAME_ID, image_record
from archery.apps.topics.robot_frames import RobotFrames
from archery.mesh.instances import describe_all
from archery.mesh.node import Node
from archery.mesh.tokens import TokenSet
from archery.protocol.messages import Image, JointState, WorldState
from archery.protocol.streams import Stream, shown_by, stream
from archery.sim.render import focal_length
from archery.sim.scene_config import TARGET_CAMERA

__all__ = ["CONVERSIONS", "Feeds", "jpeg_record"]

log = logging.getLogger("archery.foxglove")

SERVICES_EVERY = 1.0  # s: how often the services' liveliness and port rates are sent
STATIC_EVERY = 10.0  # s: how often the description and the scene are sent again while watched
RESEND_GAP = 1.0  # s: the least time between two sendings of the description or the scene
JPEG_QUALITY = 85


def jpeg_record(image: Image) -> bytes:
    """A frame as a `foxglove.CompressedImage` JPEG record (the bridge's `--jpeg`)."""
    import cv2
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from archery.apps.topics.foxglove_records import stamp
    from archery.apps.topics.image_records import FRAME_ID

    rgb = image.unpacked().to_numpy()
    ok, data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("the frame did not encode as JPEG")
    record = CompressedImage(frame_id=FRAME_ID, format="jpeg", data=data.tobytes())
    stamp(record.timestamp, round(image.stamp * 1e9))
    return record.SerializeToString()


class Feeds:
    """Starts and stops the feed of each topic (`start(topic)` returns its stop), logging what
    it derives on the topic's channel.

    Args:
        node: the bridge's node on the mesh.
        channels: {topic: channel} (`apps.foxglove.channels.open_channels`).
        frames: the robot's 3D records (`apps.topics.robot_frames`), the recorder's own.
        urdf: the robot description the robot runs (URDF text).
        jpeg: send the camera's frames as JPEG.
    """

    def __init__(
        self,
        node: Node,
        channels: dict[str, foxglove.Channel],
        frames: RobotFrames,
        urdf: str,
        *,
        jpeg: bool = False,
    ) -> None:
        self.node = node
        self.keys = node.keys
        self.channels = channels
        self.frames = frames
        self.urdf = urdf
        self.jpeg = jpeg
        self.sent: dict[str, int] = dict.fromkeys(channels, 0)  # messages logged per topic
        self._count = threading.Lock()
        self._scene_data: bytes | None = None
        self._camera_t, self._camera_q = frames.camera_pose()  # fixed in the world
        self._fovy = float(frames.model.camera(TARGET_CAMERA).fovy[0])  # degrees
        self._wanted: dict[str, threading.Event] = {}  # static topic -> a newcomer wants it
        #: the world states' key, which the robot's frames derive `/tf` from
        self.world_key = stream("world").keys(node.keys)[0]
        #: {topic: the stream table's row it shows}
        self._rows = {t: row for row in shown_by("foxglove") for t in row.channels["foxglove"]}
        self._starts: dict[str, Callable[[], Stop]] = {
            "/robot_description": self._description,
            "/scene": self._scene,
            "/mesh/services": self._services,
        }

    def start(self, topic: str) -> Stop:
        """Start following what `topic` shows; returns the function that stops it."""
        row = self._rows.get(topic)
        return self._starts[topic]() if row is None else self._follow(row, topic)

    def _follow(self, row: Stream, topic: str) -> Stop:
        """Follow `row` of the stream table, each message logged on `topic` through its
        conversion (`CONVERSIONS`; a None is not sent), at the message's stamp."""
        conversion = CONVERSIONS[row.name][topic]

        def each(message: Any) -> None:
            data = conversion(self, message)
            if data is not None:
                self._log(topic, data, round(message.stamp * 1e9))

        return follow_stream(self.node, row, each, log, name=topic)

    def _log(self, topic: str, data: bytes | dict[str, Any], ns: int | None = None) -> None:
        channel = self.channels[topic]
        channel.log(data, log_time=ns if ns is not None else time.time_ns())
        with self._count:
            self.sent[topic] += 1

    # -- the robot's description: to each newcomer, and again while watched ------------------

    def _repeat(self, topic: str, data: Callable[[], bytes | dict[str, Any]]) -> Stop:
        """Send `data()` now, when a newcomer asks (`resend`) and every `STATIC_EVERY` s until
        stopped, never twice within `RESEND_GAP` s. A message goes to every watcher (the SDK
        has no per-client send), so newcomers arriving together share one sending, and a client
        whose queue overflowed with camera frames still gets it."""
        stop, wanted = threading.Event(), threading.Event()
        self._wanted[topic] = wanted
        wanted.set()

        def work() -> None:
            while True:
                wanted.wait(STATIC_EVERY)
                if stop.is_set():
                    return
                wanted.clear()
                self._log(topic, data())
                if stop.wait(RESEND_GAP):
                    return

        thread = threading.Thread(target=work, name=f"foxglove {topic}", daemon=True)
        thread.start()

        def close() -> None:
            stop.set()
            wanted.set()
            thread.join(5)
            self._wanted.pop(topic, None)

        return close

    def _description(self) -> Stop:
        return self._repeat("/robot_description", lambda: {"data": self.urdf})

    def _scene(self) -> Stop:
        return self._repeat("/scene", self.scene)

    def scene(self) -> bytes:
        """The scene's `foxglove.SceneUpdate` (built once: a few MB of meshes)."""
        if self._scene_data is None:
            self._scene_data = self.frames.scene_update(time.time_ns()).data
        return self._scene_data

    def resend(self, topic: str) -> None:
        """Send a static topic (`/robot_description`, `/scene`) again soon, for a newcomer."""
        wanted = self._wanted.get(topic)
        if wanted is not None:
            wanted.set()

    # -- streams --------------------------------------------------------------------------------

    def camera_transform(self, ns: int) -> bytes:
        """The camera's optical frame in `world` as a `foxglove.FrameTransforms` record (two
        records' bytes joined are one record with the transforms of both)."""
        return frame_transforms(
            ns, [("world", FRAME_ID)], self._camera_t[None, :], self._camera_q[None, :]
        )

    def calibration(self, image: Image) -> bytes:
        """The `foxglove.CameraCalibration` of a frame: its size, fy = (h / 2) / tan(fovy / 2)
        and fx = fy (square pixels)."""
        focal = focal_length(image.height, self._fovy)
        ns = round(image.stamp * 1e9)
        return camera_calibration(ns, FRAME_ID, image.width, image.height, focal)

    def _services(self) -> Stop:
        """The live services and each stream port's rate, every `SERVICES_EVERY` s."""
        stop = threading.Event()
        alive = TokenSet(self.node.session, self.keys.alive_all())
        rates = PortRates()

        def work() -> None:
            while not stop.is_set():
                started = time.monotonic()
                described = describe_all(self.node.session, self.keys, timeout=SERVICES_EVERY)
                rates.update(stream_counts(described))
                names = sorted(alive.present())
                self._log("/mesh/services", {"alive": names, "ports": rates.table()})
                stop.wait(max(0.0, SERVICES_EVERY - (time.monotonic() - started)))

        thread = threading.Thread(target=work, name="foxglove /mesh/services", daemon=True)
        thread.start()

        def close() -> None:
            stop.set()
            thread.join(5 * SERVICES_EVERY)
            alive.close()

        return close


# -- the conversions: a row's message as its topic's record (None: nothing sent) ----------------


def _tf(feeds: Feeds, state: WorldState) -> bytes | None:
    ns = round(state.stamp * 1e9)
    for record in feeds.frames.derive(feeds.world_key, state, ns):  # none: another scene's
        return record.data + feeds.camera_transform(ns)
    return None


def _joints(feeds: Feeds, state: JointState) -> bytes:
    return joint_states(round(state.stamp * 1e9), state.names, state.position, state.velocity)


def _image(feeds: Feeds, image: Image) -> bytes:
    return jpeg_record(image) if feeds.jpeg else image_record(image)[1]


Conversion = Callable[[Feeds, Any], bytes | dict[str, Any] | None]
#: {row of the stream table the bridge shows: {its topic: the conversion of a row's message to
#: the topic's record, or None}}.
CONVERSIONS: dict[str, dict[str, Conversion]] = {
    "joints": {"/joint_states": _joints},
    "world": {"/tf": _tf},
    "events": {"/world/events": lambda feeds, event: event_log(event, feeds.keys.robot)},
    "camera": {"/camera/image": _image, "/camera/calibration": Feeds.calibration},
    "detections": {"/camera/annotations": lambda feeds, detection: image_marks(detection)},
    "rollouts": {"/learner/rollouts": lambda feeds, rollout: rollout_record(rollout)},
}
