"""Calling `rpc:i` verbs: typed requests, one querier per key and timeout, replies accepted
only from a service's live instance when asked, error replies raised with their codes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from typing import TypeVar

import msgspec
import zenoh

from archery.mesh import instances
from archery.mesh.acl import OPERATOR, granted, server_of
from archery.mesh.netflags import NetConfig
from archery.protocol.codec import decode, encode, validation_text
from archery.protocol.errors import (
    RpcError,
    RpcTimeout,
    UpstreamLost,
    WrongReplier,
)
from archery.protocol.keys import Keys, verb_key
from archery.protocol.messages import (
    MAX_CALLER_WAIT,
    RpcReply,
    RpcRequest,
)
from archery.protocol.robotspec import CALL_TIMEOUT
from archery.protocol.verbs import names_caller
from archery.protocol.verbs.base import Verb

__all__ = ["RpcClient", "reply_error"]

A = TypeVar("A", bound=msgspec.Struct)
R = TypeVar("R", bound=msgspec.Struct)
log = logging.getLogger("archery.node")


def reply_error(call: str, reply: RpcReply) -> RpcError:
    """The error of an error reply to `call` ("KEY VERB"): `UpstreamLost` naming the lost
    upstream service, else `RpcError` with the reply's code."""
    message = f"{call}: {reply.message}"
    if reply.code == UpstreamLost.code and reply.service:
        return UpstreamLost(reply.service, message)
    return RpcError(message, code=reply.code or "rpc_error")


