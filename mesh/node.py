"""The node base every service and tool builds on: typed pub/sub, RPC, liveliness, describe.

A `Node` owns one Zenoh session. It publishes typed messages (stamping sequence numbers and
wall time), subscribes latest-wins (state streams) or lossless FIFO (events), serves `rpc:i`
ports from a worker thread (replies are `RpcReply`: ok with a result, or an error code and
message), calls other services' RPC with a timeout, declares a liveliness token
`ROBOT/alive/NAME` once `ready()` is called and answers `ROBOT/describe/NAME` with its ports.
Malformed payloads are logged and counted, never fatal.
"""

from __future__ import annotations

import itertools
import logging
import os
import queue
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Generic, TypeVar, cast

import msgspec
import zenoh

from mesh import instances
from mesh.netflags import NetConfig, open_session
from mesh.tokens import TokenSet
from protocol.codec import MAX_PAYLOAD_BYTES, decode, encode, encode_into
from protocol.errors import (
    ArcheryError,
    DecodeError,
    RpcError,
    RpcTimeout,
    StaleState,
    UpstreamLost,
    WrongReplier,
)
from protocol.keys import Keys
from protocol.messages import (
    Describe,
    Image,
    Message,
    PortInfo,
    RpcReply,
    RpcRequest,
)
from protocol.robotspec import CALL_TIMEOUT
from protocol.verbs.base import BoundVerb, ServedVerbs, Verb
from protocol.verbs.schema import field_text

__all__ = [
    "Node",
    "Publisher",
    "RpcServer",
    "Subscription",
    "bad_args_message",
    "reply_error",
    "shutdown_on_signals",
]

M = TypeVar("M", bound=Message)
A = TypeVar("A", bound=msgspec.Struct)
R = TypeVar("R", bound=msgspec.Struct)
log = logging.getLogger("archery.node")
_STOP = object()


class _WireRequest(Message, frozen=True, tag="RpcRequest"):
    """An `RpcRequest` as the server reads it: the args stay msgpack until the verb is known,
    then decode straight into the verb's argument type."""

    verb: str
    args: msgspec.Raw = msgspec.Raw(b"\x80")  # an empty map


class _Untaken(msgspec.Struct, frozen=True, tag="-", tag_field="type"):
    """Never sent: in a union with `_WireRequest` it makes msgspec require the `type` tag (a
    lone tagged struct decodes without one)."""


_request_decoder = msgspec.msgpack.Decoder(_WireRequest | _Untaken)
_NO_TYPE = "missing required field `type`"


class Publisher(Generic[M]):
    """Publishes messages of one type on one key; stamps `seq` and wall time `stamp`.

    `lossless=True` (events) blocks rather than drops under congestion; state streams drop the
    oldest data instead (latest wins).
    """

    def __init__(self, session: zenoh.Session, key: str, message_type: type[M], lossless: bool):
        self.key = key
        self.message_type = message_type
        self._seq = 0
        self._closed = False
        self._lock = threading.Lock()
        self._buffer = bytearray()  # reused: Zenoh copies the payload out during `put`
        self._pub = session.declare_publisher(
            key,
            congestion_control=(
                zenoh.CongestionControl.BLOCK if lossless else zenoh.CongestionControl.DROP
            ),
            reliability=zenoh.Reliability.RELIABLE,
            # a frame is megabytes: on every link it queues behind state, events and RPC
            priority=zenoh.Priority.DATA_LOW if message_type is Image else zenoh.Priority.DATA,
        )

    def put(self, message: M) -> M:
        """Stamp and publish `message`; returns the stamped copy that was sent."""
        if not isinstance(message, self.message_type):
            raise TypeError(
                f"{self.key} carries {self.message_type.__name__}, got {type(message).__name__}"
            )
        with self._lock:
            self._seq += 1
            stamped = msgspec.structs.replace(message, seq=self._seq, stamp=time.time())
            encode_into(stamped, self._buffer)
            self._pub.put(self._buffer)
        return stamped

    @property
    def count(self) -> int:
        """Messages published so far (the last `seq`)."""
        return self._seq

    def matching(self) -> bool:
        """Whether at least one subscriber matches the key now."""
        # zenoh's stub says bool; the property is a MatchingStatus
        status = cast(zenoh.MatchingStatus, self._pub.matching_status)
        return bool(status.matching)

    def on_matching(self, callback: Callable[[bool], None]) -> Callable[[], None]:
        """Call `callback(matching)` whenever subscribers appear or all go; returns the function
        that stops the calls (keep a reference while it should run)."""
        listener = self._pub.declare_matching_listener(lambda s: callback(bool(s.matching)))
        return listener.undeclare

    def wait_matched(self, timeout: float) -> bool:
        """Wait until at least one subscriber matches the key; False after `timeout` s."""
        if self.matching():
            return True
        matched = threading.Event()
        stop = self.on_matching(lambda matching: matched.set() if matching else None)
        try:
            return self.matching() or matched.wait(timeout)
        finally:
            stop()

    def close(self) -> None:
        """Undeclare the publisher (idempotent)."""
        if not self._closed:
            self._closed = True
            self._pub.undeclare()


