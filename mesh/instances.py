"""One live instance per service name, and replies only from that instance.

A service's node, once ready, holds two liveliness tokens: `ROBOT/alive/NAME` (the service is
up) and `ROBOT/alive/NAME/ZID`, where ZID is its session's Zenoh id (`session.info.zid()`). A
client that expects an answer from NAME accepts it only if the replier holds NAME's instance
token (`InstanceWatch`); anything else is `WrongReplier` (code `wrong_replier`). Before a
service declares any port, `claim` refuses to start a second live instance of its name or, with
`replace`, asks the live one to stop (`accept_replace`). docs/secure.md tells both
from the user's side.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from pathlib import Path

import zenoh

from archery.mesh.runtime import ReplaceToken, read_token
from archery.mesh.tokens import TokenSet
from archery.protocol.codec import decode, encode
from archery.protocol.errors import DecodeError, DuplicateService
from archery.protocol.keys import Keys
from archery.protocol.messages import Describe, ReplaceRequest

__all__ = [
    "InstanceWatch",
    "accept_replace",
    "claim",
    "describe_all",
    "live_instances",
    "replace_requested",
    "set_stop_event",
    "zid_of",
]

log = logging.getLogger("archery.node")
_stop_event: threading.Event | None = None


def set_stop_event(stop: threading.Event) -> None:
    """The event that stops this process cleanly (set by `shutdown_on_signals`): a request to
    make way for a replacement sets it."""
    global _stop_event
    _stop_event = stop


def replace_requested(name: str) -> None:
    """A new instance of `name` started with --replace asks this one to stop."""
    if _stop_event is None:
        log.warning(
            "a new %s instance asks this one to stop, but it runs without a stop signal "
            "handler: it keeps running",
            name,
        )
        return
    log.warning("a new %s instance replaces this one: stopping", name)
    _stop_event.set()


def zid_of(session: zenoh.Session) -> str:
    """A session's Zenoh id as it appears in keys and in `reply.replier_id.zid`."""
    return str(session.info.zid())


def live_instances(session: zenoh.Session, keys: Keys, name: str, timeout: float = 2.0) -> set[str]:
    """Zenoh ids of the sessions holding an instance token of `name` now."""
    zids = set()
    for reply in session.liveliness().get(keys.alive_instances(name), timeout=timeout):
        if reply.ok is not None:
            zids.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    return zids


def describe_all(
    session: zenoh.Session,
    keys: Keys,
    name: str | None = None,
    timeout: float = 2.0,
    payload: bytes | None = None,
) -> dict[str, Describe]:
    """Every `describe` reply for `name` (each instance answers; None: every service of the
    robot), by replier Zenoh id."""
    out: dict[str, Describe] = {}
    replies = session.get(
        keys.describe_all() if name is None else keys.describe(name),
        payload=payload,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout,
    )
    for reply in replies:
        if reply.ok is None:
            continue
        zid = str(reply.replier_id.zid) if reply.replier_id is not None else "?"
        try:
            out[zid] = decode(reply.ok.payload.to_bytes(), Describe)
        except DecodeError as exc:
            log.warning("bad describe reply for %s from %s: %s", name, zid, exc)
    return out


def accept_replace(name: str, payload: bytes, token: ReplaceToken, host: str | None = None) -> str:
    """Check a `ReplaceRequest` for the live instance of `name`: "" when it may stop, else why
    not. It must come from this host, from a live process whose command line runs `name`
    with `--replace` (`/proc/PID/cmdline`), and carry this instance's `token`."""
    try:
        request = decode(payload, ReplaceRequest)
    except DecodeError as exc:
        return f"not a ReplaceRequest: {exc}"
    here = socket.gethostname() if host is None else host
    if request.service != name or request.host != here:
        return f"a request for {request.service[:64]!r} from host {request.host[:64]!r}"
    try:
        argv = Path(f"/proc/{request.pid}/cmdline").read_bytes().split(b"\0")
    except (OSError, ValueError):
        return f"no process {request.pid} on this host"
    if name.encode() not in argv or b"--replace" not in argv:
        return f"process {request.pid} does not run {name} with --replace"
    if not token.matches(request.proof):
        return (
            f"process {request.pid} did not show this instance's token (only a process of "
            f"the same user can read it from its runtime folder)"
        )
    return ""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _wait_gone(
    session: zenoh.Session, keys: Keys, name: str, zids: set[str], timeout: float
) -> set[str]:
    """Wait until none of `zids` holds an instance token of `name`; returns those left."""
    with TokenSet(session, keys.alive_instances(name)) as present:
        present.add(live_instances(session, keys, name) & zids)
        present.wait_for(lambda now: not (now & zids), timeout)
        return present.present() & zids


