"""A demonstration of the whole shot: both arms' joint trajectory with its timing and the shot's
events, as `archery demonstrate` records and checks it (a JSON file).

Times are seconds of simulated time from the first sample, joint angles radians in YARP order
(`protocol.parts`). `parse_demonstration` checks the form (JSON, fields, the arms' joint names
and counts, times increasing, long enough); `check_limits` checks the angles against joint
limits the caller knows (the simulator's). Each raises `BadDemonstration` with one line that
names what is wrong.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from protocol.errors import ArcheryError
from protocol.parts import ARM_PARTS, PARTS

__all__ = [
    "FORMAT",
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
MAX_SAMPLES = 200_000

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
    """The demonstration in `data` (JSON), its form checked.

    Raises:
        BadDemonstration: not JSON, a missing or unknown field, joints other than the arms',
            a sample of the wrong length, times not finite or not increasing, too short.
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
    return demo


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
