"""What an `rpc:i` port is asked and answers, published for whoever listens (a recording).

A server's tap publishes each request it handled (`RpcRequest`: the verb and its arguments) on
`ROBOT/SERVER/requests:o` and each reply it sent (`RpcReply`) on `ROBOT/SERVER/replies:o`
(`protocol.keys.tap_keys`), each with the tap's own sequence number. While no subscriber
matches a tap key, nothing is decoded or encoded: the cost is one look at Zenoh's matching
status per call. A reply bigger than `MAX_TAPPED_REPLY` bytes (a camera frame, a PNG) is
published without its result, which says how many bytes were left out. A lease id (the
`lease` field of arguments and results: a part's ownership token) is published as
`REDACTED`, so that a listener learns who asked what, never a token that moves an arm.
"""

from __future__ import annotations

import logging
from typing import Any

import msgspec
import zenoh

from archery.mesh.publisher import Publisher
from archery.protocol.keys import tap_keys
from archery.protocol.messages import RpcReply, RpcRequest

__all__ = ["MAX_TAPPED_REPLY", "REDACTED", "RpcTap"]

MAX_TAPPED_REPLY = 64 * 1024  # bytes of an encoded reply the tap publishes whole
REDACTED = "(redacted)"  # what a tap publishes in place of a lease id
log = logging.getLogger("archery.node")


class RpcTap:
    """The request and reply taps of one `rpc:i` port (see the module docstring).

    Args:
        session: the server's Zenoh session.
        rpc_key: the port's key, `ROBOT/…/rpc:i`.

    Raises:
        ValueError: `rpc_key` is no `rpc:i` port.
    """

    def __init__(self, session: zenoh.Session, rpc_key: str) -> None:
        keys = tap_keys(rpc_key)
        if keys is None:
            raise ValueError(f"{rpc_key!r} is no rpc:i port")
        self.requests: Publisher[RpcRequest] = Publisher(session, keys[0], RpcRequest, False)
        self.replies: Publisher[RpcReply] = Publisher(session, keys[1], RpcReply, False)

    def tap(self, verb: str | None, args: msgspec.Raw | None, reply: RpcReply, size: int) -> None:
        """Publish one handled call: its verb and msgpack arguments (None: the request could
        not be read) and the reply sent, `size` bytes encoded. Never raises."""
        try:
            if verb is not None and self.requests.matching():
                plain: Any = {} if args is None else msgspec.msgpack.decode(args)
                if not isinstance(plain, dict):
                    plain = {"args": plain}
                if plain.get("lease"):
                    plain = plain | {"lease": REDACTED}
                self.requests.put(RpcRequest(verb=verb, args=plain))
            if self.replies.matching():
                if size > MAX_TAPPED_REPLY:
                    reply = msgspec.structs.replace(reply, result={"omitted_bytes": size})
                elif getattr(reply.result, "lease", None):
                    result = msgspec.structs.replace(reply.result, lease=REDACTED)
                    reply = msgspec.structs.replace(reply, result=result)
                self.replies.put(reply)
        except Exception:
            log.exception("could not tap a call on %s", self.requests.key)

    def close(self) -> None:
        """Undeclare both publishers."""
        self.requests.close()
        self.replies.close()
