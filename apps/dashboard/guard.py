"""The dashboard's HTTP server with the guards a web app on this machine needs.

- The `Host` allow-list (`host_allowed`): only the names the dashboard is reached by directly
  are answered, so a page of another site rebound to this machine (DNS rebinding) gets nothing.
- An idle timeout (`REQUEST_TIMEOUT`): a connection that does not send its request in time is
  closed, so a half-open connection does not hold a thread and a socket for ever.
- A cap on the connections served at once (`MAX_CONNECTIONS`, a thread each): a new connection
  over it closes the oldest one still waiting for its request, or, when every one is busy
  answering, gets 503 at once (`GuardedServer.process_request`).
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

__all__ = ["LISTEN_BACKLOG", "MAX_CONNECTIONS", "REQUEST_TIMEOUT", "GuardedServer", "host_allowed"]

log = logging.getLogger("archery.dashboard")

REQUEST_TIMEOUT = 10.0  # s: the longest wait for a connection's request (each read of it)
MAX_CONNECTIONS = 64  # connections served at once (a thread and a socket each)
LISTEN_BACKLOG = 128  # connections the kernel queues until the server accepts them
_BUSY = (
    b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: 37\r\n"
    b"Connection: close\r\n\r\nthe dashboard is busy: try again soon\n"
)
_LOOPBACK = (ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("::1"))


def _split_host(header: str) -> tuple[str, int | None, bool] | None:
    """A `Host` header's name, port (None: no port) and whether the name is in brackets (an
    IPv6 address), or None when it is malformed."""
    header = header.strip().lower()
    bracketed = header.startswith("[")
    if bracketed:
        name, bracket, rest = header[1:].partition("]")
        if not bracket:
            return None
    else:
        name, colon, digits = header.partition(":")
        rest = colon + digits
    if not rest:
        return name, None, bracketed
    digits = rest[1:]
    if not rest.startswith(":") or not (digits.isascii() and digits.isdigit()):
        return None
    return name, int(digits), bracketed


def host_allowed(header: str | None, bound: str, port: int) -> bool:
    """Whether a request whose `Host` header is `header` may be answered by a server bound to
    address `bound`, port `port`: `localhost`, `127.0.0.1`, `[::1]` or `bound` (bound to every
    interface: any IP address), with `port` (without one: only when `port` is 80).

    A page of another site whose name an attacker makes resolve to this machine (DNS
    rebinding) reaches the dashboard with that name in its `Host` header; only the names the
    dashboard is reached by directly are answered. A name cannot be rebound."""
    split = _split_host(header) if header else None
    if split is None:
        return False
    name, given, bracketed = split
    if (80 if given is None else given) != port:
        return False
    if name == "localhost" and not bracketed:
        return True
    try:
        address = ipaddress.ip_address(name)
    except ValueError:
        return False  # a name: what a rebinding page sends
    if bracketed != (address.version == 6):
        return False
    bound_address = ipaddress.ip_address(bound)
    return address in _LOOPBACK or address == bound_address or bound_address.is_unspecified


class GuardedServer(ThreadingHTTPServer):
    """A `ThreadingHTTPServer` (a daemon thread per connection) that times out idle
    connections after `request_timeout` s and serves at most `max_connections` at once."""

    daemon_threads = True
    request_queue_size = LISTEN_BACKLOG

    def __init__(
        self,
        address: tuple[str, int],
        handler: type[BaseHTTPRequestHandler],
        *,
        request_timeout: float = REQUEST_TIMEOUT,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        self.request_timeout = request_timeout
        self.max_connections = max_connections
        self._lock = threading.Lock()
        # each open connection -> whether it still waits for its request, oldest first
        self._open: dict[Any, bool] = {}
        super().__init__(address, handler)

    @property
    def bound(self) -> tuple[str, int]:
        """The address and port listened on."""
        host, port = self.server_address[:2]
        return str(host), int(port)

    def allows(self, host_header: str | None) -> bool:
        """Whether a request with this `Host` header is answered (`host_allowed`)."""
        return host_allowed(host_header, *self.bound)

    def connections(self) -> tuple[int, int]:
        """(connections open, of which still waiting for their request)."""
        with self._lock:
            return len(self._open), sum(self._open.values())

    def process_request(self, request: Any, client_address: Any) -> None:
        """Serve a new connection on a thread of its own; over `max_connections`, close the
        oldest one still waiting for its request (an idle connection gives way to one that
        asks), or, when every one is busy answering, answer 503 at once."""
        evicted = None
        with self._lock:
            full = len(self._open) >= self.max_connections
            if full:
                evicted = next((c for c, waiting in self._open.items() if waiting), None)
                if evicted is not None:
                    del self._open[evicted]
            if not full or evicted is not None:
                self._open[request] = True
        if evicted is not None:
            _hang_up(evicted)  # its thread reads the end of the stream and closes it
        elif full:
            self._refuse(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._forget(request)
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._forget(request)

    def started(self, request: Any) -> bool:
        """The connection's request has arrived: it no longer gives way to a new connection;
        False when it was closed for one already."""
        with self._lock:
            if request not in self._open:
                return False
            self._open[request] = False
            return True

    def _forget(self, request: Any) -> None:
        with self._lock:
            self._open.pop(request, None)

    def _refuse(self, request: socket.socket) -> None:
        """Answer 503 without waiting (the accepting thread must not block) and close."""
        try:
            request.setblocking(False)
            request.send(_BUSY)
        except OSError:
            pass
        self.shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A connection's failure (a client gone mid-answer) is logged, never printed."""
        log.debug("connection from %s failed", client_address, exc_info=True)


def _hang_up(connection: socket.socket) -> None:
    with contextlib.suppress(OSError):
        connection.shutdown(socket.SHUT_RDWR)
