"""The node every service and tool builds on: one Zenoh session with its ports.

A `Node` owns one Zenoh session. It publishes typed messages (`mesh.publisher`), subscribes
latest-wins or lossless FIFO (`mesh.subscription`), serves `rpc:i` ports from verb tables
(`mesh.rpc_server`), calls other services' verbs (`mesh.rpc_client`), declares a liveliness
token `ROBOT/alive/NAME` once `ready()` is called, watches others' (`mesh.liveliness`,
`mesh.instances`) and answers `ROBOT/describe/NAME` with its ports. Malformed payloads are
logged and counted, never fatal.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import msgspec
import zenoh

from archery.mesh import instances
from archery.mesh.liveliness import Liveliness, OnWait
from archery.mesh.netflags import NetConfig, listens, open_session
from archery.mesh.publisher import Publisher
from archery.mesh.router import wait_for_endpoint
from archery.mesh.rpc_client import RpcClient
from archery.mesh.rpc_server import RpcServer
from archery.mesh.runtime import ReplaceToken
from archery.mesh.subscription import Subscription
from archery.protocol.codec import encode
from archery.protocol.errors import ConfigError, Unreachable
from archery.protocol.keys import Keys
from archery.protocol.messages import (
    Describe,
    Message,
    PortInfo,
)
from archery.protocol.verbs.base import ServedVerbs

__all__ = ["Node", "open_node"]

M = TypeVar("M", bound=Message)
log = logging.getLogger("archery.node")


class Node(RpcClient, Liveliness):
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
        self._ports_lock = threading.Lock()  # ports come and go from any thread (`unsubscribe`)
        self._queriers: dict[tuple[str, float], zenoh.Querier] = {}
        self._rpc_seq = itertools.count(1)  # next() is atomic: no lock per call
        self._rpc_lock = threading.Lock()
        self._closed = False
        self._token: zenoh.LivelinessToken | None = None
        self._instance_token: zenoh.LivelinessToken | None = None
        self._watch: instances.InstanceWatch | None = None
        if name is not None:
            instances.claim(self.session, self.keys, name, net.replace)
            self._replace_token = ReplaceToken(
                self.keys.robot, name, instances.zid_of(self.session)
            )
            self._describe = self.session.declare_queryable(
                self.keys.describe(name), self._on_describe
            )
            self._replace = self.session.declare_queryable(
                self.keys.replace(name), self._on_replace
            )

    def ready(self) -> None:
        """Declare the liveliness token: call once every port is declared, so whoever sees
        the service alive also finds all its ports."""
        if self.name is None:
            raise ValueError("an anonymous node has no liveliness token")
        if self._instance_token is None:
            zid = instances.zid_of(self.session)
            self._instance_token = self.session.liveliness().declare_token(
                self.keys.alive_instance(self.name, zid)
            )
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.keys.alive(self.name))

    def withdraw(self) -> None:
        """Undeclare the service's token `ROBOT/alive/NAME` while it cannot do its work (a YARP
        robot's part lost), its instance's kept so its replies are still its own: peers see the
        service missing until `ready()` declares it again."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None

    # -- context management -------------------------------------------------------------
    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything (token first, so peers see the node leave) and close.

        Never raises: a part that cannot be closed (e.g. the router is gone and Zenoh's close
        times out) is skipped, and the failures are logged as one line at the end.
        """
        if self._closed:
            return
        self._closed = True
        failures: list[str] = []

        def quietly(what: str, close: Callable[[], object]) -> None:
            try:
                close()
            except Exception as exc:  # closing must go on whatever one part raises
                failures.append(f"{what}: {exc}")

        if self._token is not None:
            quietly("liveliness token", self._token.undeclare)
        if self._instance_token is not None:
            quietly("instance token", self._instance_token.undeclare)
        if self._watch is not None:
            quietly("liveliness watch", self._watch.close)
        if self.name is not None:
            quietly("describe queryable", self._describe.undeclare)
            quietly("replace queryable", self._replace.undeclare)
            quietly("replace token", self._replace_token.close)
        with self._ports_lock:
            closables = list(self._closables)
        for item in reversed(closables):
            quietly(type(item).__name__, item.close)
        with self._rpc_lock:  # a call on another thread may declare one meanwhile
            queriers = list(self._queriers.items())
        for key, querier in queriers:
            quietly(f"querier {key[0]}", querier.undeclare)
        if self._own_session:
            quietly("session", self.session.close)
        if failures:
            unique = sorted(set(failures))
            log.warning(
                "closed %s with %d part(s) not closed cleanly: %s",
                self.name or "the node",
                len(failures),
                "; ".join(unique[:3]) + (" …" if len(unique) > 3 else ""),
            )

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
        admit: Callable[[bytes], bool] | None = None,
    ) -> Subscription[M]:
        """Subscribe to a typed stream: mode "latest" (state) or "fifo" (lossless events);
        `admit` screens raw payloads before they are decoded (see `Subscription`)."""
        sub = Subscription(self.session, key, message_type, mode, callback, admit)
        self._register(key, "sub", message_type.__name__, sub)
        return sub

    def unsubscribe(self, sub: Subscription[Any]) -> None:
        """Undeclare a subscription of this node's (`subscribe`): it leaves `describe`; one
        already gone is ignored."""
        with self._ports_lock:
            for i, closable in enumerate(self._closables):
                if closable is sub:
                    del self._closables[i], self._ports[i]
                    break
        sub.close()

    def serve(self, key: str, verbs: ServedVerbs) -> RpcServer:
        """Serve an `rpc:i` key: a verb table with its handlers bound (`VerbTable.bind`), whose
        argument and reply schemas `describe` then carries, and its taps (`mesh.rpc_tap`)."""
        server = RpcServer(self.session, key, verbs)
        self._register(key, "rpc", "RpcRequest", server)
        if server.tap is not None:  # its request and reply taps are ports too
            for publisher in (server.tap.requests, server.tap.replies):
                name = publisher.message_type.__name__
                self._register(publisher.key, "pub", name, publisher)
        self._verbs[key] = sorted(server.handlers)
        self._interfaces[key] = verbs.table.schemas
        return server

    def _register(self, key: str, kind: str, message: str, closable: Any) -> None:
        with self._ports_lock:
            self._ports.append(PortInfo(key=key, kind=kind, message=message))
            self._closables.append(closable)

    def describe(self) -> Describe:
        """This node's self-description."""
        with self._ports_lock:
            ports = list(zip(self._ports, self._closables, strict=True))
        return Describe(
            service=self.name or "",
            ports=[
                msgspec.structs.replace(port, count=source.count)
                if isinstance(source, Publisher)
                else port
                for port, source in ports
            ],
            pid=os.getpid(),
            host=socket.gethostname(),
            verbs=dict(self._verbs),
            interfaces=dict(self._interfaces),
        )

    def _on_replace(self, query: zenoh.Query) -> None:
        """A new instance asks this one to stop (`mesh.instances`): stop if it may."""
        name = self.name or ""
        payload = query.payload.to_bytes() if query.payload is not None else b""
        refused = instances.accept_replace(name, payload, self._replace_token)
        if refused:
            log.warning("refused a request to make way for another %s: %s", name, refused)
            query.reply_err(f"refused: {refused}".encode())
        else:
            query.reply(query.key_expr, b"stopping")
            instances.replace_requested(name)
        query.drop()

    def _on_describe(self, query: zenoh.Query) -> None:
        query.reply(
            query.key_expr, encode(msgspec.structs.replace(self.describe(), stamp=time.time()))
        )