class Subscription(Generic[M]):
    """Receives one message type on one key.

    mode "latest": keeps only the newest message (`latest()`, `wait_newer()`); mode "fifo": keeps
    every message in arrival order (`get()`), never dropping one. An `Image` arrives as an
    `ImageView`: its pixels a read-only view of the received payload, not a copy. An optional
    callback runs on Zenoh's thread for each valid message, in order (keep it short); with a
    callback, a fifo subscription hands every message to it instead of queueing it for `get()`.
    Invalid payloads are counted in `dropped` and logged.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        message_type: type[M],
        mode: str,
        callback: Callable[[M], None] | None,
    ) -> None:
        if mode not in ("latest", "fifo"):
            raise ValueError(f"subscription mode {mode!r} is not 'latest' or 'fifo'")
        self.key = key
        self.message_type = message_type
        self.mode = mode
        self.received = 0
        self.dropped = 0
        self.last_error = ""
        self._callback = callback
        self._latest: M | None = None
        self._latest_time = 0.0
        self._cond = threading.Condition()
        self._queue: queue.Queue[M] = queue.Queue()
        self._sub: zenoh.Subscriber | None = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            message = decode(sample.payload.to_bytes(), self.message_type, view=True)
        except DecodeError as exc:
            self.dropped += 1
            self.last_error = str(exc)
            if self.dropped <= 10 or self.dropped % 100 == 0:
                log.warning("dropped message #%d on %s: %s", self.dropped, self.key, exc)
            return
        with self._cond:
            self.received += 1
            self._latest = message
            self._latest_time = time.monotonic()
            if self.mode == "fifo" and self._callback is None:
                self._queue.put(message)
            self._cond.notify_all()
        if self._callback is not None:
            try:
                self._callback(message)
            except Exception:
                log.exception("callback for %s failed on message seq %d", self.key, message.seq)

    def latest(self) -> M | None:
        """The newest valid message, or None if none arrived yet."""
        return self._latest

    def age(self) -> float:
        """Seconds since the newest valid message arrived (inf if none did)."""
        return time.monotonic() - self._latest_time if self._latest is not None else float("inf")

    def fresh(self, max_age: float, wait: float = 0.0) -> M:
        """The newest message if it arrived within the last `max_age` s, else the next one to
        arrive within `wait` s. The age is the arrival age on this host's monotonic clock (the
        sender's stamp is on another host's clock).

        Raises:
            StaleState: no message that fresh; names the key and the newest one's age.
        """
        with self._cond:
            old = self._latest
            if old is not None and time.monotonic() - self._latest_time <= max_age:
                return old
            deadline = time.monotonic() + wait
            while self._latest is old:  # identity: a restarted publisher's seq starts again
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise StaleState(self.key, self.age(), max_age)
                self._cond.wait(remaining)
            return self._latest  # type: ignore[return-value]  # not None: a message arrived

    def wait_newer(
        self,
        timeout: float,
        predicate: Callable[[M], bool] | None = None,
        after_seq: int | None = None,
        max_age: float | None = None,
    ) -> M:
        """Block until a message newer than `after_seq` (default: the current latest) arrives
        that satisfies `predicate`.

        With `max_age`, give up as soon as the stream is silent for longer than that (no message
        arrived for `max_age` s, counting from the call when none had arrived before).

        Raises:
            RpcTimeout: nothing suitable within `timeout` seconds; the message names the key.
            StaleState: the stream went silent for longer than `max_age` s.
        """
        start = time.monotonic()
        deadline = start + timeout
        with self._cond:
            if after_seq is None:
                after_seq = self._latest.seq if self._latest is not None else -1
            while True:
                msg = self._latest
                if (
                    msg is not None
                    and msg.seq > after_seq
                    and (predicate is None or predicate(msg))
                ):
                    return msg
                now = time.monotonic()
                remaining = deadline - now
                if remaining <= 0:
                    raise RpcTimeout(
                        f"no suitable message on {self.key} within {timeout:g} s "
                        f"(received {self.received}, dropped {self.dropped})"
                    )
                if max_age is not None:
                    heard = self._latest_time if msg is not None else start
                    if now - heard > max_age:
                        age = now - heard if msg is not None else float("inf")
                        raise StaleState(self.key, age, max_age)
                    remaining = min(remaining, heard + max_age - now + 1e-3)
                self._cond.wait(remaining)

    def get(self, timeout: float | None = None) -> M:
        """Next message in arrival order (fifo mode).

        Raises:
            RpcTimeout: nothing arrived within `timeout` seconds.
        """
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            raise RpcTimeout(f"no message on {self.key} within {timeout:g} s") from None

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


def bad_args_message(verb: Verb[Any, Any], exc: msgspec.ValidationError) -> str:
    """`bad_request` text: the verb, msgspec's error and path, and what the field allows."""
    text = str(exc)
    what, _, path = text.partition(" - at `")
    path = path.rstrip("`") or "$"
    if what.startswith("$.") and " is " in what:  # a finiteness check of a struct's field
        inner, _, what = what.partition(" is ")
        path = path + inner[1:]
        what = f"Expected a finite number, got {what.split(';')[0]}"
    message = f"invalid argument of {verb.name} at `{path}`: {what}"
    allowed = field_text(verb.schema()["args"], path)
    if allowed is not None:
        return f"{message}; {allowed[0]} must be {allowed[1]}"
    names = ", ".join(verb.args.__struct_fields__) or "none"
    return f"{message}; arguments of {verb.name}: {names}"


