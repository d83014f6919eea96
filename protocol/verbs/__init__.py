"""Typed RPC verbs of every service (see `protocol.verbs.base`), and the tables by port."""

from __future__ import annotations

from archery.protocol.errors import KeyNameError
from archery.protocol.verbs import camera, controller, detector, learner, robot
from archery.protocol.verbs.base import Args, BoundVerb, NoArgs, Reply, ServedVerbs, Verb, VerbTable

__all__ = [
    "TABLES",
    "Args",
    "BoundVerb",
    "NoArgs",
    "Reply",
    "ServedVerbs",
    "Verb",
    "VerbTable",
    "names_caller",
    "table_for_key",
]

TABLES: tuple[VerbTable, ...] = (
    robot.PART_VERBS,
    robot.ARCHERY_VERBS,
    camera.CAMERA_VERBS,
    detector.DETECTOR_VERBS,
    controller.ARM_VERBS,
    controller.ARCHERY_VERBS,
    learner.LEARNER_VERBS,
)
_BY_PORT = {port: table for table in TABLES for port in table.ports}
_NAMING_CALLER = frozenset(
    (port, verb.name)
    for table in TABLES
    for port in table.ports
    for verb in table
    if verb.names_caller
)


def table_for_key(key: str) -> VerbTable:
    """The verb table of a full `rpc:i` key (robot prefix included).

    Raises:
        KeyNameError: no service's verbs are declared for that key; the message lists the keys.
    """
    _, _, port = key.partition("/")
    table = _BY_PORT.get(port)
    if table is None:
        ports = ", ".join(f"ROBOT/{p}" for p in _BY_PORT)
        raise KeyNameError(f"no verb table for {key!r}; typed rpc:i keys: {ports}")
    return table


def names_caller(key: str, verb: str) -> bool:
    """Whether a call of `verb` on the `rpc:i` key `key` names its caller (`Verb.names_caller`);
    False for a key or verb no table declares."""
    return (key.partition("/")[2], verb) in _NAMING_CALLER
