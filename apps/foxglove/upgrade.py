"""What the Foxglove server's front door checks of a WebSocket upgrade before any byte of it
reaches the SDK's server. Pure: no I/O.

- `Host`: the bound address with its port, or `localhost` / `127.0.0.1` / `[::1]` with it (the
  dashboard's rule, `apps.dashboard.guard.host_allowed`); else 421 (DNS rebinding).
- `Origin`, when sent: the Foxglove app's (`FOXGLOVE_ORIGINS`), a page of this machine
  (`http(s)://localhost`, `127.0.0.1`, `[::1]`, any port) or one added with `--allow-origin`;
  else 403. Clients that are not browsers send none.
- An operator's server: the token it printed at start in the URL's query (`?token=…`),
  compared in constant time; else 403: a connection alone never gets operator rights.
"""

from __future__ import annotations

import hmac
import ipaddress
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from archery.apps.dashboard.guard import host_allowed
from archery.protocol.errors import ConfigError
from archery.protocol.text import shown

__all__ = [
    "FOXGLOVE_ORIGINS",
    "MAX_HEAD",
    "Head",
    "Refusal",
    "UpgradeRules",
    "check_origin_flag",
    "normal_origin",
    "parse_head",
]

MAX_HEAD = 16 << 10  # bytes: the longest upgrade request head read (browsers send < 2 KiB)
#: The origins of the Foxglove app's pages: the web app, and the desktop app's renderer, a page
#: loaded from a file (Chromium and Electron name its origin `file://`).
FOXGLOVE_ORIGINS = ("https://app.foxglove.dev", "file://")
_LOCAL_NAMES = ("localhost",)
_MAX_HEADERS = 100


@dataclass(frozen=True)
class Head:
    """An HTTP request head: its method, target (path and query) and headers (names in lower
    case; a repeated header keeps every value)."""

    method: str
    target: str
    headers: dict[str, list[str]]

    def one(self, name: str) -> str | None:
        """The header's value, None when absent; raises ValueError when it is repeated."""
        values = self.headers.get(name)
        if not values:
            return None
        if len(values) > 1:
            raise ValueError(f"{name}: sent {len(values)} times")
        return values[0]


@dataclass(frozen=True)
class Refusal:
    """An upgrade refused: the HTTP status, its reason phrase and a one-line explanation (what
    the client reads and the log line names)."""

    status: int
    reason: str
    why: str

    def response(self) -> bytes:
        """The whole HTTP answer (the connection is closed after it)."""
        body = (self.why + "\n").encode()
        return (
            f"HTTP/1.1 {self.status} {self.reason}\r\nContent-Type: text/plain; charset=utf-8\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        ).encode() + body


def parse_head(data: bytes) -> Head:
    """The request head `data` (up to and with its blank line); raises ValueError naming what
    is malformed."""
    try:
        text = data.decode("latin-1")
    except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes every byte
        raise ValueError("not an HTTP request") from None
    lines = text.split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
        raise ValueError(f"not an HTTP/1.1 request line: {shown(lines[0], 80)}")
    headers: dict[str, list[str]] = {}
    fields = [line for line in lines[1:] if line]
    if len(fields) > _MAX_HEADERS:
        raise ValueError(f"{len(fields)} header lines (at most {_MAX_HEADERS})")
    for line in fields:
        name, colon, value = line.partition(":")
        if not colon or not name or name != name.strip():
            raise ValueError(f"a malformed header line: {shown(line, 80)}")
        headers.setdefault(name.lower(), []).append(value.strip())
    return Head(method=parts[0], target=parts[1], headers=headers)


def normal_origin(origin: str) -> str:
    """An origin as compared: lower case, without a trailing slash."""
    origin = origin.strip().lower()
    return origin if origin == "file://" else origin.rstrip("/")


def _local_page(origin: str) -> bool:
    """Whether `origin` is a page served by this machine: http(s) on localhost or a loopback
    address, any port."""
    url = urlsplit(origin)
    if url.scheme not in ("http", "https") or url.path or url.query or url.username:
        return False
    name = url.hostname or ""
    if name in _LOCAL_NAMES:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class UpgradeRules:
    """What one server accepts.

    Args:
        bound: the address listened on (an IP address: 0.0.0.0 inside a container), `port` its
            port.
        origins: the page origins accepted beside the Foxglove app's and local pages (normalised
            by `normal_origin`).
        token: the operator's secret (None: a read-only server, no token asked).
    """

    bound: str
    port: int
    origins: frozenset[str] = frozenset()
    token: str | None = None

    def refusal(self, head: Head) -> Refusal | None:
        """Why `head` is refused, or None when it may reach the server."""
        try:
            host, origin = head.one("host"), head.one("origin")
        except ValueError as exc:
            return Refusal(400, "Bad Request", f"refused: {exc}")
        if head.method != "GET":
            return Refusal(405, "Method Not Allowed", "a WebSocket upgrade is a GET")
        if not host_allowed(host, self.bound, self.port):
            return Refusal(
                421,
                "Misdirected Request",
                f"refused: Host {shown(host, 80)} is not this server "
                f"(connect to localhost:{self.port} or {self._where()})",
            )
        if origin is not None and not self.origin_allowed(origin):
            return Refusal(
                403,
                "Forbidden",
                f"refused: a page of {shown(origin, 80)} may not connect (only the Foxglove "
                "app and local pages; add one with --allow-origin)",
            )
        if self.token is not None and not self._token_given(head.target):
            return Refusal(
                403,
                "Forbidden",
                "refused: an operator's server needs the token of the URL it printed at start "
                "(ws://…/?token=…)",
            )
        return None

    def origin_allowed(self, origin: str) -> bool:
        """Whether a page of `origin` may connect."""
        origin = normal_origin(origin)
        return origin in FOXGLOVE_ORIGINS or origin in self.origins or _local_page(origin)

    def _token_given(self, target: str) -> bool:
        assert self.token is not None
        given = parse_qs(urlsplit(target).query).get("token", [])
        return len(given) == 1 and hmac.compare_digest(given[0].encode(), self.token.encode())

    def _where(self) -> str:
        address = ipaddress.ip_address(self.bound)
        name = f"[{address}]" if address.version == 6 else str(address)
        return f"{name}:{self.port}"


def check_origin_flag(origin: str) -> None:
    """Raise ConfigError unless `origin` (an `--allow-origin`) is an origin: scheme://host[:port]
    with nothing after, or `null` (the origin of a sandboxed frame or a file page)."""
    if origin == "null":
        return
    url = urlsplit(origin)
    if not url.scheme or not url.netloc or url.path not in ("", "/") or url.query or url.fragment:
        raise ConfigError(
            f"--allow-origin {origin!r}: give an origin, scheme://host[:port] (e.g. "
            "https://viewer.example.org)"
        )
