"""Serving an `rpc:i` key from a verb table: requests decoded straight into each verb's
arguments, handled on a worker thread (or inline for non-blocking verbs; background verbs on a
second worker at a lower CPU priority, `BACKGROUND_NICE` and SCHED_IDLE; waiting verbs each on a
thread of their own, at most `MAX_WAITING` per port and `MAX_WAITING_PER_CALLER` of them for one
caller identity), replied `RpcReply`; each handled call also
goes to the port's tap (`mesh.rpc_tap`) for whoever listens. No request is worked on after its
caller has given up (`RpcRequest.wait`): a handler reads what is left with `caller_left`.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from typing import Annotated, Any, TypeVar

import msgspec
import zenoh

from archery.mesh.memory import note_payload
from archery.mesh.priority import lower_thread_priority
from archery.mesh.rpc_tap import RpcTap
from archery.protocol.codec import MAX_PAYLOAD_BYTES, encode, validation_text
from archery.protocol.errors import (
    ArcheryError,
    Busy,
    DecodeError,
    RpcTimeout,
    UpstreamLost,
)
from archery.protocol.keys import split_verb, tap_keys, verbs_key
from archery.protocol.messages import (
    MAX_CALLER_WAIT,
    Message,
    RpcReply,
)
from archery.protocol.text import SHOWN_LIMIT, cut, shown
from archery.protocol.verbs.base import BoundVerb, ServedVerbs, Verb
from archery.protocol.verbs.schema import field_text

__all__ = [
    "ANONYMOUS",
    "MAX_WAITING",
    "MAX_WAITING_PER_CALLER",
    "RpcServer",
    "bad_args_message",
    "caller",
    "caller_left",
    "caller_or_anonymous",
]

A = TypeVar("A", bound=msgspec.Struct)
log = logging.getLogger("archery.node")

_STOP = object()
BACKGROUND_NICE = 10  # the background verbs' worker, on top of the process's niceness
MAX_WAITING = 16  # requests of waiting verbs (`Verb.waits`) one port works on at a time
# of them, those of one caller identity (`caller_or_anonymous`): a few identities holding their
# most leave the others room (in secure mode fewer than MAX_WAITING / MAX_WAITING_PER_CALLER
# identities are granted any one waiting verb)
MAX_WAITING_PER_CALLER = 4
ANONYMOUS = "anonymous"  # the one identity of every call that names no caller
_call = threading.local()  # of the request being handled: its caller's deadline and name


def caller() -> str | None:
    """The identity the request this thread handles names as its caller (`Verb.names_caller`:
    in secure mode the router lets each identity name only itself), or None when it names
    none."""
    name: str | None = getattr(_call, "caller", None)
    return name


def caller_or_anonymous() -> str:
    """The identity the limits of the request this thread handles are counted for: the caller
    it names (`caller`), or `ANONYMOUS`, one for every request that names none."""
    return caller() or ANONYMOUS


def caller_left() -> float | None:
    """Seconds until the caller of the request this thread handles gives up (≤ 0: it has), or
    None when its caller did not say (`RpcRequest.wait`) or no request is being handled."""
    deadline: float | None = getattr(_call, "deadline", None)
    return None if deadline is None else deadline - time.monotonic()


class _WireRequest(Message, frozen=True, tag="RpcRequest"):
    """An `RpcRequest` as the server reads it: the args stay msgpack until the verb is known,
    then decode straight into the verb's argument type."""

    verb: str
    args: msgspec.Raw = msgspec.Raw(b"\x80")  # an empty map
    wait: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_CALLER_WAIT)] | None = None

    def deadline(self, arrived: float) -> float | None:
        """The monotonic time at which its caller gives up, for a request that arrived at
        `arrived` (monotonic s); None when the caller did not say."""
        return None if self.wait is None else arrived + self.wait


class _Untaken(msgspec.Struct, frozen=True, tag="-", tag_field="type"):
    """Never sent: in a union with `_WireRequest` it makes msgspec require the `type` tag (a
    lone tagged struct decodes without one)."""


_request_decoder = msgspec.msgpack.Decoder(_WireRequest | _Untaken)
_NO_TYPE = "missing required field `type`"


def bad_args_message(verb: Verb[Any, Any], exc: msgspec.ValidationError) -> str:
    """`bad_request` text: the verb, msgspec's error and path, and what the field allows."""
    what, _, path = validation_text(exc).partition(" - at `")
    what = cut(what, 2 * SHOWN_LIMIT)  # it may quote the request (an unknown field's name)
    path = cut(path.rstrip("`"), SHOWN_LIMIT) or "$"
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


