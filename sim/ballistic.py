"""The paper's analytic archery world (Section IV): a ballistic arrow from the bow hand to a target.

Frame and units: the iCub `root_link` frame of `sim.geometry` (x backward, y right, z up), metres,
seconds. θ = p_string − p_bow (m) gives a launch velocity by the linear-spring bow of `sim.bow`;
the arrow starts at `BOW_HAND` and flies under gravity and, optionally, quadratic air drag
relative to a constant wind,

    a = g − K·‖v − w‖·(v − w)        (K in 1/m, w in m/s),

until it meets the target plane x = −distance (`BallisticWorld.impacts`). The observed reward
r = arrow − centre on that plane (r[0] along +y, r[1] along +z, m) has optional Gaussian noise.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from archery.protocol.direction import NoArrowDirection
from archery.protocol.vectors import finite_vector
from archery.sim.bow import Bow
from archery.sim.geometry import (
    BOW_HAND,
    INNER_RING_RADIUS,
    START_THETA,
    TARGET_DISTANCE,
    target_centre,
)

__all__ = [
    "GRAVITY",
    "BallisticError",
    "BallisticWorld",
    "Impacts",
    "Scenario",
    "ScenarioError",
    "Shot",
    "ShotError",
]

GRAVITY = np.array([0.0, 0.0, -9.81])  # m/s², root frame (z up)
_MIN_RANGE = 0.1  # m, the target plane must be at least this far in front of the bow hand
MAX_WIND = 50.0  # m/s per axis: a storm; beyond it nothing reaches a target
# (field, low, high, unit): ranges beyond which the model means nothing (and floats overflow)
_RANGES = (
    ("distance", -math.inf, 100.0, "m"),
    ("drag", 0.0, 10.0, "1/m"),
    ("noise", 0.0, 10.0, "m"),
    ("bow_stiffness", 0.0, 1e5, "N/m"),
)


class BallisticError(ValueError):
    """Base of the ballistic world's errors."""


