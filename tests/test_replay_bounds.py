"""`archery replay` publishes only what a replay may, whatever the file holds: the recorded
robot's output streams, under the robot prefix it is told. A crafted MCAP file (a joint command,
an `rpc:i` request, another robot's keys, Zenoh's admin space, a state port holding a command)
moves nothing: each such channel is skipped, named once on stderr, and never published.

Every "never received" check asserts on the receiver after a later allowed message of the same
replay has arrived (the replay publishes in file order over one session)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import msgspec
import numpy as np
import zenoh
from mcap.writer import Writer

from archery.apps.topics.image_records import image_schema
from archery.apps.topics.recording import PROFILE, SCHEMA_VERSION, to_record
from archery.mesh.acl import REPLAY, roles, rules
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.codec import decode
from archery.protocol.keys import (
    OUTPUT_PORTS,
    PORTS,
    Keys,
    output_port,
    tap_keys,
    verb_key,
    verbs_key,
)
from archery.protocol.messages import (
    Image,
    JointCommand,
    JointState,
    Message,
    RpcRequest,
    WorldEvent,
)
from tests.conftest import archery
from tests.inbox import Inbox

ROBOT = "craftbot"


def craft(path: Path, robot: str, records: list[tuple[str, Message]]) -> Path:
    """An `archery record` file of robot `robot` holding exactly `records` (key, message), in
    order, each key's channel with the schema of its message, whatever the key: what anyone
    can write with an MCAP library."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile=PROFILE, library="crafted")
        writer.add_metadata(PROFILE, {"schema_version": str(SCHEMA_VERSION), "robot": robot})
        channels: dict[tuple[str, str], int] = {}
        schemas: dict[str, int] = {}
        for i, (key, message) in enumerate(records):
            name, data = to_record(message)
            if name not in schemas:
                encoding = "protobuf" if isinstance(message, Image) else "jsonschema"
                schema = (
                    image_schema(name)
                    if isinstance(message, Image)
                    else json.dumps(msgspec.json.schema(type(message))).encode()
                )
                schemas[name] = writer.register_schema(name, encoding, schema)
            if (key, name) not in channels:
                channels[(key, name)] = writer.register_channel(
                    key, "protobuf" if isinstance(message, Image) else "json", schemas[name]
                )
            ns = 1_000_000_000 + i * 1_000_000  # 1 ms apart
            writer.add_message(channels[(key, name)], log_time=ns, data=data, publish_time=ns)
        writer.finish()
    return path


def command(part: str = "left_arm") -> JointCommand:
    return JointCommand(part=part, position=[0.5] * 3)


def event(shot: int) -> WorldEvent:
    return WorldEvent(kind="landed", shot=shot, impact_m=[0.0, 0.0])


def frame(n: int) -> Image:
    return Image.from_numpy(np.full((4, 6, 3), n, np.uint8), frame=n, sim_time=n / 10)


def crafted_records(robot: str) -> list[tuple[str, Message]]:
    """A file's worth of what a replay must not publish, among what it may; the last record is
    an allowed event (`event(99)`), the positive control."""
    k = Keys(robot)
    state = JointState(part="torso", names=["a"], position=[0.1], velocity=[0.0])
    return [
        (k.world_events(), event(1)),
        (k.command("left_arm"), command()),  # moved the live arm
        (k.command("left_arm"), command()),
        (verb_key(k.archery_rpc(), "release"), RpcRequest(verb="release")),
        (k.archery_rpc(), RpcRequest(verb="release")),
        (k.state("left_arm"), command()),  # a command on a state port
        (f"other/{k.command('left_arm').split('/', 1)[1]}", command()),
        ("other/torso/state:o", state),
        ("@/router/local/config", event(7)),
        (f"{robot}/cam/requests:o", RpcRequest(verb="grab")),  # a tap: what a caller asked
        (k.state("torso"), state),
        (k.cam_frames(), frame(1)),
        (k.world_events(), event(99)),
    ]


SKIPPED = 8  # channels of `crafted_records` a replay skips
ALLOWED = 4  # keys of `crafted_records` a replay publishes


def listening(session: zenoh.Session, prober: zenoh.Session, pattern: str, probe: str) -> Inbox:
    """A subscriber of `session` on `pattern` that has reached the router: a probe that
    `prober` published on `probe` (covered by `pattern`) has arrived."""
    inbox = Inbox(probe)
    session.declare_subscriber(pattern, inbox)
    deadline = time.monotonic() + 10
    while not inbox.wait_for_key(probe, timeout=0.1):
        assert time.monotonic() < deadline, f"the subscription to {pattern} never took"
        prober.put(probe, b"probe")
    return inbox


def _replay(path: Path, net: NetConfig, *flags: str) -> tuple[int, str, str]:
    out = archery("replay", str(path), "--rate", "100", "--connect", net.connect[0], *flags)
    return out.returncode, out.stdout, out.stderr


# -- which keys -----------------------------------------------------------------------------------
def test_the_output_streams_are_the_robots_stream_ports_but_no_input_rpc_or_tap() -> None:
    k = Keys(ROBOT)
    assert {s.pattern for s in OUTPUT_PORTS} == {
        "{part}/state:o",
        "world/state:o",
        "world/events:o",
        "cam/target:o",
        "detector/hit:o",
        "learner/rollout:o",
    }
    assert all(spec in PORTS for spec in OUTPUT_PORTS)
    assert k.state("left_arm") in k.output_streams() and k.cam_frames() in k.output_streams()
    for key in (
        k.command("left_arm"),
        k.part_rpc("left_arm"),
        k.archery_rpc(),
        f"{k.archery_rpc()}/release",
        *(tap_keys(k.cam_rpc()) or ()),
        k.alive("robot"),
        k.describe("robot"),
        "other/left_arm/state:o",
        "@/router/local/config",
        f"{ROBOT}/**",
        f"{ROBOT}/*/state:o",
        "",
    ):
        assert output_port(key, ROBOT) is None, key
    assert output_port(k.world_events(), ROBOT) is not None


