"""rmw_zenoh's wire format as `apps.ros2.wire` writes it, checked against its design document's
examples (docs/design.md of ros2/rmw_zenoh) and against zenoh-ros2-sdk's own builders; the type
hashes against the SDK's own computation; the commands' mapping onto the robot's verbs and
their checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from zenoh_ros2_sdk import utils as sdk_utils
from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment
from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, node_liveliness_keyexpr

from archery.apps.ros2 import convert, typestore
from archery.apps.ros2.graph import TOPICS
from archery.apps.ros2.wire import (
    ATTACHMENT_SIZE,
    Attachment,
    AttachmentError,
    Endpoint,
    Kind,
    NodeId,
    Qos,
    data_key,
    gid_of,
)
from archery.protocol.journal_records import AbortedRecord, DoneRecord, ProposedRecord
from archery.protocol.messages import Rollout
from archery.protocol.text import SHOWN_LIMIT
from archery.protocol.verbs import robot as rv
from tests.conftest import archery

# design.md's examples, as it prints them
NN_EXAMPLE = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
MP_EXAMPLE = (
    "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
)
KEY_EXAMPLE = (
    "0/chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
)
STRING = "std_msgs/msg/String"


def _talker_endpoint(kind: Kind, name: str = "/chatter", ros_type: str = STRING) -> Endpoint:
    node = NodeId(0, "8b20917502ee955ac4476e0266340d5c", 0, "/", "talker")
    return Endpoint(
        node,
        10,
        kind,
        name,
        typestore.dds_type_name(ros_type),
        typestore.type_hash(ros_type),
        Qos(depth=7),
    )


def test_node_token_is_the_design_documents() -> None:
    assert NodeId(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener").token() == NN_EXAMPLE


def test_publisher_token_and_key_are_the_design_documents() -> None:
    endpoint = _talker_endpoint(Kind.PUBLISHER)
    assert endpoint.token() == MP_EXAMPLE
    assert endpoint.key() == KEY_EXAMPLE


@pytest.mark.parametrize(
    ("kind", "sdk_kind"),
    [
        (Kind.SUBSCRIPTION, EntityKind.SUBSCRIPTION),
        (Kind.SERVICE, EntityKind.SERVICE),
        (Kind.CLIENT, EntityKind.CLIENT),
        (Kind.PUBLISHER, EntityKind.PUBLISHER),
    ],
)
def test_each_endpoint_kind_as_the_sdk_writes_it(kind: Kind, sdk_kind: EntityKind) -> None:
    """MS, SS, SC (and MP) tokens: the design's layout (the kind in the sixth chunk, `/` as `%`
    in every name), equal to zenoh-ros2-sdk's for a namespaced node and topic."""
    ros_type = typestore.TRIGGER if kind in (Kind.SERVICE, Kind.CLIENT) else STRING
    node = NodeId(3, "1f2e3d", 4, "/icubSim", "archery")
    ours = Endpoint(
        node,
        9,
        kind,
        "/icubSim/left_arm/command",
        typestore.dds_type_name(ros_type),
        typestore.type_hash(ros_type),
        Qos(depth=1, transient_local=True),
    )
    sdk_node = NodeEntity(3, "1f2e3d", 4, "archery", "/icubSim")
    sdk = EndpointEntity(
        sdk_node, 9, sdk_kind, ours.name, ours.dds_type, ours.hash, ours.qos.text()
    )
    assert ours.token() == endpoint_liveliness_keyexpr(sdk)
    assert node.token() == node_liveliness_keyexpr(sdk_node)
    chunks = ours.token().split("/")
    assert chunks[:6] == ["@ros2_lv", "3", "1f2e3d", "4", "9", kind.value]
    assert chunks[7:10] == ["%icubSim", "archery", "%icubSim%left_arm%command"]


