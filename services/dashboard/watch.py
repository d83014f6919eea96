"""What the dashboard shows, gathered from the mesh: the live services, each stream port's
rate, the learner's rollouts and status, and the detector's last measured frame.

Watching costs the session little: the rates come from subscribers to every stream but the
camera's frames (a subscriber to the frames would make the camera render and the router
forward 1280×720 frames for nothing but a count); the frame rate comes from the camera's
non-blocking `status` instead. The detector's frame with its overlay is drawn and PNG-encoded
on the detector's worker, where it holds up the next measurement: it is fetched after a
rollout at most every `frame_every` s, and never sooner than `1 / FRAME_DUTY` times the last
fetch's duration after it, so watching takes at most that share of the detector's time.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from typing import Any

import msgspec
import zenoh

from protocol.errors import ArcheryError
from protocol.keys import SERVICES
from protocol.messages import Rollout
from protocol.node import Node
from protocol.patterns import stream_type
from protocol.robotspec import HIT_RADIUS
from protocol.tokens import TokenSet
from protocol.verbs.base import NoArgs
from protocol.verbs.camera import CAMERA_VERBS
from protocol.verbs.detector import DETECTOR_VERBS, FrameArgs
from protocol.verbs.learner import LEARNER_VERBS
from sim.scene_config import RING_COLOURS

__all__ = ["FRAME_DUTY", "MAX_ROLLOUTS", "MeshWatch"]

log = logging.getLogger("archery.dashboard")

MAX_ROLLOUTS = 2000  # rollouts kept per session (a session's budget is at most 10 000)
_RPC_TIMEOUT = 2.0  # s: frame and status calls
FRAME_DUTY = 0.02  # the share of the detector's time the frame fetches may take at most
#: The streams whose arrivals are counted: every stream port but the camera's frames.
_COUNTED = ("*/state:o", "*/command:i", "world/events:o", "detector/hit:o", "learner/rollout:o")


def _hex(rgba: tuple[float, ...]) -> str:
    return "#" + "".join(f"{round(255 * c):02x}" for c in rgba[:3])


#: The target face as the camera sees it: (outer radius m, colour), innermost first.
FACE = [{"radius_m": r, "colour": _hex(rgba)} for r, rgba in RING_COLOURS]


class _Rates:
    """Arrival times per stream key over the last `window` s: messages per second."""

    def __init__(self, window: float) -> None:
        self.window = window
        self._lock = threading.Lock()
        self._times: dict[str, collections.deque[float]] = {}
        self._streams: dict[str, bool] = {}
        self._counts: dict[str, tuple[float, int]] = {}  # key -> (when, count reported)
        self._reported: dict[str, tuple[float, float]] = {}  # key -> (when, Hz)

    def add(self, key: str) -> None:
        is_stream = self._streams.get(key)
        if is_stream is None:
            is_stream = self._streams[key] = stream_type(key) is not None
        if not is_stream:
            return
        now = time.monotonic()
        with self._lock:
            times = self._times.setdefault(key, collections.deque())
            times.append(now)
            while times and times[0] < now - self.window:
                times.popleft()

    def count(self, key: str, total: int) -> None:
        """A port's message count as its publisher reports it (the frames, from the camera's
        status); its rate is the count's rise over the last two reports."""
        now = time.monotonic()
        with self._lock:
            last = self._counts.get(key)
            self._counts[key] = (now, total)
            if last is not None and now > last[0] and total >= last[1]:
                self._reported[key] = (now, (total - last[1]) / (now - last[0]))

    def table(self) -> list[dict[str, Any]]:
        """Each key seen, with its rate (Hz, 0 when silent for a window) and last-seen age."""
        now = time.monotonic()
        with self._lock:
            items = sorted((k, list(v)) for k, v in self._times.items())
            reported = dict(self._reported)
        out = []
        for key, times in items:
            recent = [t for t in times if t >= now - self.window]
            rate = len(recent) / self.window if recent else 0.0
            age = now - times[-1] if times else None
            out.append({"key": key, "hz": round(rate, 2), "age_s": age and round(age, 2)})
        for key, (when, rate) in sorted(reported.items()):
            out.append({"key": key, "hz": round(rate, 2), "age_s": round(now - when, 2)})
        return sorted(out, key=lambda row: row["key"])


class MeshWatch:
    """Follows one robot's mesh through `node` until `close()`; `snapshot()` is the page's
    JSON, `frame()` the detector's last frame (PNG) and its version."""

    def __init__(
        self,
        node: Node,
        *,
        window: float = 2.0,
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
        self._rates = _Rates(window)
        keys = node.keys
        self._alive = TokenSet(node.session, keys.alive_all())
        self._raw: list[zenoh.Subscriber] = [
            node.session.declare_subscriber(
                f"{keys.robot}/{pattern}", lambda sample: self._rates.add(str(sample.key_expr))
            )
            for pattern in _COUNTED
        ]
        node.subscribe(keys.learner_rollouts(), Rollout, mode="fifo", callback=self._on_rollout)
        self._frame_wanted.set()
        self._worker = threading.Thread(target=self._work, name="dashboard-mesh", daemon=True)
        self._worker.start()

    # -- mesh side ------------------------------------------------------------------------
    def _on_rollout(self, rollout: Rollout) -> None:
        if rollout.status == "proposed":
            return
        distance = math.hypot(*rollout.r_m) if rollout.r_m else None
        row = {
            "index": rollout.index,
            "status": rollout.status,
            "theta": rollout.theta,
            "r_m": rollout.r_m,
            "distance_m": distance,
            "hit": rollout.hit,
            "cause": rollout.cause,
        }
        with self._lock:
            if rollout.session != self._session:
                self._session, self._rollouts = rollout.session, []
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
        try:
            camera = self.node.call_typed(
                self.node.keys.cam_rpc(), CAMERA_VERBS["status"], NoArgs(), timeout=_RPC_TIMEOUT
            )
        except ArcheryError:
            return  # no camera: its frames' rate is not shown
        self._rates.count(self.node.keys.cam_frames(), camera.frames)

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
        for sub in self._raw:
            sub.undeclare()
        self._raw = []
