"""A demonstration of the whole shot: both arms' joint trajectory with its timing and the shot's
events, as `archery demonstrate` records and checks it (a JSON file).

Times are seconds of simulated time from the first sample, joint angles radians in YARP order
(`protocol.parts`). `parse_demonstration` checks a file's bytes (at most `MAX_BYTES`, read
bounded by the learner's reader, `services.learner.config.read_demonstration`): the form
(fields, the arms' joints, times increasing) and that a learner can play it: bounded samples,
interval and duration (a DMP's planning time and memory grow with duration / interval), events
in order within the samples; and that it is dense enough to imitate (`MAX_DT`);
`check_limits` checks the angles against joint limits the caller knows. Each raises
`BadDemonstration` with one line.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from archery.protocol.errors import ArcheryError
from archery.protocol.parts import ARM_PARTS, PARTS

__all__ = [
    "EVENT_SLACK",
    "FORMAT",
    "MAX_BYTES",
    "MAX_DT",
    "MAX_DURATION",
    "MAX_SAMPLES",
    "MIN_DT",
    "MIN_DURATION",
    "MIN_SAMPLES",
    "BadDemonstration",
    "DemoEvent",
    "Demonstration",
    "Sample",
    "check_limits",
    "encode_demonstration",
    "parse_demonstration",
]

FORMAT: Literal["archery-demonstration/1"] = "archery-demonstration/1"
MIN_SAMPLES = 20  # a movement needs at least this many samples …
MIN_DURATION = 1.0  # … over at least this long (s)
MAX_DURATION = 60.0  # s: the shipped one lasts 12.6 s; a DMP step costs ~45 µs to roll out
MIN_DT = 1e-3  # s between two samples: the DMP's step is their median interval
MAX_SAMPLES = int(MAX_DURATION / MIN_DT) + 1  # at most this many samples …
MAX_BYTES = 40_000_000  # … and bytes in the file (indented JSON: ~450 bytes a sample)
EVENT_SLACK = 0.1  # s: an event (the shot's end) may follow the last sample by this much
#: s between two samples at most: the DMPs (`services.controller.movement`: 120 basis functions
#: a phase, their forcing term fitted on the samples' finite differences, rolled out at the
#: median interval) learn the movement between samples no farther apart. The shipped whole
#: shot thinned evenly to 10 Hz still imitates within 5 mm of the demonstrated grasp (15 mm is
#: the grasp's tolerance) and θ within 2 mm; at 2.5 Hz the grasp misses by 22 mm.
MAX_DT = 0.1

Angles = Annotated[list[float], Meta(min_length=1, max_length=64, description="rad")]


class BadDemonstration(ArcheryError, ValueError):
    """A demonstration file that is malformed, too short, of the wrong joints or out of the
    joint limits."""

    code = "bad_demonstration"


class Sample(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Both arms' joint angles (rad) at time t (s)."""

    t: float
    left_arm: Angles
    right_arm: Angles


