"""A service's config fields that are also its command-line flags, each described once.

A frozen config dataclass declares its settable fields with `flag(default, help, unit=…,
low=…, high=…)`. From that one declaration `add_config_args` adds the flags (typed, with help
texts stating the unit, the valid range and the default), `config_from_args` builds the config
from the parsed flags, and `check_bounds`, called in `__post_init__`, checks every field, so a
config built in code is checked like one built from flags.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

from archery.protocol.errors import ConfigError

__all__ = [
    "FlagSpec",
    "add_config_args",
    "check_bounds",
    "config_from_args",
    "config_number",
    "flag",
]

_KEY = "archery.flag"


def config_number(
    name: str,
    value: object,
    low: float,
    high: float,
    unit: str = "",
    *,
    low_open: bool = False,
) -> float:
    """`value` as a float in [low, high] ((low, high] with `low_open`), in `unit`.

    Raises:
        ConfigError: not a finite number, or out of range; the message names `name`.
    """
    suffix = f" {unit}" if unit else ""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number{suffix}, got {value!r}")
    above = low < value if low_open else low <= value
    if not (above and value <= high):
        bracket = "(" if low_open else "["
        raise ConfigError(f"{name} must be in {bracket}{low:g}, {high:g}]{suffix}, got {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class FlagSpec:
    """What `flag` records on a field (see `flag` for the meaning of each attribute)."""

    help: str
    unit: str = ""
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: tuple[str, ...] | None = None
    parse: Callable[[str], Any] | None = None
    metavar: str | None = None
    name: str | None = None
    cli: bool = True

    def option(self, field_name: str) -> str:
        """The flag that sets the field, e.g. `--state-rate` for `state_rate`."""
        return self.name or "--" + field_name.replace("_", "-")

    def range_text(self) -> str:
        """The valid range as help text: `0.1..120`, `>= 0`, `(0, 60]`; "" if unbounded."""
        low, high = self.low, self.high
        if low is not None and high is not None:
            return f"({low:g}, {high:g}]" if self.low_open else f"{low:g}..{high:g}"
        if low is not None:
            return f"> {low:g}" if self.low_open else f">= {low:g}"
        return "" if high is None else f"<= {high:g}"


def flag(
    default: Any,
    help: str,
    *,
    unit: str = "",
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    choices: Sequence[str] | None = None,
    parse: Callable[[str], Any] | None = None,
    metavar: str | None = None,
    name: str | None = None,
    cli: bool = True,
) -> Any:
    """A dataclass field that is also a command-line flag.

    Args:
        default: the field's default (also the flag's). Must be immutable.
        help: what the setting does; the unit, range and default are appended.
        unit: the value's unit ("s", "Hz", "px", "rad"), in help and error messages.
        low, high: the valid range (inclusive; `low_open` excludes `low`); None: unbounded.
        choices: the valid values of a text setting.
        parse: turns the flag's text into the field's value (e.g. `parse_source`); it raises
            `ConfigError` for bad text.
        metavar: the value's name in the usage text.
        name: the option, when it is not `--` + the field's name with dashes (also used in
            error messages), e.g. `--no-torso`.
        cli: False for a checked field that no flag of its own sets (the service sets it from
            another flag).
    """
    spec = FlagSpec(
        help=help,
        unit=unit,
        low=low,
        high=high,
        low_open=low_open,
        choices=None if choices is None else tuple(choices),
        parse=parse,
        metavar=metavar,
        name=name,
        cli=cli,
    )
    return dataclasses.field(default=default, metadata={_KEY: spec})


@functools.cache
def _fields(cls: type) -> tuple[tuple[dataclasses.Field[Any], type | None, bool], ...]:
    """Each field of `cls` with its base type (None if not a plain class) and optionality."""
    hints = get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        kind: Any = hints[f.name]
        optional = False
        if get_origin(kind) in (Union, types.UnionType):
            args = [a for a in get_args(kind) if a is not type(None)]
            optional = len(args) < len(get_args(kind))
            kind = args[0] if len(args) == 1 else None
        plain = isinstance(kind, type) and get_origin(kind) is None
        out.append((f, kind if plain else None, optional))
    return tuple(out)


def _spec(f: dataclasses.Field[Any]) -> FlagSpec | None:
    return f.metadata.get(_KEY)


def _help(spec: FlagSpec, default: Any) -> str:
    notes = [n for n in (spec.unit, spec.range_text()) if n]
    if isinstance(default, bool):
        pass
    elif isinstance(default, int | float | str | Path):
        notes.append(f"default {default:g}" if isinstance(default, float) else f"default {default}")
    return f"{spec.help} ({'; '.join(notes)})" if notes else spec.help


def add_config_args(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add a flag for every `flag` field of the dataclass `cls`: `--state-rate` for
    `state_rate` (the option may be renamed with `name=`), typed from the field's annotation,
    with the field's default and a help text that states the unit, the valid range and the
    default; a bool field becomes a switch (`--no-NAME` when its default is True)."""
    for f, kind, _ in _fields(cls):
        spec = _spec(f)
        if spec is None or not spec.cli:
            continue
        option = spec.option(f.name)
        if kind is bool:
            action = "store_false" if f.default else "store_true"
            parser.add_argument(option, dest=f.name, action=action, help=spec.help)
            continue
        typed = kind if kind in (int, float, Path) and spec.parse is None else str
        parser.add_argument(
            option,
            dest=f.name,
            type=typed,
            default=f.default,
            choices=spec.choices,
            metavar=spec.metavar,
            help=_help(spec, f.default),
        )


