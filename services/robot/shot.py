"""The shot's state on the robot: the shot number, the release waiting for its landing, the
landing's reply and the phase a `WorldState` carries.

A release replies once the arrow has landed; at rtf 0 only once the robot also rests after the
shot (the arms settle for a few simulated ms after the landing, and a command arriving meanwhile
would start at a simulated time of the wall clock's choosing). Simulation thread only, but for
`abort` at the loop's end.
"""

from __future__ import annotations

from concurrent.futures import Future
from typing import Literal

from archery.protocol.verbs import robot as rv
from archery.services.robot.jobs import SimUnavailable
from archery.services.robot.sink import Sink
from archery.sim.arrow import Landing
from archery.sim.errors import StateError
from archery.sim.world import ArcheryWorld, ArrowState

__all__ = ["Phase", "Shots", "phase_of"]

Phase = Literal["idle", "nocked", "flying", "stuck", "missed"]


def phase_of(world: ArcheryWorld) -> Phase:
    """The shot phase for `WorldState`: idle, nocked, flying, stuck or missed."""
    state = world.arrow_state
    if state is ArrowState.LANDED:
        landing = world.landing
        return "stuck" if landing is not None and landing.hit else "missed"
    if state in (ArrowState.STOWED, ArrowState.GRASPED, ArrowState.DROPPED):
        return "idle"  # no arrow on the bow
    return "nocked" if state is ArrowState.NOCKED else "flying"


class Shots:
    """The shots since the service started and the release that waits for its landing.

    Args:
        sink: receives the shot events (nocked, released, landed / missed).
        wait_for_rest: hold a landing's reply until the robot rests (`at_rest`; rtf 0).
    """

    def __init__(self, sink: Sink, wait_for_rest: bool) -> None:
        self.number = 0  # of the latest released shot
        self._sink = sink
        self._wait_for_rest = wait_for_rest
        self._landing: Future[rv.ReleaseReply] | None = None
        self._settling: tuple[Future[rv.ReleaseReply], rv.ReleaseReply] | None = None

    @property
    def flying(self) -> bool:
        """True from a release to its landing."""
        return self._landing is not None

    def nock(self, world: ArcheryWorld) -> rv.NockReply:
        """Put a fresh arrow on the bow; the `nocked` event goes out (the world state is the
        caller's to publish)."""
        world.nock()
        t = world.sim_time
        self._sink.event("nocked", self.number + 1, t)
        return rv.NockReply(shot=self.number + 1, arrow=world.arrow_state.value, sim_time=t)

    def grasp(self, world: ArcheryWorld) -> rv.GraspReply:
        """Whole shot: close the right hand on the arrow (`ArcheryWorld.grasp`); the `grasped`
        event goes out.

        Raises:
            GraspMissed: the hand is off the shaft by more than the tolerance. StateError: not
                a whole-shot world, or an arrow is held, nocked or flying.
        """
        distance = world.grasp()
        self._sink.event("grasped", self.number + 1, world.sim_time)
        return rv.GraspReply(
            arrow=world.arrow_state.value,
            distance=distance,
            tolerance=world.config.grasp_tolerance,
            sim_time=world.sim_time,
        )

    def release(self, world: ArcheryWorld) -> Future[rv.ReleaseReply]:
        """Launch the nocked arrow; the future holds the reply once it has landed (`landed`).

        Raises:
            StateError: no arrow is nocked, or a release already waits for its landing.
            ArrowDropped: whole shot, the arrow was in the hand but off the string: it falls.
        """
        if self._landing is not None:
            raise StateError("a release is already waiting for its landing")
        world.launch()
        self.number += 1
        self._landing = Future()
        self._sink.event("released", self.number, world.sim_time)
        return self._landing

    def landed(self, landing: Landing) -> None:
        """Publish the landing's event (the only place with the ground-truth impact) and answer
        the release, at once or at rest (`wait_for_rest`). The world state goes out first: the
        caller's."""
        launch = landing.launch
        r = None if landing.r is None else landing.r.tolist()
        kind = "landed" if landing.hit else "missed"
        self._sink.event(kind, self.number, landing.sim_time, r, landing.reason or "")
        reply = rv.ReleaseReply(
            shot=self.number,
            outcome=landing.outcome.value,
            hit=landing.hit,
            reason=landing.reason or "",
            sim_time=landing.sim_time,
            release_sim_time=launch.sim_time,
            flight_time=landing.flight_time,
            theta=launch.theta.tolist(),
        )
        future, self._landing = self._landing, None
        if future is None:
            return
        if self._wait_for_rest:
            # the arms may still settle from the shot, and the states of the rest are not out
            # yet: a reply now would let the next command land at a simulated time, or start
            # from joint positions, of the wall clock's choosing
            self._settling = (future, reply)
        else:
            future.set_result(reply)

    def at_rest(self) -> None:
        """The robot rests and has published so: a landing's held reply goes out."""
        settling, self._settling = self._settling, None
        if settling is not None:
            settling[0].set_result(settling[1])

    def abort(self) -> None:
        """The loop ends: a release still in flight fails; a landed one gets its reply."""
        future, self._landing = self._landing, None
        if future is not None and not future.done():
            future.set_exception(SimUnavailable("the robot stopped before the arrow landed"))
        settling, self._settling = self._settling, None
        if settling is not None and not settling[0].done():
            settling[0].set_result(settling[1])  # landed; the robot stopped while settling
