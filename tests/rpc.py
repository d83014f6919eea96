"""Calling an `rpc:i` verb by its name from a test, with its arguments as plain data sent as
they are (as a client in another language would send them), so that the server's own checks
are what a test sees; and fake services that serve some verbs of a table."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from archery.mesh.node import Node
from archery.mesh.rpc_client import reply_error
from archery.protocol.codec import encode
from archery.protocol.errors import ArcheryError
from archery.protocol.messages import RpcRequest
from archery.protocol.robotspec import CALL_TIMEOUT
from archery.protocol.verbs import ServedVerbs, VerbTable

__all__ = ["rpc_call", "some_verbs"]


def rpc_call(
    node: Node,
    key: str,
    verb: str,
    args: dict[str, Any] | None = None,
    *,
    timeout: float = CALL_TIMEOUT,
    expect_service: str | None = None,
) -> Any:
    """Send `verb` with `args` (plain data, unchecked) to `key`; the reply's result as plain
    data.

    Raises:
        RpcError: the server replied an error (its code kept; `UpstreamLost` for
            `upstream_lost`).
        RpcTimeout, WrongReplier: as `Node.call_typed`.
    """
    request = RpcRequest(verb=verb, args=args or {}, seq=0, stamp=time.time())
    reply = node.request(
        key, encode(request), verb=verb, timeout=timeout, expect_service=expect_service
    )
    if not reply.ok:
        raise reply_error(f"{key} {verb}", reply)
    return reply.result


def some_verbs(table: VerbTable, handlers: dict[str, Callable[[Any], Any]]) -> ServedVerbs:
    """`table` bound with `handlers` for some of its verbs, for a fake service in a test; every
    other verb answers `unknown_verb` saying the fake does not serve it."""

    def unserved(name: str) -> Callable[[Any], Any]:
        def refuse(_: Any) -> Any:
            raise ArcheryError(
                f"this test's fake {table.title} does not serve {name}", code="unknown_verb"
            )

        return refuse

    return table.bind_names({n: handlers.get(n, unserved(n)) for n in table.names()})
