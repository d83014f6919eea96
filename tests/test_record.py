"""`archery record`, `replay` and `hz` over a real router: exact round trips, a recorder killed
with SIGKILL, replay timing, wildcards and rates."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory

from archery.apps.topics.recording import Recorder, from_record, open_recording, to_record
from archery.apps.topics.selfcheck import ECHO_SERVICE, run_echo
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.priority import WRITER_NICE
from archery.protocol.codec import decode, encode
from archery.protocol.errors import ConfigError, RpcTimeout
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import (
    Array,
    Detection,
    Image,
    JointState,
    Rollout,
    WorldEvent,
    WorldState,
)
from archery.protocol.verbs.camera import GrabArgs
from tests.conftest import archery, serving
from tests.spawn import spawn


def _flags(net: NetConfig) -> list[str]:
    return ["--connect", net.connect[0], "--robot", net.robot]


def _recording(
    path: Path, net: NetConfig, *patterns: str, flush: str = "0.2"
) -> subprocess.Popen[str]:
    """`archery record` of `patterns` (and any further flags among them)."""
    return spawn(
        "record",
        "--out",
        str(path),
        *patterns,
        *_flags(net),
        "--flush-interval",
        flush,
        ready="archery record: recording",
    )


def _messages() -> list[object]:
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[10:20, 5:30] = (200, 30, 40)
    ok, jpeg = cv2.imencode(".jpg", rgb)
    assert ok
    return [
        Image.from_numpy(rgb, frame=3, sim_time=1.25, seq=7, stamp=time.time()),
        Image(width=64, height=48, encoding="jpeg", data=jpeg.tobytes(), frame=4, sim_time=None),
        Image.from_numpy(rgb[:, :, 0], encoding="mono8", stamp=1.0 / 3.0),
        JointState(part="torso", names=["a", "b"], position=[0.1, 1 / 3], velocity=[0, 1e-300]),
        WorldState(qpos=Array.from_numpy(np.linspace(0, 1, 7) / 3), sim_time=0.1 + 0.2),
        WorldEvent(kind="landed", shot=2, impact_m=[0.01, -0.07]),
        Detection(frame_stamp=1.5, status="ok", r_m=[0.012345678901234, -1 / 7]),
        Rollout(
            record=DoneRecord(
                session="s",
                index=1,
                rollout=1,
                theta=[0.1, 0.2, -0.3],
                r_m=[0.01, 1 / 3],
                ret=-0.5,
                distance_m=0.3335,
                hit=False,
            )
        ),
    ]


def test_a_record_holds_the_very_bytes_that_were_published() -> None:
    for message in _messages():
        # as the recorder sees it: decoded from the wire (an int in a float field is a float)
        wire = decode(encode(message))  # type: ignore[arg-type,var-annotated]  # _messages() is a list[object]
        schema, data = to_record(wire)
        assert encode(from_record(schema, data)) == encode(wire)
        if isinstance(message, Image):
            # Foxglove's own schema reads the frame: pixels as raw bytes, no base64
            fox = {"foxglove.RawImage": RawImage, "foxglove.CompressedImage": CompressedImage}
            record = fox[schema].FromString(data)
            assert record.data == message.data
            assert abs(record.timestamp.ToNanoseconds() - message.stamp * 1e9) < 1e3  # 1 µs
            if schema == "foxglove.RawImage":
                assert (record.width, record.height) == (message.width, message.height)
                assert record.step == len(message.data) // message.height
                assert record.encoding == message.encoding
            else:
                assert record.format == message.encoding


def test_an_lz4_frame_is_recorded_as_the_raw_pixels_it_carries() -> None:
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[10:20, 5:30] = (200, 30, 40)
    packed = Image.from_numpy(rgb, "rgb8_lz4", frame=5, sim_time=2.0, seq=3, stamp=time.time())
    schema, data = to_record(decode(encode(packed), Image))
    record = RawImage.FromString(data)  # Foxglove's raw image: no LZ4 there
    assert schema == "foxglove.RawImage" and record.encoding == "rgb8"
    assert record.data == rgb.tobytes() and record.step == 64 * 3
    back = from_record(schema, data)
    assert isinstance(back, Image) and np.array_equal(back.to_numpy(), rgb)
    assert (back.frame, back.sim_time, back.seq) == (5, 2.0, 3)
    broken = msgspec.structs.replace(packed, data=packed.data[:-3])
    with pytest.raises(ValueError, match="rgb8_lz4 image"):
        to_record(broken)


def test_a_frame_that_does_not_unpack_is_counted_malformed_and_the_rest_kept(
    tmp_path: Path,
) -> None:
    rgb = np.full((48, 64, 3), 90, np.uint8)
    good = Image.from_numpy(rgb, "rgb8_lz4", seq=1, stamp=1.0)
    broken = msgspec.structs.replace(good, data=b"\xff" * 12, seq=2, stamp=2.0)
    recorder = Recorder(tmp_path / "x.mcap", "icubSim", ["icubSim/**"])
    for image in (good, broken, msgspec.structs.replace(good, seq=3, stamp=3.0)):
        recorder.put("icubSim/cam/target:o", encode(image))
    stats = recorder.close()
    assert stats.malformed == 1 and stats.written == {"icubSim/cam/target:o": 2}
    kept = [m for _, m, _ in open_recording(tmp_path / "x.mcap").messages()]
    assert [m.seq for m in kept] == [1, 3] and all(m.encoding == "rgb8" for m in kept)


def test_the_file_is_chunked_indexed_and_tells_its_schemas(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    recorder = Recorder(path, "icubSim", ["icubSim/**"], chunk_size=1024)
    keys = ["cam/target:o", "cam/target:o", "cam/target:o", "torso/state:o", "world/state:o"]
    keys += ["world/events:o", "detector/hit:o", "learner/rollout:o"]
    messages = _messages()
    for key, message in zip(keys, messages, strict=True):
        recorder.put(f"icubSim/{key}", encode(message))  # type: ignore[arg-type]  # _messages() is a list[object]
    recorder.put("icubSim/torso/state:o", b"\x93not a message")
    stats = recorder.close()
    assert stats.total == 8 and stats.malformed == 1
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 8 and summary.statistics.chunk_count >= 2
        assert summary.chunk_indexes and all(c.message_index_offsets for c in summary.chunk_indexes)
        names = {s.name for s in summary.schemas.values()}
        assert {"foxglove.RawImage", "foxglove.CompressedImage", "archery.WorldState"} <= names
        images = {"foxglove.RawImage", "foxglove.CompressedImage"}
        for schema in summary.schemas.values():
            if schema.name in images:
                assert schema.encoding == "protobuf"
                files = FileDescriptorSet.FromString(schema.data)
                assert files.file[0].name == "google/protobuf/timestamp.proto"
            else:
                assert schema.encoding == "jsonschema"
                json.loads(schema.data)
        for channel in summary.channels.values():
            image = summary.schemas[channel.schema_id].name in images
            assert channel.message_encoding == ("protobuf" if image else "json")
        assert reader.get_header().profile == "archery"
    recording = open_recording(path)
    assert recording.complete and recording.message_count == 8
    got = [encode(m) for _, m, _ in recording.messages()]
    assert got == [encode(decode(encode(m))) for m in messages]  # type: ignore[arg-type]  # _messages() is a list[object]


def test_losses_are_counted_by_sequence_gaps_and_a_full_queue(tmp_path: Path) -> None:
    rgb = np.zeros((48, 64, 3), np.uint8)
    frames = [encode(Image.from_numpy(rgb, frame=n, seq=n)) for n in (1, 2, 5, 6, 9)]
    recorder = Recorder(tmp_path / "gaps.mcap", "icubSim", ["icubSim/**"])
    for frame in frames:
        recorder.put("icubSim/cam/target:o", frame)
    recorder.put("icubSim/cam/target:o", encode(Image.from_numpy(rgb, seq=1)))  # a restart
    stats = recorder.close()
    assert (stats.total, stats.missing, stats.overflow) == (6, 4, 0)  # 3, 4, 7 and 8 missing

    # a writer that falls behind drops (and counts) rather than holding up the receiver
    full = Recorder(tmp_path / "full.mcap", "icubSim", ["icubSim/**"], max_pending=0)
    full.put("icubSim/cam/target:o", frames[0])
    assert full.close().overflow == 1


def test_recordings_of_another_schema_version_or_not_mcap_are_refused(tmp_path: Path) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("hello\n")
    with pytest.raises(ConfigError, match="is not an MCAP file"):
        open_recording(text)
    other = tmp_path / "v0.mcap"
    Recorder(other, "icubSim", ["icubSim/**"]).close()
    data = other.read_bytes().replace(
        b"schema_version\x01\x00\x00\x001", b"schema_version\x01\x00\x00\x009"
    )
    other.write_bytes(data)
    with pytest.raises(ConfigError, match="schema version 9"):
        open_recording(other)


def _events(n: int, start: int = 0) -> list[WorldEvent]:
    return [
        WorldEvent(kind="landed", shot=start + i, impact_m=[i / 1000, -i / 3000]) for i in range(n)
    ]


def _wait_on_disk(path: Path, n: int, which: Callable[[str], bool] = lambda k: True) -> None:
    """Wait until the recorder has handed `n` messages on the chosen keys to the file."""
    deadline = time.monotonic() + 30
    got = 0
    while got < n:
        assert time.monotonic() < deadline, f"{got} of {n} messages on disk"
        got = sum(1 for k, _, _ in open_recording(path).messages(recover=True) if which(k))
        time.sleep(0.05)


def test_record_then_replay_over_the_mesh(net: NetConfig, tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    with serving(run_echo, net), Node(None, net) as node:
        node.wait_alive([ECHO_SERVICE], 30)
        recorder = _recording(path, net, f"{net.robot}/world/*", f"{net.robot}/**")
        pub = node.publisher(node.keys.world_events(), WorldEvent, lossless=True)
        assert pub.wait_matched(10)
        sent = [pub.put(e) for e in _events(40)]
        _wait_on_disk(path, len(sent), lambda k: k.endswith("/world/events:o"))
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, err
    recording = open_recording(path)
    got = [(k, m) for k, m, _ in recording.messages()]
    events = [m for k, m in got if k == f"{net.robot}/world/events:o"]
    states = [m for k, m in got if k == f"{net.robot}/torso/state:o"]
    assert [encode(m) for m in events] == [encode(m) for m in sent]  # none twice, none lost
    assert len(states) >= 2 and all(isinstance(m, JointState) for m in states)
    assert f"wrote {len(got)} messages on 2 keys" in out

    # replayed into another robot prefix, in order and with the recorded spacing
    target = NetConfig(connect=net.connect, robot=net.robot + "r")
    with Node(None, target) as node:
        sub = node.subscribe(node.keys.world_events(), WorldEvent, mode="fifo")
        replay = archery(
            "replay",
            str(path),
            "--keys",
            f"{net.robot}/world/events:o",
            "--rate",
            "4",
            "--connect",
            net.connect[0],
            "--robot",
            target.robot,
        )
        assert replay.returncode == 0, replay.stderr
        assert "published 40 messages on 1 keys" in replay.stdout
        replayed = [sub.get(timeout=10) for _ in range(40)]
    assert [encode(m) for m in replayed] == [encode(m) for m in sent]


def test_a_killed_recorder_loses_at_most_its_last_chunk(net: NetConfig, tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    with Node(None, net) as node:
        recorder = _recording(path, net, f"{net.robot}/**", flush="0.2")
        pub = node.publisher(node.keys.world_events(), WorldEvent, lossless=True)
        assert pub.wait_matched(10)
        first = [pub.put(e) for e in _events(50)]
        _wait_on_disk(path, len(first))
        second = [pub.put(e) for e in _events(50, start=50)]
        recorder.kill()
        recorder.wait(30)
    assert recorder.returncode == -signal.SIGKILL
    recording = open_recording(path)
    assert not recording.complete
    with pytest.raises(ConfigError, match="unreadable record"):
        list(recording.messages())
    got = [encode(m) for _, m, _ in recording.messages(recover=True)]
    published = [encode(m) for m in first + second]
    assert len(first) <= len(got) <= len(published)
    assert got == published[: len(got)]
    # replay refuses it, and replays it with --recover
    refused = archery("replay", str(path), *_flags(net))
    assert refused.returncode == 2 and "--recover" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    replayed = archery("replay", str(path), "--recover", "--rate", "100", *_flags(net))
    assert replayed.returncode == 0, replayed.stderr
    assert f"published {len(got)} messages" in replayed.stdout


def test_hz_reports_the_rate_of_each_matching_key(net: NetConfig) -> None:
    with serving(run_echo, net), Node(None, net) as node:
        node.wait_alive([ECHO_SERVICE], 30)
        out = archery("hz", f"{net.robot}/*/state:o", "--duration", "2", *_flags(net))
    assert out.returncode == 0, out.stderr
    total = out.stdout.split("--- total\n")[1].strip().splitlines()
    assert len(total) == 1 and total[0].startswith(f"{net.robot}/torso/state:o  ")
    rate = float(total[0].split()[1])
    assert 35 < rate < 65, total[0]  # the echo service publishes at 50 Hz


def test_read_with_a_wildcard_and_a_field(net: NetConfig) -> None:
    with serving(run_echo, net), Node(None, net) as node:
        node.wait_alive([ECHO_SERVICE], 30)
        out = archery(
            "read", f"{net.robot}/*/state:o", "--count", "3", "--field", "names.1", *_flags(net)
        )
        assert out.returncode == 0, out.stderr
        lines = [json.loads(line) for line in out.stdout.splitlines()]
        assert lines == [{"key": f"{net.robot}/torso/state:o", "value": "torso_roll"}] * 3
        one = archery(
            "read", f"{net.robot}/torso/state:o", "--count", "1", "--field", "part", *_flags(net)
        )
        # a path the message does not have: one line naming it, bad input (2), nothing printed
        past = archery(
            "read", f"{net.robot}/torso/state:o", "--count", "1", "--field", "names.99",
            *_flags(net),
        )  # fmt: skip
    assert one.returncode == 0 and one.stdout.splitlines()[0] == '"torso"', one.stderr
    assert past.returncode == 2 and past.stdout == "", past.stderr
    assert "--field 'names.99': names has 3 entries, no entry '99'" in past.stderr


def test_a_recording_of_the_first_format_is_still_read(tmp_path: Path) -> None:
    # frames as JSON with base64 pixels and an `archery` object, no `format` metadata
    rgb = np.arange(48 * 64 * 3, dtype=np.uint8).reshape(48, 64, 3)
    image = Image.from_numpy(rgb, frame=3, sim_time=1.25, seq=7, stamp=1.5)
    record = {
        "timestamp": {"sec": 1, "nsec": 500_000_000},
        "frame_id": "target_camera",
        "width": 64,
        "height": 48,
        "encoding": "rgb8",
        "step": 192,
        "data": image.data,
        "archery": {"schema": 1, "seq": 7, "stamp": 1.5, "sim_time": 1.25, "frame": 3},
    }
    path = tmp_path / "v1.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="archery", library="archery")
        writer.add_metadata("archery", {"schema_version": "1", "robot": "icubSim"})
        schema = writer.register_schema("foxglove.RawImage", "jsonschema", b"{}")
        channel = writer.register_channel("icubSim/cam/target:o", "json", schema)
        writer.add_message(channel, log_time=1, data=msgspec.json.encode(record), publish_time=1)
        writer.finish()
    [(key, got, _)] = list(open_recording(path).messages())
    assert key == "icubSim/cam/target:o" and encode(got) == encode(image)


def test_the_mcap_protobuf_decoder_reads_the_frames_from_their_schema(tmp_path: Path) -> None:
    # as a generic reader (Foxglove, the mcap tools) does: from the descriptor in the file
    path = tmp_path / "frames.mcap"
    recorder = Recorder(path, "icubSim", ["icubSim/**"])
    images = [m for m in _messages() if isinstance(m, Image)]
    for image in images:
        recorder.put("icubSim/cam/target:o", encode(image))
    recorder.close()
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = [(s.name, m) for s, _, _, m in reader.iter_decoded_messages()]
    assert [name for name, _ in decoded] == [
        "foxglove.RawImage",
        "foxglove.CompressedImage",
        "foxglove.RawImage",
    ]
    for (_, record), image in zip(decoded, images, strict=True):
        assert record.data == image.data and record.frame == image.frame
        assert record.HasField("sim_time") == (image.sim_time is not None)


def test_a_replayed_grab_finds_each_rollouts_frame_by_its_stamp() -> None:
    from archery.apps.topics.observe import _Frames
    from archery.protocol.errors import BadRequest

    rgb = np.zeros((4, 4, 3), np.uint8)
    # three rollouts, each restarting the simulated clock
    shots = [
        Image.from_numpy(rgb, sim_time=t, stamp=s) for t, s in ((1.0, 10), (0.9, 20), (1.1, 30))
    ]
    frames = _Frames(keep=3)
    for shot in shots:
        frames.put(shot)
    for shot in shots:
        args = {"after_sim_time": shot.sim_time, "after_stamp": shot.stamp, "timeout": 0.1}
        assert frames.grab(GrabArgs(**args)) is shot
    assert frames.grab(GrabArgs(after_sim_time=0.9, timeout=0.1)) is shots[0]  # by sim time only
    with pytest.raises(RpcTimeout, match="no replayed frame"):
        frames.grab(GrabArgs(after_stamp=31.0, timeout=0.05))
    frames.put(Image.from_numpy(rgb, sim_time=1.0, stamp=40))  # the first is no longer kept
    with pytest.raises(BadRequest, match="no longer kept"):
        frames.grab(GrabArgs(after_sim_time=0.5, after_stamp=5.0, timeout=0.1))
    assert frames.grab(GrabArgs(after_sim_time=0.5, after_stamp=15.0, timeout=0.1)) is shots[1]


def _thread_niceness(pid: int) -> list[tuple[int, int]]:
    """The niceness and the scheduling policy of each thread of process `pid`."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        out.append((int(fields[16]), int(fields[38])))
    return out


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux's /proc")
def test_the_recorder_runs_at_a_lower_priority_when_told(net: NetConfig, tmp_path: Path) -> None:
    mine = os.getpriority(os.PRIO_PROCESS, 0)
    for flag, expected in (([], mine), (["--nice", "10"], min(19, mine + 10))):
        out = tmp_path / f"n{len(flag)}.mcap"  # a new file each: an existing one is refused
        recorder = _recording(out, net, f"{net.robot}/**", *flag)
        try:
            niceness = _thread_niceness(recorder.pid)
            # one thread, the writer, waits for idle CPU (SCHED_IDLE); every other one, Zenoh's
            # receiving threads too, has the process's niceness and class
            writer = (min(19, expected + WRITER_NICE), os.SCHED_IDLE)
            assert sorted(niceness) == [(expected, os.SCHED_OTHER)] * (len(niceness) - 1) + [writer]
        finally:
            recorder.send_signal(signal.SIGINT)
            recorder.communicate(timeout=30)
    bad = archery("record", "--out", str(tmp_path / "b.mcap"), "--nice", "20", *_flags(net))
    assert bad.returncode == 2 and "--nice" in bad.stderr and "0..19" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1


def test_attachments_are_written_first_and_read_back(tmp_path: Path) -> None:
    from archery.apps.topics.recording import CALIBRATION_ATTACHMENT, Recorder

    with_marks = Recorder(
        tmp_path / "a.mcap",
        "icubSim",
        ["icubSim/**"],
        attachments={CALIBRATION_ATTACHMENT: ("application/msgpack", b"\x81\xa1k\x01")},
    )
    with_marks.close()
    without = Recorder(tmp_path / "b.mcap", "icubSim", ["icubSim/**"])
    without.close()
    assert open_recording(tmp_path / "a.mcap").attachment(CALIBRATION_ATTACHMENT) == (
        b"\x81\xa1k\x01"
    )
    assert open_recording(tmp_path / "b.mcap").attachment(CALIBRATION_ATTACHMENT) is None
