"""What the dashboard shows, gathered from the mesh: the live services, each stream port's
rate, the learner's rollouts and status, and the detector's last measured frame.

Watching costs the session little: the rates come from the publishers' own message counts
(`PortInfo.count` in each service's `describe`, polled with the learner's status), not from
subscribing to the streams: a subscriber would have the router forward every joint state and,
for the camera's frames, make the camera render 1280×720 frames for nothing but a count. The
detector's frame with its overlay is drawn and PNG-encoded on the detector's worker, where it
holds up the next measurement: it is fetched after a rollout at most every `frame_every` s,
and never sooner than `1 / FRAME_DUTY` times the last fetch's duration after it, so watching
takes at most that share of the detector's time.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import msgspec

from mesh.instances import describe_all
from mesh.node import Node
from mesh.patterns import stream_type
from mesh.tokens import TokenSet
from protocol.errors import ArcheryError
from protocol.journal_records import DoneRecord, ProposedRecord
from protocol.messages import Rollout
from protocol.robotspec import HIT_RADIUS, SERVICES
from protocol.verbs.base import NoArgs
from protocol.verbs.detector import DETECTOR_VERBS, FrameArgs
from protocol.verbs.learner import LEARNER_VERBS
from sim.scene_config import RING_COLOURS

__all__ = ["FRAME_DUTY", "MAX_ROLLOUTS", "MeshWatch"]

log = logging.getLogger("archery.dashboard")

MAX_ROLLOUTS = 2000  # rollouts kept per session (a session's budget is at most 10 000)
_RPC_TIMEOUT = 2.0  # s: frame and status calls
FRAME_DUTY = 0.02  # the share of the detector's time the frame fetches may take at most


def _hex(rgba: tuple[float, ...]) -> str:
    return "#" + "".join(f"{round(255 * c):02x}" for c in rgba[:3])


#: The target face as the camera sees it: (outer radius m, colour), innermost first.
FACE = [{"radius_m": r, "colour": _hex(rgba)} for r, rgba in RING_COLOURS]


class _Rates:
    """Each stream port's rate from its publisher's message count, as the describe polls
    report it: the count's rise between two polls over the time between them (messages/s)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, tuple[float, int]] = {}  # key -> (when, count reported)
        self._rates: dict[str, float | None] = {}  # None: one report so far

    def update(self, counts: dict[str, int]) -> None:
        """One poll's counts {key: messages sent}; a key it lacks has lost its publisher."""
        now = time.monotonic()
        with self._lock:
            for key in self._rates.keys() - counts.keys():
                self._rates[key] = 0.0
                self._counts.pop(key, None)
            for key, total in counts.items():
                last = self._counts.get(key)
                self._counts[key] = (now, total)
                if last is None or total < last[1] or now <= last[0]:  # new, or restarted
                    self._rates[key] = None
                else:
                    self._rates[key] = (total - last[1]) / (now - last[0])

    def table(self) -> list[dict[str, Any]]:
        """Each stream port seen, with its rate (Hz; None until a second poll)."""
        with self._lock:
            rates = sorted(self._rates.items())
        return [{"key": k, "hz": None if v is None else round(v, 2)} for k, v in rates]


