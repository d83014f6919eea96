"""The learner's verbs as its clients call them: typed through `LEARNER_VERBS` (a start request
built as plain data is checked against `StartArgs` by `start_args` before it is sent), the
status reply as plain data."""

from __future__ import annotations

from typing import Any

import msgspec

from archery.mesh.node import Node
from archery.mesh.rpc_server import bad_args_message
from archery.protocol.errors import BadRequest
from archery.protocol.verbs.learner import LEARNER_VERBS, START, StartArgs

__all__ = ["learner_call", "start_args"]


def start_args(request: dict[str, Any]) -> StartArgs:
    """A `start` request (plain data) as the verb's `StartArgs`.

    Raises:
        BadRequest: it does not fit (the message names the field and what it allows).
    """
    try:
        return msgspec.convert(request, StartArgs)
    except msgspec.ValidationError as exc:
        raise BadRequest(bad_args_message(START, exc)) from None


def learner_call(
    node: Node, verb: str, start: StartArgs | None = None, *, timeout: float
) -> dict[str, Any]:
    """Call the learner's `verb` (start with its `StartArgs`, stop, status) on this node's
    robot; its status reply as plain data (fields the learner did not set are left out).

    Raises:
        RpcError, RpcTimeout: as `Node.call_typed`.
    """
    reply = node.call_typed(node.keys.learner_rpc(), LEARNER_VERBS[verb], start, timeout=timeout)
    out: dict[str, Any] = msgspec.to_builtins(reply)
    return out
