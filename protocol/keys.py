"""Key names of the mesh: iCub's YARP port names as Zenoh keys, with a robot prefix.

YARP's leading slash is dropped and `:i`, `:o`, `rpc:i` are kept, so `/icubSim/left_arm/state:o`
becomes `icubSim/left_arm/state:o`. No other module types a key string by hand: every key is
built here, and `port_of` tells which port (and so which message type) a key belongs to.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from archery.protocol.errors import KeyNameError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import SERVICES
from archery.protocol.text import shown

__all__ = [
    "ALIVE_EVERY_ROBOT",
    "DEFAULT_ROBOT",
    "OUTPUT_PORTS",
    "PORTS",
    "Keys",
    "PortSpec",
    "output_port",
    "port_of",
    "split_verb",
    "tap_keys",
    "validate_robot",
]

DEFAULT_ROBOT = "icubSim"
CARTESIAN_ARMS = ("left_arm", "right_arm", "archery")
_VERB = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,63}$")
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")
CALLER_MARK = "~"  # between a verb and its caller's identity in a call's key
# The `rpc:i` ports' paths before `/rpc:i`, for their request and reply taps.
_SERVERS = (
    *PARTS,
    "archery",
    "cam",
    "detector",
    "learner",
    *(f"cartesianController/{arm}" for arm in CARTESIAN_ARMS),
)


@dataclass(frozen=True)
class PortSpec:
    """One kind of port: its key pattern after the robot prefix, kind and message type name."""

    pattern: str  # e.g. "{part}/state:o"
    kind: str  # "pub" (stream), "events" (lossless stream), "sub" (input stream) or "rpc"
    message: str  # the message type's name in protocol.messages

    def regex(self) -> re.Pattern[str]:
        """A regex matching the full key (robot prefix included)."""
        body = re.escape(self.pattern)
        body = body.replace(r"\{part\}", "(?P<part>" + "|".join(PARTS) + ")")
        body = body.replace(r"\{arm\}", "(?P<arm>" + "|".join(CARTESIAN_ARMS) + ")")
        body = body.replace(r"\{server\}", "(?P<server>" + "|".join(_SERVERS) + ")")
        body = body.replace(r"\{service\}", r"(?P<service>[A-Za-z][A-Za-z0-9_\-]{0,63})")
        body = body.replace(r"\{instance\}", r"(?P<instance>[0-9a-f]{1,32})")
        return re.compile(r"^(?P<robot>[A-Za-z][A-Za-z0-9_\-]{0,63})/" + body + "$")


PORTS: tuple[PortSpec, ...] = (
    PortSpec("{part}/state:o", "pub", "JointState"),
    PortSpec("{part}/command:i", "sub", "JointCommand"),
    PortSpec("{part}/rpc:i", "rpc", "RpcRequest"),
    PortSpec("archery/rpc:i", "rpc", "RpcRequest"),
    PortSpec("world/state:o", "pub", "WorldState"),
    PortSpec("world/events:o", "events", "WorldEvent"),
    PortSpec("cam/target:o", "pub", "Image"),
    PortSpec("cam/rpc:i", "rpc", "RpcRequest"),
    PortSpec("detector/hit:o", "events", "Detection"),
    PortSpec("detector/rpc:i", "rpc", "RpcRequest"),
    PortSpec("cartesianController/{arm}/rpc:i", "rpc", "RpcRequest"),
    PortSpec("learner/rollout:o", "events", "Rollout"),
    PortSpec("learner/rpc:i", "rpc", "RpcRequest"),
    # what an `rpc:i` port was asked and answered, published while someone listens (`tap_keys`)
    PortSpec("{server}/requests:o", "pub", "RpcRequest"),
    PortSpec("{server}/replies:o", "pub", "RpcReply"),
    PortSpec("alive/{service}", "liveliness", "-"),
    PortSpec("alive/{service}/{instance}", "liveliness", "-"),
    PortSpec("describe/{service}", "rpc", "Describe"),
    PortSpec("replace/{service}", "rpc", "ReplaceRequest"),
)
_REGEXES = tuple((spec, spec.regex()) for spec in PORTS)
_TAPS = ("{server}/requests:o", "{server}/replies:o")
# What the robot's mesh puts out, as `archery record` records it and `archery replay` may
# publish it again: every stream and event port (joint states, the world's state and events,
# the camera's frames, detections, rollouts) but the RPC taps, which tell what a caller asked.
# Never an input (`command:i`), an `rpc:i` port, liveliness or another robot's key.
OUTPUT_PORTS: tuple[PortSpec, ...] = tuple(
    spec for spec in PORTS if spec.kind in ("pub", "events") and spec.pattern not in _TAPS
)


def validate_robot(robot: str) -> str:
    """Return `robot` if it is a valid prefix (a letter, then up to 63 of [A-Za-z0-9_-])."""
    if not isinstance(robot, str) or not _NAME.match(robot):
        raise KeyNameError(
            f"invalid robot name {robot!r}: use a letter then letters, digits, '_' or '-' "
            f"(at most 64 characters), e.g. {DEFAULT_ROBOT!r}"
        )
    return robot


def port_of(key: str) -> PortSpec:
    """The port a full key belongs to.

    Raises:
        KeyNameError: the key matches no port; the message lists the valid patterns.
    """
    for spec, regex in _REGEXES:
        if regex.match(key):
            return spec
    patterns = ", ".join("ROBOT/" + spec.pattern for spec in PORTS)
    raise KeyNameError(f"unknown key {key!r}; valid keys: {patterns}")


def output_port(key: str, robot: str) -> PortSpec | None:
    """The output port (of `OUTPUT_PORTS`) the full key `key` of robot `robot` belongs to, or
    None: an input, an `rpc:i` port, a tap, a key of another robot or of Zenoh's admin space
    (`@/...`), a wildcard, or no key at all."""
    if not isinstance(key, str) or key not in Keys(robot).output_streams():
        return None
    return port_of(key)


ALIVE_EVERY_ROBOT = "*/alive/*"  # the liveliness tokens of every service of every robot


def verb_key(rpc_key: str, verb: str, caller: str | None = None) -> str:
    """The key a call of `verb` on the `rpc:i` port `rpc_key` is sent to: `RPC_KEY/VERB`, one
    key per verb, so that access control grants each verb on its own (a server answers
    `verbs_key(rpc_key)`); `RPC_KEY/VERB~CALLER` for a verb that names its caller
    (`Verb.names_caller`), so that access control, granting each identity only its own name,
    vouches for who calls.

    Raises:
        KeyNameError: `verb` is not a verb name (a letter, then up to 63 letters, digits, `_`),
            or `caller` not an identity name.
    """
    if not isinstance(verb, str) or not _VERB.match(verb):
        raise KeyNameError(
            f"{shown(verb)} is not a verb name (a letter, then up to 63 of [A-Za-z0-9_])"
        )
    if caller is None:
        return f"{rpc_key}/{verb}"
    if not _NAME.match(caller):
        raise KeyNameError(f"{shown(caller)} is not an identity name")
    return f"{rpc_key}/{verb}{CALLER_MARK}{caller}"


def split_verb(chunk: str) -> tuple[str, str | None]:
    """(verb, caller or None) of the last chunk of a call's key (`verb_key`); the caller is
    None when the chunk names none or names it badly."""
    verb, mark, caller = chunk.partition(CALLER_MARK)
    return verb, caller if mark and _NAME.match(caller) else None


def tap_keys(rpc_key: str) -> tuple[str, str] | None:
    """The keys on which the server of the `rpc:i` port `rpc_key` publishes each request it
    handles and each reply it sends (`ROBOT/SERVER/requests:o`, `ROBOT/SERVER/replies:o`), or
    None for a key that is no `rpc:i` port of a verb table."""
    head, _, last = rpc_key.rpartition("/")
    if last != "rpc:i" or not head:
        return None
    return f"{head}/requests:o", f"{head}/replies:o"


def verbs_key(rpc_key: str) -> str:
    """The key expression a server of the `rpc:i` port `rpc_key` answers: every verb's key."""
    return f"{rpc_key}/*"


