"""What a reader of a recording trusts of it: the limits of `apps.topics.mcap_reader` and the
`--max-bytes` flag that sets one of them, and `printable`, how text read from a file (a topic,
a schema or attachment name, metadata) is shown.

No MCAP library here, so a verb can add the flag without the `record` extra.
"""

from __future__ import annotations

import argparse
import re

__all__ = [
    "MAX_EXPANSION",
    "MAX_RECORD_BYTES",
    "MAX_TIME_NS",
    "MAX_TOTAL_BYTES",
    "add_max_bytes_arg",
    "byte_size",
    "printable",
    "size_text",
    "total_cap",
]

MAX_RECORD_BYTES = 256 << 20  # one record as stored, and one chunk decompressed (bytes)
MAX_TOTAL_BYTES = 1 << 30  # the whole decompressed total's cap at least (bytes)
MAX_EXPANSION = 64  # ... and at least this many times the file's size
MAX_TIME_NS = (1 << 63) - 1  # ns since the epoch as an int64: 2262-04-11T23:47:16Z

_UNPRINTABLE = re.compile(
    r"[^\S ]|[\x00-\x1f\x7f-\x9f\u00ad\u200b-\u200f\u2028-\u202e\u2060-\u206f]"
)


def printable(text: str) -> str:
    """`text` with every control or invisible formatting character escaped as Python writes it
    (ESC as `\\x1b`, U+202E as `\\u202e`), so text read from a file cannot drive a terminal."""
    if text.isprintable():
        return text

    def escape(match: re.Match[str]) -> str:
        code = ord(match.group())
        return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"

    return _UNPRINTABLE.sub(escape, text)


def size_text(n: int) -> str:
    """A byte count for a message: "256 MiB", "1.5 GiB", "19 kB"-style, binary units."""
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if value < 1024 or unit == "TiB":
            return f"{n} B" if unit == "B" else f"{value:.4g} {unit}"
        value /= 1024
    return f"{n} B"


_SIZE = re.compile(r"(\d+)\s*([kmgt]?)(?:i?b)?", re.IGNORECASE)


def byte_size(text: str) -> int:
    """A `--max-bytes` value: bytes, or with a binary unit (512M, 4G, 4GiB); 0 for no cap.

    Raises:
        ValueError: anything else (argparse turns it into a usage error).
    """
    match = _SIZE.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"not a byte count: {text!r} (give e.g. 4G, 512M or 0 for no cap)")
    scale = 1 << (10 * " kmgt".index(match.group(2).lower() or " "))
    return int(match.group(1)) * scale


def add_max_bytes_arg(parser: argparse.ArgumentParser) -> None:
    """The `--max-bytes N` flag of a verb that reads recordings (`byte_size`; default None)."""
    parser.add_argument(
        "--max-bytes",
        type=byte_size,
        default=None,
        metavar="N",
        help="the most the file's chunks may decompress to in all (bytes, or 512M, 4G; 0: no "
        f"cap; default the greater of {MAX_TOTAL_BYTES >> 30} GiB and {MAX_EXPANSION} times the "
        "file's size)",
    )


def total_cap(file_size: int, max_bytes: int | None = None) -> int | None:
    """The whole decompressed total (bytes) a file of `file_size` bytes may give: `max_bytes`
    if given (0: no cap, None), else the greater of `MAX_TOTAL_BYTES` and `MAX_EXPANSION`
    times the file's size."""
    if max_bytes is not None:
        return max_bytes or None
    return max(MAX_TOTAL_BYTES, MAX_EXPANSION * file_size)
