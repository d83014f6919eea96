"""One exception hierarchy for the mesh; each error carries a stable code for RPC replies."""

from __future__ import annotations

__all__ = [
    "ArcheryError",
    "BadRequest",
    "Busy",
    "ConfigError",
    "DecodeError",
    "DuplicateService",
    "KeyNameError",
    "OperatorNeeded",
    "PartLost",
    "RobotError",
    "RobotLost",
    "RpcError",
    "RpcTimeout",
    "StaleState",
    "Unreachable",
    "UpstreamLost",
    "WrongReplier",
]


class ArcheryError(Exception):
    """Base of every error the project raises on purpose.

    `code` is the short machine-readable name sent in RPC error replies; the message says what
    was wrong and what would be valid.
    """

    code = "error"

    def __init__(self, message: str, *, code: str | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code

    @property
    def message(self) -> str:
        """The human-readable message."""
        return str(self.args[0]) if self.args else ""


class ConfigError(ArcheryError, ValueError):
    """An invalid configuration value (a flag, a config file entry)."""

    code = "bad_config"


class Unreachable(ConfigError):
    """Nothing answers at the endpoint a client was told to connect to (a runtime failure, not
    bad input: the same flags work once a router runs there)."""

    code = "unreachable"


class KeyNameError(ArcheryError, ValueError):
    """A malformed or unknown key name (robot prefix, part, port)."""

    code = "bad_key"


class DecodeError(ArcheryError, ValueError):
    """A payload that is not a valid message: not msgpack, wrong type or schema, NaN, too big."""

    code = "bad_message"


class BadRequest(ArcheryError, ValueError):
    """An RPC request whose arguments are invalid; raised by handlers, sent back as an error."""

    code = "bad_request"


class Busy(ArcheryError):
    """A server refused a request at once because as many of its kind as it takes wait
    already (a bound on what waiting requests may hold); the caller may try again later."""

    code = "busy"


class RpcError(ArcheryError):
    """An RPC that failed: the remote replied with an error, or nothing answered."""

    code = "rpc_error"


class RpcTimeout(RpcError, TimeoutError):
    """No reply arrived within the timeout (the service is absent, dead or stuck)."""

    code = "timeout"


class UpstreamLost(RpcError):
    """A service could not do its work because a service it calls is lost (no reply, not
    running): `service` names that upstream service (e.g. the detector's camera), so a client
    can tell the lost service from the one that replied. Travels in `RpcReply.service`."""

    code = "upstream_lost"

    def __init__(self, service: str, message: str) -> None:
        super().__init__(message)
        self.service = service


class WrongReplier(RpcError):
    """A reply came from a session that does not hold the expected service's liveliness
    token (a stray, duplicate or rogue responder); it is never used as data."""

    code = "wrong_replier"


class DuplicateService(ConfigError):
    """A service of the same robot and name is alive already."""

    code = "duplicate_service"


class StaleState(ArcheryError):
    """The newest message of a state stream is too old to use (its publisher is frozen, stuck
    or lost); the message names the key and the age. Ages are arrival ages on the receiver's
    monotonic clock, so clock differences between hosts do not matter."""

    code = "stale_state"

    def __init__(self, key: str, age: float, max_age: float) -> None:
        if age == float("inf"):
            text = f"no state on {key} within {max_age:g} s"
        else:
            text = f"the newest state on {key} is {age:.2f} s old (stale after {max_age:g} s)"
        super().__init__(f"{text}: its publisher is frozen or lost")
        self.key = key
        self.age = age


class OperatorNeeded(ArcheryError):
    """A verb the robot cannot do by itself (a real robot's `nock`, `grasp` or `reset` where no
    hand posture is configured for it): the operator does it by hand and tells the session
    (the learner's `confirm`); the message says what to do."""

    code = "operator_needed"


class PartLost(ArcheryError):
    """A verb on a part of a YARP robot whose board no longer answers: the robot is lost for
    the session, as a service whose calls time out (it waits for the part to come back)."""

    code = "part_lost"


class RobotError(RpcError):
    """What a client of the robot meets when the robot does not do what it asked
    (`mesh/robot_client.py`): `kind` says which of "not_owner" (another client holds a part),
    "busy", "not_reached" (a move ended off its targets: `moved` tells where) or "lost" (the
    robot does not answer, or its states went silent); `code` is the robot's own code and the
    message its own reason."""

    code = "robot_error"

    def __init__(self, message: str, *, kind: str, code: str | None = None, moved: object = None):
        super().__init__(message, code=code if code is not None else kind)
        self.kind = kind
        self.moved = moved


class RobotLost(RobotError, RpcTimeout):
    """A `RobotError` of kind "lost": no reply in time, or a state stream gone silent (its code:
    `timeout`, `stale_state`, `upstream_lost`)."""

    def __init__(self, message: str, *, code: str = "timeout") -> None:
        super().__init__(message, kind="lost", code=code)
