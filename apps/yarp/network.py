"""YARP's network for the bridge: its ports on loopback (or `--yarp-ip`), its name server, and
YARP's library initialised, all by one deadline (`start`).

The name server is, in this order: `--yarp-server HOST:PORT`; the one the user's YARP
configuration names (`yarp conf`), when it answers; or one the bridge runs itself, YARP's own
`yarpserver`, on a free port of the bridge's address, with a configuration of its own (the
user's is never written), its multicast fallback on a UDP port of its own. With a YARP key
(`--secure`) every process of the bridge's authenticates, and a name server that does not is
refused. The environment YARP reads is set here, before YARP is imported.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from archery.apps.up.child import popen_tied
from archery.apps.yarp.auth import AUTH_CONF, NotAuthenticated, YarpKey, authenticate
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.text import shown

__all__ = [
    "YARP_MISSING",
    "NameServer",
    "YarpNetwork",
    "free_server_port",
    "parse_server",
    "stop_group",
    "user_server",
]

YARP_MISSING = (
    "YARP's Python bindings are not installed: install YARP 3.5 (robotology-superbuild, "
    "conda-forge's `yarp`, or `make yarp` in the project's checkout) into this environment"
)
log = logging.getLogger("archery.yarp")
_CONF = "yarp.conf"  # the default namespace's file in YARP's configuration folder


@dataclass(frozen=True)
class NameServer:
    """Where a YARP name server listens, and who runs it ("given", "configured", "ours")."""

    host: str
    port: int
    origin: str

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_server(text: str) -> NameServer:
    """`HOST:PORT` of `--yarp-server`.

    Raises:
        ConfigError: not a host and a port from 1 to 65535.
    """
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--yarp-server {shown(text)}: give HOST:PORT, e.g. 127.0.0.1:10000")
    return NameServer(host.strip("[]"), int(port), "given")


def _config_home() -> Path:
    """YARP's configuration folder as YARP 3.5 finds it on Linux."""
    if home := os.environ.get("YARP_CONFIG_HOME"):
        return Path(home)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "yarp"


def user_server() -> NameServer | None:
    """The name server the user's YARP configuration names (None: none, or not readable)."""
    try:
        words = (_config_home() / _CONF).read_text(encoding="utf-8").split()
    except (OSError, UnicodeDecodeError):
        return None
    if len(words) < 2 or not words[1].isdigit():
        return None
    return NameServer(words[0], int(words[1]), "configured")


def user_key() -> YarpKey | None:
    """The YARP key the user's YARP would authenticate with (YARP's AuthHMAC): the `[AUTH]` key
    of an auth.conf in the working folder, else in YARP's configuration folder, as YARP 3.5
    looks (None: neither holds one)."""
    for folder in (Path.cwd(), _config_home()):
        path = folder / AUTH_CONF
        try:
            text = path.read_text(encoding="utf-8", errors="replace")[:_MOST]
        except OSError:
            continue
        section = ""
        for raw in text.splitlines():
            line = raw.strip()
            if line.startswith("["):
                section = line
            elif section == "[AUTH]" and len(line.split()) > 1 and line.split()[0] == "key":
                return YarpKey(path, line.split(maxsplit=1)[1].strip().encode())
    return None


class NotANameServer(ArcheryError):
    """Something answers at the name server's address, but not as a YARP name server."""

    code = "bad_state"


_QUERY = b"NAME_SERVER query /root\n"  # YARP's name server also speaks text, line by line
_END = b"*** end of message"
_MOST = 4096  # bytes of an answer read at most