class RpcClient:
    """The client half of a `Node`: what it needs is the node's session and keys."""

    session: zenoh.Session
    keys: Keys
    net: NetConfig
    name: str | None
    _queriers: dict[tuple[str, float], zenoh.Querier]
    _rpc_seq: Iterator[int]
    _rpc_lock: threading.Lock
    _watch: instances.InstanceWatch | None

    @property
    def identity(self) -> str:
        """Whose certificate this node presents in secure mode (`--identity`, else the
        service's name, else `operator`), and the name its calls give where a verb names its
        caller."""
        return self.net.identity or self.name or OPERATOR

    def call_typed(
        self,
        key: str,
        verb: Verb[A, R],
        args: A | None = None,
        *,
        timeout: float = CALL_TIMEOUT,
        expect_service: str | None = None,
    ) -> R:
        """Call a typed `verb` on an `rpc:i` key with its `Args` struct and return its `Reply`;
        with `expect_service`, only a reply from the live instance of that service is accepted.

        Raises:
            RpcError: the service replied with an error (its `code` is kept; `UpstreamLost`
                naming the lost service for `upstream_lost`), or (code
                `bad_reply`) a reply that does not match the verb's reply type.
            WrongReplier: only sessions other than `expect_service`'s live instance replied.
            RpcTimeout: nothing replied within `timeout` seconds; the message names the key.
        """
        if args is not None and not isinstance(args, verb.args):
            raise TypeError(f"{verb.name} takes {verb.args.__name__}, got {type(args).__name__}")
        seq = next(self._rpc_seq)
        request = RpcRequest(
            verb=verb.name,
            args=args if args is not None else {},  # type: ignore[arg-type]  # a Struct encodes as a map
            seq=seq,
            stamp=time.time(),
            wait=min(timeout, MAX_CALLER_WAIT),
        )
        payload = self._query(key, verb.name, encode(request), timeout, expect_service)
        try:
            reply = verb.reply_decoder.decode(payload)
        except (msgspec.ValidationError, msgspec.DecodeError, RecursionError) as exc:
            plain = decode(payload, RpcReply)  # an error reply, or a result of the wrong shape
            if not plain.ok:
                raise reply_error(f"{key} {verb.name}", plain) from None
            raise RpcError(
                f"{key} {verb.name} replied a result that is not a {verb.reply.__name__}: "
                f"{validation_text(exc) if isinstance(exc, msgspec.ValidationError) else exc}",
                code="bad_reply",
            ) from None
        if not reply.ok:
            raise reply_error(f"{key} {verb.name}", reply)
        result = reply.result
        if not isinstance(result, verb.reply):  # None: an ok without a result
            raise RpcError(
                f"{key} {verb.name} replied ok without a {verb.reply.__name__}", code="bad_reply"
            )
        return result

    def request(
        self,
        key: str,
        payload: bytes,
        *,
        verb: str,
        timeout: float = CALL_TIMEOUT,
        expect_service: str | None = None,
    ) -> RpcReply:
        """Send a raw request payload for `verb` and return the decoded `RpcReply` (no error
        raising but `WrongReplier` when `expect_service` is given and only others replied)."""
        return decode(self._query(key, verb, payload, timeout, expect_service), RpcReply)

    def _query(
        self,
        key: str,
        verb: str,
        payload: bytes,
        timeout: float,
        expect_service: str | None = None,
    ) -> bytes:
        """Send a request payload for `verb` to `KEY/VERB` (`protocol.keys.verb_key`: one key
        per verb, so the router's access control can grant each verb on its own) and return
        the first accepted reply's payload bytes."""
        target = verb_key(key, verb, self.identity if names_caller(key, verb) else None)
        querier = self._queriers.get((target, timeout))
        if querier is None:
            with self._rpc_lock:
                querier = self._queriers.get((target, timeout))
                if querier is None:
                    querier = self.session.declare_querier(
                        target, timeout=timeout, target=zenoh.QueryTarget.BEST_MATCHING
                    )
                    self._queriers[(target, timeout)] = querier
        start = time.monotonic()
        rejected: list[str] = []
        for reply in querier.get(payload=payload):
            if reply.ok is not None:
                if expect_service is None or self._from_instance(expect_service, reply, rejected):
                    return reply.ok.payload.to_bytes()
                continue
            assert reply.err is not None  # a reply is ok or an error
            log.debug("error reply on %s: %s", key, reply.err.payload.to_string())
        if rejected:
            live = sorted(self._instances().holders(str(expect_service)))
            raise WrongReplier(
                f"{key}: the reply came from {', '.join(rejected)}, not from the live "
                f"{expect_service!r} instance ({', '.join(live) or 'none alive'}); rejected"
            )
        waited = time.monotonic() - start
        denied = self._denied(key, verb, target)
        if denied is not None:
            raise RpcError(denied, code="denied")
        if waited < timeout * 0.5:
            raise RpcTimeout(
                f"no service serves {key} (no reply after {waited:.2f} s); is it running? "
                f"`archery ports` lists the live services"
            )
        raise RpcTimeout(
            f"no reply from {key} within {timeout:g} s; the service may be dead or stuck "
            f"(`archery ports` lists the live services)"
        )

    def _denied(self, key: str, verb: str, target: str) -> str | None:
        """In secure mode, when the service serving `key` is alive yet nothing replied: the
        router dropped the request, which only its access control does; the message says so.
        None otherwise (plain mode, or the service is not alive)."""
        if self.net.secure is None:
            return None
        server = server_of(self.keys.robot, key)
        if server is None or not instances.live_instances(self.session, self.keys, server):
            return None
        identity = self.identity
        if granted(self.keys.robot, identity, target):
            return None  # the rules let it through: the server is slow, stuck or busy
        return (
            f"{key} {verb}: denied by access control: the {server} is alive, but the router "
            f"drops this call from identity {identity!r} (secure mode; the rules are "
            f"{self.net.secure}/acl.json5, `archery keys`)"
        )

    def _instances(self) -> instances.InstanceWatch:
        with self._rpc_lock:
            if self._watch is None:
                self._watch = instances.InstanceWatch(self.session, self.keys)
            return self._watch

    def _from_instance(self, service: str, reply: zenoh.Reply, rejected: list[str]) -> bool:
        """Whether `reply` comes from `service`'s live instance; if not, log and note it."""
        zid = str(reply.replier_id.zid) if reply.replier_id is not None else "unknown"
        if self._instances().is_instance(service, zid):
            return True
        assert reply.ok is not None  # only ok replies are checked
        log.warning(
            "rejected a reply on %s from %s: not the live %s", reply.ok.key_expr, zid, service
        )
        rejected.append(f"session {zid}")
        return False
