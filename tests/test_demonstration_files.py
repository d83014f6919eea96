"""A demonstration file is checked for what will be done with it: `archery demonstrate --check`,
`archery imitate` and the controller read it with the one reader
(`services.controller.demonstration_file.read_demonstration`), which refuses what a learner
could not play (samples too close, too long a movement, events outside the samples or out of
order), what the robot could never play (no grasp, nock or release once each in this order, a
joint past the speed or acceleration bound; the controller before it joins the mesh) and any
file that is not a regular one of bounded size, in one line and exit status 2, without hanging
or reading without end."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from archery.apps.imitate import main as imitate
from archery.protocol.demonstration import (
    ACCELERATION_SPAN,
    EVENT_SLACK,
    FORMAT,
    MAX_ACCELERATION,
    MAX_BYTES,
    MAX_DURATION,
    MIN_DT,
    SHOT_EVENTS,
    BadDemonstration,
    DemoEvent,
    Demonstration,
    Sample,
    encode_demonstration,
    parse_demonstration,
)
from archery.protocol.errors import ConfigError
from archery.protocol.exit_status import BAD_INPUT
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import MAX_REFERENCE_SPEED, home_of
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION
from archery.services.controller.demonstration_file import read_demonstration as controller_reads
from archery.sim.scene_config import SceneConfig

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


# -- a demonstration the robot can play: the shot's events, the joints' speed and acceleration --
SHIPPED_DEMO = parse_demonstration(SHIPPED_DEMONSTRATION.read_bytes())
NAMES = [name for part in ARM_PARTS for name in PARTS[part]]


def _arms(demo: Demonstration) -> tuple[np.ndarray, np.ndarray]:
    """(times, both arms' angles: one row per sample, left then right) of `demo`."""
    t = np.array([s.t for s in demo.samples])
    return t, np.array([[*s.left_arm, *s.right_arm] for s in demo.samples])


def _with_arms(q: np.ndarray, t: np.ndarray | None = None) -> bytes:
    """The shipped demonstration with the arms' angles `q` (at times `t`, else its own)."""
    times = _arms(SHIPPED_DEMO)[0] if t is None else t
    samples = [
        Sample(t=float(at), left_arm=row[:7].tolist(), right_arm=row[7:].tolist())
        for at, row in zip(times, q, strict=True)
    ]
    return encode_demonstration(msgspec.structs.replace(SHIPPED_DEMO, samples=samples))


def _with_events(*events: tuple[float, str]) -> bytes:
    demo = msgspec.structs.replace(
        SHIPPED_DEMO,
        events=[DemoEvent(t=t, kind=kind) for t, kind in events],  # type: ignore[arg-type]
    )
    return encode_demonstration(demo)


GRASP, NOCK, RELEASE, MISS = ((e.t, e.kind) for e in SHIPPED_DEMO.events)
ELBOW = NAMES.index("r_elbow")
WRIST = NAMES.index("l_wrist_pitch")


def _bang_bang() -> tuple[bytes, str]:
    """The right elbow thrown between two angles within its limits at every sample from 4 s."""
    t, q = _arms(SHIPPED_DEMO)
    first = int(np.searchsorted(t, 4.0))
    q[first::2, ELBOW] = 0.3
    q[first + 1 :: 2, ELBOW] = 1.3
    speed = abs(q[first, ELBOW] - q[first - 1, ELBOW]) / (t[first] - t[first - 1])
    return _with_arms(q), (
        f"r_elbow moves at {speed:.3g} rad/s between t = {t[first - 1]:.3f} and {t[first]:.3f} "
        f"s (samples {first - 1} and {first}), over the robot's maximum joint speed of "
        f"{MAX_REFERENCE_SPEED:g} rad/s"
    )


def _kink() -> tuple[bytes, str]:
    """The left wrist's speed changed by 1 rad/s at one sample (1 s), within the speed bound:
    50 rad/s² there."""
    t, q = _arms(SHIPPED_DEMO)
    at = int(np.searchsorted(t, 1.0))
    q[:, WRIST] += np.clip(t - t[at], 0.0, 0.2)  # 1 rad/s for 0.2 s, then held
    w = q[at - 1 : at + 2, WRIST]
    h = t[at + 1] - t[at]  # 50 Hz: the span is one sample
    acceleration = (w[2] - 2 * w[1] + w[0]) / h**2  # the movement's own and the kink's
    return _with_arms(q), f"l_wrist_pitch accelerates at {abs(acceleration):.3g} rad/s² at"


UNPLAYABLE = {
    "no grasp": (
        _with_events(NOCK, RELEASE, MISS),
        "no grasped event: a whole shot holds grasped, nocked, released once each, in this "
        "order (events: nocked, released, missed)",
    ),
    "no nock": (_with_events(GRASP, RELEASE, MISS), "no nocked event: a whole shot holds"),
    "no release": (_with_events(GRASP, NOCK, MISS), "no released event: a whole shot holds"),
    "no event": (_with_events(), "no grasped event: a whole shot holds grasped, nocked, released"),
    "nock before grasp": (
        _with_events((GRASP[0], "nocked"), (NOCK[0], "grasped"), RELEASE, MISS),
        f"event 0 (nocked, t = {GRASP[0]:.3f} s) comes before event 1 (grasped, t = "
        f"{NOCK[0]:.3f} s): a whole shot holds grasped, nocked, released in this order",
    ),
    "release before nock": (
        _with_events(GRASP, (NOCK[0], "released"), (RELEASE[0], "nocked"), MISS),
        "event 1 (released, t = ",
    ),
    "nocked twice": (
        _with_events(GRASP, NOCK, (NOCK[0] + 0.5, "nocked"), RELEASE, MISS),
        f"event 2 (nocked, t = {NOCK[0] + 0.5:.3f} s) is a second nocked event (event 1 at "
        f"{NOCK[0]:.3f} s): a whole shot holds grasped, nocked, released once each",
    ),
    "bang-bang elbow": _bang_bang(),
    "acceleration spike": _kink(),
}


@pytest.mark.parametrize(("content", "says"), UNPLAYABLE.values(), ids=UNPLAYABLE.keys())
def test_a_demonstration_that_can_never_play_is_refused_by_check_and_the_controller(
    tmp_path: Path, content: bytes, says: str
) -> None:
    """`archery demonstrate --check` and the controller at its start (before it joins the
    mesh: its endpoint is dead, the file is what it says) refuse it: one line, exit 2."""
    path = tmp_path / "demo.json"
    path.write_bytes(content)
    with pytest.raises(BadDemonstration) as caught:
        parse_demonstration(content)
    assert says in caught.value.message, caught.value.message
    _one_line(_check(path), f"{path}: {caught.value.message}")
    started = subprocess.run(
        [str(ARCHERY), "controller", "--demonstration", str(path), "--connect", "tcp/127.0.0.1:9"],
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert started.returncode == BAD_INPUT, started
    assert started.stderr == (
        f"archery controller: --demonstration {path}: {caught.value.message}\n"
    ), started.stderr


def test_the_kink_is_named_at_its_time_with_the_bound() -> None:
    t, _ = _arms(SHIPPED_DEMO)
    at = int(np.searchsorted(t, 1.0))
    with pytest.raises(BadDemonstration) as caught:
        parse_demonstration(_kink()[0])
    assert caught.value.message.endswith(
        f"rad/s² at t = {t[at]:.3f} s (sample {at}), over the {MAX_ACCELERATION:g} rad/s² a "
        f"joint of the robot follows"
    ), caught.value.message


def _peaks(demo: Demonstration) -> tuple[float, float]:
    """(rad/s, rad/s²): the fastest joint's speed between samples and its largest acceleration
    between consecutive samples."""
    t, q = _arms(demo)
    speed = np.diff(q, axis=0) / np.diff(t)[:, None]
    acceleration = np.diff(speed, axis=0) / (0.5 * (t[2:] - t[:-2]))[:, None]
    return float(np.abs(speed).max()), float(np.abs(acceleration).max())


def test_the_shipped_demonstration_plays_with_margin() -> None:
    speed, acceleration = _peaks(SHIPPED_DEMO)
    assert speed < MAX_REFERENCE_SPEED / 3  # 0.56 rad/s
    assert acceleration < MAX_ACCELERATION / 3  # 5.8 rad/s²
    kinds = [e.kind for e in SHIPPED_DEMO.events]
    assert kinds == [*SHOT_EVENTS, "missed"]


def test_the_acceleration_bound_admits_the_robot_s_own_fastest_moves() -> None:
    """A positionMove at the fastest reference speed: the servos (bandwidth ω, critically
    damped) follow the setpoint's step of speed v with a peak acceleration v·ω/e."""
    omega = SceneConfig().servo_bandwidth
    assert SceneConfig().servo_damping_ratio == 1.0
    assert MAX_REFERENCE_SPEED * omega / math.e <= MAX_ACCELERATION


def test_a_dense_noisy_recording_is_not_refused_for_its_noise() -> None:
    """The shipped movement sampled at 512 Hz with 0.1 mrad of noise: differences of speeds at
    the sample spacing would read ~300 rad/s²; over `ACCELERATION_SPAN` it passes."""
    t, q = _arms(SHIPPED_DEMO)
    step = 2.0**-9  # s: exact sums
    dense_t = np.arange(int(t[-1] / step)) * step
    rng = np.random.default_rng(7)
    dense = np.stack([np.interp(dense_t, t, q[:, j]) for j in range(q.shape[1])], axis=1)
    dense += rng.normal(0.0, 1e-4, dense.shape)
    assert step < ACCELERATION_SPAN
    demo = parse_demonstration(_with_arms(dense, dense_t))
    speed, acceleration = _peaks(demo)
    assert speed < MAX_REFERENCE_SPEED and acceleration > 10 * MAX_ACCELERATION