def reply_error(call: str, reply: RpcReply) -> RpcError:
    """The error of an error reply to `call` ("KEY VERB"): `UpstreamLost` naming the lost
    upstream service, else `RpcError` with the reply's code."""
    message = f"{call}: {reply.message}"
    if reply.code == UpstreamLost.code and reply.service:
        return UpstreamLost(reply.service, message)
    return RpcError(message, code=reply.code or "rpc_error")


class RpcServer:
    """Serves an `rpc:i` key: decodes `RpcRequest`, runs the verb's handler, replies `RpcReply`.

    Requests for blocking verbs (the default) are handled one at a time, in order, on the
    server's worker thread (like a YARP RPC port), so a slow handler never blocks Zenoh's
    threads. A verb declared `blocking=False` (status and getters that never wait) is answered
    right on the receive path, without a thread hand-off, so it is neither slowed by the hand-off
    nor held up behind a blocking verb of the same port; it may run while a blocking handler
    does. Requests that reach no handler (undecodable, unknown verb) are answered there too.

    This is the one place a request is validated: for a typed verb table (`ServedVerbs`) the
    request's args are decoded straight into the verb's `Args` type, and anything that does not
    fit (wrong type, out of range, NaN, unknown or missing field) is answered `bad_request`
    naming the verb, the field and what is allowed; the handler gets the typed args and returns
    the verb's `Reply`. An `ArcheryError` becomes an error reply
    with its code, any other exception an "internal" error; a payload that is not a request (not
    msgpack, no `type` tag, nested too deep) `bad_message`. The server keeps serving.
    """

    def __init__(self, session: zenoh.Session, key: str, verbs: ServedVerbs) -> None:
        if not isinstance(verbs, ServedVerbs):
            raise TypeError(f"serve {key} takes a bound verb table, got {type(verbs).__name__}")
        self.key = key
        self.table = verbs.table
        self.handlers: dict[str, BoundVerb[Any, Any]] = dict(verbs.bound)
        self.inline = frozenset(
            name for name, entry in self.handlers.items() if not entry.verb.blocking
        )
        self.served = 0
        self.errors = 0
        self._seq = itertools.count(1)
        self._counts = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._queryable = session.declare_queryable(key, self._on_query)
        self._thread = threading.Thread(target=self._work, name=f"rpc {key}", daemon=True)
        self._thread.start()

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh's thread: decode the request once; answer it here unless its verb blocks."""
        try:
            request: _WireRequest | DecodeError = self._request(query)
        except DecodeError as exc:
            request = exc
        except Exception:
            log.exception("could not read a request on %s", self.key)
            query.drop()
            return
        if (
            isinstance(request, _WireRequest)
            and request.verb in self.handlers
            and request.verb not in self.inline
        ):
            self._queue.put((query, request))
        else:
            self._answer(query, request)

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            self._answer(*item)

    def _answer(self, query: zenoh.Query, request: _WireRequest | DecodeError) -> None:
        try:
            query.reply(self.key, encode(self._handle(request, next(self._seq))))
        except Exception:
            log.exception("could not reply on %s", self.key)
        finally:
            query.drop()

    def _error(self, code: str, message: str, seq: int, service: str = "") -> RpcReply:
        with self._counts:
            self.errors += 1
        return RpcReply(
            ok=False, code=code, message=message, service=service, seq=seq, stamp=time.time()
        )

    def _request(self, query: zenoh.Query) -> _WireRequest:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        if len(payload) > MAX_PAYLOAD_BYTES:
            raise DecodeError(
                f"request of {len(payload)} bytes exceeds the limit of {MAX_PAYLOAD_BYTES} bytes"
            )
        try:
            request = _request_decoder.decode(payload)
        except msgspec.ValidationError as exc:
            if _NO_TYPE in str(exc):
                raise DecodeError(
                    "the request map has no `type` field: an RpcRequest is a msgpack map "
                    "{type: 'RpcRequest', verb: str, args: map}"
                ) from None
            raise DecodeError(f"invalid RpcRequest: {exc}") from None
        except msgspec.DecodeError as exc:
            raise DecodeError(f"payload is not msgpack: {exc}") from None
        except RecursionError:
            raise DecodeError("the request nests too deep to decode") from None
        if not isinstance(request, _WireRequest):
            raise DecodeError("the request's `type` is not 'RpcRequest'")
        return request

    def _handle(self, request: _WireRequest | DecodeError, seq: int) -> RpcReply:
        with self._counts:
            self.served += 1
        if isinstance(request, DecodeError):
            return self._error(request.code, f"bad request on {self.key}: {request}", seq)
        entry = self.handlers.get(request.verb)
        if entry is None:
            verbs = ", ".join(sorted(self.handlers))
            message = f"{self.key} has no verb {request.verb!r}; verbs: {verbs}"
            return self._error("unknown_verb", message, seq)
        try:
            verb = entry.verb
            try:
                args = verb.args_decoder.decode(request.args)
            except msgspec.ValidationError as exc:
                return self._error("bad_request", bad_args_message(verb, exc), seq)
            except (msgspec.DecodeError, RecursionError):
                message = f"{verb.name}: the args are not msgpack or nest too deep"
                return self._error("bad_message", message, seq)
            result = entry.handler(args)
            if not isinstance(result, verb.reply):
                raise TypeError(
                    f"the handler returned {type(result).__name__}, not {verb.reply.__name__}"
                )
            return RpcReply(ok=True, result=result, seq=seq, stamp=time.time())
        except UpstreamLost as exc:
            return self._error(exc.code, exc.message, seq, exc.service)
        except ArcheryError as exc:
            return self._error(exc.code, exc.message, seq)
        except Exception as exc:
            log.exception("%s %s failed", self.key, request.verb)
            return self._error("internal", f"{request.verb} failed: {exc!r}", seq)

    def close(self) -> None:
        """Stop serving (pending requests get no reply and time out at the caller)."""
        if self._thread.is_alive():
            self._queryable.undeclare()
            self._queue.put(_STOP)
            self._thread.join(timeout=5)


