"""Text of verb schemas: a JSON schema (msgspec.json.schema) as field, type, constraint, default.

Used by the RPC server's error messages (the allowed values of a field) and by
`archery interface` / `archery ports --verbose` (a verb's argument and reply tables).
"""

from __future__ import annotations

import json
import sys
from typing import Any

__all__ = ["field_text", "fields_of", "render_verb", "type_text"]


def _num(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _lengths(low: int | None, high: int | None, what: str) -> str:
    if low is not None and low == high:
        return f"{what} {low}"
    parts = []
    if low is not None and low > 0:
        parts.append(f"{what} >= {low}")
    if high is not None:
        parts.append(f"{what} <= {high}")
    return ", ".join(parts)


def _range(s: dict[str, Any]) -> str:
    low = ("[", s["minimum"]) if "minimum" in s else ("(", s.get("exclusiveMinimum"))
    high = ("]", s["maximum"]) if "maximum" in s else (")", s.get("exclusiveMaximum"))
    if low[1] is not None and high[1] is not None:
        return f" in {low[0]}{_num(low[1])}, {_num(high[1])}{high[0]}"
    if low[1] is not None:
        return f" {'>=' if low[0] == '[' else '>'} {_num(low[1])}"
    if high[1] is not None:
        return f" {'<=' if high[0] == ']' else '<'} {_num(high[1])}"
    return ""


def type_text(s: dict[str, Any], defs: dict[str, Any] | None = None) -> str:
    """One schema as a short type with its constraints and unit, e.g. `float in [0.05, 60] (s)`."""
    defs = defs or {}
    if "$ref" in s:
        ref: str = s["$ref"]
        return ref.rsplit("/", 1)[-1]
    if "anyOf" in s:
        return " | ".join(type_text(x, defs) for x in s["anyOf"])
    unit = f" ({s['description']})" if "description" in s else ""
    if "enum" in s:
        return "one of " + ", ".join(json.dumps(v) for v in s["enum"]) + unit
    if "const" in s:
        return json.dumps(s["const"]) + unit
    kind = s.get("type")
    if kind is None:
        text = "any"
    elif kind == "array":
        text = f"list[{type_text(s.get('items', {}), defs)}]"
        lengths = _lengths(s.get("minItems"), s.get("maxItems"), "length")
        text += f" {lengths}" if lengths else ""
    elif kind == "object":
        values = s.get("additionalProperties")
        text = f"map[str, {type_text(values, defs)}]" if isinstance(values, dict) else "map"
    elif kind in ("number", "integer"):
        if s.get("minimum") == -sys.float_info.max and s.get("maximum") == sys.float_info.max:
            text = "finite float"  # `protocol.messages.FiniteFloat`
        else:
            text = ("float" if kind == "number" else "int") + _range(s)
    elif kind == "string":
        text = "bytes" if s.get("contentEncoding") == "base64" else "str"
        lengths = _lengths(s.get("minLength"), s.get("maxLength"), "length")
        text += f" {lengths}" if lengths else ""
    else:
        text = {"boolean": "bool", "null": "null"}.get(kind, str(kind))
    return text + unit


def fields_of(schema: dict[str, Any], name: str | None = None) -> tuple[str, list[tuple[str, ...]]]:
    """(struct name, [(field, type text, "required" or "default VALUE")]) of a struct's schema
    (the top-level one of a `msgspec.json.schema` result, or `name` from its $defs)."""
    defs = schema.get("$defs", {})
    ref = name or schema.get("$ref", "").rsplit("/", 1)[-1]
    body = defs.get(ref, schema)
    required = set(body.get("required", ()))
    rows: list[tuple[str, ...]] = []
    for field, prop in body.get("properties", {}).items():
        if field in required:
            presence = "required"
        elif "default" in prop:
            presence = f"default {json.dumps(prop['default'])}"
        else:
            presence = "optional"
        rows.append((field, type_text(prop, defs), presence))
    return ref or body.get("title", "?"), rows


def _struct_of(prop: dict[str, Any]) -> str | None:
    """The struct a property holds ($ref, possibly inside an anyOf with null), if any."""
    if "$ref" in prop:
        return str(prop["$ref"]).rsplit("/", 1)[-1]
    refs = [x["$ref"] for x in prop.get("anyOf", ()) if "$ref" in x]
    return str(refs[0]).rsplit("/", 1)[-1] if len(refs) == 1 else None


def field_text(schema: dict[str, Any], path: str) -> tuple[str, str] | None:
    """(dotted field name, type text) of the field a msgspec error path points into, e.g.
    `$.scenario.hit_radius` -> ("scenario.hit_radius", "float in [0.001, 0.25] (m)"), walking
    into nested structs; None when the path names no field."""
    defs = schema.get("$defs", {})
    body = defs.get(schema.get("$ref", "").rsplit("/", 1)[-1], schema)
    names = [part.split("[")[0] for part in path.split(".")[1:]]
    for i, name in enumerate(names):
        prop = body.get("properties", {}).get(name)
        if prop is None:
            return None
        nested = _struct_of(prop)
        if nested is None or i == len(names) - 1:
            return ".".join(names[: i + 1]), type_text(prop, defs)
        body = defs.get(nested, {})
    return None


def _table(title: str, schema: dict[str, Any], indent: str) -> list[str]:
    name, rows = fields_of(schema)
    lines = [f"{indent}{title}: {name}"]
    if not rows:
        return [*lines[:-1], f"{indent}{title}: {name} (no fields)"]
    width = max(len(r[0]) for r in rows)
    typew = max(len(r[1]) for r in rows)
    lines += [f"{indent}  {f.ljust(width)}  {t.ljust(typew)}  {p}" for f, t, p in rows]
    # nested structs (e.g. a scenario inside the arguments), once each
    defs = schema.get("$defs", {})
    for nested in defs:
        if nested != name:
            _, nested_rows = fields_of(schema, nested)
            lines.append(f"{indent}  {nested}:")
            w = max((len(r[0]) for r in nested_rows), default=0)
            tw = max((len(r[1]) for r in nested_rows), default=0)
            lines += [f"{indent}    {f.ljust(w)}  {t.ljust(tw)}  {p}" for f, t, p in nested_rows]
    return lines


def render_verb(name: str, entry: dict[str, Any], indent: str = "") -> list[str]:
    """Lines describing one verb: its doc, then its argument and reply tables."""
    lines = [f"{indent}{name}  — {entry.get('doc', '')}".rstrip(" —")]
    lines += _table("args", entry.get("args", {}), indent + "  ")
    lines += _table("reply", entry.get("reply", {}), indent + "  ")
    return lines
