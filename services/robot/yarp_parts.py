"""A YARP robot's body read through YARP's own `remote_controlboard`, one per part, moving
nothing: the axes the robot names (`IAxisInfo`), the contract's joints (`PARTS`) mapped onto
them by name, never by index (a real iCub's arm has 16 axes, 7 of the arm's and 9 of the
hand's); its joint limits (`IControlLimits`, degrees) intersected with the project's; its
encoders (`IEncoders`, degrees) read and checked against them. Every angle given out is in
radians. `yarp` is imported inside the functions; YARP's network (its name server in YARP's
configuration, `YARP_IP`) is the caller's to set up, `open_parts` checks that it answers.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from archery.protocol.errors import ConfigError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import ROBOT_TIMEOUT
from archery.protocol.text import shown
from archery.sim.scene_config import SceneConfig
from archery.sim.urdf import urdf_joint_limits

__all__ = [
    "ENCODER_MARGIN",
    "STREAM_CARRIER",
    "BodyError",
    "PartAxes",
    "YarpBody",
    "check_encoders",
    "intersect_limits",
    "map_axes",
    "open_parts",
    "project_limits",
]

log = logging.getLogger("archery.robot.yarp")

#: How far beyond its limits (rad) an encoder may read before the body is refused: a robot's
#: calibration leaves its joints a little past their software limits, never 2°.
ENCODER_MARGIN = math.radians(2.0)
_POLL = 0.02  # s between two reads of an encoder stream that has not delivered yet
#: the carrier of the state and command streams (`remote_controlboard`'s own default is udp): a
#: udp stream binds its port's number on its own, which YARP's name server hands out again as
#: soon as a port closes, so a restarted body could find it still held by a stream of before
STREAM_CARRIER = "tcp"
STALE_AFTER = 0.5  # wall s: an encoder reading older than this by its stamp is a silent board


class BodyError(ConfigError):
    """What is wrong with a YARP robot's body, in one line: no name server answers, a part's
    control board is missing, an axis the contract needs is not there, its limits do not meet
    the project's, an encoder reads NaN or out of its limits, or the encoders do not stream."""


