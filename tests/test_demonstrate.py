"""`archery demonstrate --check`: a good file passes; a malformed, short, wrong-joint or
out-of-limits one, or a missing one, is refused with one line naming what is wrong, exit 2 (a
whole shot's events, speeds and accelerations: `tests/test_demonstration_files.py`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec
import pytest

from archery.apps.demonstrate import joint_limits, main
from archery.protocol.demonstration import FORMAT, MIN_DURATION, MIN_SAMPLES
from archery.protocol.exit_status import BAD_INPUT, OK
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import home_of
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION


def _demo(samples: int = 2 * MIN_SAMPLES) -> dict[str, Any]:
    """A still demonstration at the home posture, lasting twice the shortest allowed."""
    step = 2 * MIN_DURATION / (samples - 1)
    return {
        "format": FORMAT,
        "joints": {part: list(PARTS[part]) for part in ARM_PARTS},
        "samples": [
            {"t": i * step, **{part: list(home_of(part)) for part in ARM_PARTS}}
            for i in range(samples)
        ],
        "events": [
            {"t": 0.5, "kind": "grasped"},
            {"t": 1.0, "kind": "nocked"},
            {"t": 1.5, "kind": "released"},
        ],
        "shot": "whole",
        "made": "the home posture, held",
    }


def _check(tmp_path: Path, content: bytes, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    path = tmp_path / "demo.json"
    path.write_bytes(content)
    status = main(["--check", str(path)])
    return status, capsys.readouterr().err


def test_a_good_demonstration_passes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, err = _check(tmp_path, msgspec.json.encode(_demo()), capsys)
    assert status == OK and err == ""


def _out_of_limits() -> dict[str, Any]:
    demo = _demo()
    upper = joint_limits("whole")["right_arm"][1]
    for sample in demo["samples"]:  # held there: no jump the speed bound would refuse first
        sample["right_arm"][3] = upper[3] + 0.1
    return demo


def _wrong_joints() -> dict[str, Any]:
    demo = _demo()
    demo["joints"]["left_arm"] = list(reversed(PARTS["left_arm"]))
    return demo


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (b'{"format": ', "not JSON"),
        (b'{"format": "archery-demonstration/1"}', "not a demonstration"),
        (msgspec.json.encode(_demo(MIN_SAMPLES // 2)), "too short"),
        (msgspec.json.encode(_wrong_joints()), "left_arm joints must be"),
        (msgspec.json.encode(_out_of_limits()), "r_elbow = "),
    ],
    ids=["malformed", "fields", "short", "joints", "limits"],
)
def test_a_bad_demonstration_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes, says: str
) -> None:
    status, err = _check(tmp_path, content, capsys)
    assert status == BAD_INPUT
    assert says in err and err.count("\n") == 1


def test_a_missing_file_is_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--check", str(tmp_path / "none.json")]) == BAD_INPUT
    err = capsys.readouterr().err
    assert "cannot read" in err and err.count("\n") == 1


def test_recording_into_a_missing_folder_is_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--out", str(tmp_path / "none" / "demo.json")]) == BAD_INPUT
    err = capsys.readouterr().err
    assert "no folder" in err and err.count("\n") == 1


def test_the_shipped_demonstration_passes(capsys: pytest.CaptureFixture[str]) -> None:
    shipped = SHIPPED_DEMONSTRATION
    assert main(["--check", str(shipped)]) == OK
    summary = json.loads(capsys.readouterr().out)
    assert summary["shot"] == "whole" and summary["samples"] >= MIN_SAMPLES
    assert summary["events"][:3] == ["grasped", "nocked", "released"]
