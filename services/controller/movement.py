"""The whole shot's movement as dynamic movement primitives, learned from a demonstration
(`protocol.demonstration`) with `movement_primitives`: one bimanual joint-space DMP (both arms,
14 joints, rad) up to the nock, whose goal is the demonstrated nocking posture, and one from the
nock on (draw, hold, release), whose goal is the archery posture for θ, so one movement
serves any θ. Times are seconds from the movement's start; the grasp, nock and release happen
at their demonstrated times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from movement_primitives.dmp import DMP

from archery.protocol.demonstration import BadDemonstration, Demonstration

__all__ = ["DEFAULT_WEIGHTS", "Movement", "Reproduction"]

DEFAULT_WEIGHTS = 120  # basis functions per joint and phase


@dataclass(frozen=True)
class Reproduction:
    """A movement rolled out: times (s), both arms' angles (rad, n × 7 each) and the actions'
    times (s): grasp, nock, release."""

    t: np.ndarray
    left_arm: np.ndarray
    right_arm: np.ndarray
    grasp: float
    nock: float
    release: float

    def at(self, when: float) -> tuple[np.ndarray, np.ndarray]:
        """Both arms' angles (rad) at time `when` (s), linearly interpolated, held at the ends."""
        both = np.hstack([self.left_arm, self.right_arm])
        row = np.array([np.interp(when, self.t, both[:, j]) for j in range(both.shape[1])])
        return row[:7], row[7:]


def _event(demo: Demonstration, kind: str) -> float:
    for event in demo.events:
        if event.kind == kind:
            return event.t
    raise BadDemonstration(f"the demonstration has no {kind} event: not a whole shot")


def _fit(t: np.ndarray, y: np.ndarray, dt: float, weights: int) -> DMP:
    dmp = DMP(
        n_dims=y.shape[1],
        execution_time=float(t[-1] - t[0]),
        dt=dt,
        n_weights_per_dim=weights,
        smooth_scaling=True,
    )
    dmp.imitate(t - t[0], y)
    return dmp


class Movement:
    """The DMPs of one demonstration of the whole shot.

    Args:
        demo: a whole-shot demonstration (with grasped, nocked and released events).
        weights: basis functions per joint and phase.

    Raises:
        BadDemonstration: no grasp, nock or release in it, or too few samples in a phase.
    """

    def __init__(self, demo: Demonstration, weights: int = DEFAULT_WEIGHTS) -> None:
        self.grasp, self.nock = _event(demo, "grasped"), _event(demo, "nocked")
        self.release = _event(demo, "released")
        t = np.array([s.t for s in demo.samples])
        y = np.array([[*s.left_arm, *s.right_arm] for s in demo.samples])
        self.dt = float(np.median(np.diff(t)))
        split = int(np.searchsorted(t, self.nock, side="right"))
        if split < 2 or len(t) - split < 2:
            raise BadDemonstration("too few samples before or after the nock to learn from")
        self.start = y[0]
        self.nocking = y[split - 1]  # the demonstrated posture at the nock
        self.goal = y[-1]  # the demonstrated final (archery) posture
        self._t_nock = float(t[split - 1])
        self._to_nock = _fit(t[:split], y[:split], self.dt, weights)
        self._from_nock = _fit(t[split - 1 :], y[split - 1 :], self.dt, weights)

    def reproduce(self, goal: np.ndarray | None = None) -> Reproduction:
        """Roll the DMPs out from the demonstrated start; the second phase ends at `goal`
        (both arms' angles, rad, left then right: the archery posture for θ), the
        demonstrated one when None."""
        self._to_nock.configure(start_y=self.start, goal_y=self.nocking)
        t1, y1 = self._to_nock.open_loop(step_function="rk4")
        final = self.goal if goal is None else np.asarray(goal, dtype=float)
        self._from_nock.configure(start_y=y1[-1], goal_y=final)
        t2, y2 = self._from_nock.open_loop(step_function="rk4")
        t = np.concatenate([t1, t2[1:] + t1[-1]])
        y = np.vstack([y1, y2[1:]])
        return Reproduction(
            t=t,
            left_arm=y[:, :7],
            right_arm=y[:, 7:],
            grasp=self.grasp,
            nock=float(t1[-1]),
            release=float(t1[-1]) + self.release - self._t_nock,
        )

    def error(self, demo: Demonstration) -> float:
        """Joint RMS (rad) of the reproduction with the demonstrated goal against `demo`."""
        reproduction = self.reproduce()
        rows = [np.concatenate(reproduction.at(s.t)) for s in demo.samples]
        wanted = np.array([[*s.left_arm, *s.right_arm] for s in demo.samples])
        return float(np.sqrt(np.mean((np.array(rows) - wanted) ** 2)))