@dataclass(frozen=True)
class PartAxes:
    """One part of a YARP robot as `open_parts` found it.

    Attributes:
        part: the contract's part, e.g. "left_arm".
        board: the YARP name of its control board, e.g. "/icub/left_arm".
        axes: every axis name the robot gives, in its axis order (an iCub arm's 16).
        joints: the contract's joints of the part, in `PARTS` order.
        index: the robot's axis index of each of `joints`.
        lower, upper: the limits used for each of `joints` (rad): the project's, intersected
            with the robot's when it tells them.
        from_robot: whether the robot told its limits (`IControlLimits.getLimits`); False: the
            project's limits alone.
    """

    part: str
    board: str
    axes: tuple[str, ...]
    joints: tuple[str, ...]
    index: tuple[int, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    from_robot: bool

    @property
    def unmapped(self) -> tuple[str, ...]:
        """The robot's axes no joint of the contract maps onto (an iCub hand's), in its order."""
        used = set(self.index)
        return tuple(name for i, name in enumerate(self.axes) if i not in used)


def project_limits() -> dict[str, tuple[float, float]]:
    """The project's (lower, upper) limits (rad) of every joint of `PARTS`, by name: the URDF's,
    shrunk by the simulated robot's stop margin (`SceneConfig.limit_margin`), as the simulated
    robot's `getLimits` answers them."""
    margin = SceneConfig.limit_margin
    return {name: (lo + margin, hi - margin) for name, (lo, hi) in urdf_joint_limits().items()}


def map_axes(board: str, joints: Sequence[str], axes: Sequence[str]) -> tuple[int, ...]:
    """The robot's axis index of each of `joints`, found by name in `axes` (the robot's axis
    names in its order).

    Raises:
        BodyError: a joint is not among `axes`, or is there twice; the message names the
            missing (or doubled) joints and the axes the robot has.
    """
    missing = [name for name in joints if name not in axes]
    doubled = [name for name in joints if list(axes).count(name) > 1]
    if missing or doubled:
        what = (
            f"has no axis named {', '.join(missing)}"
            if missing
            else f"names more than one axis {', '.join(doubled)}"
        )
        raise BodyError(f"{board} {what}; its axes: {', '.join(map(shown, axes)) or 'none'}")
    return tuple(list(axes).index(name) for name in joints)


def intersect_limits(
    board: str,
    joint: str,
    project: tuple[float, float],
    robot: tuple[float, float] | None,
) -> tuple[float, float]:
    """The limits (rad) a joint keeps: the project's (lower, upper), within the robot's if it
    told them (None: it did not).

    Raises:
        BodyError: the two do not overlap.
    """
    if robot is None:
        return project
    lower, upper = max(project[0], robot[0]), min(project[1], robot[1])
    if lower >= upper:
        raise BodyError(
            f"{board} {joint}: the robot's limits [{_deg(robot[0])}, {_deg(robot[1])}]° and the "
            f"project's [{_deg(project[0])}, {_deg(project[1])}]° do not overlap"
        )
    return lower, upper


def check_encoders(
    axes: PartAxes, values: Sequence[float], margin: float = ENCODER_MARGIN
) -> tuple[float, ...]:
    """`values` (rad, one per joint of `axes.joints`) if each is a number within its limits
    widened by `margin` (rad).

    Raises:
        BodyError: a value is NaN, infinite, or past its limits by more than `margin`.
    """
    for joint, axis, value, lower, upper in zip(
        axes.joints, axes.index, values, axes.lower, axes.upper, strict=True
    ):
        if not math.isfinite(value):
            raise BodyError(f"{axes.board} {joint} (axis {axis}): its encoder reads {value}")
        if not lower - margin <= value <= upper + margin:
            raise BodyError(
                f"{axes.board} {joint} (axis {axis}) reads {_deg(value)}°, outside its limits "
                f"[{_deg(lower)}, {_deg(upper)}]° by more than {math.degrees(margin):g}°"
            )
    return tuple(values)


def _deg(value: float) -> str:
    return f"{math.degrees(value):.1f}"


class YarpBody:
    """The control boards `open_parts` opened, read-only, until `close` (or the `with` block's
    end): `parts` tells what was found; `encoders` reads the joints now."""

    def __init__(
        self,
        yarp: Any,
        remote: str,
        parts: Mapping[str, PartAxes],
        drivers: Mapping[str, Any],
        timeout: float,
        margin: float,
    ) -> None:
        self.remote = remote
        self.parts = dict(parts)
        self.timeout = timeout
        self.margin = margin
        self._yarp = yarp
        self._drivers = dict(drivers)
        self._joined = True  # YARP's network, joined by `open_parts`
        self.local = f"/archery/body/{os.getpid()}"  # the prefix of this body's own ports
        self._opened = 0  # boards opened again (`reopen`), for their ports' names

    def encoders(self, parts: Sequence[str] | None = None) -> dict[str, tuple[float, ...]]:
        """Each part's (of `parts`, default all) joints now (rad, `PARTS` order), read through
        `IEncoders` (degrees) and checked (`check_encoders`); waits up to `timeout` (s) for a
        part's first state.

        Raises:
            BodyError: a part's encoders give nothing within `timeout`, or a value is refused.
        """
        out: dict[str, tuple[float, ...]] = {}
        for part in self.parts if parts is None else parts:
            axes = self.parts[part]
            encoders = self._drivers[part].viewIEncoders()
            values = self._yarp.Vector(len(axes.axes))
            deadline = time.monotonic() + self.timeout
            while not encoders.getEncoders(values.data()):
                if time.monotonic() > deadline:
                    raise BodyError(
                        f"{axes.board} gives no encoder reading within {self.timeout:g} s "
                        "(its state:o does not stream)"
                    )
                time.sleep(_POLL)
            read = [math.radians(float(values[i])) for i in axes.index]
            out[part] = check_encoders(axes, read, self.margin)
        return out

    def read(self, part: str) -> tuple[float, ...] | None:
        """`part`'s joints now (rad, `PARTS` order), or None when its board gives no reading
        now (its `stateExt:o` silent); never waits.

        Raises:
            BodyError: a value is refused (`check_encoders`: NaN, past its limits).
        """
        axes = self.parts[part]
        values = self._yarp.Vector(len(axes.axes))
        if not self._drivers[part].viewIEncoders().getEncoders(values.data()):
            return None
        return check_encoders(
            axes, [math.radians(float(values[i])) for i in axes.index], self.margin
        )

    def stale(self, part: str, max_age: float = STALE_AFTER) -> bool:
        """Whether `part`'s newest encoder reading is older than `max_age` wall s by its own
        stamps (`IEncodersTimed`), or there is none: a board whose `yarpdev` is gone still
        gives its last values for a while, never newer stamps."""
        axes = self.parts[part]
        timed = self._drivers[part].viewIEncodersTimed()
        values, stamps = self._yarp.Vector(len(axes.axes)), self._yarp.Vector(len(axes.axes))
        if timed is None or not timed.getEncodersTimed(values.data(), stamps.data()):
            return True
        newest = max(float(stamps[i]) for i in range(len(axes.axes)))
        return time.time() - newest > max_age

    def reopen(self, part: str) -> None:
        """Open `part`'s board again (the robot's side restarted it): the old
        `remote_controlboard` closed, a new one opened, its axes the same by name.

        Raises:
            BodyError: the board does not open (not back yet), or came back with other axes.
        """
        axes = self.parts[part]
        self._opened += 1
        driver = _open(self._yarp, axes.board, f"{self.local}/{part}/{self._opened}")
        try:
            found = _read_part(self._yarp, driver, part, axes.board, axes.joints, project_limits())
            if found.axes != axes.axes:
                raise BodyError(
                    f"{axes.board} came back with other axes: {', '.join(found.axes)} (it had "
                    f"{', '.join(axes.axes)})"
                )
        except BaseException:
            driver.close()
            raise
        old, self._drivers[part] = self._drivers[part], driver
        old.close()

    @property
    def yarp(self) -> Any:
        """YARP's module, its network joined until `close` (for the ports a caller opens)."""
        return self._yarp

    def driver(self, part: str) -> Any:
        """The open `remote_controlboard` of `part` (a `yarp.PolyDriver`), for the caller that
        commands the robot (`yarp_loop`); this module only reads."""
        return self._drivers[part]

    def close(self) -> None:
        """Close every control board and leave YARP's network (as `open_parts` joined it)."""
        drivers, self._drivers = self._drivers, {}
        for driver in drivers.values():
            driver.close()
        if self._joined:
            self._joined = False
            self._yarp.Network.fini()

    def __enter__(self) -> YarpBody:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _valid_name(remote: str) -> bool:
    return (
        remote.startswith("/")
        and not remote.endswith("/")
        and remote.isprintable()
        and not any(c.isspace() for c in remote)
    )


def _server(yarp: Any) -> str:
    """The name server YARP uses now, HOST:PORT."""
    contact = yarp.Network.getNameServerContact()
    return f"{contact.getHost()}:{contact.getPort()}"


def open_parts(
    remote: str,
    parts: Mapping[str, Sequence[str]] = PARTS,
    *,
    local: str | None = None,
    timeout: float = ROBOT_TIMEOUT,
    margin: float = ENCODER_MARGIN,
) -> YarpBody:
    """Open a `remote_controlboard` on each of `parts` of the YARP robot `remote` (its control
    board `REMOTE/PART`, e.g. /icub/left_arm), map the part's joints onto the robot's axes by
    name and settle their limits; nothing is commanded. A robot whose `getLimits` fails (YARP's
    `fakeMotionControl` does) keeps the project's limits: said once, as a warning.

    Args:
        remote: the robot's YARP name, e.g. "/icub".
        parts: part → its joints (the contract's names), by default `PARTS`.
        local: the prefix of this process's YARP ports (default /archery/body/PID).
        timeout: s the name server has to answer, and `encoders` to wait for a first state.
        margin: how far past its limits (rad) an encoder may read (`check_encoders`).

    Raises:
        BodyError: `remote` is not a YARP name, no name server answers, a part's control board
            is not registered or does not open, a joint is not among its axes, or the limits
            do not meet.
        ConfigError: YARP's Python bindings are not installed.
    """
    if not _valid_name(remote):
        raise BodyError(f"{shown(remote)} is not a YARP name such as /icub")
    try:
        import yarp
    except ImportError:
        raise ConfigError(
            "YARP's Python bindings are not installed (YARP 3.5: `make yarp`)"
        ) from None
    local = local or f"/archery/body/{os.getpid()}"
    yarp.Network.init()
    drivers: dict[str, Any] = {}
    try:
        if yarp.Network.getNameServerContact().getPort() <= 0:
            raise BodyError(
                "no YARP name server is configured: name the robot's with `yarp conf HOST PORT` "
                "(or a yarp.conf in YARP_CONFIG_HOME)"
            )
        if not yarp.Network.checkNetwork(timeout):
            raise BodyError(
                f"no YARP name server answers at {_server(yarp)} within {timeout:g} s (one "
                "that authenticates its connections, YARP's AuthHMAC, answers only a YARP "
                "configured with its key: auth.conf in YARP's configuration folder)"
            )
        missing = [
            f"{remote}/{part}"
            for part in parts
            if not yarp.Network.queryName(f"{remote}/{part}/rpc:i").isValid()
        ]
        if missing:
            raise BodyError(
                f"no control board at {', '.join(missing)}: the name server at {_server(yarp)} "
                "holds none of their rpc:i ports (is the robot up, and is its name "
                f"{remote}? `yarp name list` lists the ports)"
            )
        limits = project_limits()
        found: dict[str, PartAxes] = {}
        untold: list[str] = []
        for part, joints in parts.items():
            board = f"{remote}/{part}"
            drivers[part] = driver = _open(yarp, board, f"{local}/{part}")
            found[part] = axes = _read_part(yarp, driver, part, board, tuple(joints), limits)
            if not axes.from_robot:
                untold.append(part)
        if untold:
            log.warning(
                "%s does not tell its joint limits (getLimits fails on %s): the project's "
                "(the URDF's) are used",
                remote,
                ", ".join(untold),
            )
        body = YarpBody(yarp, remote, found, drivers, timeout, margin)
        body.local = local
        return body
    except BaseException:
        for driver in drivers.values():
            driver.close()
        yarp.Network.fini()
        raise


def _open(yarp: Any, board: str, local: str) -> Any:
    """A `remote_controlboard` on `board`, its ports named from `local`, its state and command
    streams over tcp (`STREAM_CARRIER`)."""
    options = yarp.Property()
    options.put("device", "remote_controlboard")
    options.put("remote", board)
    options.put("local", local)
    options.put("carrier", STREAM_CARRIER)
    driver = yarp.PolyDriver(options)
    if not driver.isValid():
        raise BodyError(f"remote_controlboard does not open {board} (its log above says why)")
    return driver


def _read_part(
    yarp: Any,
    driver: Any,
    part: str,
    board: str,
    joints: tuple[str, ...],
    limits: Mapping[str, tuple[float, float]],
) -> PartAxes:
    """The part's axes, its joints' indices and limits, read from its open `driver`."""
    info, encoders = driver.viewIAxisInfo(), driver.viewIEncoders()
    if info is None or encoders is None:
        raise BodyError(f"{board} does not tell its axes' names (no IAxisInfo)")
    count = int(encoders.getAxes())
    axes = tuple(str(info.getAxisName(i)) for i in range(count))
    index = map_axes(board, joints, axes)
    told = _robot_limits(yarp, driver, index)
    used = [
        intersect_limits(board, joint, limits[joint], None if told is None else told[k])
        for k, joint in enumerate(joints)
    ]
    return PartAxes(
        part=part,
        board=board,
        axes=axes,
        joints=joints,
        index=index,
        lower=tuple(lo for lo, _ in used),
        upper=tuple(hi for _, hi in used),
        from_robot=told is not None,
    )


def _robot_limits(yarp: Any, driver: Any, index: Sequence[int]) -> list[tuple[float, float]] | None:
    """The robot's (lower, upper) limits (rad) of the axes `index`, or None when it does not
    tell them all (no IControlLimits, a failing `getLimits`, a value not finite, lower ≥ upper)."""
    control = driver.viewIControlLimits()
    if control is None:
        return None
    out = []
    low, high = yarp.DVector(1), yarp.DVector(1)
    for axis in index:
        if not control.getLimits(axis, low, high):
            return None
        lower, upper = math.radians(float(low[0])), math.radians(float(high[0]))
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            return None
        out.append((lower, upper))
    return out
