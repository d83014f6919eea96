"""The bridge's other YARP ports: the target camera's frames as `yarp::sig::ImageOf<PixelRgb>`,
the detector's measurements and the world's events as bottles (each with its stamp as the
envelope), and the archery verbs on a text RPC port that `yarp rpc` drives.

Bottles: `<prefix>/detector/hit:o` is `status r_x r_y` (r in m: the arrow from the target's
centre, x to the robot's right, y up; `status` "ok", or "no_target" / "no_arrow" with no r);
`<prefix>/world/events:o` is `kind shot [x y z] reason` (the impact in m, root frame, where
there is one). `<prefix>/archery/rpc:i` answers `reset`, `nock`, `release`, `grasp` (a whole
shot robot's), `status` and `help`: `ok …` with the verb's reply as key value pairs, or
`fail code message` (read-only: every verb but `status` and `help` is refused); `json VERB`
answers `ok TEXT`, TEXT the whole typed reply as JSON (`ArcheryPort._respond_json`).
"""

from __future__ import annotations

import bisect
import logging
import threading
from collections.abc import Callable
from typing import Any

import msgspec

from archery.apps.yarp.controlboard import close_port, open_port, serve_rpc
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import ArcheryError
from archery.protocol.messages import Detection, Image, WorldEvent, WorldState
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import NoArgs, Verb

__all__ = ["ArcheryPort", "SeenClock", "event_bottle", "image_to", "reward_bottle"]

log = logging.getLogger("archery.yarp")

#: the archery verbs of the text port; `status` and `help` only read
VERBS: dict[str, tuple[Verb[Any, Any], bool]] = {
    "reset": (rv.RESET, True),
    "nock": (rv.NOCK, True),
    "release": (rv.RELEASE, True),
    "grasp": (rv.GRASP, True),
    "status": (rv.ARCHERY_STATUS, False),
}


class SeenClock:
    """When the simulated world was last known to be in the state of a given simulated time:
    the wall stamps (s) of the robot's world states, kept for the last `kept` sim times (the
    record starts over when sim time goes back: a reset). A rendered frame shows one world
    state (its `sim_time`); its YARP envelope takes `seen(frame)`, the wall time its world was
    that, not when the frame was published, so that a YARP reader asking for a frame "captured
    after" a wall time never gets a re-sent render of an older world."""

    def __init__(self, kept: int = 512) -> None:
        self._lock = threading.Lock()
        self._kept = kept
        self._times: list[float] = []  # sim s, increasing
        self._stamps: list[float] = []  # wall s of the newest world state at each

    def state(self, state: WorldState) -> None:
        """Record a world state (its sim time, s, and wall stamp, s)."""
        if state.sim_time is None:
            return
        with self._lock:
            if self._times and state.sim_time < self._times[-1]:
                self._times.clear()
                self._stamps.clear()
            if self._times and state.sim_time == self._times[-1]:
                self._stamps[-1] = max(self._stamps[-1], state.stamp)
                return
            self._times.append(state.sim_time)
            self._stamps.append(state.stamp)
            if len(self._times) > self._kept:
                del self._times[0], self._stamps[0]

    def seen(self, image: Image) -> float:
        """The wall time (s) the world was last known in `image`'s state: the stamp of the
        world state of its sim time; one not recorded (yet), the newest recorded before it (a
        lower bound: it was published later); the image's own stamp when nothing tells."""
        if image.sim_time is None:
            return image.stamp
        with self._lock:
            k = bisect.bisect_right(self._times, image.sim_time)
            if k and self._times[k - 1] == image.sim_time:
                return self._stamps[k - 1]
            if k:
                return max(self._stamps[:k])
            return image.stamp


def image_to(yarp: Any, out: Any, image: Image) -> None:
    """Copy `image`'s pixels (any colour encoding of the mesh) into the `ImageRgb` `out`."""
    pixels = image.to_numpy()
    if pixels.ndim == 2:  # mono8: grey as RGB
        import numpy as np

        pixels = np.repeat(pixels[:, :, None], 3, axis=2)
    source = yarp.ImageRgb()
    source.setExternal(pixels, image.width, image.height)
    out.copy(source)


def reward_bottle(out: Any, detection: Detection) -> None:
    """`status r_x r_y` (m) of a measurement into the bottle `out`."""
    out.clear()
    out.addString(detection.status)
    if detection.r_m is not None:
        for x in detection.r_m:
            out.addFloat64(x)


