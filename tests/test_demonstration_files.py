"""A demonstration file is checked for what will be done with it: `archery demonstrate --check`,
`archery imitate` and the learner read it with the one reader
(`services.learner.config.read_demonstration`), which refuses what a learner could not play
(samples too close, too long a movement, events outside the samples or out of order) and any
file that is not a regular one of bounded size, in one line and exit status 2, without hanging
or reading without end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from archery.apps.imitate import main as imitate
from archery.protocol.demonstration import (
    EVENT_SLACK,
    FORMAT,
    MAX_BYTES,
    MAX_DURATION,
    MIN_DT,
    BadDemonstration,
    parse_demonstration,
)
from archery.protocol.errors import ConfigError
from archery.protocol.exit_status import BAD_INPUT
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import home_of
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION
from archery.services.controller.demonstration_file import read_demonstration as controller_reads

ARCHERY = Path(sys.executable).parent / "archery"  # the installed console script


def _demo(times: list[float], events: list[tuple[float, str]] | None = None) -> bytes:
    """A still demonstration at the home posture with samples at `times` (s)."""
    if events is None:
        events = [(times[1], "grasped"), (times[-3], "nocked"), (times[-2], "released")]
    return msgspec.json.encode(
        {
            "format": FORMAT,
            "joints": {part: list(PARTS[part]) for part in ARM_PARTS},
            "samples": [
                {"t": t, **{part: list(home_of(part)) for part in ARM_PARTS}} for t in times
            ],
            "events": [{"t": t, "kind": kind} for t, kind in events],
            "shot": "whole",
        }
    )


def _even(n: int, step: float) -> list[float]:
    return [i * step for i in range(n)]


BAD = {
    # 40 samples 0.1 ms apart, then one at 1,000 s: a DMP of 10 million steps
    "dense then long": (_demo([*_even(40, 1e-4), 1000.0]), "shortest sample interval"),
    "dt 1e-7": (_demo([*_even(40, 1e-7), 2.0]), "shortest sample interval"),
    "last time 1e12 s": (_demo([*_even(40, 0.02), 1e12]), "too long: 1e+12 s"),
    "1,000 s": (_demo(_even(101, 10.0)), "too long: 1000 s"),
    "event before the samples": (
        _demo(_even(60, 0.02), [(-1.0, "grasped"), (0.5, "nocked")]),
        "event 0 (grasped): time -1.0 s is outside the samples' 0 .. 1.18 s",
    ),
    "event after the samples": (
        _demo(_even(60, 0.02), [(0.2, "grasped"), (1.18 + 2 * EVENT_SLACK, "released")]),
        "event 1 (released)",
    ),
    "events out of order": (
        _demo(_even(60, 0.02), [(0.8, "nocked"), (0.2, "grasped")]),
        "event 1 (grasped): time 0.2 s comes before",
    ),
}


@pytest.mark.parametrize(("content", "says"), BAD.values(), ids=BAD.keys())
def test_what_a_learner_cannot_play_is_refused_by_every_reader(
    tmp_path: Path, content: bytes, says: str
) -> None:
    path = tmp_path / "demo.json"
    path.write_bytes(content)
    with pytest.raises(BadDemonstration) as caught:
        parse_demonstration(content)
    assert says in caught.value.message and "\n" not in caught.value.message
    with pytest.raises(ConfigError) as refused:
        controller_reads(path)  # the controller's `--demonstration` and `archery imitate`
    assert refused.value.message == f"--demonstration {path}: {caught.value.message}"


def test_imitate_refuses_it_before_it_plans(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "demo.json"
    path.write_bytes(BAD["dense then long"][0])
    assert imitate([str(path)]) == BAD_INPUT  # no robot asked: the file is refused first
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "shortest sample interval" in err


def test_the_bounds_leave_the_shipped_demonstration_and_a_slack_end_in() -> None:
    shipped = controller_reads(SHIPPED_DEMONSTRATION)
    assert shipped.events[-1].t > shipped.samples[-1].t  # its shot ended after its last sample
    assert shipped.samples[-1].t < MAX_DURATION / 2
    times = [s.t for s in shipped.samples]
    assert float(np.diff(times).min()) > 10 * MIN_DT


def _check(path: Path | str) -> subprocess.CompletedProcess[str]:
    """`archery demonstrate --check PATH` as a user runs it, guarded against a hang."""
    return subprocess.run(
        [str(ARCHERY), "demonstrate", "--check", str(path)],
        capture_output=True,
        text=True,
        timeout=30,
        stdin=subprocess.DEVNULL,
    )


def _one_line(result: subprocess.CompletedProcess[str], says: str) -> None:
    assert result.returncode == BAD_INPUT, result
    assert result.stderr.count("\n") == 1 and says in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and result.stdout == ""


def test_check_refuses_a_fifo_without_waiting_for_a_writer(tmp_path: Path) -> None:
    fifo = tmp_path / "demo.json"
    os.mkfifo(fifo)
    _one_line(_check(fifo), f"{fifo}: not a regular file (a FIFO)")


def test_check_refuses_a_device_and_a_folder(tmp_path: Path) -> None:
    _one_line(_check("/dev/zero"), "/dev/zero: not a regular file (a character device)")
    _one_line(_check(tmp_path), f"{tmp_path}: not a regular file (a folder)")


def test_check_refuses_a_file_past_the_size_cap_without_reading_it(tmp_path: Path) -> None:
    big = tmp_path / "demo.json"
    with big.open("wb") as f:
        f.truncate(MAX_BYTES + 1)  # sparse: no disk written
    _one_line(_check(big), f"too large: {MAX_BYTES + 1} bytes")


def test_check_refuses_a_movement_too_long_to_play_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "demo.json"
    path.write_bytes(BAD["last time 1e12 s"][0])
    _one_line(_check(path), "too long")


def test_a_recording_faster_than_a_learner_plays_is_thinned_to_the_shortest_interval() -> None:
    from archery.apps.demonstrate import _spaced

    times = [i * 4e-4 for i in range(100)]  # a 2.5 kHz state stream
    kept = _spaced(times)
    assert kept[0] == 0.0 and float(np.diff(kept).min()) >= MIN_DT
    assert len(kept) >= times[-1] / (MIN_DT + 4e-4)  # none dropped past the next one due
