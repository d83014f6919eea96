"""The bridge's other YARP ports: the target camera's frames as `yarp::sig::ImageOf<PixelRgb>`,
the detector's measurements and the world's events as bottles (each with its stamp as the
envelope), and the archery verbs on a text RPC port that `yarp rpc` drives.

Bottles: `<prefix>/detector/hit:o` is `status r_x r_y` (r in m: the arrow from the target's
centre, x to the robot's right, y up; `status` "ok", or "no_target" / "no_arrow" with no r);
`<prefix>/world/events:o` is `kind shot [x y z] reason` (the impact in m, root frame, where
there is one). `<prefix>/archery/rpc:i` answers `reset`, `nock`, `release`, `grasp` (a whole
shot robot's), `status` and `help`: `ok …` with the verb's reply as key value pairs, or
`fail code message` (read-only: every verb but `status` and `help` is refused).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import msgspec

from archery.apps.yarp.controlboard import close_port, open_port, serve_rpc
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import ArcheryError
from archery.protocol.messages import Detection, Image, WorldEvent
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import NoArgs, Verb

__all__ = ["ArcheryPort", "event_bottle", "image_to", "reward_bottle"]

log = logging.getLogger("archery.yarp")

#: the archery verbs of the text port; `status` and `help` only read
VERBS: dict[str, tuple[Verb[Any, Any], bool]] = {
    "reset": (rv.RESET, True),
    "nock": (rv.NOCK, True),
    "release": (rv.RELEASE, True),
    "grasp": (rv.GRASP, True),
    "status": (rv.ARCHERY_STATUS, False),
}


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
        """Answer one request: `ok key value …` or `fail code message`."""
        reply.clear()
        word = request.get(0).toString() if request.size() else ""
        if word == "help" or (request.size() == 0):
            reply.addString("ok")
            reply.addString("verbs: " + ", ".join(VERBS) + (" (read-only)" * (not self.operator)))
            return
        found = VERBS.get(word)
        if found is None or request.size() != 1:
            _fail(reply, "bad_request", f"unknown request {shown(request.toString())}; try help")
            log.warning("%s: %s refused: unknown", self.name, shown(request.toString()))
            return
        verb, moves = found
        if moves and not self.operator:
            _fail(reply, "read_only", "read-only bridge (start `archery yarp --operator`)")
            log.warning("%s: %s refused: read-only", self.name, word)
            return
        try:
            args: Any = rv.ResetArgs() if verb is rv.RESET else NoArgs()
            result = self.robot.call(verb, args)
        except ArcheryError as exc:
            _fail(reply, exc.code, str(exc))
            return
        reply.addString("ok")
        _add_plain(reply, msgspec.to_builtins(result))

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
