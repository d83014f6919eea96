"""One part of the robot as YARP 3.5's `remote_controlboard` expects a control board server:
`<prefix>/<part>/rpc:i` answers the control board vocabularies, `state:o` streams the encoders
(a `yarp::sig::Vector`) and `stateExt:o` the `jointData` the client reads its encoders from,
`command:i` takes the streaming commands. Angles in degrees on YARP's side, radians on the
mesh's; the board maps YARP's units and names onto the one robot client (`RobotClient`): every
move goes through the part's own verbs (`positionMove`, `setRefSpeeds`) and so under its lease
rules. Read-only (the default): every `set` and every streamed command is
refused (a `[fail]` bottle, one log line) and nothing reaches the robot. An output port
(`Output`) never waits on a slow reader: a connection still busy is skipped, one that takes
nothing for `STALL` s is dropped.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from archery.apps.yarp import vocabs as v
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import ArcheryError
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import TOLERANCES
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv

__all__ = [
    "PATIENCE",
    "STALL",
    "ControlBoard",
    "Output",
    "close_port",
    "joint_data",
    "open_port",
    "serve_rpc",
]

log = logging.getLogger("archery.yarp")

#: `jointData`'s vector fields after the joint positions, in their order on the wire: velocity,
#: acceleration, motor position, velocity and acceleration, torque, PWM, current (each with its
#: validity flag), then the control and interaction modes (integer vectors)
_OTHER_FLOATS = 8
_MODES = 2
#: what a `set` or a streamed command meets on a read-only bridge
READ_ONLY = "read-only bridge (start `archery yarp --operator` to move the robot)"


#: how many times a port is opened before the bridge gives up (each time on a port number this
#: machine has just given out as free: the name server's own numbering, in a row from its
#: port, can fall on a number another program already holds)
OPEN_ATTEMPTS = 5


def open_port(yarp: Any, port: Any, name: str) -> Any:
    """`port` opened as `name` on a free TCP port of YARP's address (`YARP_IP`), registered with
    the name server (`close_port` unregisters it).

    Raises:
        ArcheryError: it did not open after `OPEN_ATTEMPTS` tries.
    """
    host = os.environ.get("YARP_IP", "127.0.0.1")
    for _ in range(OPEN_ATTEMPTS):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.bind((host, 0))
            number = probe.getsockname()[1]
        contact = yarp.Network.registerContact(yarp.Contact(name, "tcp", host, number))
        if port.open(contact, False):  # registered above: YARP registers no given number itself
            return port
        yarp.Network.unregisterName(name)
    raise ArcheryError(f"YARP port {name} did not open (is the name server reachable?)")


#: s a connection of an output port may take nothing before YARP drops it
STALL = 2.0
#: s a write waits for the message before it to be taken before it skips a busy connection
PATIENCE = 0.02


class Output:
    """A buffered YARP output port (`self.port`, of the class `kind`, e.g.
    `yarp.BufferedPortVector`: `prepare`, `setEnvelope`) on a plain port whose connections time
    out after `STALL` s, opened as `name`; `send` writes without waiting on a slow connection."""

    def __init__(self, yarp: Any, kind: Any, name: str) -> None:
        self.yarp, self.name = yarp, name
        plain = yarp.Port()
        plain.setTimeout(STALL)  # before any connection: each connection gets it
        open_port(yarp, plain, name)
        self.port: Any = kind(plain)  # YARP's BufferedPort on the plain port's connections
        self._plain = plain  # after `port`, so that it is freed after it: the port uses it
        self._busy_since: float | None = None
        self._logged = False

    def send(self) -> None:
        """Write the prepared message: each connection that has taken the one before gets it; a
        connection still busy after `PATIENCE` s is skipped (it gets a later one), and one busy
        for half of `STALL` is logged once (YARP drops it at `STALL`)."""
        deadline = time.monotonic() + PATIENCE
        while self.port.isWriting() and time.monotonic() < deadline:
            time.sleep(PATIENCE / 20)
        now = time.monotonic()
        if not self.port.isWriting():
            self._busy_since, self._logged = None, False
        elif self._busy_since is None:
            self._busy_since = now
        elif now - self._busy_since >= STALL / 2 and not self._logged:
            self._logged = True
            log.warning(
                "%s: a connection has taken nothing for %g s (a reader that does not read): "
                "dropped at %g s, the other readers go on",
                self.name,
                STALL / 2,
                STALL,
            )
        self.port.write(False)

    def close(self) -> None:
        if self.port is None:
            return
        self.port.interrupt()
        close_port(self.yarp, self._plain)
        self.port.close()
        self.port = None  # the buffered port freed before the plain one it writes through


def serve_rpc(
    yarp: Any,
    port: Any,
    respond: Callable[[Any, Any], None],
    closing: threading.Event,
    name: str,
) -> None:
    """Answer `port`'s requests with `respond(request, reply)` until `closing` is set: one at a
    time, in order, like a YARP RPC server. A failure inside `respond` is a `[fail]` reply and
    one logged error (the request quoted), and the port goes on serving."""
    while not closing.is_set():
        request, reply = yarp.Bottle(), yarp.Bottle()
        if not port.read(request, True):
            continue
        try:
            respond(request, reply)
        except Exception:
            log.exception("%s: %s failed", name, shown(request.toString()))
            reply.clear()
            reply.addVocab32(v.FAIL)
        port.reply(reply)


def close_port(yarp: Any, port: Any) -> None:
    """Close a port `open_port` opened and take its name off the name server."""
    name = port.getName()
    port.close()
    if name:
        yarp.Network.unregisterName(name)


def _deg(values: Sequence[float]) -> list[float]:
    return [math.degrees(x) for x in values]


class BadCommand(ValueError):
    """A request the control board refuses before it reaches the mesh (its message says why)."""


def joint_data(yarp: Any, out: Any, state: JointState) -> None:
    """Fill the bottle `out` with `state` as YARP's `jointData` (its wire form: 22 fields, each
    vector then its validity flag): the positions (deg) and velocities (deg/s) valid, the rest
    zeros marked invalid, the modes position (`VOCAB_CM_POSITION`) marked invalid."""
    out.clear()
    n = len(state.position)
    for values, valid in (
        (_deg(state.position), True),
        (_deg(state.velocity), True),
        *(([0.0] * n, False) for _ in range(_OTHER_FLOATS - 1)),
    ):
        field = out.addList()
        for x in values:
            field.addFloat64(x)
        out.addVocab32(v.OK if valid else v.FAIL)
    for _ in range(_MODES):
        field = out.addList()
        for _ in range(n):
            field.addInt32(0)
        out.addVocab32(v.FAIL)


class ControlBoard:
    """The YARP ports of one part, served until `close`: YARP's degrees and joint indices mapped
    onto the robot client's radians and joint names. It keeps the part's newest joint state
    (`joints`, fed by `publish`) and the moves sent through it and not yet seen reached.

    Args:
        yarp: the `yarp` module (its network initialised).
        robot: the one client of the mesh's robot (shared by every part's board).
        part: the part's name (`PARTS`).
        prefix: the robot's YARP name, e.g. "/icubSim".
        operator: take `set` requests and streamed commands (else refuse them).
    """

    def __init__(
        self, yarp: Any, robot: RobotClient, part: str, prefix: str, *, operator: bool
    ) -> None:
        self.yarp, self.robot, self.part, self.operator = yarp, robot, part, operator
        self.names: tuple[str, ...] = PARTS[part]
        self.name = f"{prefix}/{part}"
        #: the part's newest joint state (rad), None until the first
        self.joints: JointState | None = None
        #: the targets (rad) of the moves sent and not yet seen reached, by joint name
        self._moving: dict[str, float] = {}
        self.counts = {"states": 0, "requests": 0, "refused": 0, "commands": 0}
        self._stamp = yarp.Stamp()
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self.rpc = self._open(yarp.RpcServer(), "rpc:i")
        self.state = Output(yarp, yarp.BufferedPortVector, f"{self.name}/state:o")
        self.state_ext = Output(yarp, yarp.BufferedPortBottle, f"{self.name}/stateExt:o")
        self.command = self._open(yarp.BufferedPortBottle(), "command:i")
        self._threads = [
            threading.Thread(target=self._serve, name=f"yarp-{part}-rpc", daemon=True),
            threading.Thread(target=self._commands, name=f"yarp-{part}-cmd", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def _open(self, port: Any, leaf: str) -> Any:
        return open_port(self.yarp, port, f"{self.name}/{leaf}")

    # -- the stream ----------------------------------------------------------------------------
    def publish(self, state: JointState) -> None:
        """Write one joint state on `state:o` and `stateExt:o` (its stamp their envelope)."""
        self.joints = state
        with self._lock:
            self._stamp = self.yarp.Stamp(self._stamp.getCount() + 1, state.stamp)
            vector = self.state.port.prepare()
            vector.resize(len(state.position))
            for i, x in enumerate(state.position):
                vector[i] = math.degrees(x)
            self.state.port.setEnvelope(self._stamp)
            self.state.send()  # a reader that keeps up gets each; a stalled one, none
            joint_data(self.yarp, self.state_ext.port.prepare(), state)
            self.state_ext.port.setEnvelope(self._stamp)
            self.state_ext.send()
            self.counts["states"] += 1

    # -- the part's verbs (rad) ----------------------------------------------------------------
    def _call(self, verb: Any, args: Any = None) -> Any:
        return self.robot.part_call(self.part, verb, args)

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """The part's software limits (rad), asked once (by the client)."""
        return self.robot.limits(self.part)

    def done(self) -> bool:
        """The part's motion done, and every move sent through here seen reached (within
        `TOLERANCES["rest"]` rad) on a joint state: the robot takes a move at its next step, so
        its own flag may still tell of the motion before it."""
        if self._moving:
            state = self.joints
            if state is None:
                return False
            where = dict(zip(state.names, state.position, strict=True))
            reached = TOLERANCES["rest"]
            if any(abs(where[name] - x) > reached for name, x in self._moving.items()):
                return False
            self._moving.clear()
        return bool(self._call(rv.CHECK_MOTION_DONE).done)

    def speeds(self) -> list[float]:
        return list(self._call(rv.GET_REF_SPEEDS).speeds)

    # -- rpc:i -----------------------------------------------------------------------------------
    def _serve(self) -> None:
        serve_rpc(self.yarp, self.rpc, self.respond, self._closing, f"{self.name}/rpc:i")

    def respond(self, request: Any, reply: Any) -> None:
        """Answer one control board request into `reply` (`[fail]` for what it refuses)."""
        self.counts["requests"] += 1
        reply.clear()
        try:
            self._answer(request, reply)
        except (BadCommand, ArcheryError) as exc:
            self.counts["refused"] += 1
            log.warning("%s/rpc:i: %s refused: %s", self.name, shown(request.toString()), exc)
            reply.clear()
            reply.addVocab32(v.FAIL)
            return
        reply.addVocab32(v.OK)

    def _answer(self, request: Any, reply: Any) -> None:
        if request.size() < 2 or not request.get(0).isVocab32():
            raise BadCommand("a control board request is [get] or [set], then what")
        verb, what = request.get(0).asVocab32(), request.get(1).asVocab32()
        if what == v.PROTOCOL and verb == v.GET:
            reply.addVocab32(v.PROTOCOL)
            for number in v.PROTOCOL_VERSION:
                reply.addInt32(number)
            return
        if verb == v.GET:
            reply.addVocab32(v.IS)
            reply.add(request.get(1))
            self._get(what, request, reply)
            self._stamp_reply(reply)
        elif verb == v.SET:
            if not self.operator:
                raise BadCommand(READ_ONLY)
            self._set(what, request)
        else:
            raise BadCommand(f"unknown verb [{v.vocab_text(verb)}]")

    def _stamp_reply(self, reply: Any) -> None:
        reply.addVocab32(v.TIMESTAMP)
        reply.addInt32(self._stamp.getCount())
        reply.addFloat64(self._stamp.getTime())

    def _joint(self, request: Any, at: int = 2) -> int:
        item = request.get(at)
        n = len(self.names)
        if not item.isInt32() or not 0 <= item.asInt32() < n:
            raise BadCommand(f"a joint index from 0 to {n - 1} is wanted at {at}")
        return int(item.asInt32())

    def _floats(self, item: Any, count: int) -> list[float]:
        """`count` finite numbers (deg) of a list item."""
        values = item.asList() if item.isList() else None
        if values is None or values.size() != count:
            raise BadCommand(f"a list of {count} numbers is wanted")
        return [self._number(values.get(i)) for i in range(count)]

    @staticmethod
    def _number(item: Any) -> float:
        if not (item.isFloat64() or item.isInt32()):
            raise BadCommand("a number is wanted")
        x = float(item.asFloat64())
        if not math.isfinite(x):
            raise BadCommand(f"a finite number is wanted, got {x}")
        return x

    def _group(self, request: Any) -> list[int]:
        """The joints of a group request: [set|get] [what] n (j1 … jn)."""
        n = request.get(2)
        joints = request.get(3).asList() if request.get(3).isList() else None
        if not n.isInt32() or joints is None or joints.size() != n.asInt32():
            raise BadCommand("a group is a count, then a list of that many joint indices")
        return [self._joint(joints, i) for i in range(joints.size())]

    def _get(self, what: int, request: Any, reply: Any) -> None:
        n = len(self.names)
        if what == v.AXES:
            reply.addInt32(n)
        elif what in (v.ENCODER, v.ENCODERS):
            if self.joints is None:
                raise BadCommand("no joint state has come from the robot yet")
            degrees = _deg(self.joints.position)
            if what == v.ENCODER:
                reply.addFloat64(degrees[self._joint(request)])
            else:
                _add_list(reply, degrees)
        elif what == v.LIMITS:
            j = self._joint(request)
            low, high = self.limits()
            reply.addFloat64(math.degrees(low[j]))
            reply.addFloat64(math.degrees(high[j]))
        elif what in (v.DONE, v.DONES, v.MOTION_DONE_GROUP):
            if what == v.DONE:
                self._joint(request)
            elif what == v.MOTION_DONE_GROUP:
                self._group(request)
            reply.addInt32(int(self.done()))
        elif what in (v.REF_SPEED, v.REF_SPEEDS):
            speeds = _deg(self.speeds())
            if what == v.REF_SPEED:
                reply.addFloat64(speeds[self._joint(request)])
            else:
                _add_list(reply, speeds)
        elif what in (v.POSITION_MOVE, v.POSITION_MOVES):
            targets = _deg(self._call(rv.GET_TARGETS).position)
            if what == v.POSITION_MOVE:
                reply.addFloat64(targets[self._joint(request)])
            else:
                _add_list(reply, targets)
        elif what == v.INFO_NAME:
            reply.addString(self.names[self._joint(request)])
        else:
            raise BadCommand(f"unknown request [get] [{v.vocab_text(what)}]")

    def _set(self, what: int, request: Any) -> None:
        n = len(self.names)
        if what == v.POSITION_MOVE:
            joints, values = [self._joint(request)], [self._number(request.get(3))]
        elif what == v.POSITION_MOVES:
            joints, values = list(range(n)), self._floats(request.get(2), n)
        elif what == v.POSITION_MOVE_GROUP:
            joints = self._group(request)
            values = self._floats(request.get(4), len(joints))
        elif what in (v.REF_SPEED, v.REF_SPEEDS, v.REF_SPEED_GROUP):
            self._set_speeds(what, request)
            return
        else:
            raise BadCommand(f"unknown request [set] [{v.vocab_text(what)}]")
        self.move(joints, values)

    def move(self, joints: Sequence[int], degrees: Sequence[float]) -> None:
        """Move `joints` (indices) to `degrees`, each inside the part's limits, by the part's
        `positionMove` (its lease rules)."""
        low, high = self.limits()
        radians = [math.radians(x) for x in degrees]
        for j, x in zip(joints, radians, strict=True):
            if not low[j] <= x <= high[j]:
                raise BadCommand(
                    f"{self.names[j]} to {math.degrees(x):g}° lies outside its limits "
                    f"{math.degrees(low[j]):g}° … {math.degrees(high[j]):g}°"
                )
        names = [self.names[j] for j in joints]
        self._call(rv.POSITION_MOVE, rv.PositionMoveArgs(position=radians, names=names))
        self._moving.update(zip(names, radians, strict=True))

    def _set_speeds(self, what: int, request: Any) -> None:
        n = len(self.names)
        if what == v.REF_SPEEDS:
            wanted = dict(enumerate(self._floats(request.get(2), n)))
        elif what == v.REF_SPEED:
            wanted = {self._joint(request): self._number(request.get(3))}
        else:
            joints = self._group(request)
            wanted = dict(zip(joints, self._floats(request.get(4), len(joints)), strict=True))
        speeds = self.speeds()
        for j, x in wanted.items():
            if x <= 0:
                raise BadCommand(f"a reference speed is > 0 deg/s, got {x:g}")
            speeds[j] = math.radians(x)
        self._call(rv.SET_REF_SPEEDS, rv.SetRefSpeedsArgs(speeds=speeds))

    # -- command:i -------------------------------------------------------------------------------
    def _commands(self) -> None:
        """Streamed commands (`CommandMessage`: a head bottle, then the values): position direct
        and position moves go to the part's `command:i`; anything else, or any on a read-only
        bridge, is refused with a log line (at most one a second)."""
        if self.operator:  # read-only: no command path at all (no publisher on its command:i)
            self.robot.command(self.part, ())  # the publisher declared, nothing sent
        last_log = 0.0
        while not self._closing.is_set():
            message = self.command.read(True)
            if message is None:
                continue
            try:
                joints, values = self._streamed(message)
                low, high = self.limits()
                radians = np.radians(values)
                if np.any(radians < low[joints]) or np.any(radians > high[joints]):
                    raise BadCommand("a value lies outside the joint's limits")
                names = [self.names[j] for j in joints]
                self.robot.command(self.part, radians.tolist(), names=names)
                self.counts["commands"] += 1
            except Exception as exc:  # refused: a bad command, the mesh's error, or a failure
                self.counts["refused"] += 1
                now = time.monotonic()
                if now - last_log >= 1.0:
                    last_log = now
                    log.warning(
                        "%s/command:i: %s refused: %s (%d refused so far)",
                        self.name,
                        shown(message.toString()),
                        exc,
                        self.counts["refused"],
                    )

    def _streamed(self, message: Any) -> tuple[list[int], list[float]]:
        if not self.operator:
            raise BadCommand(READ_ONLY)
        if message.size() != 2 or not message.get(0).isList() or not message.get(1).isList():
            raise BadCommand("a streamed command is (head) (values)")
        head, body = message.get(0).asList(), message.get(1).asList()
        n = len(self.names)
        kind = head.get(0).asVocab32() if head.size() and head.get(0).isVocab32() else 0
        if kind == v.POSITION_DIRECT:
            return [self._joint(head, 1)], self._floats(message.get(1), 1)
        if kind in (v.POSITION_DIRECTS, v.POSITION_MOVES):
            return list(range(n)), self._floats(message.get(1), n)
        raise BadCommand(f"unknown streamed command [{v.vocab_text(kind)}] of {body.size()} values")

    def close(self) -> None:
        self._closing.set()
        for port in (self.rpc, self.command):
            port.interrupt()
        for thread in self._threads:
            thread.join(timeout=5)
        for port in (self.rpc, self.command):
            close_port(self.yarp, port)
        for output in (self.state, self.state_ext):
            output.close()


def _add_list(reply: Any, values: Sequence[float]) -> None:
    items = reply.addList()
    for x in values:
        items.addFloat64(x)
