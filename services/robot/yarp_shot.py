"""The shot on a YARP robot that has no archery port of its own (a lab's iCub), as the paper
shot it: `release` moves one finger joint to its open angle (`--release-joint r_index_proximal
--release-open DEG`); `grasp`, `nock` and `reset` move the hand to a configured posture
(`--hand-postures FILE`: {verb: {axis: degrees}}), or, where none is configured, answer
`operator_needed`: the operator does it by hand and confirms it to the session (the learner's
`OperatorDesk`). The robot does not see its arrow land: its release replies once the finger is
open, outcome "released", and its `status` says `world.landing` "camera" (the detector tells
the landing from the frames). Nothing is invented: no ground truth, no θ at the release.

`LabShot` moves the hand's axes (mapped by name) by `positionMove` at `REFERENCE_SPEED` and
judges them there from the encoders within `TOLERANCES["rest"]`, never by `checkMotionDone`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import msgspec

from archery.protocol.errors import ArcheryError, OperatorNeeded
from archery.protocol.robotspec import REFERENCE_SPEED, TOLERANCES
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv
from archery.services.robot.hand_postures import read_postures
from archery.services.robot.yarp_parts import BodyError, YarpBody
from archery.services.robot.yarp_presence import BoardsLock

if TYPE_CHECKING:
    from archery.services.robot.config import RobotConfig

__all__ = [
    "HAND_TIMEOUT",
    "RELEASE_JOINT",
    "AxisRef",
    "EventsIgnored",
    "LabShot",
    "Shot",
    "lab_shot",
]

log = logging.getLogger("archery.robot")

RELEASE_JOINT = "r_index_proximal"  # the paper's: "one joint in the index finger"
HAND_TIMEOUT = 5.0  # wall s a hand posture (or the release finger) has to be reached
_POLL = 0.01  # wall s between two readings of the hand's encoders
_BY_HAND = {
    "grasp": "put an arrow in the right hand",
    "nock": "put an arrow on the bow with its nock on the string, in the right hand",
    "reset": "ready the robot for a session (hands free, an arrow at hand)",
}


class Shot(Protocol):
    """Who answers a YARP body's archery verbs."""

    def grasp(self) -> rv.GraspReply: ...
    def nock(self) -> rv.NockReply: ...
    def release(self) -> rv.ReleaseReply: ...
    def reset(self, seed: Any = None) -> rv.ResetReply: ...
    def status(self) -> rv.ArcheryStatusReply: ...
    def close(self) -> None: ...


def lab_shot(
    body: YarpBody,
    lock: BoardsLock,
    clock: Callable[[], float],
    config: RobotConfig,
    status: Callable[[str, int, dict[str, Any]], rv.ArcheryStatusReply],
) -> LabShot | None:
    """The finger release of `config` (`release_joint`, `release_open`, `hand_postures`) on
    `body`; None (said once) when no release joint is given and the robot has no
    `RELEASE_JOINT`: its archery verbs are then refused.

    Raises:
        BodyError: a release joint or a posture's axis given is not the robot's, or an angle
            is outside its limits, or the postures file does not read.
    """
    joint = config.release_joint or RELEASE_JOINT
    postures, first = read_postures(config.hand_postures) if config.hand_postures else ({}, ())
    if not config.release_joint and not any(joint in a.axes for a in body.parts.values()):
        if postures:
            raise BodyError(
                f"--hand-postures without a release: {body.remote} has no {RELEASE_JOINT} "
                "axis; give --release-joint AXIS"
            )
        log.warning(
            "%s has no %s axis and no --archery-rpc: the archery verbs are refused (give "
            "--release-joint AXIS --release-open DEG, or the robot's --archery-rpc PORT)",
            body.remote,
            RELEASE_JOINT,
        )
        return None
    return LabShot(body, lock, clock, joint, config.release_open, postures, status, first)


class NotReached(ArcheryError):
    """A hand axis did not reach its angle within `HAND_TIMEOUT`."""

    code = "not_reached"


@dataclass(frozen=True)
class AxisRef:
    """One axis of the robot found by name: its part, index on the part's board and limits
    (degrees; None where the robot does not tell them)."""

    name: str
    part: str
    index: int
    limits: tuple[float, float] | None


