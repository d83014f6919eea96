"""Calling an `rpc:i` verb by its name from a test: through the port's verb table (arguments
converted to the verb's `Args` type before anything is sent, the reply decoded into its `Reply`
type), both as plain data, so a test can write its arguments and read its reply as dicts."""

from __future__ import annotations

import time
from typing import Any

import msgspec

from mesh.node import Node, bad_args_message
from protocol.codec import encode
from protocol.errors import BadRequest, RpcError
from protocol.messages import RpcRequest
from protocol.robotspec import CALL_TIMEOUT
from protocol.verbs import VerbTable, table_for_key

__all__ = ["rpc_call"]


def rpc_call(
    node: Node,
    key: str,
    verb: str,
    args: dict[str, Any] | None = None,
    *,
    timeout: float = CALL_TIMEOUT,
    expect_service: str | None = None,
    table: VerbTable | None = None,
    unchecked: bool = False,
) -> Any:
    """Call `verb` (a name) on `key` with `args`; the reply as plain data (`table`: the verb
    table of a port outside the project's tables, e.g. a test's own). `unchecked`: send `args`
    as they are, for tests of what a server does with a request no typed client would send.

    Raises:
        BadRequest: the port has no such verb, or `args` do not fit its arguments.
        RpcError, RpcTimeout, WrongReplier: as `Node.call_typed`.
    """
    if unchecked:
        request = RpcRequest(verb=verb, args=args or {}, seq=0, stamp=time.time())
        plain = node.request(key, encode(request), timeout=timeout, expect_service=expect_service)
        if not plain.ok:
            raise RpcError(f"{key} {verb}: {plain.message}", code=plain.code or "rpc_error")
        return plain.result
    table = table or table_for_key(key)
    if verb not in table.names():
        raise BadRequest(f"{key} has no verb {verb!r}; verbs: {', '.join(table.names())}")
    typed = table[verb]
    try:
        request = msgspec.convert(args or {}, typed.args)
    except msgspec.ValidationError as exc:
        raise BadRequest(bad_args_message(typed, exc)) from None
    reply = node.call_typed(key, typed, request, timeout=timeout, expect_service=expect_service)
    return msgspec.to_builtins(reply)