def config_from_args(cls: type, args: argparse.Namespace, **fixed: Any) -> Any:
    """The config `cls` from parsed flags (`add_config_args`) and the `fixed` values (those
    the flags do not give: `net=…`, nested configs); a field's `parse` runs on its text.

    Raises:
        ConfigError: a bad value; the message names the flag and what is valid.
    """
    values: dict[str, Any] = {}
    for f, _, _ in _fields(cls):
        spec = _spec(f)
        if spec is None or not spec.cli or f.name in fixed or not hasattr(args, f.name):
            continue
        value = getattr(args, f.name)
        if spec.parse is not None and isinstance(value, str):
            value = spec.parse(value)
        values[f.name] = value
    return cls(**values, **fixed)


def _integer(label: str, value: Any, spec: FlagSpec) -> int:
    low, high = spec.low, spec.high
    valid = isinstance(value, int) and not isinstance(value, bool)
    valid = valid and (low is None or value >= low) and (high is None or value <= high)
    if not valid:
        within = spec.range_text().replace("..", ", ")
        within = f" in [{within}]" if low is not None and high is not None else f" {within}"
        unit = f" {spec.unit}" if spec.unit else ""
        raise ConfigError(f"{label} must be an integer{within.rstrip()}{unit}, got {value!r}")
    return int(value)


def _checked(label: str, value: Any, kind: type | None, spec: FlagSpec | None) -> Any:
    """`value` checked against the field's type and declaration (maybe converted)."""
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{label} must be true or false, got {value!r}")
    elif kind is float and spec is not None:
        low = -math.inf if spec.low is None else spec.low
        high = math.inf if spec.high is None else spec.high
        return config_number(label, value, low, high, spec.unit, low_open=spec.low_open)
    elif kind is int and spec is not None:
        return _integer(label, value, spec)
    elif spec is not None and spec.choices is not None:
        if value not in spec.choices:
            raise ConfigError(f"{label} {value!r} is not one of {', '.join(spec.choices)}")
    elif kind is Path and isinstance(value, str):
        return Path(value)
    elif kind is not None and kind not in (int, float) and not isinstance(value, kind):
        raise ConfigError(f"{label} must be a {kind.__name__}, got {value!r}")
    return value


def check_bounds(config: Any) -> None:
    """Check every field of the dataclass instance `config` (call it in `__post_init__`)
    against its declaration, so a config built in code is checked like one built from flags.

    Numbers must lie in their declared range (floats are stored as float), integers be
    integers, text be one of its choices, bools be bools and nested configs of their
    annotated class. Fields annotated `X | None` may be None.

    Raises:
        ConfigError: the first bad field; the message names its flag (or field) and what is
            valid.
    """
    cls: type = type(config)
    for f, kind, optional in _fields(cls):
        value = getattr(config, f.name)
        if value is None and optional:
            continue
        spec = _spec(f)
        label = f.name if spec is None or kind is bool else spec.option(f.name)
        checked = _checked(label, value, kind, spec)
        if checked is not value:
            object.__setattr__(config, f.name, checked)