class RpcServer:
    """Serves an `rpc:i` key: decodes `RpcRequest`, runs the verb's handler, replies `RpcReply`.

    Requests for blocking verbs (the default) are handled one at a time, in order, on the
    server's worker thread (like a YARP RPC port), so a slow handler never blocks Zenoh's
    threads. A verb declared `blocking=False` (status and getters that never wait) is answered
    right on the receive path, without a thread hand-off, so it is neither slowed by the hand-off
    nor held up behind a blocking verb of the same port; it may run while a blocking handler
    does. Requests that reach no handler (undecodable, unknown verb) are answered there too.

    A request's form is validated here, once: for a typed verb table (`ServedVerbs`) the
    request's args are decoded straight into the verb's `Args` type, whose fields carry the
    constraints (type, size, range, finite), and anything that does not fit (wrong type, out of
    range, NaN, unknown or missing field) is answered `bad_request` naming the verb, the field
    and what is allowed; the handler gets the typed args, which its core does not check again
    (only what depends on the service's own state or configuration, such as the controller's θ
    box), and returns the verb's `Reply`. An `ArcheryError` becomes an error reply
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
        self.background = frozenset(
            name
            for name, entry in self.handlers.items()
            if entry.verb.background and entry.verb.blocking
        )
        self.waits = frozenset(
            name
            for name, entry in self.handlers.items()
            if entry.verb.waits and entry.verb.blocking
        )
        self._in_hand: dict[str, int] = {}  # the waiting verbs' requests in hand, by caller
        self._waiting: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._pool = threading.Lock()
        self._waiters = 0  # threads started for the waiting verbs (at most MAX_WAITING)
        self._idle = 0  # of them, those waiting for a request
        self._queued = 0  # requests handed to them and not yet taken
        self.served = 0
        self.errors = 0
        self._seq = itertools.count(1)
        self._counts = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._later: queue.SimpleQueue[Any] = queue.SimpleQueue()  # the background verbs'
        self.tap = RpcTap(session, key) if tap_keys(key) is not None else None
        self._threads = [
            threading.Thread(target=self._work, args=(self._queue,), name=f"rpc {key}", daemon=True)
        ]
        if self.background:
            self._threads.append(
                threading.Thread(
                    target=self._work,
                    args=(self._later, BACKGROUND_NICE),
                    name=f"rpc {key} background",
                    daemon=True,
                )
            )
        for thread in self._threads:
            thread.start()
        self._queryable = session.declare_queryable(verbs_key(key), self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh's thread: decode the request once; answer it here unless its verb blocks."""
        arrived = time.monotonic()
        try:
            request: _WireRequest | ArcheryError = self._request(query)
        except DecodeError as exc:
            request = exc
        except Exception:
            log.exception("could not read a request on %s", self.key)
            query.drop()
            return
        sent_to = str(query.key_expr).rsplit("/", 1)[-1]
        verb, named = split_verb(sent_to)
        if isinstance(request, _WireRequest) and request.verb != verb:  # ACL grants by key
            request = DecodeError(
                f"the request names verb {shown(request.verb)} but was sent to "
                f"{self.key}/{shown(sent_to)}"
            )
        if (
            isinstance(request, _WireRequest)
            and request.verb in self.handlers
            and request.verb not in self.inline
        ):
            if request.verb in self.waits:
                self._start_waiting(query, request, arrived, named)
                return
            later = request.verb in self.background
            (self._later if later else self._queue).put((query, request, arrived, named))
        else:
            self._answer(query, request, arrived, named)

    def _start_waiting(
        self, query: zenoh.Query, request: _WireRequest, arrived: float, named: str | None
    ) -> None:
        """A waiting verb's request on a thread of the waiting verbs (beside the port's worker),
        or `busy` at once when its caller has `MAX_WAITING_PER_CALLER` of them in hand already,
        or the port `MAX_WAITING`."""
        who = named or ANONYMOUS
        with self._pool:
            mine, total = self._in_hand.get(who, 0), sum(self._in_hand.values())
            if mine < MAX_WAITING_PER_CALLER and total < MAX_WAITING:
                self._in_hand[who] = mine + 1
                # threads are kept and reused; one more is started only when fewer are idle
                # than requests wait for one
                self._queued += 1
                if self._idle < self._queued and self._waiters < MAX_WAITING:
                    self._waiters += 1
                    name = f"rpc {self.key} waiting {self._waiters}"
                    threading.Thread(target=self._wait_work, name=name, daemon=True).start()
                self._waiting.put((query, request, arrived, named))
                return
        if mine >= MAX_WAITING_PER_CALLER:
            why = (
                f"{MAX_WAITING_PER_CALLER} requests of its waiting verbs from {shown(who)} are "
                f"in hand (the most it takes from one caller)"
            )
        else:
            why = f"{MAX_WAITING} requests of its waiting verbs are in hand (the most it takes)"
        busy = Busy(f"{self.key} {request.verb}: busy, {why}; try again later")
        self._answer(query, busy, arrived, named)

    def _wait_work(self) -> None:
        """A thread of the waiting verbs: one request at a time, its slot given back after."""
        while True:
            with self._pool:
                self._idle += 1
            item = self._waiting.get()
            if item is _STOP:
                return
            with self._pool:
                self._idle -= 1
                self._queued -= 1
            who = item[3] or ANONYMOUS
            try:
                self._answer(*item)
            finally:
                with self._pool:
                    left = self._in_hand.pop(who) - 1
                    if left:
                        self._in_hand[who] = left
            del item

    def _work(self, jobs: queue.SimpleQueue[Any], nice: int = 0) -> None:
        if nice:
            lower_thread_priority(nice, idle=True)
        while True:
            item = jobs.get()
            if item is _STOP:
                return
            self._answer(*item)
            del item  # the request is not kept while waiting for the next one

    def _answer(
        self,
        query: zenoh.Query,
        request: _WireRequest | ArcheryError,
        arrived: float,
        named: str | None,
    ) -> None:
        """Handle `request` (arrived at monotonic `arrived` s, its key naming caller `named`),
        reply, and tap the call."""
        _call.caller = named
        try:
            reply = self._handle(request, next(self._seq), arrived)
            payload = encode(reply)
            query.reply(query.key_expr, payload)
        except Exception:
            log.exception("could not reply on %s", self.key)
            return
        finally:
            query.drop()
            _call.caller = None
        if self.tap is not None:
            if isinstance(request, _WireRequest):
                self.tap.tap(request.verb, request.args, reply, len(payload))
            else:
                self.tap.tap(None, None, reply, len(payload))

    def _error(self, code: str, message: str, seq: int, service: str = "") -> RpcReply:
        with self._counts:
            self.errors += 1
        return RpcReply(
            ok=False, code=code, message=message, service=service, seq=seq, stamp=time.time()
        )

    def _request(self, query: zenoh.Query) -> _WireRequest:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        note_payload(len(payload))
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
            raise DecodeError(f"invalid RpcRequest: {cut(str(exc), 2 * SHOWN_LIMIT)}") from None
        except msgspec.DecodeError as exc:
            raise DecodeError(f"payload is not msgpack: {cut(str(exc))}") from None
        except RecursionError:
            raise DecodeError("the request nests too deep to decode") from None
        if not isinstance(request, _WireRequest):
            raise DecodeError("the request's `type` is not 'RpcRequest'")
        return request

    def _handle(self, request: _WireRequest | ArcheryError, seq: int, arrived: float) -> RpcReply:
        with self._counts:
            self.served += 1
        if isinstance(request, DecodeError):
            return self._error(request.code, f"bad request on {self.key}: {request}", seq)
        if isinstance(request, ArcheryError):
            return self._error(request.code, request.message, seq)
        entry = self.handlers.get(request.verb)
        if entry is None:
            verbs = ", ".join(sorted(self.handlers))
            message = f"{self.key} has no verb {shown(request.verb)}; verbs: {verbs}"
            return self._error("unknown_verb", message, seq)
        deadline = request.deadline(arrived)
        if deadline is not None and deadline <= time.monotonic():
            message = (
                f"{self.key} {request.verb}: not handled, its caller gave up waiting "
                f"({request.wait:g} s) before its turn came"
            )
            return self._error(RpcTimeout.code, message, seq)
        _call.deadline = deadline
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
            return self._error("internal", f"{request.verb} failed: {shown(exc)}", seq)
        finally:
            _call.deadline = None

    def close(self) -> None:
        """Stop serving (pending requests get no reply and time out at the caller)."""
        if self._threads[0].is_alive():
            self._queryable.undeclare()
            self._queue.put(_STOP)
            self._later.put(_STOP)
            for _ in range(self._waiters):
                self._waiting.put(_STOP)
            for thread in self._threads:
                thread.join(timeout=5)
            if self.tap is not None:
                self.tap.close()
