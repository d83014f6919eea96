"""What the dashboard shows of one robot, gathered from the mesh: the live services, each stream
port's rate, the learner's rollouts and status, the detector's last measured frame and, while a
page shows it, the camera's scene view (the whole robot from the side camera).

Watching costs the session little: the rates come from the publishers' own message counts
(`apps.port_rates`), not from subscribing to the streams; the detector's frame is fetched at most
a share of the detector's time (`MeshWatch._work`), and the scene view only while a page shows it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import msgspec

from archery.apps.port_rates import PortRates, stream_counts
from archery.mesh.instances import describe_all
from archery.mesh.node import Node
from archery.mesh.tokens import TokenSet
from archery.protocol.errors import ArcheryError
from archery.protocol.journal_records import DoneRecord, ProposedRecord
from archery.protocol.keys import Keys
from archery.protocol.messages import Rollout
from archery.protocol.robotspec import HIT_RADIUS, SERVICES
from archery.protocol.verbs import learner as learner_verbs
from archery.protocol.verbs.base import NoArgs
from archery.protocol.verbs.camera import SCENE
from archery.protocol.verbs.detector import FRAME, FrameArgs
from archery.sim.scene_config import RING_COLOURS

__all__ = ["FRAME_DUTY", "MAX_ROLLOUTS", "SCENE_INTEREST", "MeshWatch"]

log = logging.getLogger("archery.dashboard")

MAX_ROLLOUTS = 2000  # rollouts kept per session (a session's budget is at most 10 000)
_RPC_TIMEOUT = 2.0  # s: frame and status calls
FRAME_DUTY = 0.25  # the share of the detector's time the frame fetches may take at most
FRAME_EVERY = 0.5  # s between frame fetches at least: the page's poll period (`POLL_MS`)
SCENE_INTEREST = 3.0  # s: the scene view is fetched while a page asked for it this recently


def _hex(rgba: tuple[float, ...]) -> str:
    return "#" + "".join(f"{round(255 * c):02x}" for c in rgba[:3])


#: The target face as the camera sees it: (outer radius m, colour), innermost first.
FACE = [{"radius_m": r, "colour": _hex(rgba)} for r, rgba in RING_COLOURS]


class MeshWatch:
    """Follows one robot's mesh (`robot`, default the node's) through `node` until `close()`;
    `snapshot()` is the page's JSON, `frame()` the detector's last frame (PNG) with its version,
    `scene()` the camera's last scene view (JPEG) with its version."""

    def __init__(
        self,
        node: Node,
        *,
        robot: str | None = None,
        status_every: float = 2.0,
        frame_every: float = FRAME_EVERY,
    ) -> None:
        self.node = node
        self.keys = node.keys if robot is None else Keys(robot)
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
        self._frame_rollout: int | None = None  # the rollout whose measurement it shows
        self._frame_error = ""
        self._scene: dict[str, Any] = {"version": 0, "status": "off", "error": ""}
        self._scene_jpeg: bytes | None = None
        self._scene_wanted_at = -math.inf  # monotonic s: a page last asked for the scene view
        self._scene_due = 0.0  # monotonic s: when the camera may be asked again
        self._frame_wanted = threading.Event()
        self._status_wanted = threading.Event()  # the status changed (a confirm): fetch it now
        self._wake = threading.Event()  # a rollout, a page wanting the scene, or close()
        self._stop = threading.Event()
        self._rates = PortRates()
        self._rollout_index: int | None = None  # the newest finished rollout
        keys = self.keys
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
            self._rollout_index = record.index
        self._frame_wanted.set()
        self._wake.set()  # the detector has measured the rollout's frame

    def _work(self) -> None:
        """Fetch the frame when a rollout asks for it, the scene view while a page wants it and
        the learner's status every `status_every` s; calls never run on Zenoh's threads.

        The detector's frame with its overlay is drawn and PNG-encoded on the detector's
        worker: it is fetched after each rollout, right after the detector measured it and
        while the robot moves to the next shot (a posture and a flight: the detector idles
        then), and never sooner than `1 / FRAME_DUTY` times the last fetch's duration after
        the one before, so watching takes at most that share of the detector's time however
        fast rollouts come, nor sooner than `frame_every` s (`FRAME_EVERY`, the page's poll
        period: a page shows no more frames than it polls). The scene view is asked of the
        camera (`scene`, which never waits) only while a page showed interest in it within the
        last `SCENE_INTEREST` s, at the camera's own period; nobody looking, nothing is
        rendered.
        """
        next_status = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_status or self._status_wanted.is_set():
                self._status_wanted.clear()
                self._fetch_status()
                next_status = time.monotonic() + self.status_every
                if self.frame()[1] == 0:
                    self._frame_wanted.set()  # no frame yet: ask again (the detector may be up)
            wake = next_status
            if self._frame_wanted.is_set():
                wait = max(self.frame_every, self._frame_took / FRAME_DUTY)
                next_frame = self._frame_fetched + wait
                if time.monotonic() >= next_frame:
                    self._frame_wanted.clear()
                    with self._lock:
                        rollout = self._rollout_index
                    self._frame_fetched = time.monotonic()
                    fetched = self._fetch_frame(rollout)
                    took = time.monotonic() - self._frame_fetched
                    self._frame_took = took if fetched else 0.0  # a failed call costs no work
                    continue
                wake = min(wake, next_frame)
            if self.scene_wanted():
                if time.monotonic() >= self._scene_due:
                    self._fetch_scene()
                    continue
                wake = min(wake, self._scene_due)
            elif self._scene["status"] != "off":
                with self._lock:
                    self._scene = self._scene | {"status": "off"}
            self._wake.wait(max(0.0, wake - time.monotonic()))
            self._wake.clear()  # what woke it is in the flags checked above

    def _fetch_status(self) -> None:
        try:
            reply = self.node.call_typed(
                self.keys.learner_rpc(),
                learner_verbs.STATUS,
                NoArgs(),
                timeout=_RPC_TIMEOUT,
            )
            status = {k: v for k, v in msgspec.to_builtins(reply).items() if v is not None}
        except ArcheryError as exc:
            status = {"state": "unreachable", "error": str(exc)}
        with self._lock:
            self._status = status
        described = describe_all(self.node.session, self.keys, timeout=_RPC_TIMEOUT)
        self._rates.update(stream_counts(described))

    def _fetch_frame(self, rollout: int | None) -> bool:
        """Fetch the detector's frame (of the measurement of `rollout`, the newest finished
        one when asked); whether it came."""
        try:
            reply = self.node.call_typed(
                self.keys.detector_rpc(),
                FRAME,
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
            self._frame_rollout = rollout
        return True

    def _fetch_scene(self) -> None:
        """Ask the camera for its newest scene view (a call that never waits there)."""
        period = 1.0
        try:
            reply = self.node.call_typed(self.keys.cam_rpc(), SCENE, NoArgs(), timeout=_RPC_TIMEOUT)
        except ArcheryError as exc:
            with self._lock:
                self._scene = self._scene | {"status": "unavailable", "error": str(exc)}
            self._scene_due = time.monotonic() + self.status_every
            return
        period = reply.period
        image = reply.image
        with self._lock:
            scene = self._scene | {"status": reply.status, "error": ""}
            if image is not None and image.data != self._scene_jpeg:
                self._scene_jpeg = image.data
                scene |= {
                    "version": scene["version"] + 1,
                    "sim_time": image.sim_time,
                    "width": image.width,
                    "height": image.height,
                }
            self._scene = scene
        self._scene_due = time.monotonic() + period

    def status_soon(self) -> None:
        """The learner's status changed (the page confirmed its operator's request): fetch it
        now rather than at the next `status_every`."""
        self._status_wanted.set()
        self._wake.set()

    def want_scene(self) -> None:
        """A page shows the scene view: fetch it for the next `SCENE_INTEREST` s."""
        wanted = self.scene_wanted()
        self._scene_wanted_at = time.monotonic()
        if not wanted:
            self._wake.set()

    def scene_wanted(self) -> bool:
        """Whether a page asked for the scene view within the last `SCENE_INTEREST` s."""
        return time.monotonic() - self._scene_wanted_at < SCENE_INTEREST

    # -- page side ------------------------------------------------------------------------
    def frame(self) -> tuple[bytes | None, int]:
        """The detector's last measured frame with its overlay (PNG) and its version."""
        with self._lock:
            return self._png, self._frame_version

    def scene(self) -> tuple[bytes | None, int]:
        """The camera's last scene view (JPEG) and its version."""
        with self._lock:
            return self._scene_jpeg, int(self._scene["version"])

    def snapshot(self) -> dict[str, Any]:
        """Everything the page draws, as JSON-ready builtins."""
        alive = self._alive.present()
        with self._lock:
            rollouts = list(self._rollouts)
            status = dict(self._status)
            frame = {
                "version": self._frame_version,
                "rollout": self._frame_rollout,
                "error": self._frame_error,
            }
            scene = dict(self._scene)
        names = list(SERVICES) + sorted(alive - set(SERVICES))
        return {
            "robot": self.keys.robot,
            "time": time.time(),
            "services": [{"name": n, "alive": n in alive} for n in names],
            "rates": self._rates.table(),
            "session": self._session,
            "rollouts": rollouts,
            "learner": status,
            "frame": frame,
            "scene": scene,
            "face": FACE,
            "hit_radius_m": status.get("hit_radius_m", HIT_RADIUS),
        }

    def close(self) -> None:
        """Stop the worker and undeclare the subscriptions (the node closes the rest)."""
        self._stop.set()
        self._wake.set()
        self._worker.join(timeout=2 * _RPC_TIMEOUT + 1)
        self._alive.close()