class Node:
    """One process's presence on the mesh. Use as a context manager.

    Args:
        name: the service name (liveliness token `ROBOT/alive/NAME`); None for anonymous tools.
        net: network settings (from the common flags).
        session: an already open session to use (the node then does not close it).
    """

    def __init__(
        self, name: str | None, net: NetConfig, *, session: zenoh.Session | None = None
    ) -> None:
        self.name = name
        self.net = net
        self.keys = Keys(net.robot)
        self._own_session = session is None
        self.session = (
            session if session is not None else open_session(net.with_identity(name or "operator"))
        )
        self._ports: list[PortInfo] = []
        self._verbs: dict[str, list[str]] = {}
        self._interfaces: dict[str, dict[str, Any]] = {}
        self._closables: list[Any] = []
        self._queriers: dict[tuple[str, float], zenoh.Querier] = {}
        self._rpc_seq = itertools.count(1)  # next() is atomic: no lock per call
        self._rpc_lock = threading.Lock()
        self._closed = False
        self._token: zenoh.LivelinessToken | None = None
        self._instance_token: zenoh.LivelinessToken | None = None
        self._watch: instances.InstanceWatch | None = None
        if name is not None:
            instances.claim(self.session, self.keys, name, net.replace)
            self._describe = self.session.declare_queryable(
                self.keys.describe(name), self._on_describe
            )

    def ready(self) -> None:
        """Declare the liveliness token: call once every port is declared, so whoever sees
        the service alive also finds all its ports."""
        if self.name is None:
            raise ValueError("an anonymous node has no liveliness token")
        if self._token is None:
            zid = instances.zid_of(self.session)
            self._instance_token = self.session.liveliness().declare_token(
                self.keys.alive_instance(self.name, zid)
            )
            self._token = self.session.liveliness().declare_token(self.keys.alive(self.name))

    # -- context management -------------------------------------------------------------
    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything (token first, so peers see the node leave) and close."""
        if self._closed:
            return
        self._closed = True
        if self._token is not None:
            self._token.undeclare()
            assert self._instance_token is not None  # declared together with _token
            self._instance_token.undeclare()
        if self._watch is not None:
            self._watch.close()
        if self.name is not None:
            self._describe.undeclare()
        for item in reversed(self._closables):
            try:
                item.close()
            except Exception:
                log.exception("closing %r", item)
        for querier in self._queriers.values():
            querier.undeclare()
        if self._own_session:
            self.session.close()

    # -- ports --------------------------------------------------------------------------
    def publisher(self, key: str, message_type: type[M], *, lossless: bool = False) -> Publisher[M]:
        """Declare a typed publisher (`lossless` for event streams that must not drop)."""
        pub = Publisher(self.session, key, message_type, lossless)
        self._register(key, "events" if lossless else "pub", message_type.__name__, pub)
        return pub

    def subscribe(
        self,
        key: str,
        message_type: type[M],
        *,
        mode: str = "latest",
        callback: Callable[[M], None] | None = None,
    ) -> Subscription[M]:
        """Subscribe to a typed stream: mode "latest" (state) or "fifo" (lossless events)."""
        sub = Subscription(self.session, key, message_type, mode, callback)
        self._register(key, "sub", message_type.__name__, sub)
        return sub

    def serve(self, key: str, verbs: ServedVerbs) -> RpcServer:
        """Serve an `rpc:i` key: a verb table with its handlers bound (`VerbTable.bind`), whose
        argument and reply schemas `describe` then carries."""
        server = RpcServer(self.session, key, verbs)
        self._register(key, "rpc", "RpcRequest", server)
        self._verbs[key] = sorted(server.handlers)
        self._interfaces[key] = verbs.table.schemas
        return server

    def _register(self, key: str, kind: str, message: str, closable: Any) -> None:
        self._ports.append(PortInfo(key=key, kind=kind, message=message))
        self._closables.append(closable)

    def describe(self) -> Describe:
        """This node's self-description."""
        return Describe(
            service=self.name or "",
            ports=[
                msgspec.structs.replace(port, count=source.count)
                if isinstance(source, Publisher)
                else port
                for port, source in zip(self._ports, self._closables, strict=True)
            ],
            pid=os.getpid(),
            host=socket.gethostname(),
            verbs=dict(self._verbs),
            interfaces=dict(self._interfaces),
        )

    def _on_describe(self, query: zenoh.Query) -> None:
        if query.payload is not None and query.payload.to_bytes() == instances.REPLACE:
            instances.replace_requested(self.name or "")
        query.reply(
            query.key_expr, encode(msgspec.structs.replace(self.describe(), stamp=time.time()))
        )

    # -- rpc client ---------------------------------------------------------------------
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
        )
        payload = self._query(key, encode(request), timeout, expect_service)
        try:
            reply = verb.reply_decoder.decode(payload)
        except (msgspec.ValidationError, msgspec.DecodeError, RecursionError) as exc:
            plain = decode(payload, RpcReply)  # an error reply, or a result of the wrong shape
            if not plain.ok:
                raise reply_error(f"{key} {verb.name}", plain) from None
            raise RpcError(
                f"{key} {verb.name} replied a result that is not a {verb.reply.__name__}: {exc}",
                code="bad_reply",
            ) from None
        if not reply.ok:
            raise reply_error(f"{key} {verb.name}", reply)
        if reply.result is None:
            raise RpcError(
                f"{key} {verb.name} replied ok without a {verb.reply.__name__}", code="bad_reply"
            )
        return reply.result

    def request(
        self,
        key: str,
        payload: bytes,
        *,
        timeout: float = CALL_TIMEOUT,
        expect_service: str | None = None,
    ) -> RpcReply:
        """Send a raw request payload and return the decoded `RpcReply` (no error raising but
        `WrongReplier` when `expect_service` is given and only others replied)."""
        return decode(self._query(key, payload, timeout, expect_service), RpcReply)

    def _query(
        self, key: str, payload: bytes, timeout: float, expect_service: str | None = None
    ) -> bytes:
        """Send a request payload and return the first accepted reply's payload bytes."""
        querier = self._queriers.get((key, timeout))
        if querier is None:
            with self._rpc_lock:
                querier = self._queriers.get((key, timeout))
                if querier is None:
                    querier = self.session.declare_querier(
                        key, timeout=timeout, target=zenoh.QueryTarget.BEST_MATCHING
                    )
                    self._queriers[(key, timeout)] = querier
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
        if waited < timeout * 0.5:
            raise RpcTimeout(
                f"no service serves {key} (no reply after {waited:.2f} s); is it running? "
                f"`archery ports` lists the live services"
            )
        raise RpcTimeout(
            f"no reply from {key} within {timeout:g} s; the service may be dead or stuck "
            f"(`archery ports` lists the live services)"
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

    # -- liveliness ---------------------------------------------------------------------
    def alive(self, timeout: float = 1.0) -> set[str]:
        """Names of the services of this robot whose liveliness token is up now."""
        names = set()
        for reply in self.session.liveliness().get(self.keys.alive_all(), timeout=timeout):
            if reply.ok is not None:
                names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return names

    def wait_alive(self, services: Iterable[str], timeout: float = 30.0) -> None:
        """Block until every named service is alive (by liveliness, never by sleeping).

        Raises:
            RpcTimeout: some are still missing after `timeout` seconds; the message lists them.
        """
        wanted = set(services)
        with TokenSet(self.session, self.keys.alive_all()) as alive:
            if not alive.wait_for(lambda seen: wanted <= seen, timeout):
                missing = ", ".join(sorted(wanted - alive.present()))
                raise RpcTimeout(
                    f"services not alive after {timeout:g} s: {missing} (robot {self.keys.robot!r})"
                )

    def wait_gone(self, service: str, timeout: float = 30.0) -> None:
        """Block until the service's liveliness token disappears.

        Raises:
            RpcTimeout: still alive after `timeout` seconds.
        """
        deadline = time.monotonic() + timeout
        gone = threading.Event()

        def on_token(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                gone.set()

        sub = self.session.liveliness().declare_subscriber(self.keys.alive(service), on_token)
        try:
            if service not in self.alive():
                return
            if not gone.wait(max(0.0, deadline - time.monotonic())):
                raise RpcTimeout(f"service {service!r} still alive after {timeout:g} s")
        finally:
            sub.undeclare()


def shutdown_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so a service can end cleanly with exit status 0."""
    stop = threading.Event()
    instances.set_stop_event(stop)

    def handle(signum: int, frame: object) -> None:
        log.info("signal %d: shutting down", signum)
        stop.set()

    signal.signal(signal.SIGINT, handle)
    signal.signal(signal.SIGTERM, handle)
    return stop
