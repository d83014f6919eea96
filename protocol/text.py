"""Received values and texts as they may appear in an error message, a log line or a counter:
one line, cut short.

A message can carry a string of megabytes (a part name, a verb, an unknown field's name); quoting
it whole would make every reply, log line and counter that names it as big. `shown` quotes a
received value: its `repr`, on one line, at most `limit` characters, a long one
cut with "… (N chars)" (or "N bytes", "N items") saying how long it was. `cut` does the same for a
text that may quote received data already (a decoder's error message). Both look only at the
first `limit` characters' worth of the value, so quoting a huge value costs no more than a short
one. Pure: no I/O.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

__all__ = ["SHOWN_LIMIT", "cut", "shown"]

SHOWN_LIMIT = 200  # characters of a quoted value, by default, "… (N chars)" included

_MAX_DEPTH = 20  # nesting levels of lists, tuples and dicts spelled out; deeper ones are cut
_LINE_BREAK = re.compile(r"\s*[\r\n]+\s*")


class _Cut(Exception):
    """Raised inside `_fragments` when the value nests deeper than `_MAX_DEPTH`."""


def _fragments(value: object, budget: int, depth: int = 0) -> Iterator[str]:
    """The pieces of `repr(value)`, in order, without building the whole of it: a string or
    bytes longer than `budget` is sliced before its repr is taken; lists, tuples and dicts are
    spelled out item by item (the consumer stops once it has enough)."""
    if isinstance(value, str | bytes | bytearray):
        yield repr(value[:budget] if len(value) > budget else value)
        return
    kind = type(value)
    if kind in (list, tuple, dict):
        if depth >= _MAX_DEPTH:
            raise _Cut
        assert isinstance(value, list | tuple | dict)
        brackets = {list: "[]", tuple: "()", dict: "{}"}[kind]
        yield brackets[0]
        if isinstance(value, dict):
            for i, (key, item) in enumerate(value.items()):
                yield ", " if i else ""
                yield from _fragments(key, budget, depth + 1)
                yield ": "
                yield from _fragments(item, budget, depth + 1)
        else:
            for i, item in enumerate(value):
                yield ", " if i else ""
                yield from _fragments(item, budget, depth + 1)
            if kind is tuple and len(value) == 1:
                yield ","
        yield brackets[1]
        return
    yield repr(value)


def _size(value: object) -> str:
    """How long `value` is, for the mark of a cut: " (N chars)", " (N bytes)", " (N items)"."""
    if isinstance(value, str):
        return f" ({len(value)} chars)"
    if isinstance(value, bytes | bytearray):
        return f" ({len(value)} bytes)"
    if type(value) in (list, tuple, dict):
        n = len(value)  # type: ignore[arg-type]  # a list, tuple or dict
        return f" ({n} item{'' if n == 1 else 's'})"
    return ""


def _ending(text: str, limit: int, mark: str) -> str:
    """The one-line `text` cut to `limit` characters, `mark` included."""
    if "\n" in text or "\r" in text:
        text = _LINE_BREAK.sub(" ", text)
    return text[: max(0, limit - len(mark))] + mark


def cut(text: str, limit: int = SHOWN_LIMIT) -> str:
    """`text` on one line (line breaks and the blanks around them become one space), at most
    `limit` characters: a longer one ends with "… (N chars)", N its length. For a text that may
    quote what was received (e.g. a decoder's error message)."""
    if "\n" in text or "\r" in text:
        text = _LINE_BREAK.sub(" ", text)
    if len(text) <= limit:
        return text
    return _ending(text, limit, f"… ({len(text)} chars)")


def shown(value: object, limit: int = SHOWN_LIMIT) -> str:
    """`repr(value)` on one line, at most `limit` characters: how a message quotes a value it
    received. A value whose repr is longer is cut and marked with "…" and its length: " (N
    chars)" for a string, " (N bytes)" for bytes, " (N items)" for a list, tuple or dict.

    Only about `limit` characters of the repr are built, however big the value (a list or dict
    nesting deeper than 20 levels is cut there)."""
    pieces: list[str] = []
    length = 0
    whole = True
    try:
        for piece in _fragments(value, limit + 1):
            pieces.append(piece)
            length += len(piece)
            if length > limit:
                whole = False
                break
    except _Cut:
        whole = False
    text = "".join(pieces)
    if whole:
        return cut(text, limit)
    return _ending(text, limit, "…" + _size(value))
