"""The whole shot's demonstration files: the one shipped with the controller
(`demonstrations/README.md`) and the bounded reader of a file a user names."""

from __future__ import annotations

from pathlib import Path

from archery.mesh.regular_file import FileRefused, read_regular
from archery.protocol.demonstration import (
    MAX_BYTES,
    BadDemonstration,
    Demonstration,
    parse_demonstration,
)
from archery.protocol.errors import ConfigError

__all__ = ["SHIPPED_DEMONSTRATION", "read_demonstration"]

#: The demonstration of the whole shot that ships with the package (`demonstrations/README.md`).
SHIPPED_DEMONSTRATION = Path(__file__).parent / "demonstrations" / "whole-shot.json"


def read_demonstration(
    path: str | Path | None = None, flag: str = "--demonstration"
) -> Demonstration:
    """The whole shot's demonstration at `path` (None: `SHIPPED_DEMONSTRATION`), checked
    (`parse_demonstration`); its errors name the `flag` that gave it ("" for a positional
    argument). Used by `archery demonstrate --check`, `imitate` and the
    controller: only a regular file is read (a folder, a FIFO or a device is refused without
    a blocking open), and at most `MAX_BYTES` + 1 bytes of it (`mesh.regular_file`).

    Raises:
        ConfigError: it cannot be read, is not a regular file, is too large, or is not a valid
            demonstration (one line).
    """
    path = Path(path or SHIPPED_DEMONSTRATION)
    named = f"{flag} {path}" if flag else str(path)
    try:
        return parse_demonstration(read_regular(path, MAX_BYTES))
    except FileRefused as refused:
        if refused.problem == "cannot_open":
            why = f"cannot read it ({refused.detail})"
        elif refused.problem == "not_regular":
            why = f"not a regular file ({refused.detail})"
        else:
            size = f"{refused.size} bytes" if refused.problem == "too_large" else "more"
            why = f"too large: {size}, a demonstration file holds at most {MAX_BYTES} bytes"
        raise ConfigError(f"{named}: {why}") from None
    except BadDemonstration as exc:
        raise ConfigError(f"{named}: {exc.message}") from None
