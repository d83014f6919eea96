"""A trajectory's joint path: time-stamped waypoints checked against a part's rules and
interpolated quintically (velocities given or central differences, accelerations zero at the
waypoints), from where the joints' setpoints are at its start. Times in s of simulated time
from the start, angles in rad, velocities in rad/s. Pure: no mesh, no world.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from archery.protocol.errors import BadRequest
from archery.protocol.text import shown

__all__ = ["BAD_TRAJECTORY", "BadTrajectory", "JointPath", "plan_path"]

BAD_TRAJECTORY = "bad_trajectory"


class BadTrajectory(BadRequest):
    """A trajectory that breaks a rule of its form; nothing moved."""

    code = BAD_TRAJECTORY


@dataclass(frozen=True)
class JointPath:
    """Waypoints `q[i]` (rad) with velocities `v[i]` (rad/s) at times `t[i]` (s), `t[0] = 0` the
    start (where the setpoints were, at rest). `at(t)` is quintic between two waypoints with
    zero acceleration at both, held at the last waypoint after it."""

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    #: `t` as floats, for `at`'s bisection (it runs before every physics step)
    times: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "times", tuple(float(x) for x in self.t))

    @property
    def duration(self) -> float:
        """s from the start to the last waypoint."""
        return float(self.t[-1])

    @property
    def goal(self) -> np.ndarray:
        """The last waypoint (rad)."""
        goal: np.ndarray = self.q[-1]
        return goal

    def at(self, when: float) -> np.ndarray:
        """The joints' positions (rad) at `when` s from the start."""
        t = self.times
        if when >= t[-1]:
            return np.array(self.q[-1])
        if when <= 0.0:
            return np.array(self.q[0])
        i = bisect.bisect_right(t, when) - 1
        h = t[i + 1] - t[i]
        s = (when - t[i]) / h
        s2 = s * s
        s3 = s2 * s
        s4 = s3 * s
        s5 = s4 * s
        h0 = 1.0 - 10.0 * s3 + 15.0 * s4 - 6.0 * s5
        h1 = s - 6.0 * s3 + 8.0 * s4 - 3.0 * s5
        h4 = -4.0 * s3 + 7.0 * s4 - 3.0 * s5
        h5 = 10.0 * s3 - 15.0 * s4 + 6.0 * s5
        q, v = self.q, self.v
        result: np.ndarray = h0 * q[i] + h5 * q[i + 1] + h * (h1 * v[i] + h4 * v[i + 1])
        return result


def _rows(what: str, rows: Sequence[Sequence[float]], n: int, width: int) -> np.ndarray:
    if len(rows) != n:
        raise BadTrajectory(f"{what}: {len(rows)} rows for {n} times")
    for i, row in enumerate(rows):
        if len(row) != width:
            raise BadTrajectory(f"{what}[{i}] has {len(row)} values for {width} joints")
    array = np.asarray(rows, dtype=float).reshape(n, width)
    if not np.all(np.isfinite(array)):
        raise BadTrajectory(f"{what} must be finite numbers (NaN or infinity found)")
    return array


def plan_path(
    start: np.ndarray,
    times: Sequence[float],
    positions: Sequence[Sequence[float]],
    velocities: Sequence[Sequence[float]] | None,
    lower: np.ndarray,
    upper: np.ndarray,
    names: Sequence[str],
    max_duration: float,
) -> JointPath:
    """The path from `start` (rad, the setpoints now) through the waypoints.

    Args:
        start: the joints' setpoints at the start (rad).
        times: the waypoints' times (s from the start, > 0, strictly increasing).
        positions: one row per time, one angle per joint (rad).
        velocities: as `positions` (rad/s); None: central differences of the neighbours,
            zero at the last waypoint.
        lower, upper: each joint's limits, the clamp tolerance included (rad).
        names: the joints' names, for the messages.
        max_duration: the last time's bound (s).

    Raises:
        BadTrajectory: times not > 0 or not increasing or past `max_duration`, rows of the
            wrong length, NaN or infinity, a waypoint outside a joint's limits.
    """
    t = np.asarray(times, dtype=float)
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise BadTrajectory("times must be finite numbers (s from the start)")
    if t[0] <= 0.0 or np.any(np.diff(t) <= 0.0):
        raise BadTrajectory(
            f"times must be > 0 s and strictly increasing, got {shown([float(x) for x in t[:8]])}"
        )
    if t[-1] > max_duration:
        raise BadTrajectory(f"the last time {t[-1]:g} s is past the bound of {max_duration:g} s")
    width = len(names)
    q = _rows("positions", positions, t.size, width)
    outside = (q < lower) | (q > upper)
    if outside.any():
        row, joint = (int(x) for x in np.argwhere(outside)[0])
        raise BadTrajectory(
            f"positions[{row}] puts {names[joint]} at {q[row, joint]:.4f} rad, outside "
            f"[{lower[joint]:.4f}, {upper[joint]:.4f}]"
        )
    times_all = np.concatenate([[0.0], t])
    q_all = np.vstack([start, q])
    if velocities is None:
        v_all = np.zeros_like(q_all)
        v_all[1:-1] = (q_all[2:] - q_all[:-2]) / (times_all[2:] - times_all[:-2])[:, None]
    else:
        v_all = np.vstack([np.zeros(width), _rows("velocities", velocities, t.size, width)])
    return JointPath(t=times_all, q=q_all, v=v_all)
