"""The mesh's messages as ROS 2's standard messages, and ROS 2 commands as the robot's verbs (a
part's position targets, or a trajectory the robot plays at its points' times): the mapping
of the node and of `archery export --ros2` (docs/ros2.md tells it
topic by topic). Stamps are the mesh's wall stamps (s since the epoch)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from archery.apps.ros2.typestore import new
from archery.apps.topics.image_records import FRAME_ID
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Image, JointState, Rollout, WorldEvent
from archery.protocol.parts import PARTS
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv

if TYPE_CHECKING:
    from archery.apps.topics.robot_frames import RobotFrames

__all__ = [
    "FLOAT_COMMAND",
    "LANDING_FRAME",
    "ROLLOUT_SEGMENTS",
    "TRAJECTORY_COMMAND",
    "CommandError",
    "camera_info",
    "command_args",
    "description",
    "image",
    "joint_state",
    "landing",
    "rollout",
    "stamp",
    "static_tf",
    "tf_message",
]

FLOAT_COMMAND = "std_msgs/msg/Float64MultiArray"
TRAJECTORY_COMMAND = "trajectory_msgs/msg/JointTrajectory"
LANDING_FRAME = "target"  # the target plane: x to the robot's right, y up (m)
#: The segments of a rollout's `data`, in order, each labelled by one dimension of its layout.
ROLLOUT_SEGMENTS = ("rollout", "hit", "distance_m", "theta_m", "r_m")


class CommandError(ValueError):
    """A ROS 2 command that moves nothing: it names the part and what is wrong."""


def stamp(seconds: float) -> Any:
    """A `builtin_interfaces/msg/Time` of a wall stamp (s since the epoch)."""
    ns = max(0, round(seconds * 1e9))
    return new("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(seconds: float, frame: str) -> Any:
    return new("std_msgs/msg/Header", stamp=stamp(seconds), frame_id=frame)


def joint_state(state: JointState) -> Any:
    """A part's `state:o` as `sensor_msgs/msg/JointState`: its joints' URDF names, positions
    (rad) and velocities (rad/s); no efforts."""
    return new(
        "sensor_msgs/msg/JointState",
        header=_header(state.stamp, ""),
        name=list(state.names),
        position=np.asarray(state.position, dtype=np.float64),
        velocity=np.asarray(state.velocity, dtype=np.float64),
        effort=np.zeros(0, dtype=np.float64),
    )


def tf_message(
    seconds: float,
    links: Sequence[tuple[str, str]],
    translations: np.ndarray,
    rotations: np.ndarray,
) -> Any:
    """A `tf2_msgs/msg/TFMessage`: link i is `links[i]` = (parent, child) at `translations[i]`
    (m) and `rotations[i]` (w, x, y, z) in its parent's frame."""
    transforms = []
    for (parent, child), t, q in zip(links, translations, rotations, strict=True):
        transform = new(
            "geometry_msgs/msg/Transform",
            translation=new(
                "geometry_msgs/msg/Vector3", x=float(t[0]), y=float(t[1]), z=float(t[2])
            ),
            rotation=new(
                "geometry_msgs/msg/Quaternion",
                x=float(q[1]),
                y=float(q[2]),
                z=float(q[3]),
                w=float(q[0]),
            ),
        )
        transforms.append(
            new(
                "geometry_msgs/msg/TransformStamped",
                header=_header(seconds, parent),
                child_frame_id=child,
                transform=transform,
            )
        )
    return new("tf2_msgs/msg/TFMessage", transforms=transforms)


def static_tf(frames: RobotFrames, seconds: float) -> Any:
    """`/tf_static` at wall stamp `seconds`: the robot's fixed transforms (`world` to the URDF's
    root, then every fixed joint of the URDF) and the camera's optical frame in `world` (the
    image's `frame_id`)."""
    translations, rotations = frames.static_poses()
    camera_t, camera_q = frames.camera_pose()
    return tf_message(
        seconds,
        [*frames.static_links, ("world", FRAME_ID)],
        np.concatenate([translations, camera_t[None, :]]),
        np.concatenate([rotations, camera_q[None, :]]),
    )