class LabShot:
    """The archery verbs of a YARP robot without an archery port (module doc).

    Args:
        body: the robot's open control boards.
        lock: the lock that serialises the body's YARP calls (the loop's).
        clock: wall s since the body's start (the replies' `sim_time`).
        release_joint, release_open: the finger axis the release opens, and to what angle
            (degrees).
        postures: {verb: {axis: degrees}} for grasp, nock, reset (`read_postures`).
        status: builds the robot's status from the shot's (phase, shot) and world.
        operator_first: the verbs whose posture waits for the operator's hand first.

    Raises:
        BodyError: an axis named is not the robot's (the message names the robot's axes), is
            named on two parts, or an angle is outside the robot's limits for it.
    """

    def __init__(
        self,
        body: YarpBody,
        lock: BoardsLock,
        clock: Callable[[], float],
        release_joint: str,
        release_open: float,
        postures: Mapping[str, Mapping[str, float]],
        status: Callable[[str, int, dict[str, Any]], rv.ArcheryStatusReply],
        operator_first: tuple[str, ...] = (),
    ) -> None:
        self.body, self._lock, self._clock, self._status = body, lock, clock, status
        self.operator_first = operator_first
        self._asked: str | None = None  # the verb whose operator's part was asked last
        self.finger = self._axis(release_joint, "--release-joint")
        self._check(self.finger, release_open, "--release-open")
        self.open = release_open
        self.postures: dict[str, list[tuple[AxisRef, float]]] = {}
        for verb, angles in postures.items():
            refs = [
                (self._axis(name, f"--hand-postures {verb}"), deg) for name, deg in angles.items()
            ]
            for ref, deg in refs:
                self._check(ref, deg, f"--hand-postures {verb} {ref.name}")
            self.postures[verb] = refs
        self._shots = 0
        self._phase = "idle"
        speed = math.degrees(REFERENCE_SPEED)
        for ref in {self.finger, *(r for refs in self.postures.values() for r, _ in refs)}:
            control = body.driver(ref.part).viewIPositionControl()
            if control is None or not control.setRefSpeed(ref.index, speed):
                raise BodyError(f"{body.parts[ref.part].board} {ref.name}: refuses a speed")

    def _axis(self, name: str, flag: str) -> AxisRef:
        found = [
            (part, axes.axes.index(name))
            for part, axes in self.body.parts.items()
            if name in axes.axes
        ]
        if len(found) != 1:
            boards = ", ".join(axes.board for axes in self.body.parts.values())
            what = "no axis" if not found else "more than one axis"
            raise BodyError(f"{flag} {shown(name)}: {what} of that name on {boards}")
        part, index = found[0]
        return AxisRef(name, part, index, self._limits(part, index))

    def _limits(self, part: str, index: int) -> tuple[float, float] | None:
        control = self.body.driver(part).viewIControlLimits()
        yarp = self.body.yarp
        low, high = yarp.DVector(1), yarp.DVector(1)
        if control is None or not control.getLimits(index, low, high):
            return None
        lower, upper = float(low[0]), float(high[0])
        return (lower, upper) if math.isfinite(lower) and math.isfinite(upper) else None

    def _check(self, ref: AxisRef, deg: float, flag: str) -> None:
        if ref.limits is not None and not ref.limits[0] <= deg <= ref.limits[1]:
            raise BodyError(
                f"{flag} {deg:g}°: outside {ref.name}'s limits [{ref.limits[0]:g}, "
                f"{ref.limits[1]:g}]° on {self.body.parts[ref.part].board}"
            )

    # -- moving the hand ---------------------------------------------------------------------
    def _read(self, ref: AxisRef) -> float:
        """`ref`'s encoder now (degrees), NaN when the board gives none."""
        encoders = self.body.driver(ref.part).viewIEncoders()
        values = self.body.yarp.Vector(len(self.body.parts[ref.part].axes))
        with self._lock:
            ok = encoders.getEncoders(values.data())
        return float(values[ref.index]) if ok else math.nan

    def _move(self, moves: list[tuple[AxisRef, float]], what: str) -> None:
        """Each axis to its angle (degrees), then wait until the encoders show them all there.

        Raises:
            NotReached: not all there within `HAND_TIMEOUT` (the message names the axes).
        """
        with self._lock:
            for ref, deg in moves:
                control = self.body.driver(ref.part).viewIPositionControl()
                if not control.positionMove(ref.index, deg):
                    raise NotReached(f"{what}: {ref.name} refuses positionMove to {deg:g}°")
        tolerance = math.degrees(TOLERANCES["rest"])
        deadline = time.monotonic() + HAND_TIMEOUT
        while True:
            off = [(ref, deg, self._read(ref)) for ref, deg in moves]
            off = [(r, d, v) for r, d, v in off if not abs(v - d) <= tolerance]
            if not off:
                return
            if time.monotonic() > deadline:
                told = ", ".join(f"{r.name} at {v:.1f}° (asked {d:g}°)" for r, d, v in off)
                raise NotReached(f"{what}: not reached within {HAND_TIMEOUT:g} s: {told}")
            time.sleep(_POLL)

    def _posture(self, verb: str) -> None:
        """The configured posture of `verb`; where the operator's hand is needed (no posture,
        or one listed in the postures' "operator"), the first call answers `OperatorNeeded`
        and the next one, once the operator confirmed, takes the posture (if any)."""
        moves = self.postures.get(verb)
        if (moves is None or verb in self.operator_first) and self._asked != verb:
            self._asked = verb
            then = f"; the robot then takes its {verb} posture" if moves else ""
            raise OperatorNeeded(
                f"{verb}: {_BY_HAND[verb]}{then} (the robot's hand needs the operator's)"
            )
        self._asked = None
        if moves is not None:
            self._move(moves, f"the {verb} posture")

    # -- the verbs ----------------------------------------------------------------------------
    def grasp(self) -> rv.GraspReply:
        """The grasp posture; the operator's hand without one."""
        self._posture("grasp")
        return rv.GraspReply(arrow="", distance=0.0, tolerance=0.0, sim_time=self._clock())

    def nock(self) -> rv.NockReply:
        """The nock posture (the release finger closed on the string); the operator's without
        one."""
        self._posture("nock")
        self._phase = "nocked"
        return rv.NockReply(shot=self._shots + 1, arrow="", sim_time=self._clock())

    def release(self) -> rv.ReleaseReply:
        """The release finger to its open angle; replies once the encoder shows it there (the
        arrow's landing is the camera's to tell)."""
        self._move([(self.finger, self.open)], "the release")
        self._shots += 1
        self._phase = "idle"
        now = self._clock()
        return rv.ReleaseReply(
            shot=self._shots,
            outcome="released",
            hit=False,
            reason=f"{self.finger.name} opened to {self.open:g}°; the camera tells the landing",
            sim_time=now,
            release_sim_time=now,
            flight_time=0.0,
        )

    def reset(self, seed: Any = None) -> rv.ResetReply:
        """The reset posture; the operator's hand without one (a seed is no use to a real
        robot: it is echoed)."""
        self._posture("reset")
        self._phase = "idle"
        return rv.ResetReply(sim_time=self._clock(), seed=seed, shot=self._shots)

    def status(self) -> rv.ArcheryStatusReply:
        """The robot's status: its shot count and phase, `world.landing` "camera"."""
        world = {
            "landing": "camera",
            "release": {"joint": self.finger.name, "open_deg": self.open},
            "hand_postures": sorted(self.postures),
        }
        return self._status(self._phase, self._shots, world)

    def close(self) -> None:
        """Nothing of its own to close: the body's boards are the loop's."""


class EventsIgnored:
    """The robot's own archery port (`yarp_archery.ArcheryLink`) with what it tells of the
    arrow's flight dropped, as a robot that does not see its arrow (`--landing camera`): its
    release's outcome "released", no θ, its status's `world.landing` "camera"."""

    def __init__(self, link: Any) -> None:
        self.link = link
        self.grasp, self.nock, self.close = link.grasp, link.nock, link.close

    def release(self) -> rv.ReleaseReply:
        """The robot's release, its landing and θ dropped."""
        told = self.link.release()
        return rv.ReleaseReply(
            shot=told.shot,
            outcome="released",
            hit=False,
            reason="the robot's landing ignored (--landing camera); the camera tells it",
            sim_time=told.release_sim_time,
            release_sim_time=told.release_sim_time,
            flight_time=0.0,
        )

    def reset(self, seed: Any = None) -> rv.ResetReply:
        """The robot's reset."""
        reply: rv.ResetReply = self.link.reset(seed)
        return reply

    def status(self) -> rv.ArcheryStatusReply:
        """The robot's status, its world saying the camera tells the landing."""
        told: rv.ArcheryStatusReply = self.link.status()
        return msgspec.structs.replace(told, world=told.world | {"landing": "camera"})
