"""The exit-status rule of every `archery` verb and service.

0 success; 1 a runtime failure (nothing at the endpoint, busy, denied, timed out, refused by
the robot, a session that failed); 2 bad input (anything the user typed that can be judged
wrong: a flag, a value, a missing file or folder, an unknown verb, local or remote); 130 after
Ctrl-C before the verb finished its task. A service or `archery up` stopped by Ctrl-C or SIGTERM
once running ends with 0: stopping is how they end.
"""

from __future__ import annotations

__all__ = ["BAD_INPUT", "BAD_INPUT_CODES", "FAILURE", "INTERRUPTED", "OK", "for_error"]

OK = 0
FAILURE = 1
BAD_INPUT = 2
INTERRUPTED = 130

# Error codes (`ArcheryError.code`, also those of a remote service's reply) that mean the
# request itself was wrong: the user can fix it by typing something else.
BAD_INPUT_CODES = frozenset(
    {
        "bad_config",
        "bad_key",
        "bad_message",
        "bad_request",
        "unknown_verb",
        "bad_calibration",
        "bad_journal",
        "bad_model",
        "bad_image",
        "bad_demonstration",
    }
)


def for_error(code: str) -> int:
    """The exit status of a verb that ended with an error of this code (its own, or a remote
    service's reply): `BAD_INPUT` for the codes of `BAD_INPUT_CODES`, `INTERRUPTED` for
    "interrupted", `FAILURE` for every other (busy, timeout, denied, unavailable, …)."""
    if code in BAD_INPUT_CODES:
        return BAD_INPUT
    return INTERRUPTED if code == "interrupted" else FAILURE