class MeshWatch:
    """Follows one robot's mesh through `node` until `close()`; `snapshot()` is the page's
    JSON, `frame()` the detector's last frame (PNG) and its version."""

    def __init__(
        self,
        node: Node,
        *,
        status_every: float = 2.0,
        frame_every: float = 2.0,
    ) -> None:
        self.node = node
        self.status_every = status_every
        self.frame_every = frame_every
        self._frame_fetched = -math.inf
        self._frame_took = 0.0  # s: the last frame call's duration
        self._lock = threading.Lock()
        self._rollouts: list[dict[str, Any]] = []
        self._session = ""
        self._status: dict[str, Any] = {}
        self._png: bytes | None = None
        self._frame_version = 0
        self._frame_error = ""
        self._frame_wanted = threading.Event()
        self._stop = threading.Event()
        self._rates = _Rates()
        keys = node.keys
        self._alive = TokenSet(node.session, keys.alive_all())
        node.subscribe(keys.learner_rollouts(), Rollout, mode="fifo", callback=self._on_rollout)
        self._frame_wanted.set()
        self._worker = threading.Thread(target=self._work, name="dashboard-mesh", daemon=True)
        self._worker.start()

    # -- mesh side ------------------------------------------------------------------------
    def _on_rollout(self, rollout: Rollout) -> None:
        record = rollout.record
        if isinstance(record, ProposedRecord):
            return
        if isinstance(record, DoneRecord):
            r_m, distance, hit, cause = record.r_m, math.hypot(*record.r_m), record.hit, ""
        else:
            r_m, distance, hit, cause = None, None, False, record.note()
        row = {
            "index": record.index,
            "status": record.kind,
            "theta": record.theta,
            "r_m": r_m,
            "distance_m": distance,
            "hit": hit,
            "cause": cause,
        }
        with self._lock:
            if record.session != self._session:
                self._session, self._rollouts = record.session, []
            self._rollouts.append(row)
            del self._rollouts[:-MAX_ROLLOUTS]
        self._frame_wanted.set()  # the detector has measured the rollout's frame

    def _work(self) -> None:
        """Fetch the frame when a rollout asks for it, and the learner's status every
        `status_every` s; calls never run on Zenoh's threads."""
        next_status = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_status:
                self._fetch_status()
                next_status = time.monotonic() + self.status_every
                if self.frame()[1] == 0:
                    self._frame_wanted.set()  # no frame yet: ask again (the detector may be up)
            if self._frame_wanted.is_set():
                wait = max(self.frame_every, self._frame_took / FRAME_DUTY)
                next_frame = self._frame_fetched + wait
                if time.monotonic() >= next_frame:
                    self._frame_wanted.clear()
                    self._frame_fetched = time.monotonic()
                    fetched = self._fetch_frame()
                    took = time.monotonic() - self._frame_fetched
                    self._frame_took = took if fetched else 0.0  # a failed call costs no work
                    continue
                self._stop.wait(max(0.0, min(next_frame, next_status) - time.monotonic()))
                continue
            self._frame_wanted.wait(max(0.0, next_status - time.monotonic()))

    def _fetch_status(self) -> None:
        try:
            reply = self.node.call_typed(
                self.node.keys.learner_rpc(),
                LEARNER_VERBS["status"],
                NoArgs(),
                timeout=_RPC_TIMEOUT,
            )
            status = {k: v for k, v in msgspec.to_builtins(reply).items() if v is not None}
        except ArcheryError as exc:
            status = {"state": "unreachable", "error": str(exc)}
        with self._lock:
            self._status = status
        described = describe_all(self.node.session, self.node.keys, timeout=_RPC_TIMEOUT)
        self._rates.update(
            {
                port.key: port.count
                for describe in described.values()
                for port in describe.ports
                if port.kind in ("pub", "events") and stream_type(port.key) is not None
            }
        )

    def _fetch_frame(self) -> bool:
        """Fetch the detector's frame; whether it came."""
        try:
            reply = self.node.call_typed(
                self.node.keys.detector_rpc(),
                DETECTOR_VERBS["frame"],
                FrameArgs(overlay=True),
                timeout=_RPC_TIMEOUT,
            )
        except ArcheryError as exc:
            with self._lock:
                self._frame_error = str(exc)
            return False
        with self._lock:
            self._png, self._frame_error = reply.png, ""
            self._frame_version += 1
        return True

    # -- page side ------------------------------------------------------------------------
    def frame(self) -> tuple[bytes | None, int]:
        """The detector's last measured frame with its overlay (PNG) and its version."""
        with self._lock:
            return self._png, self._frame_version

    def snapshot(self) -> dict[str, Any]:
        """Everything the page draws, as JSON-ready builtins."""
        alive = self._alive.present()
        with self._lock:
            rollouts = list(self._rollouts)
            status = dict(self._status)
            frame = {"version": self._frame_version, "error": self._frame_error}
        names = list(SERVICES) + sorted(alive - set(SERVICES))
        return {
            "robot": self.node.keys.robot,
            "time": time.time(),
            "services": [{"name": n, "alive": n in alive} for n in names],
            "rates": self._rates.table(),
            "session": self._session,
            "rollouts": rollouts,
            "learner": status,
            "frame": frame,
            "face": FACE,
            "hit_radius_m": status.get("hit_radius_m", HIT_RADIUS),
        }

    def close(self) -> None:
        """Stop the worker and undeclare the subscriptions (the node closes the rest)."""
        self._stop.set()
        self._frame_wanted.set()
        self._worker.join(timeout=2 * _RPC_TIMEOUT + 1)
        self._alive.close()
