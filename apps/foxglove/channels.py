"""The bridge's channels: each live topic with its schema, and the Foxglove SDK channel made
for it. Topic names follow ROS 2's conventions (`/tf`, `/joint_states`, `/robot_description`);
the table in docs/foxglove.md maps each to the mesh key it follows."""

from __future__ import annotations

import json
from dataclasses import dataclass

import foxglove

from archery.apps.foxglove.marks import ROLLOUT_SCHEMA
from archery.apps.topics.foxglove_records import (
    CAMERA_CALIBRATION,
    FRAME_TRANSFORMS,
    IMAGE_ANNOTATIONS,
    JOINT_STATES,
    LOG,
    SCENE_UPDATE,
    schema_data,
)
from archery.apps.topics.image_records import COMPRESSED, RAW, image_schema

__all__ = ["CALIBRATION", "TOPICS", "Topic", "open_channels"]


@dataclass(frozen=True)
class Topic:
    """A live topic: its name, schema name and whether it is protobuf (else JSON)."""

    name: str
    schema: str
    protobuf: bool = True


_STRING_SCHEMA = {"type": "object", "properties": {"data": {"type": "string"}}}
_SERVICES_SCHEMA = {
    "type": "object",
    "title": "archery.MeshServices",
    "properties": {
        "alive": {"type": "array", "items": {"type": "string"}},
        "ports": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"key": {"type": "string"}, "hz": {"type": ["number", "null"]}},
            },
        },
    },
}
_JSON_SCHEMAS = {
    "std_msgs/msg/String": _STRING_SCHEMA,
    "archery.RolloutPoint": ROLLOUT_SCHEMA,
    "archery.MeshServices": _SERVICES_SCHEMA,
}

TF = Topic("/tf", FRAME_TRANSFORMS)
JOINTS = Topic("/joint_states", JOINT_STATES)
DESCRIPTION = Topic("/robot_description", "std_msgs/msg/String", protobuf=False)
SCENE = Topic("/scene", SCENE_UPDATE)
IMAGE = Topic("/camera/image", RAW)
IMAGE_JPEG = Topic("/camera/image", COMPRESSED)
CALIBRATION = Topic("/camera/calibration", CAMERA_CALIBRATION)
MARKS = Topic("/camera/annotations", IMAGE_ANNOTATIONS)
ROLLOUTS = Topic("/learner/rollouts", "archery.RolloutPoint", protobuf=False)
EVENTS = Topic("/world/events", LOG)
SERVICES = Topic("/mesh/services", "archery.MeshServices", protobuf=False)

#: Every topic the bridge serves (the camera's as raw frames; `--jpeg`: `IMAGE_JPEG`).
TOPICS = (TF, JOINTS, DESCRIPTION, SCENE, IMAGE, CALIBRATION, MARKS, ROLLOUTS, EVENTS, SERVICES)


def _schema(topic: Topic) -> foxglove.Schema:
    if not topic.protobuf:
        data = json.dumps(_JSON_SCHEMAS[topic.schema]).encode()
        return foxglove.Schema(name=topic.schema, encoding="jsonschema", data=data)
    if topic.schema in (RAW, COMPRESSED):
        data = image_schema(topic.schema)
    else:
        data = schema_data(topic.schema)
    return foxglove.Schema(name=topic.schema, encoding="protobuf", data=data)


def open_channels(
    context: foxglove.Context, robot: str, *, jpeg: bool = False
) -> dict[str, foxglove.Channel]:
    """{topic name: channel} of every topic in `context`, each carrying its robot's name in
    its metadata."""
    channels = {}
    for topic in TOPICS:
        if topic is IMAGE and jpeg:
            topic = IMAGE_JPEG
        channels[topic.name] = foxglove.Channel(
            topic.name,
            message_encoding="protobuf" if topic.protobuf else "json",
            schema=_schema(topic),
            metadata={"robot": robot},
            context=context,
        )
    return channels