def test_qos_text_as_the_sdk_encodes_it() -> None:
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability

    assert Qos(depth=7).text() == "::,7:,:,:,,"
    latched = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)
    assert Qos(depth=1, transient_local=True).text() == latched.encode()
    sensor = QosProfile(reliability=QosReliability.BEST_EFFORT, history_depth=5)
    assert Qos(depth=5, best_effort=True).text() == sensor.encode()


def test_attachment_is_33_bytes_the_sdk_reads() -> None:
    gid = _talker_endpoint(Kind.PUBLISHER).gid()
    data = Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    assert len(data) == ATTACHMENT_SIZE == 33
    theirs = SdkAttachment.from_bytes(data)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (
        7,
        1_700_000_000_123_456_789,
        gid,
    )
    mine = SdkAttachment(sequence_id=3, timestamp_ns=5, gid=gid).to_bytes()
    assert Attachment.decode(mine) == Attachment(3, 5, gid)


@pytest.mark.parametrize(
    "data", [None, b"", b"\x00" * 32, b"\x00" * 34, b"\x00" * 16 + b"\x08" + b"\x00" * 16]
)
def test_a_malformed_attachment_is_refused(data: bytes | None) -> None:
    with pytest.raises(AttachmentError):
        Attachment.decode(data)


def _sdk_hash(ros_type: str) -> str:
    """The SDK's own RIHS01 computation, given the definitions rosbags writes."""
    text, _ = typestore.messages().generate_msgdef(ros_type, ros_version=2)
    main, *rest = text.split("=" * 80 + "\n")
    deps = {}
    for block in rest:
        head, _, body = block.partition("\n")
        package, name = head.removeprefix("MSG: ").split("/")
        deps[f"{package}/msg/{name}"] = body
    return sdk_utils.get_type_hash(ros_type, main, deps)


@pytest.mark.parametrize(
    "ros_type", sorted({t.ros_type for t in TOPICS} | {convert.TRAJECTORY_COMMAND})
)
def test_type_hashes_agree_with_the_sdks(ros_type: str) -> None:
    assert typestore.type_hash(ros_type) == _sdk_hash(ros_type)


def test_trigger_hash_agrees_with_the_sdks() -> None:
    """A service's hash covers its request, response and event; an empty request holds ROS 2's
    one placeholder member."""
    sdk = sdk_utils.compute_service_type_hash(
        typestore.TRIGGER,
        "uint8 structure_needs_at_least_one_member",
        "bool success\nstring message",
    )
    assert typestore.type_hash(typestore.TRIGGER) == sdk


def test_data_key_strips_one_slash_each_side() -> None:
    assert data_key(5, "/a/b/", "T", "H") == "5/a/b/T/H"


