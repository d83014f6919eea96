"""Key patterns of the observation tools (`record`, `replay`, `hz`, `read`): Zenoh key
expressions such as `icubSim/**` or `icubSim/*/state:o`, checked against the known stream ports.

A pattern is refused when it is not a key expression, or when no stream port (`pub`, `events`
or `sub` in `protocol.keys.PORTS`) of any robot could ever match it, so a typo fails at once
instead of recording nothing.
"""

from __future__ import annotations

import functools

import zenoh

from archery.mesh.cliargs import clean_zenoh_error
from archery.protocol.errors import KeyNameError
from archery.protocol.keys import CARTESIAN_ARMS, PORTS
from archery.protocol.messages import MESSAGE_TYPES, Message
from archery.protocol.parts import PARTS

__all__ = ["STREAM_KINDS", "check_pattern", "is_wildcard", "stream_type"]

STREAM_KINDS = ("pub", "events", "sub")


@functools.cache
def _stream_shapes() -> tuple[zenoh.KeyExpr, ...]:
    """Every stream key with a wildcard robot chunk (`*/torso/state:o`, …)."""
    shapes = []
    for spec in PORTS:
        if spec.kind not in STREAM_KINDS:
            continue
        for part in PARTS if "{part}" in spec.pattern else ("",):
            for arm in CARTESIAN_ARMS if "{arm}" in spec.pattern else ("",):
                body = spec.pattern.replace("{part}", part).replace("{arm}", arm)
                shapes.append(zenoh.KeyExpr("*/" + body))
    return tuple(shapes)


def is_wildcard(pattern: str) -> bool:
    """Whether a key expression names more than one key."""
    return "*" in pattern or "$" in pattern


def check_pattern(pattern: str) -> zenoh.KeyExpr:
    """The key expression of `pattern`.

    Raises:
        KeyNameError: not a valid key expression, or it matches no stream port.
    """
    try:
        expr = zenoh.KeyExpr.autocanonize(pattern)
    except (zenoh.ZError, ValueError) as exc:
        raise KeyNameError(
            f"{pattern!r} is not a key expression: {clean_zenoh_error(exc)}"
        ) from None
    if not any(expr.intersects(shape) for shape in _stream_shapes()):
        raise KeyNameError(
            f"key pattern {pattern!r} matches no stream port; e.g. ROBOT/** (everything), "
            f"ROBOT/*/state:o (joint states), ROBOT/cam/target:o (camera frames)"
        )
    return expr


def stream_type(key: str) -> type[Message] | None:
    """The message type of a concrete stream key, or None when it is no stream port."""
    from archery.protocol.keys import port_of

    try:
        spec = port_of(key)
    except KeyNameError:
        return None
    return MESSAGE_TYPES[spec.message] if spec.kind in STREAM_KINDS else None