class DemoEvent(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A shot event of the robot's `world/events:o` at time t (s)."""

    t: float
    kind: Literal["grasped", "nocked", "released", "landed", "missed"]


class Demonstration(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The file: its format tag, the arms' joint names, the samples, the events, the robot's
    shot ("posture" or "whole") and how it was made (free text)."""

    format: Literal["archery-demonstration/1"]
    joints: dict[str, list[str]]
    samples: Annotated[list[Sample], Meta(max_length=MAX_SAMPLES)]
    events: list[DemoEvent]
    shot: Literal["posture", "whole"]
    made: Annotated[str, Meta(max_length=2000)] = ""


def parse_demonstration(data: bytes) -> Demonstration:
    """The demonstration in `data` (JSON), its form checked, and what a learner plays bounded:
    at most `MAX_SAMPLES` samples, at least `MIN_DT` s apart, over `MIN_DURATION` to
    `MAX_DURATION` s (a DMP rolls out one step per median interval, ~45 µs each), at most
    `MAX_DT` s apart (the DMPs learn nothing between samples farther apart), every event
    in order within the samples' span (the shot's end may follow the last sample by
    `EVENT_SLACK` s: the recording stops at it).

    Raises:
        BadDemonstration: not JSON, a missing or unknown field, joints other than the arms',
            a sample of the wrong length, times not finite, not increasing, too close or too
            far apart, too short or too long, an event outside the samples or out of order.
    """
    try:
        demo = msgspec.json.decode(data, type=Demonstration)
    except msgspec.ValidationError as exc:
        raise BadDemonstration(f"not a demonstration: {exc}") from None
    except msgspec.DecodeError as exc:
        raise BadDemonstration(f"not JSON: {exc}") from None
    if set(demo.joints) != set(ARM_PARTS):
        raise BadDemonstration(
            f"joints must name the parts {', '.join(ARM_PARTS)}, got {', '.join(demo.joints)}"
        )
    for part in ARM_PARTS:
        if tuple(demo.joints[part]) != PARTS[part]:
            wanted, got = ", ".join(PARTS[part]), ", ".join(demo.joints[part])
            raise BadDemonstration(f"{part} joints must be {wanted}, got {got}")
    if len(demo.samples) < MIN_SAMPLES:
        raise BadDemonstration(
            f"too short: {len(demo.samples)} samples, a demonstration needs {MIN_SAMPLES}"
        )
    previous = -math.inf
    for i, sample in enumerate(demo.samples):
        if not math.isfinite(sample.t) or sample.t <= previous:
            raise BadDemonstration(f"sample {i}: time {sample.t!r} s does not follow {previous} s")
        if sample.t - previous < MIN_DT:
            raise BadDemonstration(
                f"sample {i}: time {sample.t!r} s follows {previous!r} s by less than "
                f"{MIN_DT:g} s, the shortest sample interval a learner plays"
            )
        previous = sample.t
        for part in ARM_PARTS:
            angles = getattr(sample, part)
            if len(angles) != len(PARTS[part]):
                raise BadDemonstration(
                    f"sample {i}: {part} has {len(angles)} angles, not {len(PARTS[part])}"
                )
            if not all(math.isfinite(a) for a in angles):
                raise BadDemonstration(f"sample {i}: {part} angles must be finite")
    duration = demo.samples[-1].t - demo.samples[0].t
    if duration < MIN_DURATION:
        raise BadDemonstration(
            f"too short: {duration:.3f} s, a demonstration lasts at least {MIN_DURATION:g} s"
        )
    if duration > MAX_DURATION:
        raise BadDemonstration(
            f"too long: {duration:.6g} s, a demonstration lasts at most {MAX_DURATION:g} s"
        )
    _check_density(demo)
    _check_events(demo)
    return demo


def _check_density(demo: Demonstration) -> None:
    """No two samples farther apart than `MAX_DT`."""
    gap, i = max((b.t - a.t, i) for i, (a, b) in enumerate(pairwise(demo.samples)))
    if gap > MAX_DT + 1e-9:  # a sum of simulated steps is not exactly MAX_DT
        raise BadDemonstration(
            f"too sparse to imitate: {gap:.3f} s between samples {i} and {i + 1} (t = "
            f"{demo.samples[i].t:.3f} s), the DMPs need one at least every {MAX_DT:g} s "
            f"({1 / MAX_DT:g} Hz of simulated time): record it again with `archery demonstrate "
            f"--out`, at the robot's --state-rate (50 Hz by default) whatever its rtf"
        )


def _check_events(demo: Demonstration) -> None:
    """Every event finite, in order, within the samples' span (+ `EVENT_SLACK`)."""
    first, last = demo.samples[0].t, demo.samples[-1].t
    previous = first
    for i, event in enumerate(demo.events):
        if not first <= event.t <= last + EVENT_SLACK:
            raise BadDemonstration(
                f"event {i} ({event.kind}): time {event.t!r} s is outside the samples' "
                f"{first:g} .. {last:g} s"
            )
        if event.t < previous:
            raise BadDemonstration(
                f"event {i} ({event.kind}): time {event.t!r} s comes before the event ahead "
                f"of it ({previous!r} s)"
            )
        previous = event.t


def check_limits(
    demo: Demonstration, limits: Mapping[str, tuple[Sequence[float], Sequence[float]]]
) -> None:
    """Check every angle against its part's (lower, upper) limits (rad).

    Raises:
        BadDemonstration: the first angle out of its limits, named with its sample and joint.
    """
    for i, sample in enumerate(demo.samples):
        for part in ARM_PARTS:
            lower, upper = limits[part]
            for name, angle, low, high in zip(
                PARTS[part], getattr(sample, part), lower, upper, strict=True
            ):
                if not low <= angle <= high:
                    raise BadDemonstration(
                        f"sample {i} (t = {sample.t:.3f} s): {name} = {angle:.4f} rad is out of "
                        f"its limits [{low:.4f}, {high:.4f}] rad"
                    )


def encode_demonstration(demo: Demonstration) -> bytes:
    """The demonstration as indented JSON."""
    return msgspec.json.format(msgspec.json.encode(demo), indent=1)