def test_the_replay_identity_may_publish_the_output_streams_and_serve_the_camera_only() -> None:
    k = Keys(ROBOT)
    role = roles(ROBOT)[REPLAY]
    assert set(role.publish) == {*k.output_streams(), *(tap_keys(k.cam_rpc()) or ())}
    assert role.serve == (verbs_key(k.cam_rpc()),)
    assert role.subscribe == () and role.call == () and not role.watch
    granted = [r for r in rules(ROBOT)["rules"] if r["id"].startswith(f"{REPLAY}-")]
    assert {r["id"] for r in granted} == {
        "replay-publish",
        "replay-publish-match",
        "replay-serve",
        "replay-serve-queries",
    }
    keys = {key for r in granted for key in r["key_exprs"]}
    assert not [key for key in keys if "command:i" in key or "/alive" in key]
    # `**` only where it learns of its subscribers (a recorder's `ROBOT/**` among them)
    wide = {r["id"] for r in granted if any("**" in key for key in r["key_exprs"])}
    assert wide == {"replay-publish-match"}
    (match,) = [r for r in granted if r["id"] == "replay-publish-match"]
    assert match["messages"] == ["declare_subscriber"] and match["flows"] == ["egress"]


# -- over the mesh ---------------------------------------------------------------------------
def test_a_crafted_file_publishes_only_the_robots_output_streams(
    net: NetConfig, tmp_path: Path
) -> None:
    """The recording's own robot prefix (no --robot): its output streams go out as recorded;
    the command, the `rpc:i` keys, the tap, the state port holding a command, `other/…` and
    `@/…` do not, each named once on stderr."""
    path = craft(tmp_path / "crafted.mcap", net.robot, crafted_records(net.robot))
    k = Keys(net.robot)
    with Node(None, net) as node, Node(None, net) as prober:
        mine = listening(node.session, prober.session, f"{net.robot}/**", k.world_state())
        other = listening(node.session, prober.session, "other/**", "other/world/state:o")
        status, out, err = _replay(path, net)
        assert status == 0, err
        assert mine.wait_for_key(k.world_events(), n=2)  # the control, published last
    events = [decode(p, WorldEvent) for key, p in mine.items if key == k.world_events()]
    assert [e.shot for e in events] == [1, 99]
    assert sorted(set(mine.received())) == sorted(
        {k.world_events(), k.state("torso"), k.cam_frames()}
    )
    assert other.received() == []
    assert f"published {ALLOWED} messages on 3 keys" in out
    assert f"{SKIPPED + 1} messages on {SKIPPED} channels skipped" in out
    lines = err.strip().splitlines()
    assert len(lines) == SKIPPED, err
    assert all(line.startswith("archery replay: skipped channel ") for line in lines)
    assert sum(f"'{k.command('left_arm')}'" in line for line in lines) == 1  # once, of two
    assert any("'@/router/local/config'" in line for line in lines)
    assert any("JointCommand messages, not the port's JointState" in line for line in lines)


def test_a_replay_under_another_prefix_takes_no_other_robots_key(
    net: NetConfig, tmp_path: Path
) -> None:
    """--robot T: the recording's robot's streams go out under T; `other/…`'s are skipped,
    never renamed into T (`other/torso/state:o` is no state of T's torso)."""
    path = craft(tmp_path / "crafted.mcap", net.robot, crafted_records(net.robot))
    target = Keys(net.robot + "t")
    with Node(None, net) as node, Node(None, net) as prober:
        inbox = listening(node.session, prober.session, f"{target.robot}/**", target.world_state())
        status, out, err = _replay(path, net, "--robot", target.robot)
        assert status == 0, err
        assert inbox.wait_for_key(target.world_events(), n=2)  # the control, published last
    torso = [p for key, p in inbox.items if key == target.state("torso")]
    assert len(torso) == 1  # the recorded robot's torso, not other/'s
    assert target.command("left_arm") not in inbox.received()
    assert f"published {ALLOWED} messages on 3 keys" in out
    assert "skipped channel 'other/torso/state:o'" in err


def test_a_file_with_nothing_a_replay_may_publish_is_refused_and_its_names_shown_safely(
    net: NetConfig, tmp_path: Path
) -> None:
    """Only commands, one under a key with a terminal escape, a line break and 10,000
    characters: one line each, quoted and cut, nothing published, exit status 2."""
    k = Keys(net.robot)
    evil = f"{net.robot}/\x1b[2J\nleft_arm/" + "x" * 10_000
    path = craft(
        tmp_path / "commands.mcap",
        net.robot,
        [(k.command("left_arm"), command()), (evil, command()), (k.command("torso"), command())],
    )
    status, out, err = _replay(path, net)
    assert status == 2, err
    assert "published 0 messages" in out
    lines = err.strip().splitlines()
    assert len(lines) == 4 and lines[-1].startswith("archery replay: nothing replayed"), err
    assert "\x1b" not in err and all(len(line) < 500 for line in lines)
    assert "chars)" in lines[1]
