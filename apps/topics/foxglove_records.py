"""Foxglove's schemas as protobuf records: frame transforms, joint states, a scene of meshes and
primitives, image annotations, a camera's calibration and logs, with the schema data (a
`FileDescriptorSet`) a channel carries.

Poses are metres and unit quaternions (x, y, z, w, Foxglove's order); times are ns since the
epoch. The messages are Foxglove's own (`foxglove-schemas-protobuf`), unextended.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from functools import cache
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor

__all__ = [
    "CAMERA_CALIBRATION",
    "DERIVED_SCHEMAS",
    "FRAME_TRANSFORMS",
    "IMAGE_ANNOTATIONS",
    "JOINT_STATES",
    "LOG",
    "SCENE_UPDATE",
    "camera_calibration",
    "frame_transforms",
    "joint_states",
    "schema_data",
    "stamp",
    "stl_bytes",
]

FRAME_TRANSFORMS = "foxglove.FrameTransforms"
JOINT_STATES = "foxglove.JointStates"
SCENE_UPDATE = "foxglove.SceneUpdate"
IMAGE_ANNOTATIONS = "foxglove.ImageAnnotations"  # the live bridge's, no recording's
LOG = "foxglove.Log"
CAMERA_CALIBRATION = "foxglove.CameraCalibration"  # the live bridge's, no recording's
#: Schemas of the records a recorder derives (no mesh message has them: a replay skips them).
DERIVED_SCHEMAS = frozenset({FRAME_TRANSFORMS, JOINT_STATES, SCENE_UPDATE})
_CLASSES: dict[str, Any] = {
    FRAME_TRANSFORMS: FrameTransforms,
    JOINT_STATES: JointStates,
    SCENE_UPDATE: SceneUpdate,
    IMAGE_ANNOTATIONS: ImageAnnotations,
    LOG: Log,
    CAMERA_CALIBRATION: CameraCalibration,
}


def _files(file: FileDescriptor, seen: dict[str, descriptor_pb2.FileDescriptorProto]) -> None:
    """`file` and its dependencies, dependencies first, into `seen`."""
    for dependency in file.dependencies:
        if dependency.name not in seen:
            _files(dependency, seen)
    proto = descriptor_pb2.FileDescriptorProto()
    file.CopyToProto(proto)
    seen[file.name] = proto


@cache
def schema_data(name: str) -> bytes:
    """The serialized `FileDescriptorSet` of the schema `name` (one of this module's names)."""
    seen: dict[str, descriptor_pb2.FileDescriptorProto] = {}
    _files(_CLASSES[name].DESCRIPTOR.file, seen)
    return descriptor_pb2.FileDescriptorSet(file=list(seen.values())).SerializeToString()


def stamp(target: Any, ns: int) -> None:
    """Set a protobuf `Timestamp` field to `ns` ns since the epoch."""
    target.seconds, target.nanos = divmod(int(ns), 1_000_000_000)


def frame_transforms(
    ns: int,
    links: Sequence[tuple[str, str]],
    translations: np.ndarray,
    rotations: np.ndarray,
) -> bytes:
    """A `foxglove.FrameTransforms` record: link i is `links[i]` = (parent, child), placed at
    `translations[i]` (m) and `rotations[i]` (w, x, y, z) in its parent's frame."""
    message = FrameTransforms()
    for (parent, child), t, q in zip(links, translations, rotations, strict=True):
        transform = message.transforms.add(parent_frame_id=parent, child_frame_id=child)
        stamp(transform.timestamp, ns)
        transform.translation.x, transform.translation.y, transform.translation.z = map(float, t)
        rotation = transform.rotation
        rotation.w, rotation.x, rotation.y, rotation.z = map(float, q)
    return message.SerializeToString()


def camera_calibration(ns: int, frame_id: str, width: int, height: int, focal: float) -> bytes:
    """A `foxglove.CameraCalibration` record of a pinhole camera without distortion: focal
    length `focal` (px) on both axes (square pixels), the principal point at the image's centre
    in Foxglove's pixel coordinates ((0, 0) the top-left corner of the top-left pixel: cx =
    width / 2, cy = height / 2); `frame_id` the optical frame (z forward, x right, y down)."""
    cx, cy = 0.5 * width, 0.5 * height
    message = CameraCalibration(
        frame_id=frame_id,
        width=width,
        height=height,
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[focal, 0.0, cx, 0.0, focal, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[focal, 0.0, cx, 0.0, 0.0, focal, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )
    stamp(message.timestamp, ns)
    return message.SerializeToString()


def joint_states(
    ns: int, names: Iterable[str], position: Iterable[float], velocity: Iterable[float]
) -> bytes:
    """A `foxglove.JointStates` record: each joint's position (rad) and velocity (rad/s)."""
    message = JointStates()
    stamp(message.timestamp, ns)
    for name, q, dq in zip(names, position, velocity, strict=True):
        message.joints.add(name=name, position=q, velocity=dq)
    return message.SerializeToString()


def stl_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary STL of the triangles `faces` (N, 3 vertex indices) of `vertices` (M, 3, m)."""
    triangles = np.asarray(vertices, dtype=np.float32)[np.asarray(faces)]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    record = np.zeros(
        len(triangles), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")]
    )
    record["n"], record["v"] = normals, triangles
    header = b"archery mesh".ljust(80, b" ")
    return header + np.uint32(len(triangles)).tobytes() + record.tobytes()
