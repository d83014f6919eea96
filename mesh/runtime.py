"""A service instance's runtime folder and the secret a successor must read from it.

A live instance of service NAME writes a random token to
`RUNTIME/ROBOT/NAME/ZID` (ZID: its Zenoh session id), in a folder only its user may enter
(mode 0700) and a file only its user may read (0600). A new instance started with `--replace`
on the same host reads it and puts it in its `ReplaceRequest`; the live one stops only for a
request that carries its token (`mesh.instances.accept_replace`), so a process of another user
cannot forge a replacement, whatever its command line says. RUNTIME is
`$XDG_RUNTIME_DIR/archery` when that folder exists (the user's tmpfs, emptied at logout), else
`~/.cache/archery/run`, else (a home the user cannot write) `TMP/archery-UID`; a folder of
another user there is refused.
"""

from __future__ import annotations

import contextlib
import hmac
import logging
import os
import secrets
import stat
import tempfile
from pathlib import Path

__all__ = ["ReplaceToken", "read_token", "runtime_dir"]

log = logging.getLogger("archery.node")

TOKEN_BYTES = 32  # random bytes of a token (64 hex characters)


def runtime_dir() -> Path:
    """The folder of this user's instance tokens (not created here)."""
    base = os.environ.get("XDG_RUNTIME_DIR", "")
    if base and Path(base).is_dir():
        return Path(base) / "archery"
    home = Path.home()
    cache = home / ".cache"
    if os.access(cache if cache.is_dir() else home, os.W_OK):
        return cache / "archery" / "run"
    # a container run as a user the image's home does not belong to
    return Path(tempfile.gettempdir()) / f"archery-{os.getuid()}"


def _path(robot: str, name: str, zid: str) -> Path:
    return runtime_dir() / robot / name / zid


def _private_folder(folder: Path) -> None:
    """Make `folder` (and its parents under the runtime folder) this user's alone.

    Raises:
        OSError: it cannot be made, or belongs to another user.
    """
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    for part in (folder, folder.parent, folder.parent.parent):  # NAME, ROBOT, RUNTIME
        info = part.stat()
        if info.st_uid != os.getuid():
            raise OSError(f"{part} belongs to another user")
        if stat.S_IMODE(info.st_mode) & 0o077:
            part.chmod(0o700)


class ReplaceToken:
    """This instance's token, written on creation and removed by `close`.

    `value` is "" when it could not be written (logged): then no request can stop this
    instance, which keeps running until it is stopped by a signal.
    """

    def __init__(self, robot: str, name: str, zid: str) -> None:
        self.path = _path(robot, name, zid)
        self.value = secrets.token_hex(TOKEN_BYTES)
        try:
            _private_folder(self.path.parent)
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as stream:
                stream.write(self.value)
        except OSError as exc:
            log.warning(
                "cannot write the replace token %s (%s): no --replace can stop this %s",
                self.path,
                exc,
                name,
            )
            self.value = ""

    def matches(self, proof: str) -> bool:
        """Whether `proof` is this instance's token (compared in constant time)."""
        return bool(self.value) and hmac.compare_digest(proof.encode(), self.value.encode())

    def close(self) -> None:
        """Remove the file (idempotent)."""
        if self.value:
            with contextlib.suppress(OSError):
                self.path.unlink()


def read_token(robot: str, name: str, zid: str) -> str:
    """The token of the live instance `zid` of `name`, or "" when this user cannot read one
    (another host's or another user's instance, or none)."""
    try:
        return _path(robot, name, zid).read_text()[: 2 * TOKEN_BYTES]
    except (OSError, UnicodeDecodeError):
        return ""