def _answers(server: NameServer, deadline: float, key: YarpKey | None = None) -> bool:
    """True once `server` answers a name query as a YARP name server (with `key`: after YARP's
    handshake with it), False while nothing listens there; by `deadline` (time.monotonic()).

    Raises:
        NotANameServer: what answers is not one (the message quotes what it sent), does not
            authenticate with `key`, or is silent until `deadline`.
    """
    try:
        with socket.create_connection(
            (server.host, server.port), timeout=max(deadline - time.monotonic(), 0.01)
        ) as conn:
            if key is not None:
                authenticate(conn, key, deadline)
            conn.sendall(_QUERY)
            answer = b""
            while _END not in answer and len(answer) < _MOST:
                conn.settimeout(max(deadline - time.monotonic(), 0.01))
                chunk = conn.recv(_MOST)
                if not chunk:
                    break
                answer += chunk
    except ConnectionRefusedError:
        return False
    except NotAuthenticated as exc:
        raise NotANameServer(f"the YARP name server at {server}: {exc}") from None
    except OSError as exc:
        raise NotANameServer(f"the YARP name server at {server} does not answer: {exc}") from None
    if answer.strip() == _END:  # a name server that has not registered itself yet
        return False
    if b"registration name /root" not in answer:
        text = answer.decode("utf-8", errors="replace")
        raise NotANameServer(
            f"what answers at {server} is not a YARP name server: it sent {shown(text)}"
        )
    return True


#: where a name server of the bridge's own listens: below the ports this machine hands out for
#: outgoing connections (Linux: from 32768), for YARP numbers the ports it registers in a row
#: from the name server's, and a number taken by a connection would fail to bind
SERVER_PORTS = range(20000, 32000, 100)
SERVER_BLOCK = 64  # the ports after a name server's that must be free when it starts


def free_server_port(host: str) -> int:
    """A port for a YARP name server on `host` whose next `SERVER_BLOCK` ports are free too.

    Raises:
        ConfigError: no such block is free.
    """
    for base in random.sample(SERVER_PORTS, len(SERVER_PORTS)):
        try:
            with contextlib.ExitStack() as held:
                for port in range(base, base + SERVER_BLOCK):
                    probe = held.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
                    probe.bind((host, port))
            return base
        except OSError:
            continue
    raise ConfigError(f"no free block of {SERVER_BLOCK} ports on {host} for a YARP name server")


def _yarpserver() -> str:
    """YARP's `yarpserver`: the program itself where the `yarp` package holds it (its Python
    launcher would outlive a bridge that dies), else the launcher beside this Python."""
    spec = importlib.util.find_spec("yarp")  # found, not imported: YARP's environment is not set
    for folder in (spec.submodule_search_locations or []) if spec else []:
        if (binary := Path(folder) / "bin" / "yarpserver").is_file():
            return str(binary)
    here = Path(sys.executable).parent / "yarpserver"
    found = str(here) if here.exists() else shutil.which("yarpserver")
    if found is None:
        raise ConfigError(
            "no yarpserver to run (it comes with YARP's tools); give --yarp-server HOST:PORT"
        )
    return found


def _package_dirs() -> dict[str, str]:
    """YARP's data and plugin folders in the `yarp` package, as its import sets them (for its
    programs run without their launcher)."""
    spec = importlib.util.find_spec("yarp")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        here = Path(folder)
        if (here / "share" / "yarp").is_dir():
            return {
                "YARP_DATA_DIRS": str(here / "share" / "yarp"),
                "YARP_PLUGINS_DIR": str(here / "lib" / "yarp"),
            }
    return {}


def stop_group(proc: subprocess.Popen[Any]) -> None:
    """Stop `proc` and what it started (a Python launcher of YARP's tools runs the tool as its
    child): SIGTERM to its process group, SIGKILL after 5 s (a tool that closes its ports
    slowly, as `yarp read` can on a loaded machine, does not hold up its caller)."""
    for sig, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, None)):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _answering(server: NameServer | None, key: YarpKey | None) -> NameServer | None:
    """`server` (the user's configured one) if it answers as a name server (with `key`, one
    that authenticates with it), else None."""
    if server is None:
        return None
    try:
        return server if _answers(server, time.monotonic() + 1.0, key) else None
    except NotANameServer as exc:
        log.warning("%s; the bridge runs a name server of its own", exc)
        return None


