"""The arrow's shot in the MuJoCo scene: launch from the hands, drag, impact, the Landing result.

The arrow's tip leaves from the bow hand (the simulated `l_hand_dh_frame` site) along −θ/‖θ‖
for θ = p_string − p_bow, at the speed of `sim.bow.Bow` (`launch_velocity`), flies as a free
MuJoCo body under gravity and the drag law of the analytic model `sim.ballistic`
(`ArrowFlight`), and lands where its tip's path crosses the target plane or the floor
(`ArrowFlight.after_step`). The result r = tip − centre on the plane, r[0] along +y (the
robot's right) and r[1] along +z (up), in metres, is the shot's ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import mujoco
import numpy as np

from archery.protocol.direction import arrow_direction
from archery.sim.bow import Bow
from archery.sim.errors import StateError
from archery.sim.scene import ScenePhysics

__all__ = [
    "ArrowFlight",
    "Landing",
    "Launch",
    "Outcome",
    "arrow_quat",
    "drag_acceleration",
    "launch_velocity",
    "noisy_velocity",
]


class Outcome(StrEnum):
    """How a shot ended."""

    TARGET = "target"  # the tip met the target face
    OUTSIDE_FACE = "outside_face"  # the tip crossed the target plane outside the face
    GROUND = "ground"  # the tip reached the floor first
    TIMEOUT = "timeout"  # still flying after the time limit


@dataclass(frozen=True, eq=False)
class Launch:
    """The arrow's state at release.

    Attributes:
        position: tip position = bow hand position (m, root frame).
        velocity: launch velocity (m/s, root frame), noise included.
        theta: θ = p_string − p_bow at release (m); the whole shot: the arrow's, its nock − p_bow.
        wind: wind velocity for this shot (m/s, root frame), gust included.
        sim_time: simulated time of the release (s).
    """

    position: np.ndarray
    velocity: np.ndarray
    theta: np.ndarray
    wind: np.ndarray
    sim_time: float

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly copy (arrays become lists)."""
        return {
            "position": self.position.tolist(),
            "velocity": self.velocity.tolist(),
            "theta": self.theta.tolist(),
            "wind": self.wind.tolist(),
            "sim_time": self.sim_time,
        }