@dataclass(frozen=True)
class Keys:
    """Builds every key of one robot (prefix `robot`, default `icubSim`)."""

    robot: str = DEFAULT_ROBOT

    def __post_init__(self) -> None:
        validate_robot(self.robot)

    def _part(self, part: str) -> str:
        if part not in PARTS:
            raise KeyNameError(f"unknown part {part!r}; valid parts: {', '.join(PARTS)}")
        return part

    def state(self, part: str) -> str:
        """Joint state stream of a controlboard part, e.g. `icubSim/left_arm/state:o`."""
        return f"{self.robot}/{self._part(part)}/state:o"

    def command(self, part: str) -> str:
        """Joint position command input of a part, e.g. `icubSim/left_arm/command:i`."""
        return f"{self.robot}/{self._part(part)}/command:i"

    def part_rpc(self, part: str) -> str:
        """Controlboard RPC of a part, e.g. `icubSim/torso/rpc:i`."""
        return f"{self.robot}/{self._part(part)}/rpc:i"

    def archery_rpc(self) -> str:
        """The archery verbs of the robot: nock, release, reset, status."""
        return f"{self.robot}/archery/rpc:i"

    def world_state(self) -> str:
        """Scene state for the camera: sim time and qpos."""
        return f"{self.robot}/world/state:o"

    def world_events(self) -> str:
        """Released / landed / missed events, with the ground-truth impact (tests and plots)."""
        return f"{self.robot}/world/events:o"

    def cam_frames(self) -> str:
        """Camera frames of the target."""
        return f"{self.robot}/cam/target:o"

    def cam_rpc(self) -> str:
        """Camera RPC: grab a frame newer than a stamp."""
        return f"{self.robot}/cam/rpc:i"

    def detector_hits(self) -> str:
        """Detections stream."""
        return f"{self.robot}/detector/hit:o"

    def detector_rpc(self) -> str:
        """Detector RPC: measure, calibrate."""
        return f"{self.robot}/detector/rpc:i"

    def cartesian_rpc(self, arm: str) -> str:
        """Cartesian controller RPC of `left_arm`, `right_arm` or `archery` (both arms)."""
        if arm not in CARTESIAN_ARMS:
            raise KeyNameError(
                f"unknown cartesian controller {arm!r}; valid: {', '.join(CARTESIAN_ARMS)}"
            )
        return f"{self.robot}/cartesianController/{arm}/rpc:i"

    def learner_rollouts(self) -> str:
        """Every rollout of the learner."""
        return f"{self.robot}/learner/rollout:o"

    def learner_rpc(self) -> str:
        """Learner RPC: start, stop, status."""
        return f"{self.robot}/learner/rpc:i"

    def output_streams(self) -> tuple[str, ...]:
        """Every key of this robot's output ports (`OUTPUT_PORTS`), one per part where the port
        is a part's, e.g. `icubSim/left_arm/state:o`, `icubSim/world/events:o`."""
        return tuple(
            f"{self.robot}/{spec.pattern.format(part=part)}"
            for spec in OUTPUT_PORTS
            for part in (PARTS if "{part}" in spec.pattern else ("",))
        )

    def alive(self, service: str) -> str:
        """Liveliness token of a service (like a YARP name server entry)."""
        return f"{self.robot}/alive/{self._service(service)}"

    def alive_instance(self, service: str, zid: str) -> str:
        """Liveliness token naming the session (Zenoh id) that runs a service, so a client
        can tell the live instance's replies from anyone else's."""
        if not re.fullmatch(r"[0-9a-f]{1,32}", zid):
            raise KeyNameError(f"invalid instance id {zid!r}: a Zenoh id in lowercase hex")
        return f"{self.alive(service)}/{zid}"

    def alive_instances(self, service: str) -> str:
        """Key expression matching the instance tokens of one service."""
        return f"{self.alive(service)}/*"

    def describe(self, service: str) -> str:
        """Where a service answers `describe` with its ports and message types."""
        return f"{self.robot}/describe/{self._service(service)}"

    def replace(self, service: str) -> str:
        """Where a service's live instance takes a `ReplaceRequest` from its replacement."""
        return f"{self.robot}/replace/{self._service(service)}"

    def describe_all(self) -> str:
        """Key expression matching every service's `describe`."""
        return f"{self.robot}/describe/*"

    def alive_all(self) -> str:
        """Key expression matching the liveliness tokens of every service of this robot."""
        return f"{self.robot}/alive/*"

    @staticmethod
    def _service(service: str) -> str:
        if not _NAME.match(service):
            raise KeyNameError(
                f"invalid service name {service!r}; known services: {', '.join(SERVICES)}"
            )
        return service