def _fallback_port() -> int:
    """A free UDP port for the multicast fallback of a `yarpserver` of the bridge's own
    (`YARP_PORT_RANGE`), so that it never meets another's: YARP 3.5 built without ACE binds
    that port for its sender without sharing it, and a second yarpserver on the same port
    exits; so bound, the fallback never listens (with ACE it would take name-server commands,
    unauthenticated, from any UDP datagram)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("0.0.0.0", 0))
        return int(probe.getsockname()[1])


class YarpNetwork:
    """YARP set up for the bridge until `close`: the environment, the name server, `yarp`
    imported and initialised (`self.yarp`, after `start`).

    Args:
        ip: the address YARP's ports register and listen on.
        server: the name server to use (None: the user's, else one of the bridge's own).
        key: the deployment's YARP key (`--secure`): every connection of the bridge's, and of its
            own name server, authenticates with it; None: none does (YARP's default).
    """

    def __init__(self, ip: str, server: NameServer | None, key: YarpKey | None = None) -> None:
        self.ip, self.key = ip, key
        self.server: NameServer | None = server
        self.stage = "probing the name server"  # what `start` does now, for a late start's words
        self.yarp: Any = None
        self._own: subprocess.Popen[bytes] | None = None
        self._initialised = False
        self._folder: tempfile.TemporaryDirectory[str] | None = None

    def start(self, deadline: float) -> None:
        """Find or run the name server, import YARP and initialise it, by `deadline`
        (time.monotonic()). YARP's own calls cannot be interrupted: a server that hangs inside
        one is for the caller to give up on (`abandon`).

        Raises:
            ConfigError: YARP is not installed, or no name server can be had.
            ArcheryError: the name server does not answer (as one) by `deadline`.
        """
        os.environ["YARP_IP"] = self.ip
        server = self.server
        if server is None:
            server = _answering(user_server(), self.key)
        if server is None:
            server = NameServer(self.ip, free_server_port(self.ip), "ours")
            folder = self._private(server)
            env = {**os.environ, "YARP_PORT_RANGE": str(_fallback_port())}
            with open(folder / "yarpserver.log", "wb") as out:  # its registrations, each a line
                self._own = popen_tied(  # it dies with the bridge, even a crashed one
                    [_yarpserver(), "--read", "--socket", str(server.port)],
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    cwd=folder,  # YARP reads an auth.conf of its working folder first
                    env={**_package_dirs(), **env},
                    start_new_session=True,  # a launcher script and the server: one group
                )
        elif server.origin == "given" or self.key is not None:
            self._private(server)
        self.server = server
        while not self._answers(server, deadline):
            if self._own is not None and self._own.poll() is not None:
                assert self._folder is not None
                log_file = Path(self._folder.name) / "yarpserver.log"
                text = log_file.read_text(encoding="utf-8", errors="replace")
                raise ArcheryError(f"yarpserver on {server} exited: {shown(text.strip()[-300:])}")
            if time.monotonic() > deadline:
                raise ArcheryError(f"no YARP name server answers at {server} by --wait")
            time.sleep(0.05)
        self.stage = "initialising YARP"
        try:
            import yarp
        except ImportError:
            raise ConfigError(YARP_MISSING) from None
        self.yarp = yarp
        yarp.Network.init()
        self._initialised = True
        self.stage = "checking the name server with YARP"
        if not yarp.Network.checkNetwork(max(deadline - time.monotonic(), 0.1)):
            raise ArcheryError(f"the YARP name server at {server} does not answer as one")
        self.stage = "registering the bridge's ports"

    def _answers(self, server: NameServer, deadline: float) -> bool:
        return _answers(server, min(deadline, time.monotonic() + 1.0), self.key)

    def _private(self, server: NameServer) -> Path:
        """A configuration folder of the bridge's own (0700) that names `server` and holds the
        deployment's YARP key, if any."""
        self._folder = tempfile.TemporaryDirectory(prefix="archery-yarp-")
        folder = Path(self._folder.name)
        (folder / _CONF).write_text(f"{server.host} {server.port} yarp\n")
        if self.key is not None:
            fd = os.open(folder / AUTH_CONF, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as out:
                out.write(b"[AUTH]\nkey " + self.key.secret + b"\n")
        os.environ["YARP_CONFIG_HOME"] = str(folder)
        return folder

    def abandon(self) -> None:
        """What `close` does without YARP's own calls: for a start stuck inside one of them,
        before the process ends."""
        self._initialised = False
        self.close()

    def close(self) -> None:
        """Stop the bridge's own name server, if it runs one, and drop its configuration."""
        if self._initialised:
            self._initialised = False
            self.yarp.Network.fini()
        if self._own is not None:
            stop_group(self._own)
            self._own = None
        if self._folder is not None:
            self._folder.cleanup()
            self._folder = None
