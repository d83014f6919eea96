"""Typed RPC verbs: one Struct for a verb's arguments, one for its reply, and the verb tables.

A `Verb` names a verb of an `rpc:i` port with its `Args` and `Reply` types and a one-line doc;
a `VerbTable` lists the verbs of one kind of port. A service binds a handler to every verb of a
table (`VerbTable.bind`) and serves the result (`Node.serve`); the `RpcServer` decodes each
request's arguments straight into the verb's `Args` type, so handlers only ever see valid,
typed arguments. Callers use `Node.call_typed`, which decodes the reply into the verb's `Reply`.

Constraints live in the types (`Annotated[float, Meta(ge=..., le=...)]`, lengths, `Literal`);
`Args` forbid unknown fields, and every float in an `Args` or `Reply` must be finite.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import msgspec

from archery.protocol.messages import check_finite_fields

__all__ = ["Args", "BoundVerb", "NoArgs", "Reply", "ServedVerbs", "Verb", "VerbTable"]


class Args(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base of every verb's arguments: unknown fields are refused, floats must be finite."""

    def __post_init__(self) -> None:
        check_finite_fields(self, "$.")


class NoArgs(Args, frozen=True):
    """A verb that takes no arguments."""


class Reply(msgspec.Struct, frozen=True, kw_only=True):
    """Base of every verb's reply: floats must be finite."""

    def __post_init__(self) -> None:
        check_finite_fields(self, "$.")


A = TypeVar("A", bound=msgspec.Struct)
R = TypeVar("R", bound=msgspec.Struct)


@dataclass(frozen=True)
class Verb(Generic[A, R]):
    """One verb: its name, argument and reply types, and a one-line doc.

    `blocking=False` declares that the handler never waits (no sleep, no call, no wait on a
    stream, on another thread's job or on a lock held across one): the server then answers it
    right on the receive path instead of queueing it behind the blocking verbs of its port.

    `reads=True` declares that the verb changes nothing (no motion, no setting, no session):
    the read-only `viewer` identity may call it (`mesh.acl`).

    `background=True` declares a blocking verb whose work serves an observer (a picture for a
    dashboard or a session's folder), not a rollout: the server runs it on a worker of its own
    at a lower CPU priority (`mesh.rpc_server`), so it neither queues ahead of the port's other
    verbs nor takes a core from them on a busy machine.

    `waits=True` declares a blocking verb that waits for something to happen in the world (a
    fresh frame) for up to a timeout its caller gives: the server runs each such request on a
    thread of its own beside the port's worker, never on it, at most `MAX_WAITING` of them per
    port at a time (the excess refused at once with `busy`), and the handler never waits past
    its caller's own timeout (`mesh.rpc_server.caller_left`).

    `names_caller=True` declares a verb whose server must know who calls (a claim of a part: the
    lease's owner): a call goes to `PORT/VERB~IDENTITY` (`protocol.keys.verb_key`), and in
    secure mode the router grants each identity only its own name there (`mesh.acl`), so the
    name the server reads (`mesh.rpc_server.caller`) is vouched for.
    """

    name: str
    args: type[A]
    reply: type[R]
    doc: str
    blocking: bool = True
    reads: bool = False
    background: bool = False
    waits: bool = False
    names_caller: bool = False

    @functools.cached_property
    def args_decoder(self) -> msgspec.msgpack.Decoder[A]:
        """Decodes a request's msgpack args straight into `args`."""
        return msgspec.msgpack.Decoder(self.args)

    @functools.cached_property
    def reply_decoder(self) -> msgspec.msgpack.Decoder[Any]:
        """Decodes a whole `RpcReply` whose result is this verb's reply (or None)."""
        from archery.protocol.messages import RpcReply

        typed = msgspec.defstruct(
            "RpcReply",
            [("result", self.reply | None, None)],
            bases=(RpcReply,),
            frozen=True,
            kw_only=True,
            tag="RpcReply",
            tag_field="type",
        )
        return msgspec.msgpack.Decoder(typed)

    def to(self, handler: Callable[[A], R]) -> BoundVerb[A, R]:
        """This verb served by `handler`, which takes its `Args` and returns its `Reply` (mypy
        checks both where the handler is bound)."""
        return BoundVerb(self, handler)

    def schema(self) -> dict[str, Any]:
        """{"doc", "args", "reply"}: the doc and JSON schemas of the argument and reply types."""
        return {
            "doc": self.doc,
            "args": msgspec.json.schema(self.args),
            "reply": msgspec.json.schema(self.reply),
        }


@dataclass(frozen=True)
class BoundVerb(Generic[A, R]):
    """A verb and the handler that serves it (takes the typed args, returns the typed reply)."""

    verb: Verb[A, R]
    handler: Callable[[A], R]


@dataclass(frozen=True)
class ServedVerbs:
    """A verb table with a handler bound to each of its verbs: what `Node.serve` takes."""

    table: VerbTable
    bound: Mapping[str, BoundVerb[Any, Any]]


@dataclass(frozen=True)
class VerbTable:
    """The verbs of one kind of `rpc:i` port.

    Attributes:
        title: what serves the port (e.g. "robot controlboard").
        ports: the key suffixes after the robot prefix this table serves (e.g. "torso/rpc:i").
        verbs: the verbs, in the order they are documented.
    """

    title: str
    ports: tuple[str, ...]
    verbs: tuple[Verb[Any, Any], ...]
    _by_name: dict[str, Verb[Any, Any]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        by_name = {v.name: v for v in self.verbs}
        if len(by_name) != len(self.verbs):
            raise ValueError(f"{self.title}: a verb name is listed twice")
        object.__setattr__(self, "_by_name", by_name)

    def __getitem__(self, name: str) -> Verb[Any, Any]:
        return self._by_name[name]

    def __iter__(self) -> Iterator[Verb[Any, Any]]:
        return iter(self.verbs)

    def names(self) -> list[str]:
        """The verb names, sorted."""
        return sorted(self._by_name)

    def bind(self, *bound: BoundVerb[Any, Any]) -> ServedVerbs:
        """Bind a handler to every verb, each as `VERB.to(handler)` (typed per verb).

        Raises:
            ValueError: a verb has no handler, is bound twice, or is not of this table.
        """
        by_name = {b.verb.name: b for b in bound}
        foreign = sorted(b.verb.name for b in bound if self._by_name.get(b.verb.name) is not b.verb)
        missing = sorted(set(self._by_name) - set(by_name))
        if foreign or missing or len(by_name) != len(bound):
            raise ValueError(
                f"{self.title}: handlers must match the verbs exactly; "
                f"missing {missing}, not verbs {foreign}"
            )
        return ServedVerbs(self, by_name)

    def bind_names(self, handlers: Mapping[str, Callable[[Any], Any]]) -> ServedVerbs:
        """Bind a handler to every verb by name, untyped (a fake serving any table in a test).

        Raises:
            ValueError: as `bind`, or a name is no verb of this table.
        """
        extra = sorted(set(handlers) - set(self._by_name))
        if extra:
            missing = sorted(set(self._by_name) - set(handlers))
            raise ValueError(
                f"{self.title}: handlers must match the verbs exactly; "
                f"missing {missing}, not verbs {extra}"
            )
        return self.bind(*(self._by_name[name].to(h) for name, h in handlers.items()))

    @functools.cached_property
    def schemas(self) -> dict[str, dict[str, Any]]:
        """verb name -> `Verb.schema()` (computed once)."""
        return {v.name: v.schema() for v in self.verbs}