def _floats(values: list[float]) -> object:
    return typestore.new(
        convert.FLOAT_COMMAND,
        layout=typestore.new("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0),
        data=np.array(values, dtype=np.float64),
    )


def _duration(seconds: float) -> object:
    ns = round(seconds * 1e9)
    return typestore.new(
        "builtin_interfaces/msg/Duration", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
    )


def _trajectory(
    names: list[str],
    points: list[list[float]],
    times: list[float] | None = None,
    velocities: list[list[float]] | None = None,
) -> object:
    """A JointTrajectory: point i at `times[i]` (default i + 1 s), with `velocities[i]` (default
    none)."""
    empty = np.zeros(0, dtype=np.float64)

    def point(i: int, values: list[float]) -> object:
        return typestore.new(
            "trajectory_msgs/msg/JointTrajectoryPoint",
            positions=np.array(values, dtype=np.float64),
            velocities=empty if velocities is None else np.array(velocities[i], dtype=np.float64),
            accelerations=empty,
            effort=empty,
            time_from_start=_duration(i + 1.0 if times is None else times[i]),
        )

    return typestore.new(
        convert.TRAJECTORY_COMMAND,
        header=typestore.new("std_msgs/msg/Header", stamp=convert.stamp(0.0), frame_id=""),
        joint_names=names,
        points=[point(i, p) for i, p in enumerate(points)],
    )


def test_a_float_command_becomes_a_position_move() -> None:
    args = convert.command_args("torso", convert.FLOAT_COMMAND, _floats([0.1, 0.2, 0.3]))
    assert args == rv.PositionMoveArgs(position=[0.1, 0.2, 0.3])


def test_a_trajectory_keeps_every_points_time() -> None:
    message = _trajectory(
        ["l_elbow", "l_shoulder_pitch"], [[0.0, 0.1], [0.5, -0.2]], times=[0.5, 1.25]
    )
    args = convert.command_args("left_arm", convert.TRAJECTORY_COMMAND, message)
    assert args == rv.PartTrajectoryArgs(
        times=[0.5, 1.25],
        positions=[[0.0, 0.1], [0.5, -0.2]],
        velocities=None,
        names=["l_elbow", "l_shoulder_pitch"],
    )


def test_a_trajectorys_velocities_go_when_every_point_carries_them() -> None:
    names, points = ["torso_pitch", "torso_yaw"], [[0.1, 0.2], [0.3, 0.4]]
    every = _trajectory(names, points, velocities=[[1.0, 2.0], [3.0, 4.0]])
    args = convert.command_args("torso", convert.TRAJECTORY_COMMAND, every)
    assert isinstance(args, rv.PartTrajectoryArgs)
    assert args.velocities == [[1.0, 2.0], [3.0, 4.0]] and args.times == [1.0, 2.0]
    one = _trajectory(names, points, velocities=[[1.0, 2.0], []])
    args = convert.command_args("torso", convert.TRAJECTORY_COMMAND, one)
    assert isinstance(args, rv.PartTrajectoryArgs) and args.velocities is None


def _yaw(times: list[float], **kwargs: list[list[float]]) -> object:
    return _trajectory(["torso_yaw"], [[0.1 * (i + 1)] for i in range(len(times))], times, **kwargs)


@pytest.mark.parametrize(
    ("ros_type", "message", "said"),
    [
        (convert.FLOAT_COMMAND, _floats([0.1, 0.2]), "needs 3 positions"),
        (convert.FLOAT_COMMAND, _floats([0.1, math.nan, 0.0]), "NaN"),
        (convert.FLOAT_COMMAND, _floats([0.1, math.inf, 0.0]), "infinite"),
        (convert.TRAJECTORY_COMMAND, _trajectory(["l_elbow"], [[0.1]]), "some of torso_yaw"),
        (
            convert.TRAJECTORY_COMMAND,
            _trajectory(["torso_yaw", "torso_yaw"], [[0, 0]]),
            "each once",
        ),
        (convert.TRAJECTORY_COMMAND, _trajectory(["torso_yaw"], []), "without points"),
        (convert.TRAJECTORY_COMMAND, _trajectory(["torso_yaw"], [[0.1, 0.2]]), "2 positions for 1"),
        (convert.TRAJECTORY_COMMAND, _yaw([0.0, 1.0]), r"> 0 s .*got \[0\.0, 1\.0\]"),
        (convert.TRAJECTORY_COMMAND, _yaw([0.5, 0.5, 1.0]), r"increase .*got \[0\.5, 0\.5, 1\.0\]"),
        (convert.TRAJECTORY_COMMAND, _yaw([1.0, 0.5]), "increase from point to point"),
        (convert.TRAJECTORY_COMMAND, _yaw([1.0, rv.MAX_TRAJECTORY_DURATION + 1]), "past 120 s"),
        (convert.TRAJECTORY_COMMAND, _yaw([1.0], velocities=[[0.1, 0.2]]), "2 velocities for 1"),
        (convert.TRAJECTORY_COMMAND, _yaw([1.0], velocities=[[math.nan]]), "velocities holds NaN"),
        (
            convert.TRAJECTORY_COMMAND,
            _trajectory(["torso_yaw"], [[0.1], [math.nan]]),
            "point 1's positions holds NaN",
        ),
        (
            convert.TRAJECTORY_COMMAND,
            _yaw([0.01 * (i + 1) for i in range(rv.MAX_TRAJECTORY_POINTS + 1)]),
            "2001 points, more than 2000",
        ),
    ],
)
def test_a_bad_command_is_refused(ros_type: str, message: object, said: str) -> None:
    with pytest.raises(convert.CommandError, match=said):
        convert.command_args("torso", ros_type, message)


@pytest.mark.parametrize("domain", ["233", "-1"])
def test_a_domain_outside_0_to_232_exits_2(domain: str) -> None:
    done = archery("ros2", "--domain", domain, "--connect", "tcp/127.0.0.1:9", timeout=60)
    assert done.returncode == 2
    assert "0 to 232" in done.stderr and len(done.stderr.strip().splitlines()) == 1


# rmw_zenoh's own `simplified_XXH3_128bits` (rmw_zenoh_cpp/src/detail/simplified_xxhash3.cpp),
# built and run on design.md's tokens, stored as `Entity` stores it (low64, then high64)
RMW_ZENOH_GIDS = {
    MP_EXAMPLE: "eb85fa883b7846dc448a4501890ad062",
    NN_EXAMPLE: "5bd72f4daf53c0bb00c7394e7fc19547",
    "short": "89dedfe9d5127012921725952605de5a",
}


@pytest.mark.parametrize(("token", "gid"), sorted(RMW_ZENOH_GIDS.items()))
def test_a_gid_is_rmw_zenohs_xxh3_128_of_the_token(token: str, gid: str) -> None:
    assert gid_of(token).hex() == gid


def test_an_endpoints_gid_is_that_of_its_token() -> None:
    endpoint = _talker_endpoint(Kind.PUBLISHER)
    assert endpoint.token() == MP_EXAMPLE
    assert endpoint.gid().hex() == RMW_ZENOH_GIDS[MP_EXAMPLE]


def _done(rollout: int) -> DoneRecord:
    return DoneRecord(
        index=rollout - 1, rollout=rollout, theta=[0.1, 0.2], r_m=[0.03, -0.04],
        distance_m=0.05, hit=True,
    )  # fmt: skip


def test_a_done_rollout_is_published_and_the_others_are_not() -> None:
    message = convert.rollout(Rollout(record=_done(3)))
    assert message is not None
    assert list(message.data) == [3.0, 1.0, 0.05, 0.1, 0.2, 0.03, -0.04]
    assert [d.label for d in message.layout.dim] == list(convert.ROLLOUT_SEGMENTS)
    proposed = ProposedRecord(index=0, theta=[0.1, 0.2])
    aborted = AbortedRecord(
        index=0, theta=[0.1, 0.2], code="no_arrow", cause="none seen", retry_theta=[0.1, 0.2]
    )
    assert convert.rollout(Rollout(record=proposed)) is None
    assert convert.rollout(Rollout(record=aborted)) is None


@pytest.mark.parametrize(
    "names",
    [
        ["l_elbow\narchery.ros2 ERROR forged: the robot was reset"],
        [f"joint_{i}" + "x" * 1000 for i in range(10_000)],
        ["torso_yaw", "torso_pitch\r\nforged"],
    ],
    ids=["newline", "10 MB of names", "a known and a forged name"],
)
def test_a_received_name_is_quoted_on_one_short_line(names: list[str]) -> None:
    message = _trajectory(names, [[0.0] * len(names)])
    with pytest.raises(convert.CommandError) as caught:
        convert.command_args("torso", convert.TRAJECTORY_COMMAND, message)
    text = str(caught.value)
    assert "\n" not in text and "\r" not in text
    assert len(text) < 2 * SHOWN_LIMIT + 200
