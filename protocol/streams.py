"""What the viewers show of the mesh, declared once: the graph's streams as data.

Each `Stream` row names one output port of the mesh (`protocol/keys.py`'s `OUTPUT_PORTS`), its
message type, how a viewer follows it (the newest state, or every event) and, for each viewer,
the channels it shows it on, named as the viewer publishes them (`{part}`: each part's name).
A viewer maps the table: it follows `shown_by(viewer)`, each row through its conversion
(`apps/<viewer>/`: a dict keyed by the row's `name`, checked against the table by
`tests/test_streams.py`). A new stream reaches every viewer by one row here and one
conversion per viewer that shows it. The viewers: the dashboard (`apps/dashboard/`), Foxglove
(`apps/foxglove/`), ROS 2 (`apps/ros2/`) and YARP (`apps/yarp/`). The recorder (`archery
record`) is no viewer of the table: it keeps every output port's raw messages under their keys.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from archery.protocol.keys import OUTPUT_PORTS, Keys
from archery.protocol.messages import (
    Detection,
    Image,
    JointState,
    Rollout,
    WorldEvent,
    WorldState,
)
from archery.protocol.parts import PARTS

__all__ = ["STREAMS", "VIEWERS", "Stream", "shown_by", "stream"]

#: Every viewer of the mesh that maps the table.
VIEWERS: tuple[str, ...] = ("dashboard", "foxglove", "ros2", "yarp")

Message = type[JointState | WorldState | WorldEvent | Image | Detection | Rollout]


@dataclass(frozen=True)
class Stream:
    """One stream of the mesh a viewer may show.

    Attributes:
        name: the row's name, the key of each viewer's conversions.
        port: its output port's pattern after the robot's name (`OUTPUT_PORTS`).
        message: its message type.
        follow: "latest" (a state: a slow viewer skips to the newest) or "events" (every one).
        channels: {viewer: its channel names}; a viewer absent does not show the stream.
    """

    name: str
    port: str
    message: Message
    follow: Literal["latest", "events"]
    channels: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def keys(self, keys: Keys) -> tuple[str, ...]:
        """The stream's full keys on `keys`' robot: one per part for a part's port."""
        parts = PARTS if "{part}" in self.port else ("",)
        return tuple(f"{keys.robot}/{self.port.format(part=part)}" for part in parts)


def _row(
    name: str,
    port: str,
    message: Message,
    follow: Literal["latest", "events"],
    **channels: tuple[str, ...],
) -> Stream:
    return Stream(name, port, message, follow, MappingProxyType(channels))


#: The streams the viewers show (the camera's RPC, the taps and the inputs are no viewer's).
STREAMS: tuple[Stream, ...] = (
    _row(
        "joints",
        "{part}/state:o",
        JointState,
        "events",
        foxglove=("/joint_states",),
        ros2=("joint_states",),
        yarp=("/{part}/state:o", "/{part}/stateExt:o"),
    ),
    _row(
        "world",
        "world/state:o",
        WorldState,
        "latest",
        foxglove=("/tf",),
        ros2=("/tf",),
    ),
    _row(
        "events",
        "world/events:o",
        WorldEvent,
        "events",
        foxglove=("/world/events",),
        ros2=("world/landing",),
        yarp=("/world/events:o",),
    ),
    _row(
        "camera",
        "cam/target:o",
        Image,
        "latest",
        foxglove=("/camera/image", "/camera/calibration"),
        ros2=("camera/image_raw", "camera/camera_info"),
        yarp=("/cam/target:o",),
    ),
    _row(
        "detections",
        "detector/hit:o",
        Detection,
        "events",
        foxglove=("/camera/annotations",),
        yarp=("/detector/hit:o",),
    ),
    _row(
        "rollouts",
        "learner/rollout:o",
        Rollout,
        "events",
        dashboard=("rollouts",),
        foxglove=("/learner/rollouts",),
        ros2=("learner/rollout",),
    ),
)


def shown_by(viewer: str) -> tuple[Stream, ...]:
    """The rows `viewer` shows, in the table's order.

    Raises:
        KeyError: not one of `VIEWERS`.
    """
    if viewer not in VIEWERS:
        raise KeyError(f"unknown viewer {viewer!r}; viewers: {', '.join(VIEWERS)}")
    return tuple(row for row in STREAMS if viewer in row.channels)


def stream(name: str) -> Stream:
    """The row named `name` (KeyError naming the rows when there is none)."""
    for row in STREAMS:
        if row.name == name:
            return row
    raise KeyError(f"no stream {name!r}; streams: {', '.join(row.name for row in STREAMS)}")


assert {row.port for row in STREAMS} <= {spec.pattern for spec in OUTPUT_PORTS}
