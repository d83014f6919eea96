"""The Foxglove server's front door: the listener users connect to, before the SDK's server.

The SDK's server listens on an internal loopback port behind TLS that only the door trusts. The
door checks each connection's upgrade head (`apps.foxglove.upgrade`), then relays both ways frame
by frame, reading one side only once the other took what it was given (a client that never
reads holds a few `CHUNK`s here). It answers the clients' `fetchAsset` requests itself, one at a
time per connection between the server's frames, so the 3D panel's burst of 39 never overflows
the SDK's small per-client queue. A client that takes no byte for `STALL_AFTER` s while bytes
wait for it, or that the SDK's server closes, is dropped and logged once; at most
`max_connections` at once (the next one: 503).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import ssl
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from archery.apps.foxglove.upgrade import MAX_HEAD, Refusal, parse_head
from archery.apps.foxglove.upgrade import Head as _Head
from archery.mesh.memory import BIG_PAYLOAD, note_payload
from archery.protocol.text import cut, shown

__all__ = ["CHUNK", "HEAD_TIMEOUT", "MAX_CONNECTIONS", "STALL_AFTER", "FrontDoor", "client_name"]

log = logging.getLogger("archery.foxglove")

HEAD_TIMEOUT = 5.0  # s: the longest wait for a connection's upgrade request head
MAX_CONNECTIONS = 16  # connections served at once (the default of --max-clients)
CHUNK = 64 << 10  # bytes: read from one side and written to the other at a time
INNER_BUFFER = 256 << 10  # bytes: the kernel's receive buffer of the link to the SDK's server
STALL_AFTER = 10.0  # s: a client that takes no byte this long while bytes wait is dropped
CLOSE_WAIT = 0.5  # s: the longest a closing door waits for its relays to end
#: fetchAsset requests of one connection waiting for their answers; with more, the door reads
#: nothing more from that client until one is answered
MAX_PENDING_ASSETS = 256
MAX_REQUEST = 4096  # bytes: a client's text message the door reads for a fetchAsset
_FETCH_ASSET_RESPONSE = 4  # the ws-protocol's binary opcode of an asset's answer
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
        assets: the bytes of the asset a `fetchAsset` URI names (None: no such asset), read in
            a worker thread; the door answers those requests itself. Without it they go to the
            SDK's server.
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
        assets: Callable[[str], bytes | None] | None = None,
    ) -> None:
        self.inner = inner
        self.assets = assets
        self.dropped = 0  # clients dropped since start (stalled, or closed by the SDK)
        self.inner_tls = inner_tls
        self.max_connections = max_connections
        self.open = 0  # connections open (the loop's thread only)
        self.refused = 0  # upgrades refused since start
        self._loop = asyncio.new_event_loop()
        self._tasks: set[asyncio.Task[None]] = set()
        self._transports: set[asyncio.WriteTransport] = set()  # both sides of every connection
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
        self._transports.add(writer.transport)
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
                # what the SDK's server kept for the client (its queue of camera frames, the
                # robot description) is freed with it: given back once the closes stop coming
                note_payload(BIG_PAYLOAD)
        except (OSError, asyncio.CancelledError):
            pass  # the client went, or the door closes
        finally:
            writer.close()
            self._tasks.discard(task)
            self._transports.discard(writer.transport)

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
        self._transports.add(inner_writer.transport)
        try:
            sock = inner_writer.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, INNER_BUFFER)
            inner_writer.write(_without_extensions(data))
            link = _Link(reader, writer, inner_reader, inner_writer, self.assets)
            why = await link.relay()
            if why is not None:
                self.dropped += 1
                log.warning("%s: dropped: %s", client_name(peer), why)
        finally:
            inner_writer.close()
            self._transports.discard(inner_writer.transport)

    def close(self) -> None:
        """Stop listening and close every connection, both its sides, at once (idempotent):
        the sockets are aborted, so the SDK's server sees each of its clients gone (a link left
        open would hold its stop), and each relay is cancelled and given `CLOSE_WAIT` s to end."""
        if self._loop.is_closed():
            return

        async def stop() -> None:
            if self._server is not None:
                self._server.close()
            for transport in list(self._transports):
                transport.abort()
            tasks = list(self._tasks)
            for task in tasks:
                task.cancel()
            if tasks:
                await asyncio.wait(tasks, timeout=CLOSE_WAIT)
            self._loop.stop()

        with contextlib.suppress(RuntimeError):  # the loop already stopped
            asyncio.run_coroutine_threadsafe(stop(), self._loop)
        self._thread.join(CLOSE_WAIT + 1.0)


async def _answer(writer: asyncio.StreamWriter, refusal: Refusal) -> None:
    writer.write(refusal.response())
    with contextlib.suppress(OSError, TimeoutError):
        await asyncio.wait_for(writer.drain(), 1.0)


def client_name(peer: Any) -> str:
    """A connection's peer as `host:port` (`[host]:port` for IPv6)."""
    if isinstance(peer, tuple) and len(peer) >= 2:
        host, port = peer[0], peer[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    return str(peer)


def _without_extensions(head: bytes) -> bytes:
    """An upgrade request head without its `Sec-WebSocket-Extensions` lines: frames stay plain
    (no compression), so the door can read and insert them."""
    lines = head.split(b"\r\n")
    kept = [line for line in lines if not line.lower().startswith(b"sec-websocket-extensions:")]
    return b"\r\n".join(kept)


class _Stalled(Exception):
    """The client took no byte for `STALL_AFTER` s while bytes waited for it."""


async def _drain(writer: asyncio.StreamWriter) -> None:
    """Wait until the client took what it was given, at most `STALL_AFTER` s."""
    try:
        await asyncio.wait_for(writer.drain(), STALL_AFTER)
    except TimeoutError:
        raise _Stalled from None


@dataclass
class _Frame:
    """A WebSocket frame's header: its bytes, FIN, opcode, payload size and masking key."""

    raw: bytes
    fin: bool
    opcode: int
    size: int
    mask: bytes


async def _frame(reader: asyncio.StreamReader) -> _Frame:
    """The next frame's header (IncompleteReadError: the stream ended)."""
    raw = await reader.readexactly(2)
    size = raw[1] & 0x7F
    if size >= 126:
        more = await reader.readexactly(2 if size == 126 else 8)
        raw += more
        size = int.from_bytes(more, "big")
    mask = await reader.readexactly(4) if raw[1] & 0x80 else b""
    return _Frame(raw + mask, bool(raw[0] & 0x80), raw[0] & 0x0F, size, mask)


def _unmask(payload: bytes, mask: bytes) -> bytes:
    if not mask:
        return payload
    n = len(payload)
    key = (mask * (n // 4 + 1))[:n]
    return (int.from_bytes(payload, "big") ^ int.from_bytes(key, "big")).to_bytes(n, "big")


def _fetch_asset(text: bytes) -> tuple[str, int] | None:
    """(uri, request id) of a `fetchAsset` request; None for any other message."""
    if b"fetchAsset" not in text:
        return None
    try:
        message = json.loads(text)
    except ValueError:
        return None
    if not isinstance(message, dict) or message.get("op") != "fetchAsset":
        return None
    uri, request = message.get("uri"), message.get("requestId")
    if not isinstance(uri, str) or type(request) is not int or not 0 <= request < 1 << 32:
        return None  # malformed: the SDK's server answers it
    return uri, request


def _asset_frame(request: int, data: bytes | None, uri: str) -> bytes:
    """The server's binary frame answering fetchAsset `request`: the asset's bytes, or (None)
    an error naming `uri`."""
    error = b"" if data is not None else f"no such asset: {shown(uri)}".encode()
    status = b"\x00" if data is not None else b"\x01"
    payload = b"".join(
        (
            bytes([_FETCH_ASSET_RESPONSE]),
            request.to_bytes(4, "little"),
            status,
            len(error).to_bytes(4, "little"),
            error,
            data or b"",
        )
    )
    n = len(payload)
    if n < 126:
        head = bytes([0x82, n])
    elif n < 1 << 16:
        head = bytes([0x82, 126]) + n.to_bytes(2, "big")
    else:
        head = bytes([0x82, 127]) + n.to_bytes(8, "big")
    return head + payload


async def _copy(
    source: asyncio.StreamReader, sink: asyncio.StreamWriter, size: int, client: bool
) -> None:
    """Copy `size` bytes, `CHUNK` at a time, each taken by `sink` before the next is read (the
    client: within `STALL_AFTER` s)."""
    while size > 0:
        data = await source.read(min(CHUNK, size))
        if not data:
            raise asyncio.IncompleteReadError(b"", size)
        sink.write(data)
        await (_drain(sink) if client else sink.drain())
        size -= len(data)


class _Link:
    """One client's relay: its frames to the SDK's server, fetchAsset requests answered here;
    the server's frames to the client, the answers inserted between them."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        inner_reader: asyncio.StreamReader,
        inner_writer: asyncio.StreamWriter,
        assets: Callable[[str], bytes | None] | None,
    ) -> None:
        self.reader, self.writer = reader, writer
        self.inner_reader, self.inner_writer = inner_reader, inner_writer
        self.assets = assets
        self.requests: asyncio.Queue[tuple[str, int]] = asyncio.Queue(MAX_PENDING_ASSETS)
        self.sending = asyncio.Lock()  # held while a frame goes to the client
        self.client_closed = False  # the client sent a close frame
        self.server_closed = False  # the server sent one first: it dropped the client

    async def relay(self) -> str | None:
        """Relay until one side ends; why the client was dropped (None: it left)."""
        ways = {
            asyncio.ensure_future(self._from_client()),
            asyncio.ensure_future(self._to_client()),
        }
        if self.assets is not None:
            ways.add(asyncio.ensure_future(self._answer_assets(self.assets)))
        try:
            done, _ = await asyncio.wait(ways, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for way in ways:
                way.cancel()
            await asyncio.gather(*ways, return_exceptions=True)
        if any(not way.cancelled() and isinstance(way.exception(), _Stalled) for way in done):
            self.writer.transport.abort()  # what waits for it is dropped with it
            return f"it read nothing for {STALL_AFTER:g} s"
        if self.server_closed and not self.client_closed:
            return "the Foxglove server closed it (its queue of replies was full)"
        return None

    async def _from_client(self) -> None:
        """The client's frames to the server, its fetchAsset requests kept for `_answer_assets`."""
        fragmented = False
        with contextlib.suppress(asyncio.IncompleteReadError):
            while True:
                frame = await _frame(self.reader)
                if frame.opcode == 0x8:
                    self.client_closed = True
                if (
                    self.assets is not None
                    and frame.opcode == 0x1
                    and frame.fin
                    and not fragmented
                    and frame.size <= MAX_REQUEST
                ):
                    payload = await self.reader.readexactly(frame.size)
                    request = _fetch_asset(_unmask(payload, frame.mask))
                    if request is not None:
                        await self.requests.put(request)
                        continue
                    self.inner_writer.write(frame.raw + payload)
                    await self.inner_writer.drain()
                    continue
                if frame.opcode < 0x8:
                    fragmented = not frame.fin
                self.inner_writer.write(frame.raw)
                await _copy(self.reader, self.inner_writer, frame.size, client=False)

    async def _to_client(self) -> None:
        """The server's answer to the upgrade, then its frames, each whole."""
        async with self.sending:
            try:
                head = await self.inner_reader.readuntil(b"\r\n\r\n")
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                return
            self.writer.write(head)
            await _drain(self.writer)
        if not head.startswith(b"HTTP/1.1 101"):
            while data := await self.inner_reader.read(CHUNK):  # a refusal's body
                self.writer.write(data)
                await _drain(self.writer)
            return
        held = False
        fragmented = False
        try:
            while True:
                try:
                    frame = await _frame(self.inner_reader)
                except asyncio.IncompleteReadError:
                    return
                if frame.opcode == 0x8 and not self.client_closed:
                    self.server_closed = True
                if not held:
                    await self.sending.acquire()
                    held = True
                self.writer.write(frame.raw)
                await _copy(self.inner_reader, self.writer, frame.size, client=True)
                if frame.opcode < 0x8:
                    fragmented = not frame.fin
                if not fragmented:
                    self.sending.release()
                    held = False
        finally:
            if held:
                self.sending.release()

    async def _answer_assets(self, assets: Callable[[str], bytes | None]) -> None:
        """Answer the fetchAsset requests in turn, each between two of the server's frames."""
        while True:
            uri, request = await self.requests.get()
            try:
                data = await asyncio.to_thread(assets, uri)
            except OSError as exc:
                log.warning("asset %s: %s", shown(uri), exc)
                data = None
            frame = _asset_frame(request, data, uri)
            async with self.sending:
                self.writer.write(frame)
                await _drain(self.writer)