def description(urdf: str) -> Any:
    """The robot description (URDF text) as `std_msgs/msg/String`."""
    return new("std_msgs/msg/String", data=urdf)


def image(frame: Image, frame_id: str) -> Any:
    """A camera frame as `sensor_msgs/msg/Image`: `rgb8` (a colour frame of any encoding,
    decoded) or `mono8`, rows packed (`step` = width × channels).

    Raises:
        ValueError: a compressed frame that does not decode."""
    pixels = frame.to_numpy()
    encoding = "mono8" if pixels.ndim == 2 else "rgb8"
    pixels = np.ascontiguousarray(pixels)
    height, width = pixels.shape[:2]
    return new(
        "sensor_msgs/msg/Image",
        header=_header(frame.stamp, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=pixels.strides[0],
        data=pixels.reshape(-1),
    )


def camera_info(seconds: float, frame_id: str, width: int, height: int, focal: float) -> Any:
    """`sensor_msgs/msg/CameraInfo` of the rendered pinhole camera: focal length `focal` (px),
    the principal point at the image's centre (pixel (0, 0) centred on its top-left pixel), no
    distortion."""
    cx, cy = 0.5 * width - 0.5, 0.5 * height - 0.5
    return new(
        "sensor_msgs/msg/CameraInfo",
        header=_header(seconds, frame_id),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=np.array([focal, 0, cx, 0, focal, cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3, dtype=np.float64).reshape(-1),
        p=np.array([focal, 0, cx, 0, 0, focal, cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=0,
        binning_y=0,
        roi=new(
            "sensor_msgs/msg/RegionOfInterest",
            x_offset=0,
            y_offset=0,
            height=0,
            width=0,
            do_rectify=False,
        ),
    )


def rollout(message: Rollout) -> Any | None:
    """A done rollout as `std_msgs/msg/Float64MultiArray`: `data` is the rollout number, hit
    (1 or 0), ‖r‖ (m), θ (m) and r (m), one after the other; the layout's dimensions label these
    segments in order (`ROLLOUT_SEGMENTS`, each with its size). None for a proposed or aborted
    rollout."""
    done = message.record
    if not isinstance(done, DoneRecord):
        return None
    values: list[list[float]] = [
        [float(done.rollout)],
        [1.0 if done.hit else 0.0],
        [float(done.distance_m)],
        [float(v) for v in done.theta],
        [float(v) for v in done.r_m],
    ]
    dims = [
        new("std_msgs/msg/MultiArrayDimension", label=label, size=len(part), stride=len(part))
        for label, part in zip(ROLLOUT_SEGMENTS, values, strict=True)
    ]
    return new(
        FLOAT_COMMAND,
        layout=new("std_msgs/msg/MultiArrayLayout", dim=dims, data_offset=0),
        data=np.array([v for part in values for v in part], dtype=np.float64),
    )


def landing(event: WorldEvent) -> Any | None:
    """A `landed` or `missed` event as `geometry_msgs/msg/PointStamped`: the ground-truth
    impact on the target plane (frame `target`: x to the robot's right, y up; m). None for
    other events and for a landing without an impact."""
    if event.kind not in ("landed", "missed") or not event.impact_m:
        return None
    x, y, z = ([*event.impact_m, 0.0, 0.0])[:3]
    return new(
        "geometry_msgs/msg/PointStamped",
        header=_header(event.stamp, LANDING_FRAME),
        point=new("geometry_msgs/msg/Point", x=float(x), y=float(y), z=float(z)),
    )


def _finite(part: str, values: Sequence[float], what: str = "a command") -> list[float]:
    out = [float(v) for v in values]
    if not all(math.isfinite(v) for v in out):
        raise CommandError(f"{part}: {what} holds NaN or an infinite value")
    return out


def _seconds(duration: Any) -> float:
    """A `builtin_interfaces/msg/Duration` in s."""
    return (int(duration.sec) * 1_000_000_000 + int(duration.nanosec)) / 1e9


def command_args(
    part: str, ros_type: str, message: Any
) -> rv.PositionMoveArgs | rv.PartTrajectoryArgs:
    """The robot verb's arguments of a ROS 2 command for `part`:

    * `std_msgs/msg/Float64MultiArray`: `positionMove`, one position (rad) per joint of the
      part, in its order (`protocol.parts.PARTS`);
    * `trajectory_msgs/msg/JointTrajectory`: `followTrajectory`, played by the robot in its own
      loop. `joint_names` are some of the part's joints, each once; each point's
      `time_from_start` (sec + nanosec, s of simulated time from when the robot accepts it;
      > 0 and increasing from point to point) is its waypoint's time, its `positions` (rad) the
      waypoint; the `velocities` (rad/s) are passed when every point carries them (else the
      robot takes its own). The header's stamp, the accelerations and the efforts are not
      used; the tolerances are the verb's defaults.

    Raises:
        CommandError: the wrong count, an unknown or repeated joint, no point, a time at or
            below 0 s or not after the one before, more than `MAX_TRAJECTORY_POINTS` points or
            `MAX_TRAJECTORY_DURATION` s, NaN or infinity.
    """
    joints = PARTS[part]
    if ros_type == FLOAT_COMMAND:
        data = list(message.data)
        if len(data) != len(joints):
            raise CommandError(
                f"{part}: a command needs {len(joints)} positions ({', '.join(joints)}), "
                f"got {len(data)}"
            )
        return rv.PositionMoveArgs(position=_finite(part, data))
    names = list(message.joint_names)
    if len(names) > len(joints) or not names or len(set(names)) != len(names):
        raise CommandError(
            f"{part}: joint_names must be some of {', '.join(joints)}, each once; got "
            f"{shown(names)}"
        )
    unknown = [n for n in names if n not in joints]
    if unknown:
        raise CommandError(
            f"{part}: joint_names must be some of {', '.join(joints)}; unknown: {shown(unknown)}"
        )
    points = message.points
    if not points:
        raise CommandError(f"{part}: a trajectory without points moves nothing")
    if len(points) > rv.MAX_TRAJECTORY_POINTS:
        raise CommandError(
            f"{part}: a trajectory of {len(points)} points, more than {rv.MAX_TRAJECTORY_POINTS}"
        )
    times = [_seconds(point.time_from_start) for point in points]
    if times[0] <= 0.0 or any(b <= a for a, b in itertools.pairwise(times)):
        raise CommandError(
            f"{part}: time_from_start must be > 0 s and increase from point to point; got "
            f"{shown(times)}"
        )
    if times[-1] > rv.MAX_TRAJECTORY_DURATION:
        raise CommandError(
            f"{part}: the last point at {times[-1]:g} s is past {rv.MAX_TRAJECTORY_DURATION:g} s"
        )
    positions: list[list[float]] = []
    velocities: list[list[float]] | None = []
    for i, point in enumerate(points):
        row = list(point.positions)
        if len(row) != len(names):
            raise CommandError(
                f"{part}: point {i} has {len(row)} positions for {len(names)} joint names"
            )
        positions.append(_finite(part, row, f"point {i}'s positions"))
        speeds = list(point.velocities)
        if speeds and len(speeds) != len(names):
            raise CommandError(
                f"{part}: point {i} has {len(speeds)} velocities for {len(names)} joint names"
            )
        speeds = _finite(part, speeds, f"point {i}'s velocities")
        if not speeds:
            velocities = None
        elif velocities is not None:
            velocities.append(speeds)
    return rv.PartTrajectoryArgs(
        times=times, positions=positions, velocities=velocities, names=names
    )