@dataclass(frozen=True, eq=False)
class Landing:
    """Where and when a shot ended.

    Attributes:
        outcome: how it ended (`Outcome`).
        r: tip − target centre on the target plane (m): r[0] along +y, r[1] along +z; set when
            the tip crossed the plane (TARGET, OUTSIDE_FACE), None otherwise.
        point: final tip position (m, root frame).
        velocity: tip velocity at that point (m/s).
        sim_time: simulated time of the landing (s).
        flight_time: time from release to landing (s).
        launch: the release that started the flight.
    """

    outcome: Outcome
    r: np.ndarray | None
    point: np.ndarray
    velocity: np.ndarray
    sim_time: float
    flight_time: float
    launch: Launch

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly copy (arrays become lists; the outcome its string value)."""
        return {
            "outcome": self.outcome.value,
            "hit": self.hit,
            "r": None if self.r is None else self.r.tolist(),
            "point": self.point.tolist(),
            "velocity": self.velocity.tolist(),
            "sim_time": self.sim_time,
            "flight_time": self.flight_time,
            "launch": self.launch.to_dict(),
        }

    @property
    def hit(self) -> bool:
        """True if the arrow stuck in the target face."""
        return self.outcome is Outcome.TARGET

    @property
    def reason(self) -> str | None:
        """None for a hit, else why the shot missed ("outside_face", "ground", "timeout")."""
        return None if self.hit else self.outcome.value


def drag_acceleration(velocity: np.ndarray, wind: np.ndarray, drag: float) -> np.ndarray:
    """Quadratic drag a = −K‖v − w‖(v − w) (m/s²) for velocity v, wind w (m/s), K (1/m)."""
    relative = np.asarray(velocity, dtype=float) - np.asarray(wind, dtype=float)
    return -drag * float(np.linalg.norm(relative)) * relative


def arrow_quat(direction: np.ndarray) -> np.ndarray:
    """Orientation (w, x, y, z) that points the arrow's +x along `direction`, kept upright.

    The arrow's z axis is the one closest to world +z; a vertical direction uses world +y as
    the reference instead.
    """
    # plain floats: the whole shot pins a nocked arrow with this at every physics step
    dx, dy, dz = (float(v) for v in direction)
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    if norm < 1e-12:
        dx, dy, dz, norm = -1.0, 0.0, 0.0, 1.0
    x0, x1, x2 = dx / norm, dy / norm, dz / norm
    if abs(x2) < 0.999:  # y = ẑ × x
        y0, y1, y2 = -x1, x0, 0.0
    else:  # y = ŷ × x
        y0, y1, y2 = x2, 0.0, -x0
    n = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    y0, y1, y2 = y0 / n, y1 / n, y2 / n
    z0, z1, z2 = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.array([x0, y0, z0, x1, y1, z1, x2, y2, z2]))
    return quat


def launch_velocity(
    theta: np.ndarray,
    bow: Bow,
    rng: np.random.Generator | None = None,
    speed_noise: float = 0.0,
    direction_noise: float = 0.0,
) -> np.ndarray:
    """Launch velocity (m/s) for θ = p_string − p_bow (m) as measured at the release: the bow's
    speed along −θ/‖θ‖, with the noise of `noisy_velocity`.

    Raises:
        NoArrowDirection: the hands coincide, so there is no direction to shoot in.
    """
    return noisy_velocity(
        arrow_direction(theta), bow.launch_speed(theta), rng, speed_noise, direction_noise
    )


def noisy_velocity(
    direction: np.ndarray,
    speed: float,
    rng: np.random.Generator | None = None,
    speed_noise: float = 0.0,
    direction_noise: float = 0.0,
) -> np.ndarray:
    """`speed` (m/s) along the unit vector `direction`; with `rng`, the speed is scaled by
    (1 + speed_noise·N(0, 1)) (kept ≥ 0) and the direction is tilted by direction_noise·N(0, 1)
    radians about each of two axes perpendicular to it."""
    if rng is not None:
        # Always draw the same three numbers, so the stream does not depend on the settings.
        eps_speed, eps_a, eps_b = rng.standard_normal(3)
        speed *= max(0.0, 1.0 + speed_noise * eps_speed)
        ref = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
        side = np.cross(ref, direction)
        side /= np.linalg.norm(side)
        up = np.cross(direction, side)
        direction = direction + direction_noise * (eps_a * side + eps_b * up)
        direction /= np.linalg.norm(direction)
    velocity: np.ndarray = speed * direction
    return velocity


class ArrowFlight:
    """One arrow's flight in a scene, from launch to landing; call around every physics step.

    The arrow is a free MuJoCo body under gravity. Air drag is an explicit force at its centre
    of mass, written to `xfrc_applied` before every physics step (`before_step`; MuJoCo's own
    fluid model is switched off in the scene):

        a_drag = −K·‖v − w‖·(v − w)      K in 1/m, v the arrow's and w the wind's velocity (m/s),

    the same law as the analytic model of `sim.ballistic`. The arrow does not rotate in flight.
    Its velocity starts half a step back (a leapfrog start), which makes MuJoCo's semi-implicit
    Euler exact for the drag-free parabola and second-order accurate with drag.

    Args:
        physics: the scene's physics queries.
        launch: the release state; the arrow is placed and given its velocity here.
        drag: K (1/m) of the drag law.
        plane_x: the target plane x (m).
        centre: target centre (m, root frame).
        face_radius: target face radius (m).
        floor_z: floor height (m).
        max_flight_time: the flight ends as TIMEOUT after this long (s).
    """

    def __init__(
        self,
        physics: ScenePhysics,
        launch: Launch,
        *,
        drag: float,
        plane_x: float,
        centre: np.ndarray,
        face_radius: float,
        floor_z: float,
        max_flight_time: float,
    ) -> None:
        self.physics = physics
        self.launch = launch
        self.drag = float(drag)
        self.plane_x = float(plane_x)
        self.centre = np.asarray(centre, dtype=float)
        self.face_radius = float(face_radius)
        self.floor_z = float(floor_z)
        self.max_flight_time = float(max_flight_time)
        self._mass = physics.arrow_mass
        self._gravity_force = physics.arrow_mass * physics.gravity
        physics.set_arrow_pose(launch.position, arrow_quat(launch.velocity))
        # Leapfrog start: MuJoCo's semi-implicit Euler moves positions with the end-of-step
        # velocity, so a velocity held half a step back makes every step follow the exact
        # parabola under gravity (otherwise the arrow drifts down by g·t·dt/2).
        accel = physics.gravity + drag_acceleration(launch.velocity, launch.wind, self.drag)
        physics.set_arrow_velocity(launch.velocity - 0.5 * physics.timestep * accel)
        self._prev_tip = launch.position.copy()
        self._prev_vel = launch.velocity.copy()
        self._prev_time = launch.sim_time
        self.landing: Landing | None = None

    def before_step(self) -> None:
        """Apply this step's drag force (N) from the arrow's current velocity."""
        if self.landing is None:
            velocity = self.physics.arrow_velocity()
            self._prev_tip = self.physics.arrow_tip()
            self._prev_vel = velocity
            self._prev_time = self.physics.time
            if self.drag > 0.0:
                accel = drag_acceleration(velocity, self.launch.wind, self.drag)
                self.physics.set_arrow_force(self._mass * accel)
            else:
                self.physics.set_arrow_force(np.zeros(3))

    def after_step(self) -> Landing | None:
        """Check the step's path for an impact; on one, freeze the arrow there and return it.

        The tip's path over the step is tested against the target plane x = `plane_x`
        (−distance) and the floor z = `floor_z` (−root_height); the crossing is interpolated
        inside the step, so the reported point does not depend on how far the arrow moved in
        one step. At the plane, a tip within the face radius is a hit; one outside it is a miss
        that is still reported on the plane (like the paper's arrows put back on the wall at
        their impact point). The arrow is then frozen there, pointing along its velocity.
        """
        if self.landing is not None:
            return None
        physics = self.physics
        p0, v0, t0 = self._prev_tip, self._prev_vel, self._prev_time
        p1, v1, t1 = physics.arrow_tip(), physics.arrow_velocity(), physics.time
        events: list[tuple[float, Outcome]] = []
        if p0[0] > self.plane_x >= p1[0]:
            events.append(((p0[0] - self.plane_x) / (p0[0] - p1[0]), Outcome.TARGET))
        if p0[2] > self.floor_z >= p1[2]:
            events.append(((p0[2] - self.floor_z) / (p0[2] - p1[2]), Outcome.GROUND))
        if events:
            s, outcome = min(events, key=lambda e: e[0])
            s = float(s)
        elif t1 - self.launch.sim_time >= self.max_flight_time:
            s, outcome = 1.0, Outcome.TIMEOUT
        else:
            return None
        point = p0 + s * (p1 - p0)
        velocity = v0 + s * (v1 - v0)
        when = float(t0 + s * (t1 - t0))
        r = None
        if outcome is Outcome.TARGET:
            point[0] = self.plane_x  # exact on the plane
            r = np.array([point[1] - self.centre[1], point[2] - self.centre[2]])
            if math.hypot(r[0], r[1]) > self.face_radius:
                outcome = Outcome.OUTSIDE_FACE
        elif outcome is Outcome.GROUND:
            point[2] = self.floor_z
        self.landing = Landing(
            outcome=outcome,
            r=r,
            point=point,
            velocity=velocity,
            sim_time=when,
            flight_time=when - self.launch.sim_time,
            launch=self.launch,
        )
        self.freeze()
        return self.landing

    def freeze(self) -> None:
        """Hold the landed arrow still at its impact pose (gravity cancelled, zero velocity)."""
        if self.landing is None:
            raise StateError("the arrow has not landed yet; there is no impact pose to hold")
        self.physics.set_arrow_pose(self.landing.point, arrow_quat(self.landing.velocity))
        self.physics.set_arrow_velocity(np.zeros(3))
        self.physics.set_arrow_force(-self._gravity_force)
