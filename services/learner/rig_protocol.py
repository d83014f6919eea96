"""What a learning session sees of the other services: the `Rig` protocol and the results of
its calls (θ in m, times in s). Every call may raise `RigError` or `ServiceLost`
(`services.learner.errors`).

The mesh implements it in `services.learner.rig` (`MeshRig`); tests and labs pass their own.
Pure: no Zenoh.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from archery.protocol.theta import ThetaBox

__all__ = ["Measurement", "PostureResult", "Rig", "Shot"]


@dataclass(frozen=True)
class PostureResult:
    """The controller's answer: reached in time, why not, the θ measured (m), timings (s)."""

    reached: bool
    reason: str
    theta_measured: list[float]
    timing: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Shot:
    """A released arrow, landed: the robot's shot number, landing sim time (s), the wall time
    (s since the epoch) just before the arrow was nocked (a frame captured later and rendered
    at or after the landing shows this arrow), what the robot says for the log, and the θ (m)
    the arrow was launched with (the hands at the release, from the robot's reply; None when
    the rig does not know it)."""

    shot: int
    sim_time: float
    stamp: float
    outcome: str
    timing: dict[str, float] = field(default_factory=dict)
    theta_launched: list[float] | None = None
    #: the detector's baseline taken before the release, when the camera tells the landing
    #: (a robot that does not see the arrow land: `MeshRig.landing`); None: the robot told it
    baseline: int | None = None


@dataclass(frozen=True)
class Measurement:
    """The detector's answer: status ok / no_target / no_arrow, r (m) when ok, the reply."""

    status: str
    r_m: list[float] | None
    detection: dict[str, Any]
    timing: dict[str, float] = field(default_factory=dict)


class Rig(Protocol):
    """The other services as one session sees them (every call may raise `RigError` or
    `ServiceLost`)."""

    services: tuple[str, ...]

    def missing(self) -> list[str]:
        """Services not alive now."""

    def lost_ago(self, service: str) -> float | None:
        """Seconds since `service` was seen going (None if it was not)."""

    def wait_services(self, timeout: float, stop: threading.Event) -> bool:
        """Wait until every service is alive (True) or `stop` is set (False).

        Raises ServiceLost when some are still missing after `timeout` s."""

    def theta_box(self) -> ThetaBox:
        """The controller's θ box (m)."""

    def follow_shot(self) -> str:
        """Follow the robot's shot: on a `--shot whole` robot every `move_to` asks the
        controller for the whole movement towards the posture; the robot's shot (posture or
        whole)."""

    def setup(self) -> dict[str, Any]:
        """The robot's world (`sim.world.WorldConfig.to_dict`), its shot count and the
        controller's trajectory time (s): what replaying a shot needs, for the journal."""

    def reset(self, seed: int) -> None:
        """Robot to its home posture, shot noise reseeded."""

    def move_to(self, theta: np.ndarray) -> PostureResult:
        """Move to the archery posture for θ (m) and wait until the motion is done."""

    def shoot(self) -> Shot:
        """Nock an arrow and release it; returns once it has landed."""

    def measure(self, shot: Shot) -> Measurement:
        """Detect target centre and arrow tip in a frame newer than the landing."""

    def truth(self, shot: Shot) -> list[float] | None:
        """The robot's ground-truth r (m) of the shot, for the log only (None if unknown)."""

    def hit_frame(self, shot: Shot, measurement: Measurement) -> bytes | None:
        """The measured frame of the shot with the detection drawn on it (PNG), if available."""
