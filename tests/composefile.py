"""The compose file's YAML subset, read without a YAML library: nested `key:` blocks whose leaves
are JSON values (docker-compose.yml keeps to it, so what this reads is what a YAML parser reads)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

__all__ = ["read_compose"]

_LINE = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w-]*):(?: (?P<value>.+))?$")


def read_compose(path: Path) -> dict[str, Any]:
    """Read the compose file's YAML subset: nested `key:` blocks whose leaves are JSON values.

    Anything else (anchors, block lists, bare strings) is an error, so what this reads is what
    a YAML parser reads."""
    root: dict[str, Any] = {}
    stack: list[tuple[int, dict[str, Any]]] = [(-1, root)]
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        match = _LINE.match(line)
        assert match, f"{path.name} line {number} is outside the subset: {line!r}"
        indent = len(match["indent"])
        while indent <= stack[-1][0]:
            stack.pop()
        parent = stack[-1][1]
        assert match["key"] not in parent, f"line {number}: {match['key']!r} repeated"
        if match["value"] is None:
            parent[match["key"]] = child = {}
            stack.append((indent, child))
        else:
            parent[match["key"]] = json.loads(match["value"])
    return root
