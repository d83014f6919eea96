"""`archery export FILE.mcap --ros2 OUT`: a recording as a ROS 2 bag (rosbag2, MCAP storage,
CDR) of the topics the live node publishes (`apps.ros2.graph.TOPICS`, converted by the same
`apps.ros2.convert`), each message at the time it was recorded; the robot description and
`/tf_static` once, at the first message's time. OUT is a new folder in an existing one; an
existing bag there is replaced with `--force` only (any other file or folder never)."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from archery.mesh.cliargs import ArgumentParser, add_force_arg, check_new_folder
from archery.protocol.errors import ArcheryError, ConfigError, DecodeError
from archery.protocol.exit_status import BAD_INPUT, FAILURE, OK

__all__ = ["build_parser", "check_bag_out", "export", "main"]

BAG_METADATA = "metadata.yaml"  # what every rosbag2 folder holds


def build_parser() -> ArgumentParser:
    """The flags of `archery export`."""
    parser = ArgumentParser(
        prog="archery export",
        description="convert an `archery record` recording for other tools: --ros2 OUT writes "
        "a ROS 2 bag (MCAP, CDR) of the topics `archery ros2` publishes",
    )
    parser.add_argument("recording", metavar="FILE.mcap", help="a recording of `archery record`")
    parser.add_argument(
        "--ros2", metavar="OUT", required=True, help="the ROS 2 bag to write (a new folder)"
    )
    parser.add_argument("--namespace", help="the topics' namespace (default /ROBOT)")
    add_force_arg(parser, "an existing bag at --ros2 (a folder holding a metadata.yaml)")
    return parser


def _is_bag(folder: Path) -> bool:
    """Whether `folder` is a rosbag2 bag: its metadata.yaml and files only (no subfolder)."""
    return (
        folder.is_dir()
        and not folder.is_symlink()
        and (folder / BAG_METADATA).is_file()
        and all(entry.is_file() and not entry.is_symlink() for entry in folder.iterdir())
    )


def check_bag_out(out: Path, *, force: bool) -> bool:
    """Whether the bag folder `out` replaces an existing bag (`force`, and a bag is there);
    else it is checked as a new folder (`mesh.cliargs.check_new_folder`).

    Raises:
        ConfigError: one line naming --ros2, the value and what to give instead.
    """
    if force and _is_bag(out):
        return True
    try:
        check_new_folder(out, "--ros2")
    except ConfigError as exc:
        if out.is_dir() and _is_bag(out):
            raise ConfigError(f"{exc.message}, or --force to replace the bag") from None
        raise
    return False


def export(
    path: Path, out: Path, namespace: str | None = None, *, force: bool = False
) -> dict[str, int]:
    """Write the ROS 2 bag `out` of the recording `path`; {topic: messages written}. With
    `force` an existing bag at `out` is replaced (`check_bag_out`), once the recording opens.

    Raises:
        ConfigError: an unreadable recording, an existing `out`, a bad namespace.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    from archery.apps.ros2 import convert, typestore
    from archery.apps.ros2.graph import TOPICS
    from archery.apps.ros2.wire import check_name
    from archery.apps.topics.image_records import FRAME_ID
    from archery.apps.topics.recording import DESCRIPTION_METADATA, open_recording
    from archery.apps.topics.robot_frames import DESCRIPTION_ATTACHMENT, RobotFrames
    from archery.protocol.messages import Image, JointState, Rollout, WorldEvent, WorldState
    from archery.sim.render import focal_length
    from archery.sim.scene_config import SceneConfig
    from archery.sim.urdf import urdf_text

    replace = check_bag_out(out, force=force)
    recording = open_recording(path)
    robot = recording.metadata.get("robot", "")
    try:
        prefix = check_name(namespace or f"/{robot}", "--namespace")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    described = recording.leading_metadata(DESCRIPTION_METADATA) or {}
    scene = SceneConfig(**json.loads(described["scene"])) if "scene" in described else SceneConfig()
    frames = RobotFrames(robot, scene)
    urdf = recording.attachment(DESCRIPTION_ATTACHMENT)
    counts: dict[str, int] = {}
    if replace:
        shutil.rmtree(out)

    def name(topic: str) -> str:
        return topic if topic.startswith("/") else f"{prefix.rstrip('/')}/{topic}"

    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        store = typestore.messages()
        connections = {
            t.name: writer.add_connection(name(t.name), t.ros_type, typestore=store) for t in TOPICS
        }
        types = {t.name: t.ros_type for t in TOPICS}

        def write(topic: str, message: Any, ns: int) -> None:
            if message is None:
                return
            data = typestore.serialize(message, types[topic])
            writer.write(connections[topic], ns, data)
            counts[name(topic)] = counts.get(name(topic), 0) + 1

        first = True
        for key, message, ns in recording.messages(recover=not recording.complete):
            if first:
                first = False
                seconds = ns / 1e9
                text = urdf.decode() if urdf is not None else urdf_text()
                write("robot_description", convert.description(text), ns)
                write("/tf_static", convert.static_tf(frames, seconds), ns)
            if isinstance(message, JointState):
                write("joint_states", convert.joint_state(message), ns)
            elif isinstance(message, WorldState) and key == f"{robot}/world/state:o":
                poses = frames.state_poses(message)
                if poses is not None:  # else another scene's
                    tf = convert.tf_message(message.stamp, frames.links, *poses)
                    write("/tf", tf, ns)
            elif isinstance(message, Image):
                image = convert.image(message, FRAME_ID)
                focal = focal_length(image.height, scene.camera_fovy)
                info = convert.camera_info(
                    message.stamp, FRAME_ID, image.width, image.height, focal
                )
                write("camera/image_raw", image, ns)
                write("camera/camera_info", info, ns)
            elif isinstance(message, Rollout):
                write("learner/rollout", convert.rollout(message), ns)
            elif isinstance(message, WorldEvent):
                write("world/landing", convert.landing(message), ns)
    return counts


def main(argv: list[str] | None = None) -> int:
    """`archery export FILE.mcap --ros2 OUT`; exit 2 for a bad recording or output."""
    args: argparse.Namespace = build_parser().parse_args(argv)
    try:
        counts = export(Path(args.recording), Path(args.ros2), args.namespace, force=args.force)
    except (ConfigError, DecodeError) as exc:
        print(f"archery export: {exc}", file=sys.stderr)
        return BAD_INPUT
    except ArcheryError as exc:
        print(f"archery export: {exc}", file=sys.stderr)
        return FAILURE
    total = sum(counts.values())
    print(f"archery export: wrote {total} messages on {len(counts)} topics to {args.ros2}")
    for topic, n in sorted(counts.items()):
        print(f"  {topic}: {n}")
    return OK