def claim(
    session: zenoh.Session, keys: Keys, name: str, replace: bool, timeout: float = 30.0
) -> None:
    """Make sure no other instance of `name` is alive before this one declares its ports.

    If one is alive, this one refuses to start (`DuplicateService`, exit status 2) naming the
    pid and host of the live one (from its `describe` reply), unless `replace`. With
    `replace`, the live instance is asked to stop by a `ReplaceRequest` on its own key
    `ROBOT/replace/NAME` (never by a message to another port): it stops only when the request
    comes from a process of its own host, alive, whose command line runs `NAME` with
    `--replace`, and carries the token the live instance wrote to its runtime folder, which
    only the same user can read (`mesh.runtime`; `accept_replace`); anything else is refused
    and logged, and the service runs on. In secure mode the router lets only NAME's own
    identity and the operator send it. A service run by `service_main` stops as on SIGTERM,
    cleanly, and the new one waits until its tokens are gone; a process that cannot stop that
    way keeps running (logged on both sides) and the new one starts anyway after `timeout` s,
    so two instances then run until the old one is stopped.

    Raises:
        DuplicateService: one is alive (and `replace` is off); the message names its pid and
            host.
    """
    own = zid_of(session)
    others = live_instances(session, keys, name) - {own}
    if not others:
        return
    described = {z: d for z, d in describe_all(session, keys, name).items() if z in others}
    host = socket.gethostname()
    if described and all(d.host == host and not _pid_alive(d.pid) for d in described.values()):
        # The process is gone but the router has not noticed yet (a crash): wait for its lease.
        left = _wait_gone(session, keys, name, others, timeout=15.0)
        if not left:
            return
    where = "; ".join(
        f"pid {d.pid} on {d.host} (instance {z})" for z, d in sorted(described.items())
    ) or ", ".join(f"instance {z} (no describe reply)" for z in sorted(others))
    if not replace:
        raise DuplicateService(
            f"{name} is running already for robot {keys.robot!r}: {where}. Stop it, or start "
            f"this one with --replace to make the live one stop"
        )
    log.warning("replacing the live %s: %s", name, where)
    for zid in sorted(others):  # each instance proves its own token
        proof = read_token(keys.robot, name, zid)
        request = ReplaceRequest(service=name, host=host, pid=os.getpid(), proof=proof)
        for reply in session.get(keys.replace(name), payload=encode(request), timeout=5.0):
            if reply.err is not None:
                log.warning("the live %s refused: %s", name, reply.err.payload.to_string()[:300])
    start = time.monotonic()
    left = _wait_gone(session, keys, name, others, timeout)
    if left:
        log.warning(
            "the old %s (%s) is still alive after %.0f s; starting anyway: two instances run "
            "until it stops",
            name,
            ", ".join(sorted(left)),
            timeout,
        )
    else:
        log.info("the old %s stopped after %.2f s", name, time.monotonic() - start)


class InstanceWatch:
    """Which session holds each service's instance token, kept current by liveliness
    subscribers (one per service name, declared on first use).

    Every Zenoh reply carries the id of the session that sent it (`reply.replier_id.zid`),
    which is checked against these holders. With the router's access control (`--secure`)
    only NAME's certificate may hold NAME's tokens; on a plain mesh anyone can, so the check
    only guards against mistakes (a stray or duplicate service), not against an attacker.

    A subscriber's history (the tokens declared before it) arrives a moment after it is
    declared, and a liveliness query made in that moment may come back empty although the
    router holds the token (zenoh 1.10.2: from 2 in 10,000 to 5 in 500 of the queries made
    right after declaring such a subscriber, each back within 0.2 ms; none of 10,000 without
    one; `benchmarks/bench_liveliness.py`). So a replier not heard of yet is waited for, by
    event, for up to `settle` seconds (s) before it is refused.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, settle: float = 1.0) -> None:
        self._session = session
        self._keys = keys
        self._settle = settle
        self._holders: dict[str, TokenSet] = {}
        self._lock = threading.Lock()

    def _tokens(self, name: str) -> TokenSet:
        with self._lock:
            tokens = self._holders.get(name)
            if tokens is None:
                tokens = TokenSet(self._session, self._keys.alive_instances(name))
                self._holders[name] = tokens
            return tokens

    def holders(self, name: str) -> set[str]:
        """Zenoh ids holding `name`'s instance token, as far as this watch has heard."""
        return self._tokens(name).present()

    def is_instance(self, name: str, zid: str) -> bool:
        """Whether `zid` holds `name`'s instance token (waits up to `settle` s for it to be
        heard of, then asks the router once more before saying no)."""
        tokens = self._tokens(name)
        if tokens.wait_for(lambda now: zid in now, self._settle):
            return True
        tokens.add(live_instances(self._session, self._keys, name) & {zid})
        return zid in tokens.present()

    def close(self) -> None:
        """Undeclare the subscribers."""
        with self._lock:
            tokens, self._holders = list(self._holders.values()), {}
        for token_set in tokens:
            token_set.close()
