"""The line a program prints when it begins to wait, and its line at a Ctrl-C.

Every wait of a program says what it waits for and for how long at most, on stderr, the moment
it begins (not once it is over): `waiting_line` words it. The mesh layer never prints: what
waits there takes an `on_wait(what, limit)` callback, and `announce(PROG)` is that callback for
`archery PROG`; the programs' own waits print through `announce` too, so every waiting line is
worded here.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # a type only: `archery --help` imports no Zenoh
    from archery.mesh.liveliness import OnWait

__all__ = ["announce", "interrupted_line", "waiting_for", "waiting_line"]


def waiting_for(what: str, limit: float) -> str:
    """`waiting up to LIMIT s for WHAT (Ctrl-C to stop)`; `limit` in s (shown to 0.1 s)."""
    return f"waiting up to {round(limit, 1):g} s for {what} (Ctrl-C to stop)"


def waiting_line(prog: str, what: str, limit: float) -> str:
    """The waiting line of `archery PROG`; `limit` in s. E.g. `archery learn: waiting up to
    60 s for the router at tcp/127.0.0.1:7447 (Ctrl-C to stop)`, `archery learn: waiting up to
    60 s for the services: robot, camera (Ctrl-C to stop)`."""
    return f"archery {prog}: {waiting_for(what, limit)}"


def announce(prog: str) -> OnWait:
    """The `on_wait(what, limit)` callback that prints the waiting line of `archery PROG` on
    stderr at once (flushed).

    What waits in the mesh layer (`mesh.node.open_node`, `Node.wait_alive`,
    `Node.missing_after`) takes such a callback (`mesh.liveliness.OnWait`: what is waited for,
    a noun phrase, and the limit in s), called once when a wait actually begins (nothing to
    wait for: no call). The programs' own waits (the services `archery up` starts, the robots
    of an experiment, a resumed session's start) print through it too.
    """

    def on_wait(what: str, limit: float) -> None:
        print(waiting_line(prog, what, limit), file=sys.stderr, flush=True)

    return on_wait


def interrupted_line(prog: str) -> str:
    """The line of `archery PROG` stopped by Ctrl-C (exit status 130) in a wait or any
    other place where the program has nothing more to say."""
    return f"archery {prog}: interrupted (Ctrl-C)"
