"""The checks of the environments' `make` keywords and `reset` options: a bad one is a
`ValueError` naming it, whatever was wrong with it (an unknown name, a value of the wrong
type or range), its message bounded (`MESSAGE_LIMIT` characters: a value is quoted with
`protocol.text`)."""

from __future__ import annotations

import contextlib
import inspect
import math
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from archery.protocol.text import cut, shown

__all__ = [
    "MESSAGE_LIMIT",
    "flag",
    "keyword_errors",
    "make_keywords",
    "number",
    "refuse_unknown",
    "reset_options",
]

MESSAGE_LIMIT = 400  # characters of a bad keyword's or a bad action's message at most


@contextlib.contextmanager
def keyword_errors() -> Iterator[None]:
    """Raise whatever a keyword's check raised as a `ValueError` of at most `MESSAGE_LIMIT`
    characters: a ValueError (or a subclass, e.g. `sim.ballistic.ScenarioError`) whose message
    is short passes as it is; a longer one, or a TypeError, becomes a ValueError with the
    message cut."""
    try:
        yield
    except ValueError as exc:
        if len(str(exc)) <= MESSAGE_LIMIT:
            raise
        raise ValueError(cut(str(exc), MESSAGE_LIMIT)) from None
    except TypeError as exc:
        raise ValueError(cut(str(exc), MESSAGE_LIMIT)) from None


def make_keywords(env: type) -> tuple[str, ...]:
    """The keyword-only parameters of `env`'s constructor: what `gymnasium.make` may pass."""
    parameters = inspect.signature(env.__init__).parameters.values()  # type: ignore[misc]
    return tuple(p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY)


def refuse_unknown(env_id: str, given: Mapping[str, object], valid: Iterable[str]) -> None:
    """Refuse keywords an environment does not take (`**given`), naming them and the valid ones.

    Raises:
        ValueError: `given` is not empty.
    """
    if given:
        names = ", ".join(shown(name, 40) for name in list(given)[:5])
        raise ValueError(
            cut(f"{env_id} takes no keyword {names}; its keywords: {', '.join(valid)}", 400)
        )


def number(name: str, value: object, unit: str) -> float:
    """A real number keyword (not a bool, not a string), finite.

    Raises:
        ValueError: it is not one.
    """
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name} must be a number ({unit}), got {shown(value)}")
    result = float(value)
    if not math.isfinite(result):
        raise ValueError(f"{name} must be finite ({unit}), got {shown(value)}")
    return result


def flag(name: str, value: object) -> bool:
    """A true/false keyword.

    Raises:
        ValueError: it is neither.
    """
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be True or False, got {shown(value)}")
    return bool(value)


def reset_options(env_id: str, options: object, valid: Iterable[str]) -> dict[str, Any]:
    """`reset`'s options: None or a dict of the option names `valid`.

    Raises:
        ValueError: not a dict, or an option the environment does not take.
    """
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ValueError(f"{env_id} reset options must be a dict or None, got {shown(options)}")
    unknown = [k for k in options if k not in set(valid)]
    if unknown:
        names = ", ".join(shown(k, 40) for k in unknown[:5])
        raise ValueError(f"{env_id} reset takes no option {names}; its options: {', '.join(valid)}")
    return options
