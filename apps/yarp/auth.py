"""YARP's authentication in a secure deployment (YARP 3.5's AuthHMAC): the deployment's key
(`DIR/yarp/auth.conf`: `[AUTH]` `key ...`, `archery keys init`), and YARP's handshake spoken
from Python, so the bridge probes a name server with the key and checks that its own ports
refuse whoever lacks it. The handshake: the accepting side sends an 8-byte nonce n1 and
HMAC-SHA256(key, n1); the connecting side answers n2 and HMAC(key, n1‖n2); the acceptor ends
with n3 and HMAC(key, n1‖n2‖n3). A wrong digest, or 2 s without one, and YARP drops the
connection before it reads a byte of its header."""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import socket
import time
from dataclasses import dataclass
from pathlib import Path

from archery.mesh.credentials import YARP_AUTH
from archery.protocol.errors import ArcheryError, ConfigError

__all__ = ["AUTH_CONF", "NotAuthenticated", "YarpKey", "authenticate", "check_port", "read_key"]

AUTH_CONF = "auth.conf"  # the file YARP looks for (working folder, YARP_CONFIG_HOME, ..._DIRS)
NONCE, DIGEST = 8, 32
_KEY = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{15,255}$")  # a word to YARP's parser, not a number
_MOST = 4096  # bytes of an auth.conf read at most


@dataclass(frozen=True, repr=False)
class YarpKey:
    """A deployment's YARP key: the file it came from and the key's bytes."""

    path: Path
    secret: bytes

    def __repr__(self) -> str:  # the key itself is never shown
        return f"YarpKey({self.path})"


def read_key(deployment: str | Path) -> YarpKey:
    """The YARP key of the deployment folder `deployment`.

    Raises:
        ConfigError: no such file, unreadable, or not a key `archery keys` wrote (one line,
            naming the file).
    """
    path = Path(deployment) / YARP_AUTH
    make = f"`archery keys yarp {deployment}` writes one"
    try:
        with path.open("rb") as file:
            data = file.read(_MOST + 1)
    except FileNotFoundError:
        raise ConfigError(
            f"--secure {deployment}: no YARP key {path} (every YARP connection of the bridge is "
            f"authenticated with it); {make}"
        ) from None
    except OSError as exc:
        raise ConfigError(f"--secure {deployment}: cannot read {path} ({exc.strerror})") from None
    section, key = "", None
    for raw in data[:_MOST].decode("utf-8", errors="replace").splitlines():
        line = raw.strip()
        if line.startswith("["):
            section = line
        elif section == "[AUTH]" and line.split(maxsplit=1)[:1] == ["key"]:
            key = line.split(maxsplit=1)[1].strip() if len(line.split()) > 1 else ""
    if key is None or not _KEY.match(key):
        raise ConfigError(f"--secure {deployment}: {path} holds no YARP key; {make} (--force)")
    if len(key) % 16 == 8:  # YARP 3.5 would write past its copy of the key: see YARP_KEY_PREFIX
        raise ConfigError(
            f"--secure {deployment}: {path}: a key of {len(key)} characters crashes YARP 3.5; "
            f"{make} (--force)"
        )
    return YarpKey(path, key.encode())


class NotAuthenticated(ArcheryError):
    """A YARP peer that does not authenticate with the deployment's key."""

    code = "denied"


def _digest(key: YarpKey, *parts: bytes) -> bytes:
    return hmac.new(key.secret, b"".join(parts), hashlib.sha256).digest()


def _exactly(conn: socket.socket, size: int, deadline: float, what: str) -> bytes:
    data = b""
    while len(data) < size:
        left = deadline - time.monotonic()
        if left <= 0:
            raise NotAuthenticated(f"it sent no {what} in time: it does not authenticate")
        conn.settimeout(left)
        try:
            chunk = conn.recv(size - len(data))
        except TimeoutError:
            continue
        if not chunk:
            raise NotAuthenticated(f"it closed the connection before its {what}")
        data += chunk
    return data


def authenticate(conn: socket.socket, key: YarpKey, deadline: float) -> None:
    """YARP's handshake as a connecting port (YARP's `authDest`) on the connected `conn`, by
    `deadline` (time.monotonic()): afterwards `conn` is a YARP connection, as from YARP's own
    client. The socket's timeout is changed.

    Raises:
        NotAuthenticated: the peer sent no challenge in time (it does not authenticate), or one
            made with another key.
        OSError: the connection failed.
    """
    n1 = _exactly(conn, NONCE, deadline, "challenge")
    mac1 = _exactly(conn, DIGEST, deadline, "challenge")
    if not hmac.compare_digest(mac1, _digest(key, n1)):
        raise NotAuthenticated(f"it authenticates with another key than {key.path}'s")
    n2 = os.urandom(NONCE)
    conn.sendall(n2 + _digest(key, n1, n2))
    n3 = _exactly(conn, NONCE, deadline, "last word of the handshake")
    mac3 = _exactly(conn, DIGEST, deadline, "last word of the handshake")
    if not hmac.compare_digest(mac3, _digest(key, n1, n2, n3)):
        raise NotAuthenticated(f"it authenticates with another key than {key.path}'s")


def check_port(host: str, port: int, key: YarpKey, timeout: float = 5.0) -> None:
    """Connect to a YARP port and authenticate with `key`, then close: the port demands the
    deployment's key of whoever connects.

    Raises:
        NotAuthenticated: it does not (the message says how).
        OSError: nothing to connect to.
    """
    deadline = time.monotonic() + timeout
    with socket.create_connection((host, port), timeout=timeout) as conn:
        authenticate(conn, key, deadline)
