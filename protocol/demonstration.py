"""A demonstration of the whole shot: both arms' joint trajectory with its timing and the shot's
events, as `archery demonstrate` records and checks it (a JSON file). Times are s of simulated
time, angles rad in YARP order (`protocol.parts`). `parse_demonstration` checks a file's bytes
(at most `MAX_BYTES`, read bounded by `services.controller.demonstration_file`): the form; what
a learner can play (bounded samples, interval and duration, events in order within the samples,
dense enough to imitate: `MAX_DT`); that it is a whole shot (grasped, nocked and released once
each, in this order); and that the robot can follow it: every joint within `MAX_REFERENCE_SPEED`
between samples and within `MAX_ACCELERATION` over `ACCELERATION_SPAN`. `check_limits` checks
the angles against joint limits the caller knows. Each raises `BadDemonstration` with one line.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Annotated, Literal

import msgspec
import numpy as np
from msgspec import Meta

from archery.protocol.errors import ArcheryError
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import MAX_REFERENCE_SPEED

__all__ = [
    "ACCELERATION_SPAN",
    "EVENT_SLACK",
    "FORMAT",
    "MAX_ACCELERATION",
    "MAX_BYTES",
    "MAX_DT",
    "MAX_DURATION",
    "MAX_SAMPLES",
    "MIN_DT",
    "MIN_DURATION",
    "MIN_SAMPLES",
    "SHOT_EVENTS",
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
#: The events a whole shot's demonstration holds once each, in this order (a landing or a miss
#: may follow): the DMPs' two phases meet at the nock, and the controller grasps and nocks at
#: their demonstrated times; without them every rollout would abort.
SHOT_EVENTS = ("grasped", "nocked", "released")
#: rad/s²: the most a joint of the demonstration may accelerate. The robot's joints follow their
#: setpoints through position servos of bandwidth ω = 25 rad/s, critically damped (the
#: simulator's `SceneConfig.servo_bandwidth`); a `positionMove` at the fastest reference speed,
#: `MAX_REFERENCE_SPEED` v, starts its setpoint at v at once, and the joint's acceleration then
#: peaks at v·ω/e = 18.4 rad/s². A demonstration recorded from such moves passes; the shipped
#: one peaks at 5.8 rad/s².
MAX_ACCELERATION = 20.0
#: s: accelerations are the change of speed between the spans of at least this much either side
#: of a sample (the robot's joint-state period at its default 50 Hz): consecutive samples at
#: 50 Hz or sparser, while a denser recording's position noise ε, which adds up to 4ε/span² to
#: the estimate (1 rad/s² for ε = 0.1 mrad), is not read as an acceleration. An average over the
#: spans, so never more than the movement's true peak. Speeds are those between samples.
ACCELERATION_SPAN = 0.02

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
    `EVENT_SLACK` s: the recording stops at it); the `SHOT_EVENTS` once each, in their order;
    every joint's speed between two samples within `MAX_REFERENCE_SPEED`, its acceleration
    (over `ACCELERATION_SPAN`) within `MAX_ACCELERATION`.

    Raises:
        BadDemonstration: not JSON, a missing or unknown field, joints other than the arms',
            a sample of the wrong length, times not finite, not increasing, too close or too
            far apart, too short or too long, an event outside the samples or out of order;
            a shot event missing, doubled or out of order; a joint too fast or accelerating
            too hard (its name, time, value and bound).
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
    _check_shot_events(demo)
    _check_motion(demo)
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


def _check_shot_events(demo: Demonstration) -> None:
    """`SHOT_EVENTS` once each, in their order (the events are in time order already)."""
    wanted = ", ".join(SHOT_EVENTS)
    first: dict[str, tuple[int, float]] = {}
    for i, event in enumerate(demo.events):
        if event.kind not in SHOT_EVENTS:
            continue
        if event.kind in first:
            j, t = first[event.kind]
            raise BadDemonstration(
                f"event {i} ({event.kind}, t = {event.t:.3f} s) is a second {event.kind} event "
                f"(event {j} at {t:.3f} s): a whole shot holds {wanted} once each"
            )
        first[event.kind] = (i, event.t)
    for kind in SHOT_EVENTS:
        if kind not in first:
            raise BadDemonstration(
                f"no {kind} event: a whole shot holds {wanted} once each, in this order "
                f"(events: {', '.join(e.kind for e in demo.events) or 'none'})"
            )
    for before, after in pairwise(SHOT_EVENTS):
        (i, t_before), (j, t_after) = first[before], first[after]
        if j < i:
            raise BadDemonstration(
                f"event {j} ({after}, t = {t_after:.3f} s) comes before event {i} ({before}, "
                f"t = {t_before:.3f} s): a whole shot holds {wanted} in this order"
            )


def _check_motion(demo: Demonstration) -> None:
    """Every joint's speed between two samples within `MAX_REFERENCE_SPEED` (rad/s), its
    acceleration over `ACCELERATION_SPAN` within `MAX_ACCELERATION` (rad/s²); the first sample
    past a bound named."""
    names = [name for part in ARM_PARTS for name in PARTS[part]]
    t = np.array([sample.t for sample in demo.samples])
    q = np.array([[*sample.left_arm, *sample.right_arm] for sample in demo.samples])
    dt = np.diff(t)  # ≥ MIN_DT: checked
    speed = np.diff(q, axis=0) / dt[:, None]
    fast = np.abs(speed) > MAX_REFERENCE_SPEED
    if fast.any():
        i, joint = (int(x) for x in np.argwhere(fast)[0])
        raise BadDemonstration(
            f"{names[joint]} moves at {abs(speed[i, joint]):.3g} rad/s between t = {t[i]:.3f} "
            f"and {t[i + 1]:.3f} s (samples {i} and {i + 1}), over the robot's maximum joint "
            f"speed of {MAX_REFERENCE_SPEED:g} rad/s"
        )
    n = t.size
    slack = 1e-6  # s: sample times are sums of simulated steps
    after = np.searchsorted(t, t + ACCELERATION_SPAN - slack, side="left")
    before = np.searchsorted(t, t - ACCELERATION_SPAN + slack, side="right") - 1
    inner = np.flatnonzero((before >= 0) & (after < n))
    if inner.size == 0:
        return
    j, k = after[inner], before[inner]
    ahead = (q[j] - q[inner]) / (t[j] - t[inner])[:, None]
    behind = (q[inner] - q[k]) / (t[inner] - t[k])[:, None]
    acceleration = (ahead - behind) / (0.5 * (t[j] - t[k]))[:, None]
    hard = np.abs(acceleration) > MAX_ACCELERATION
    if hard.any():
        row, joint = (int(x) for x in np.argwhere(hard)[0])
        i = int(inner[row])
        raise BadDemonstration(
            f"{names[joint]} accelerates at {abs(acceleration[row, joint]):.3g} rad/s² at "
            f"t = {t[i]:.3f} s (sample {i}), over the {MAX_ACCELERATION:g} rad/s² a joint of "
            f"the robot follows"
        )


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