def open_node(
    net: NetConfig, wait: float = 0.0, name: str | None = None, on_wait: OnWait | None = None
) -> Node:
    """A node on the mesh, waiting up to `wait` s for the router to listen (`archery up &` or
    `archery router &` followed at once by a tool). Only while nothing listens: a router that
    listens yet refuses the session (another deployment's certificate) fails at the attempt after
    the one that saw it listen (the first may have come just before the router listened).

    Args:
        wait: the limit (s); 0: no wait.
        on_wait: called once with "the router at ENDPOINT" and `wait` the moment the wait
            begins (nothing listens yet); never when the router answers at once
            (`mesh.liveliness.OnWait`: the mesh layer never prints).

    Raises:
        Unreachable: no router listens at the endpoint after `wait` s.
        ConfigError: other bad settings (e.g. a missing deployment file).
    """
    deadline = time.monotonic() + wait
    announced = again = False
    while True:
        try:
            return Node(name, net)
        except Unreachable:
            left = deadline - time.monotonic()
            if left <= 0 or not net.connect:
                raise
            if listens(net.connect[0]):
                if again:  # it listened at the attempt before too: it refuses the session
                    raise
                again = True  # it may have begun to listen since the attempt: once more
                continue
            if on_wait is not None and not announced:
                on_wait(f"the router at {net.connect[0]}", wait)
                announced = True
            with contextlib.suppress(ConfigError):  # then the session says why, once more
                wait_for_endpoint(net.connect[0], left)