class ScenarioError(BallisticError):
    """An invalid scenario parameter (distance, wind, drag, noise, stiffness, start θ).

    `field` names the parameter, so a command line can name its flag.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class ShotError(BallisticError):
    """A θ that cannot be shot at the target (wrong shape, no draw, never reaches the plane)."""


@dataclass(frozen=True)
class Scenario:
    """Every parameter of one simulated range, validated.

    Attributes:
        distance: robot root to target plane (m); the plane is x = −distance.
        wind: constant wind velocity (m/s, root frame). It acts only through drag.
        drag: K in a = −K‖v − w‖(v − w) (1/m); 0 gives the paper's drag-free ballistic model.
        noise: std of the Gaussian observation noise added to each component of r (m).
        bow_stiffness: k of the linear-spring bow (N/m of draw), see `sim.bow.Bow`.
        start: the initial policy θ = p_string − p_bow (m).
    """

    distance: float = TARGET_DISTANCE
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    drag: float = 0.0
    noise: float = 0.0
    bow_stiffness: float = Bow().stiffness
    start: tuple[float, float, float] = field(default_factory=lambda: tuple(START_THETA.tolist()))

    def __post_init__(self) -> None:
        wind = finite_vector("wind", self.wind, ScenarioError, unit="m/s")
        start = finite_vector("start", self.start, ScenarioError, unit="m")
        object.__setattr__(self, "wind", tuple(wind.tolist()))
        object.__setattr__(self, "start", tuple(start.tolist()))
        for name in ("distance", "drag", "noise", "bow_stiffness"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ScenarioError(f"{name} must be a finite number, got {value!r}", name)
            object.__setattr__(self, name, float(value))
        min_distance = -float(BOW_HAND[0]) + _MIN_RANGE
        if self.distance < min_distance:
            raise ScenarioError(
                f"distance {self.distance!r} m puts the target behind or at the bow hand; "
                f"use a distance >= {min_distance:.2f} m",
                "distance",
            )
        if self.bow_stiffness <= 0:
            raise ScenarioError(
                f"bow_stiffness must be > 0 (N/m), got {self.bow_stiffness!r}", "bow_stiffness"
            )
        for name, low, high, unit in _RANGES:
            value = getattr(self, name)
            if value < low:
                raise ScenarioError(f"{name} must be >= {low:g} ({unit}), got {value!r}", name)
            if value > high:
                raise ScenarioError(f"{name} must be <= {high:g} ({unit}), got {value!r}", name)
        if max(abs(w) for w in self.wind) > MAX_WIND:
            raise ScenarioError(
                f"wind must be at most {MAX_WIND:g} m/s per axis, got {self.wind}", "wind"
            )
        if self.drag == 0 and any(self.wind):
            raise ScenarioError(
                f"wind {self.wind} has no effect without air drag (it acts through drag only); "
                "set drag > 0 or leave the wind at 0,0,0"
            )

    @property
    def bow(self) -> Bow:
        """The bow model of this scenario."""
        return Bow(stiffness=self.bow_stiffness)

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly copy of the parameters (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass(frozen=True)
class Impacts:
    """Where a batch of arrows meets the target plane.

    Attributes:
        r: (n, 2) true arrow − centre offsets on the target plane (m): +y, +z.
        points: (n, 3) impact points (m, root frame).
        flight_time: (n,) seconds from release to impact.
    """

    r: np.ndarray
    points: np.ndarray
    flight_time: np.ndarray


@dataclass(frozen=True)
class Shot:
    """One rollout's outcome.

    Attributes:
        theta: the policy θ that was shot (m).
        r: the observed reward vector (m), true offset plus observation noise.
        r_true: the true offset of the arrow from the centre (m); ground truth for plots and tests.
        point: impact point (m, root frame).
        flight_time: seconds from release to impact.
        hit: ‖r_true‖ < the innermost ring's radius (5 cm).
    """

    theta: np.ndarray
    r: np.ndarray
    r_true: np.ndarray
    point: np.ndarray
    flight_time: float
    hit: bool


class BallisticWorld:
    """The simulated range: shoot θ, observe r.

    Gymnasium-like: `reset(seed)` seeds the observation noise, `step(θ)` fires one arrow, and
    the same seed gives the same numbers bit for bit. The physics (`impacts`, `trajectory`) is
    pure and vectorised over many θ at once; only `observe` draws random numbers.

    Args:
        scenario: the range's parameters.
        dt: RK4 step (s) when drag is on.
        max_time: give up on an arrow that has not reached the target plane after this long (s).
    """

    def __init__(
        self, scenario: Scenario | None = None, *, dt: float = 2e-3, max_time: float = 5.0
    ) -> None:
        self.scenario = scenario if scenario is not None else Scenario()
        if not (math.isfinite(dt) and dt > 0):
            raise ScenarioError(f"dt must be a positive number of seconds, got {dt!r}")
        if not (math.isfinite(max_time) and max_time > dt):
            raise ScenarioError(f"max_time must be a number of seconds > dt, got {max_time!r}")
        self.dt = float(dt)
        self.max_time = float(max_time)
        self._bow = self.scenario.bow
        self._centre = target_centre(self.scenario.distance)
        self._plane_x = float(self._centre[0])
        self._wind = np.array(self.scenario.wind)
        self._rng = np.random.default_rng()

    @property
    def centre(self) -> np.ndarray:
        """Target centre (m, root frame)."""
        return self._centre.copy()

    def reset(self, seed: int | np.random.SeedSequence | None = None) -> None:
        """Seed the observation noise; the same seed gives the same observations bit for bit."""
        self._rng = np.random.default_rng(seed)

    # -- physics (pure) -------------------------------------------------------------------------

    def launch(self, thetas: np.ndarray) -> np.ndarray:
        """Launch velocities (n, 3) in m/s for θ rows (n, 3) in metres: the bow's speed
        d·sqrt(η·k/m) for the draw d = ‖θ‖ − brace height, along −θ/‖θ‖.

        Raises:
            ShotError: a θ is not a finite 3-vector or gives no draw (‖θ‖ <= brace height).
        """
        thetas = self._as_thetas(thetas)
        velocities = np.empty_like(thetas)
        for i, theta in enumerate(thetas):
            try:
                velocities[i] = self._bow.launch_velocity(theta)
            except NoArrowDirection as exc:
                raise ShotError(str(exc)) from exc
            if self._bow.draw(theta) <= 0.0:
                raise ShotError(
                    f"θ={theta.tolist()} m gives no draw: ‖θ‖ must exceed the bow's brace height "
                    f"{self._bow.brace_height} m"
                )
        return velocities

    def impacts(self, thetas: np.ndarray) -> Impacts:
        """True impacts on the target plane for θ rows (n, 3) in metres (no observation noise).

        Without drag the flight has a closed form; with drag it is integrated with fixed-step
        RK4 and the plane crossing is found by cubic Hermite interpolation inside the last step.

        Raises:
            ShotError: a θ cannot be shot or its arrow never reaches the target plane.
        """
        thetas = self._as_thetas(thetas)
        v0 = self.launch(thetas)
        p0 = np.broadcast_to(BOW_HAND, v0.shape).astype(float)
        if self.scenario.drag == 0.0:
            points, times = self._closed_form(thetas, p0, v0)
        else:
            points, times = self._integrate(thetas, p0, v0)
        r = np.stack([points[:, 1] - self._centre[1], points[:, 2] - self._centre[2]], axis=1)
        return Impacts(r=r, points=points, flight_time=times)

    def trajectory(self, theta: np.ndarray, n_points: int = 50) -> np.ndarray:
        """Positions (m, root frame) from release to impact, at least `n_points` of them."""
        thetas = self._as_thetas(np.asarray(theta, dtype=float).reshape(1, -1))
        v0 = self.launch(thetas)[0]
        p0 = BOW_HAND.astype(float)
        hit = self.impacts(thetas)
        t_end = float(hit.flight_time[0])
        if self.scenario.drag == 0.0:
            t = np.linspace(0.0, t_end, max(2, n_points))[:, None]
            return p0 + v0 * t + 0.5 * GRAVITY * t * t
        p, v = p0[None, :].copy(), v0[None, :].copy()
        steps = max(1, math.ceil(t_end / self.dt))
        dt = t_end / steps
        positions = [p[0].copy()]
        for _ in range(steps):
            p, v = self._rk4(p, v, dt)
            positions.append(p[0].copy())
        positions[-1] = hit.points[0]
        return np.array(positions)

    # -- task (observation) ---------------------------------------------------------------------

    def observe(self, r_true: np.ndarray) -> np.ndarray:
        """The observed reward vector: r_true (m) plus N(0, noise²) per component."""
        r_true = np.asarray(r_true, dtype=float)
        if self.scenario.noise == 0.0:
            return r_true.copy()
        return r_true + self.scenario.noise * self._rng.standard_normal(r_true.shape)

    def step(self, theta: np.ndarray) -> Shot:
        """Shoot one arrow with the policy θ (m) and observe where it lands."""
        theta = np.asarray(theta, dtype=float)
        hit = self.impacts(theta.reshape(1, -1))
        r_true = hit.r[0]
        return Shot(
            theta=theta.copy(),
            r=self.observe(r_true),
            r_true=r_true,
            point=hit.points[0],
            flight_time=float(hit.flight_time[0]),
            hit=bool(np.hypot(r_true[0], r_true[1]) < INNER_RING_RADIUS),
        )

    # -- internals ------------------------------------------------------------------------------

    @staticmethod
    def _as_thetas(thetas: np.ndarray) -> np.ndarray:
        array = np.asarray(thetas, dtype=float)
        if array.ndim != 2 or array.shape[1] != 3 or not np.all(np.isfinite(array)):
            raise ShotError(f"θ must be finite rows of 3 numbers (m), got shape {array.shape}")
        return array

    def _closed_form(
        self, thetas: np.ndarray, p0: np.ndarray, v0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        vx = v0[:, 0]
        bad = vx >= 0.0
        if np.any(bad):
            theta = thetas[np.argmax(bad)].tolist()
            raise ShotError(
                f"θ={theta} m points the arrow away from the target (the string hand must be "
                "behind the bow hand, θ[0] > 0)"
            )
        t = (self._plane_x - p0[:, 0]) / vx
        points = p0 + v0 * t[:, None] + 0.5 * GRAVITY * (t * t)[:, None]
        points[:, 0] = self._plane_x
        return points, t

    def _accel(self, v: np.ndarray) -> np.ndarray:
        rel = v - self._wind
        speed = np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] + rel[:, 2] * rel[:, 2])
        return GRAVITY - self.scenario.drag * speed[:, None] * rel

    def _rk4(self, p: np.ndarray, v: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        a1 = self._accel(v)
        v2 = v + 0.5 * dt * a1
        a2 = self._accel(v2)
        v3 = v + 0.5 * dt * a2
        a3 = self._accel(v3)
        v4 = v + dt * a3
        a4 = self._accel(v4)
        p_next = p + dt / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v_next = v + dt / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        return p_next, v_next

    def _integrate(
        self, thetas: np.ndarray, p0: np.ndarray, v0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        n = len(thetas)
        points = np.full((n, 3), np.nan)
        times = np.full(n, np.nan)
        done = np.zeros(n, dtype=bool)
        p, v, t = p0.copy(), v0.copy(), 0.0
        dt = self.dt
        while not np.all(done):
            if t >= self.max_time:
                theta = thetas[np.argmin(done)].tolist()
                raise ShotError(
                    f"the arrow shot with θ={theta} m did not reach the target plane "
                    f"x={self._plane_x} m within {self.max_time} s (too much drag or headwind)"
                )
            p_next, v_next = self._rk4(p, v, dt)
            crossed = ~done & (p_next[:, 0] <= self._plane_x)
            if np.any(crossed):
                idx = np.flatnonzero(crossed)
                tau = self._crossing(p[idx], v[idx], p_next[idx], v_next[idx], dt)
                points[idx] = self._hermite(p[idx], v[idx], p_next[idx], v_next[idx], dt, tau)
                points[idx, 0] = self._plane_x
                times[idx] = t + tau * dt
                done |= crossed
            p, v, t = p_next, v_next, t + dt
        return points, times

    def _crossing(
        self, p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray, dt: float
    ) -> np.ndarray:
        """Fraction τ ∈ [0, 1] of the step where the Hermite cubic x(τ) meets the plane."""
        x0, x1 = p0[:, 0], p1[:, 0]
        tau = np.clip((x0 - self._plane_x) / (x0 - x1), 0.0, 1.0)
        for _ in range(8):  # Newton on the cubic, from the linear guess
            x = self._hermite(p0, v0, p1, v1, dt, tau)[:, 0] - self._plane_x
            dx = self._hermite_rate(p0, v0, p1, v1, dt, tau)[:, 0]
            safe = np.where(dx < 0.0, dx, -1e-12)
            tau = np.clip(tau - x / safe, 0.0, 1.0)
        return tau

    @staticmethod
    def _hermite(
        p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray, dt: float, tau: np.ndarray
    ) -> np.ndarray:
        s = tau[:, None]
        h00 = 2 * s**3 - 3 * s**2 + 1
        h10 = s**3 - 2 * s**2 + s
        h01 = -2 * s**3 + 3 * s**2
        h11 = s**3 - s**2
        return h00 * p0 + h10 * dt * v0 + h01 * p1 + h11 * dt * v1

    @staticmethod
    def _hermite_rate(
        p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray, dt: float, tau: np.ndarray
    ) -> np.ndarray:
        """d/dτ of the Hermite cubic (m per unit τ)."""
        s = tau[:, None]
        return (
            (6 * s**2 - 6 * s) * p0
            + (3 * s**2 - 4 * s + 1) * dt * v0
            + (-6 * s**2 + 6 * s) * p1
            + (3 * s**2 - 2 * s) * dt * v1
        )
