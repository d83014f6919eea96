"""A trajectory's joint path: time-stamped waypoints checked against a part's rules (the
limits, and the joint speed bound `positionMove` keeps, `MAX_REFERENCE_SPEED`: between
waypoints and in the velocities given) and interpolated quintically (velocities given or central
differences, accelerations zero at the waypoints), from where the joints' setpoints are at its
start. Times in s of simulated time from the start, angles in rad, velocities in rad/s. Pure:
no mesh, no world.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from archery.protocol.errors import BadRequest
from archery.protocol.robotspec import MAX_REFERENCE_SPEED
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
    max_speed: float = MAX_REFERENCE_SPEED,
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
        max_speed: every joint's speed bound (rad/s): |Δq|/Δt from the waypoint before (the
            first from `start`), each velocity given, and the played path's peak between them.

    Raises:
        BadTrajectory: times not > 0 or not increasing or past `max_duration`, rows of the
            wrong length, NaN or infinity, a waypoint outside a joint's limits, a joint faster
            than `max_speed` (the first such waypoint, named with its joint and speed).
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
    _check_speeds(times_all, q_all, names, max_speed)
    if velocities is None:
        v_all = np.zeros_like(q_all)
        v_all[1:-1] = (q_all[2:] - q_all[:-2]) / (times_all[2:] - times_all[:-2])[:, None]
    else:
        given = _rows("velocities", velocities, t.size, width)
        fast = np.abs(given) > max_speed * (1.0 + _SLACK)
        if fast.any():
            row, joint = (int(x) for x in np.argwhere(fast)[0])
            raise BadTrajectory(
                f"velocities[{row}] gives {names[joint]} {given[row, joint]:.4g} rad/s, over "
                f"the maximum joint speed of {max_speed:g} rad/s"
            )
        v_all = np.vstack([np.zeros(width), given])
    _check_path_speed(times_all, q_all, v_all, names, max_speed)
    return JointPath(t=times_all, q=q_all, v=v_all)


_SLACK = 1e-9  # relative: a speed computed at the bound is not past it
_PEAK_SLACK = 1e-3  # relative: the sampled peak of a quintic at the bound is not past it
#: where on each segment (0: its start, 1: its end) the quintic's speed is sampled for its peak
_S = np.linspace(0.0, 1.0, 33)
_S2, _S3, _S4 = _S**2, _S**3, _S**4
#: the derivatives of `JointPath.at`'s basis in s: dq/dt = D5 Δq/h + D1 v_i + D4 v_i+1
_D5 = 30.0 * _S2 - 60.0 * _S3 + 30.0 * _S4
_D1 = 1.0 - 18.0 * _S2 + 32.0 * _S3 - 15.0 * _S4
_D4 = -12.0 * _S2 + 28.0 * _S3 - 15.0 * _S4


def _check_path_speed(
    t: np.ndarray, q: np.ndarray, v: np.ndarray, names: Sequence[str], max_speed: float
) -> None:
    """The speed of the path the robot plays (quintic between waypoints: from rest to rest it
    peaks at 1.875 times the average) within `max_speed` everywhere, not only on average."""
    h = np.diff(t)[:, None, None]
    dq = np.diff(q, axis=0)[:, None, :]
    speed = np.abs(
        _D5[None, :, None] * dq / h
        + _D1[None, :, None] * v[:-1, None, :]
        + _D4[None, :, None] * v[1:, None, :]
    ).max(axis=1)
    over = _first_over(speed, max_speed * (1.0 + _PEAK_SLACK))
    if over is None:
        return
    row, joint = over
    raise BadTrajectory(
        f"from {_origin(row)} to positions[{row}] the path moves {names[joint]} at up to "
        f"{speed[row, joint]:.4g} rad/s (quintic between waypoints), over "
        f"the maximum joint speed of {max_speed:g} rad/s: add waypoints or give it more time"
    )


def _check_speeds(t: np.ndarray, q: np.ndarray, names: Sequence[str], max_speed: float) -> None:
    """|Δq|/Δt (rad/s) of every joint from each waypoint to the next (`t[0]`, `q[0]`: the
    start) within `max_speed`."""
    step = np.abs(np.diff(q, axis=0))
    dt = np.diff(t)
    with np.errstate(over="ignore"):  # 6 rad in 1e-320 s: an infinite speed, refused
        speed = step / dt[:, None]
    over = _first_over(speed, max_speed * (1.0 + _SLACK))
    if over is None:
        return
    row, joint = over
    raise BadTrajectory(
        f"positions[{row}] moves {names[joint]} at {speed[row, joint]:.4g} rad/s "
        f"({step[row, joint]:.4f} rad in {dt[row]:.4g} s from {_origin(row)}), over the maximum "
        f"joint speed of {max_speed:g} rad/s"
    )


def _first_over(speed: np.ndarray, bound: float) -> tuple[int, int] | None:
    """(segment, joint) of the first speed (rad/s) past `bound`; None when none is."""
    fast = np.argwhere(speed > bound)
    return None if fast.size == 0 else (int(fast[0][0]), int(fast[0][1]))


def _origin(row: int) -> str:
    """Where segment `row` of a path starts, as a message names it."""
    return "the setpoint at the start" if row == 0 else f"positions[{row - 1}]"
