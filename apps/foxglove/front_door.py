"""The Foxglove server's front door: the listener users connect to, before the SDK's server.

The SDK's server shows Python nothing of an upgrade request, so it listens on an internal
loopback port behind TLS whose certificate (made at start) only the front door trusts: a web
page that finds that port cannot speak to it. The front door reads each connection's upgrade
head (at most `MAX_HEAD` bytes within `HEAD_TIMEOUT` s), checks it (`apps.foxglove.upgrade`),
only then connects to the SDK's server and relays both ways, `CHUNK` bytes at a time, reading
one side only once the other took what it was given: a client that never reads holds a few
`CHUNK`s here, and the SDK's per-client queue (`message_backlog_size`) drops its oldest
messages. At most `max_connections` at once; the next one gets 503 and is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import threading
from collections.abc import Callable

from archery.apps.foxglove.upgrade import MAX_HEAD, Refusal, parse_head
from archery.apps.foxglove.upgrade import Head as _Head
from archery.protocol.text import cut

__all__ = ["CHUNK", "HEAD_TIMEOUT", "MAX_CONNECTIONS", "FrontDoor"]

log = logging.getLogger("archery.foxglove")

HEAD_TIMEOUT = 5.0  # s: the longest wait for a connection's upgrade request head
MAX_CONNECTIONS = 16  # connections served at once (the default of --max-clients)
CHUNK = 64 << 10  # bytes: read from one side and written to the other at a time
INNER_BUFFER = 256 << 10  # bytes: the kernel's receive buffer of the link to the SDK's server
_BUSY = Refusal(503, "Service Unavailable", "the Foxglove server is full: try again later")
_LISTEN_BACKLOG = 128


class FrontDoor:
    """Listens on `host`:`port` (0: a free one) and relays checked upgrades to `inner`.

    Args:
        host, port: where users connect.
        inner: (address, port) of the SDK's server; `inner_tls` the context that trusts it.
        check: the refusal of a request head (`UpgradeRules.refusal` of the bound address), or
            None to let it through; given the bound (address, port) once listening.
        max_connections: connections at once (the next one gets 503).
    """

    def __init__(
        self,
        host: str,
        port: int,
        inner: tuple[str, int],
        inner_tls: ssl.SSLContext,
        check: Callable[[tuple[str, int]], Callable[[_Head], Refusal | None]],
        *,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        self.inner = inner
        self.inner_tls = inner_tls
        self.max_connections = max_connections
        self.open = 0  # connections open (the loop's thread only)
        self.refused = 0  # upgrades refused since start
        self._loop = asyncio.new_event_loop()
        self._tasks: set[asyncio.Task[None]] = set()
        self._ready = threading.Event()
        self._failed: BaseException | None = None
        self._server: asyncio.Server | None = None
        self._check_of = check
        self._check: Callable[[_Head], Refusal | None] = lambda head: _BUSY
        self._thread = threading.Thread(
            target=self._run, args=(host, port), name="foxglove front door", daemon=True
        )
        self._thread.start()
        self._ready.wait()
        if self._failed is not None:
            raise self._failed

    @property
    def bound(self) -> tuple[str, int]:
        """The address and port listened on."""
        assert self._server is not None
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    def _run(self, host: str, port: int) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(
                    self._serve, host, port, limit=MAX_HEAD, backlog=_LISTEN_BACKLOG
                )
            )
            self._check = self._check_of(self.bound)
        except BaseException as exc:
            self._failed = exc
            self._ready.set()
            self._loop.close()
            return
        self._ready.set()
        try:
            self._loop.run_forever()
        finally:
            self._loop.run_until_complete(self._loop.shutdown_asyncgens())
            self._loop.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            if self.open >= self.max_connections:
                self.refused += 1
                await _answer(writer, _BUSY)
                return
            self.open += 1
            try:
                await self._upgrade(reader, writer)
            finally:
                self.open -= 1
        except (OSError, asyncio.CancelledError):
            pass  # the client went, or the door closes
        finally:
            writer.close()
            self._tasks.discard(task)

    async def _upgrade(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        try:
            data = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT)
        except TimeoutError:
            log.info("%s: no request within %g s: closed", peer, HEAD_TIMEOUT)
            return
        except asyncio.LimitOverrunError:
            await _answer(writer, Refusal(431, "Request Header Fields Too Large", "too long"))
            return
        except asyncio.IncompleteReadError:
            return  # closed before its request ended
        try:
            refusal = self._check(parse_head(data))
        except ValueError as exc:
            refusal = Refusal(400, "Bad Request", cut(f"refused: {exc}"))
        if refusal is not None:
            self.refused += 1
            log.warning("%s: %s", peer, refusal.why)
            await _answer(writer, refusal)
            return
        inner_reader, inner_writer = await asyncio.open_connection(
            *self.inner,
            ssl=self.inner_tls,
            server_hostname=self.inner[0],
            limit=CHUNK,
        )
        try:
            sock = inner_writer.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, INNER_BUFFER)
            inner_writer.write(data)
            await _relay(reader, writer, inner_reader, inner_writer)
        finally:
            inner_writer.close()

    def close(self) -> None:
        """Stop listening and close every connection (idempotent)."""
        if self._loop.is_closed():
            return

        def stop() -> None:
            if self._server is not None:
                self._server.close()
            for task in list(self._tasks):
                task.cancel()
            self._loop.call_later(0.05, self._loop.stop)

        with contextlib.suppress(RuntimeError):  # the loop already stopped
            self._loop.call_soon_threadsafe(stop)
        self._thread.join(2.0)


async def _answer(writer: asyncio.StreamWriter, refusal: Refusal) -> None:
    writer.write(refusal.response())
    with contextlib.suppress(OSError, TimeoutError):
        await asyncio.wait_for(writer.drain(), 1.0)


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    """Copy `source` to `sink` until either ends, never holding more than a `CHUNK` unsent
    beyond the transport's own high-water mark (`drain`)."""
    while data := await source.read(CHUNK):
        sink.write(data)
        await sink.drain()


async def _relay(
    reader: asyncio.StreamReader,
    writer: asyncio.StreamWriter,
    inner_reader: asyncio.StreamReader,
    inner_writer: asyncio.StreamWriter,
) -> None:
    """Relay both ways until one side ends; then the other is closed."""
    ways = {
        asyncio.ensure_future(_pipe(reader, inner_writer)),
        asyncio.ensure_future(_pipe(inner_reader, writer)),
    }
    try:
        await asyncio.wait(ways, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for way in ways:
            way.cancel()
        await asyncio.gather(*ways, return_exceptions=True)