def event_bottle(out: Any, event: WorldEvent) -> None:
    """`kind shot [x y z] reason` of a world event into the bottle `out`."""
    out.clear()
    out.addString(event.kind)
    out.addInt32(event.shot)
    if event.impact_m is not None:
        impact = out.addList()
        for x in event.impact_m:
            impact.addFloat64(x)
    if event.reason:
        out.addString(event.reason)


class ArcheryPort:
    """The archery verbs on `<prefix>/archery/rpc:i`, as text bottles, until `close`, each
    through the one robot client `robot`."""

    def __init__(self, yarp: Any, robot: RobotClient, prefix: str, *, operator: bool) -> None:
        self.yarp, self.robot, self.operator = yarp, robot, operator
        self.name = f"{prefix}/archery/rpc:i"
        self.port = open_port(yarp, yarp.RpcServer(), self.name)
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="yarp-archery", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        serve_rpc(self.yarp, self.port, self.respond, self._closing, self.name)

    def respond(self, request: Any, reply: Any) -> None:
        """Answer one request: `ok key value …` (`json VERB`: `ok TEXT`, the reply as JSON) or
        `fail code message`."""
        reply.clear()
        word = request.get(0).toString() if request.size() else ""
        if word == "json" and request.size() >= 2:
            self._respond_json(request, reply)
            return
        if word == "help" or (request.size() == 0):
            reply.addString("ok")
            reply.addString("verbs: " + ", ".join(VERBS) + (" (read-only)" * (not self.operator)))
            return
        verb = self._verb(request, reply, word, request.size() == 1)
        if verb is None:
            return
        try:
            args: Any = rv.ResetArgs() if verb is rv.RESET else NoArgs()
            result = self.robot.call(verb, args)
        except ArcheryError as exc:
            _fail(reply, exc.code, str(exc))
            return
        reply.addString("ok")
        _add_plain(reply, msgspec.to_builtins(result))

    def _verb(
        self, request: Any, reply: Any, word: str, well_formed: bool
    ) -> Verb[Any, Any] | None:
        """The verb `word` names, or None with `reply` the refusal: an unknown or malformed
        request, or a verb that moves on a read-only bridge."""
        found = VERBS.get(word)
        if found is None or not well_formed:
            _fail(reply, "bad_request", f"unknown request {shown(request.toString())}; try help")
            log.warning("%s: %s refused: unknown", self.name, shown(request.toString()))
            return None
        verb, moves = found
        if moves and not self.operator:
            _fail(reply, "read_only", "read-only bridge (start `archery yarp --operator`)")
            log.warning("%s: %s refused: read-only", self.name, word)
            return None
        return verb

    def _respond_json(self, request: Any, reply: Any) -> None:
        """`json VERB` (`json reset SEED`, SEED an integer in [0, 2**63)): `ok TEXT`, TEXT the
        verb's reply encoded as JSON, or `fail code message`."""
        word = request.get(1).toString()
        seed = request.get(2) if request.size() == 3 else None
        seeded = word == "reset" and seed is not None and (seed.isInt32() or seed.isInt64())
        verb = self._verb(request, reply, word, request.size() == 2 or seeded)
        if verb is None:
            return
        try:
            args: Any = NoArgs()
            if verb is rv.RESET:
                args = rv.ResetArgs(seed=seed.asInt64() if seeded and seed is not None else None)
            result = self.robot.call(verb, args)
        except (ArcheryError, msgspec.ValidationError) as exc:
            _fail(reply, getattr(exc, "code", "bad_request"), str(exc))
            return
        reply.addString("ok")
        reply.addString(msgspec.json.encode(result).decode())

    def close(self) -> None:
        self._closing.set()
        self.port.interrupt()
        self._thread.join(timeout=5)
        close_port(self.yarp, self.port)


def _fail(reply: Any, code: str, message: str) -> None:
    reply.clear()
    reply.addString("fail")
    reply.addString(code)
    reply.addString(message)


def _add_plain(out: Any, value: Any) -> None:
    """A reply's plain fields into a bottle: key value pairs, lists as lists."""
    adders: dict[type, Callable[[Any], Any]] = {
        bool: lambda x: out.addInt32(int(x)),
        int: out.addInt64,
        float: out.addFloat64,
        str: out.addString,
    }
    if isinstance(value, dict):
        for key, item in value.items():
            out.addString(str(key))
            _add_plain(out, item) if not isinstance(item, dict | list) else _add_plain(
                out.addList(), item
            )
    elif isinstance(value, list):
        for item in value:
            if isinstance(item, dict | list):
                _add_plain(out.addList(), item)
            else:
                _add_plain(out, item)
    elif value is None:
        out.addString("none")
    else:
        adders.get(type(value), lambda x: out.addString(str(x)))(value)
