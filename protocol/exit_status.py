"""The one exit-status rule of every `archery` verb and service.

0 success; 1 a runtime failure (nothing at the endpoint, busy, denied, timed out, refused by
the robot, a session that failed); 2 bad input (anything the user typed that can be judged
wrong: a flag, a value, a missing file or folder, an unknown verb, local or remote); 130 after
Ctrl-C before the verb finished its task. A service or `archery up` stopped by Ctrl-C or SIGTERM
once running ends with 0: stopping is how they end.
"""

from __future__ import annotations

__all__ = ["BAD_INPUT", "FAILURE", "INTERRUPTED", "OK"]

OK = 0
FAILURE = 1
BAD_INPUT = 2
INTERRUPTED = 130
