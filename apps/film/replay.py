"""One rollout of a session, simulated again from its journal, as the states a film shows.

The journal holds what the shot depended on: the session's seed (the robot was reset with it
before the first rollout), each attempt's θ, the robot's shot number, and in its header's `rig`
the robot's world parameters (scene, bow, wind, noise) and shot count and the controller's
trajectory time. `ShotReplay` rebuilds that world and yields the filmed rollout; a journal
without `rig` (an older learner) is replayed with the default world, and says so. Times are
simulated seconds; positions metres in the root frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archery.protocol.errors import BadRequest, ConfigError
from archery.protocol.journal_records import DoneRecord, HeaderRecord, ProposedRecord
from archery.protocol.parts import PARTS
from archery.services.controller.cartesian import reference_speeds
from archery.services.controller.config import ControllerConfig
from archery.services.controller.posture import ArcheryPosture
from archery.services.learner.journal import JOURNAL_NAME, JournalState, read_records
from archery.sim.arrow import Landing
from archery.sim.errors import SimError
from archery.sim.world import ArcheryWorld, WorldConfig

__all__ = ["POSTURE", "FilmFrame", "Rollout", "ShotReplay", "load_rollout"]

SLOW_MOTION = 0.1  # the flight plays at this fraction of real time
HOLD_NOCK_S = 0.4  # s of simulated time the nocked arrow is shown before the release
HOLD_RELEASE_S = 0.3  # s of video the arrow is shown at its release
HOLD_IMPACT_S = 1.5  # s of video the landed arrow is shown
POSTURE = "posture & draw"  # the move to θ's posture draws the string hand back to θ
MAX_MOVE_S = 20.0  # s of simulated time a move may take before the replay gives up on it


@dataclass(frozen=True)
class FilmFrame:
    """One state to film: the qpos, its simulated time (s), the phase shown, for how many
    video frames it stays on screen and whether the arrow has left the bow (from the release
    on: the camera follows it, `apps.film.framing`)."""

    qpos: np.ndarray
    sim_time: float
    phase: str
    repeat: int = 1
    released: bool = False


@dataclass(frozen=True)
class Rollout:
    """The done record of the rollout to film, the θ (m) the robot held before it and the
    robot's launches since the session's reset before this shot."""

    header: HeaderRecord
    done: DoneRecord
    previous_theta: list[float] | None
    launches_before: int


def load_rollout(path: Path, rollout: int | None) -> Rollout:
    """The rollout `rollout` (1-based, done rollouts) of the session journaled at `path` (a
    journal or its folder); None: the session's first hit.

    Raises:
        services.learner.journal.JournalError: unreadable journal or another version.
        BadRequest: no such rollout, or no hit when `rollout` is None.
    """
    path = Path(path)
    if path.is_dir():
        path = path / JOURNAL_NAME
    records, _ = read_records(path)
    state = JournalState.from_records(records, str(path))
    done = state.done
    if rollout is None:
        hits = [d for d in done if d.hit]
        if not hits:
            raise BadRequest(
                f"session {state.session} has no hit in its {len(done)} rollouts; "
                f"name one with --rollout N"
            )
        target = hits[0]
    else:
        if not 1 <= rollout <= len(done):
            raise BadRequest(
                f"session {state.session} has {len(done)} done rollouts; --rollout {rollout} "
                f"is not among them"
            )
        target = done[rollout - 1]
    previous: list[float] | None = None  # the robot holds the last attempt's posture
    for record in records:
        if isinstance(record, ProposedRecord) and record.index < target.index:
            previous = record.theta
    first = next((d.shot for d in done if d.shot is not None), None)
    rig = state.header.rig if isinstance(state.header.rig, dict) else {}
    if isinstance(rig.get("shot"), int):
        launches = (target.shot or 0) - rig["shot"] - 1
    else:
        launches = (target.shot or 0) - (first or 0)
    return Rollout(state.header, target, previous, max(0, launches))


class ShotReplay:
    """The rollout simulated again: `frames(fps)` yields what a film of it shows.

    It rebuilds the journal's world, moves the robot to the previous attempt's posture
    unfilmed, advances the shot noise past the session's earlier launches, then yields the
    filmed rollout: the move to the posture for θ (solved as the controller solves it), the
    nock, the release and flight (slowed down) and the arrow on the target.

    Args:
        rollout: the rollout and its session's header (`load_rollout`).
        posture: the controller's posture solver (built with its default settings if None;
            building it searches its reference posture, ~1 s).

    Raises:
        BadRequest: the header's world parameters are not valid.
    """

    def __init__(self, rollout: Rollout, posture: ArcheryPosture | None = None) -> None:
        self.rollout = rollout
        rig = rollout.header.rig if isinstance(rollout.header.rig, dict) else {}
        self.recorded_world = bool(rig.get("world"))
        try:
            config = WorldConfig.from_dict(rig["world"]) if rig.get("world") else WorldConfig()
        except (SimError, ConfigError) as exc:
            raise BadRequest(f"the journal's world parameters are not valid: {exc}") from None
        self.traj_time = float(rig.get("traj_time", ControllerConfig().traj_time))
        self.world = ArcheryWorld(config)
        self.posture = posture or ArcheryPosture(ControllerConfig().posture)
        self.landing: Landing | None = None

    @property
    def theta(self) -> np.ndarray:
        """θ of the filmed rollout (m)."""
        return np.array(self.rollout.done.theta)

    def _move_to(self, theta: list[float] | np.ndarray) -> None:
        """Command the posture for θ as the controller does: targets solved from its reference
        posture, each joint's reference speed covering its move in the trajectory time."""
        q = self.posture.solve(np.asarray(theta, dtype=float)).q
        world = self.world
        for part in PARTS:
            joints = PARTS[part]
            if not any(j in q for j in joints):
                continue
            current = world.joint_positions(part)
            low, high = world.joint_limits(part)
            target = np.clip([q.get(j, c) for j, c in zip(joints, current, strict=True)], low, high)
            world.set_reference_speeds(part, reference_speeds(target - current, self.traj_time))
            world.set_joint_targets(part, target)

    def _settle(self, step: float) -> Iterator[float]:
        """Step until the motion is done, `step` s at a time; yields the sim time after each."""
        start = self.world.sim_time
        while not self.world.motion_done():
            self.world.step(step)
            yield self.world.sim_time
            if self.world.sim_time - start > MAX_MOVE_S:
                raise BadRequest(
                    f"the posture for θ = {self.theta.tolist()} m was not reached within "
                    f"{MAX_MOVE_S:g} s of simulated time"
                )

    def frames(self, fps: float) -> Iterator[FilmFrame]:
        """The filmed rollout at `fps` video frames per second: the posture move (the draw: it
        brings the string hand to θ from the bow hand) and the nock at real time, the release
        held, the flight slowed down to `SLOW_MOTION`, the landed arrow held."""
        world = self.world
        world.reset(self.rollout.header.seed)
        if self.rollout.previous_theta is not None:
            self._move_to(self.rollout.previous_theta)
            for _ in self._settle(0.05):
                pass
        world.skip_shots(self.rollout.launches_before)
        yield FilmFrame(world.qpos(), world.sim_time, POSTURE, repeat=round(0.5 * fps))
        self._move_to(self.theta)
        for t in self._settle(1.0 / fps):
            yield FilmFrame(world.qpos(), t, POSTURE)
        world.nock()
        world.step(world.timestep)
        for _ in range(max(1, round(HOLD_NOCK_S * fps))):
            yield FilmFrame(world.qpos(), world.sim_time, "nock")
            world.step(1.0 / fps)
        world.launch()
        yield FilmFrame(
            world.qpos(),
            world.sim_time,
            "release",
            repeat=round(HOLD_RELEASE_S * fps),
            released=True,
        )
        dt = SLOW_MOTION / fps
        while True:
            landing = world.step(dt)
            if landing is not None:
                self.landing = landing
                break
            yield FilmFrame(world.qpos(), world.sim_time, f"flight ×{SLOW_MOTION:g}", released=True)
        yield FilmFrame(
            world.qpos(),
            world.sim_time,
            "impact",
            repeat=round(HOLD_IMPACT_S * fps),
            released=True,
        )

    def landing_error_m(self) -> float | None:
        """Distance (m) between the replayed landing's r and the journal's ground truth, once
        the frames are through; None when either is unknown."""
        truth = self.rollout.done.truth_r_m
        landing = self.landing
        if truth is None or landing is None or landing.r is None:
            return None
        return math.dist(landing.r, truth)
