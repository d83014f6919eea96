"""`archery info FILE.mcap`: what a recording holds, from its summary or, cut short, as far
as it reads."""

from __future__ import annotations

from pathlib import Path

from archery.apps.topics.info import read_info, render
from archery.apps.topics.recording import CALIBRATION_ATTACHMENT, Recorder
from archery.protocol.codec import encode
from archery.protocol.messages import JointState, WorldEvent
from tests.conftest import archery


def _recording(path: Path) -> None:
    """10 joint states over 0.9 s and 2 events, and an attachment."""
    recorder = Recorder(
        path, "icubSim", ["icubSim/**"], attachments={CALIBRATION_ATTACHMENT: ("x/y", b"abc")}
    )
    start = 1_800_000_000_000_000_000
    for i in range(10):
        state = JointState(part="torso", names=["a"], position=[0.0], velocity=[0.0], seq=i + 1)
        recorder.put("icubSim/torso/state:o", encode(state), start + i * 100_000_000)
    for i in range(2):
        event = WorldEvent(kind="reset", seq=i + 1)
        recorder.put("icubSim/world/events:o", encode(event), start + i * 900_000_000)
    recorder.close()


def test_info_reads_a_complete_recording_from_its_summary(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _recording(path)
    info = read_info(path)
    assert info.complete and info.messages == 12 and info.stopped is None
    assert abs(info.duration_s - 0.9) < 1e-9 and info.profile == "archery"
    assert info.attachments == [(CALIBRATION_ATTACHMENT, "x/y", 3)]
    text = render(info)
    assert "Duration:      0.900 s" in text and "Messages:      12" in text
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("  ")}
    torso = lines["icubSim/torso/state:o"].split()
    assert torso[1:5] == ["10", "msgs", "11.11", "Hz"] and "archery.JointState" in torso
    assert "(json, jsonschema)" in lines["icubSim/world/events:o"]
    assert "schema_version=1" in text and f"({path.stat().st_size} bytes)" in text


def test_a_cut_recording_prints_what_it_holds_then_exits_2(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _recording(path)
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    done = archery("info", str(cut))
    assert done.returncode == 2
    assert "cut short" in done.stdout and "Messages:" in done.stdout
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"archery info: {cut} is cut short")
    ok = archery("info", str(path))
    assert ok.returncode == 0 and ok.stderr == "" and "Channels:      2" in ok.stdout
