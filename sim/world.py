"""The simulated archery robot as a seeded, Gymnasium-like world: joints, nock, release, landing.

`ArcheryWorld` is the task logic on top of the physics queries of `sim.scene.ScenePhysics`:
position-controlled joints per YARP part (targets clamped to the joint limits and approached at
a limited reference speed, like iCub's position control), an arrow that is stowed, nocked
between the hands (in the whole shot first grasped, `sim.whole_shot`), flying or landed, and
the shot of `sim.arrow`. Units: metres, radians,
seconds, root frame (x backward, y right, z up).

`reset(seed)` restores the home posture at time 0 and seeds the shot noise, so the same seed
and the same commands give the same landing bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Protocol

import mujoco
import numpy as np

from archery.protocol.errors import ConfigError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import MAX_REFERENCE_SPEED, REFERENCE_SPEED, home_of
from archery.protocol.vectors import finite_vector
from archery.sim.arrow import ArrowFlight, Landing, Launch, arrow_quat, launch_velocity
from archery.sim.bow import Bow
from archery.sim.errors import ArrowDropped, CommandError, StateError
from archery.sim.geometry import START_THETA, TARGET_DIAMETER, target_centre
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import SceneConfig
from archery.sim.whole_shot import WholeShot

__all__ = ["ArcheryWorld", "ArrowState", "SetpointSource", "WorldConfig"]


class SetpointSource(Protocol):
    """What `ArcheryWorld.play` follows: the joints it drives (indices of the world's joint
    vector, `ArcheryWorld.joint_indices`) and their setpoints (rad) at a simulated time (s)."""

    joints: np.ndarray

    def setpoints(self, sim_time: float) -> np.ndarray: ...


class ArrowState(StrEnum):
    """Where the arrow is."""

    STOWED = "stowed"  # beside the robot (in the whole shot: in its holder), not on the bow
    GRASPED = "grasped"  # in the right hand, off the string (the whole shot)
    NOCKED = "nocked"  # tip at the bow hand, along the string-to-bow-hand line, following the hands
    DROPPED = "dropped"  # fell from the opened hand; lies on the floor once there
    FLYING = "flying"
    LANDED = "landed"  # frozen where it met the target plane or the floor, or timed out


@dataclass(frozen=True)
class WorldConfig:
    """Every parameter of the simulated robot and shot, validated.

    Attributes:
        scene: the MuJoCo scene's parameters.
        bow: the bow model (its arrow mass must equal the scene's).
        drag: K of the drag law a = −K‖v − w‖(v − w) (1/m); 0 switches drag off.
        wind: constant wind velocity (m/s, root frame); acts through drag only.
        wind_gust: standard deviation of a random wind added per shot, per axis (m/s).
        speed_noise: relative standard deviation of the launch speed (the bow's variability).
        direction_noise: standard deviation of the launch direction, per axis (rad).
        reference_speed: default joint reference speed: how fast a joint's setpoint moves
            toward its target (rad/s).
        position_tolerance: motion is done when every joint is this close to its target (rad).
        velocity_tolerance: … and every joint is slower than this (rad/s).
        max_flight_time: a flight still going after this long ends as a timeout (s).
        grasp_tolerance: the whole shot's grasp takes the arrow only when the hand's grasp site
            is at most this far from its shaft (m).
        nock_tolerance: the whole shot's nock takes only when the arrow's nock is at most this
            far from the string's rest nocking point (m).
    """

    scene: SceneConfig = field(default_factory=SceneConfig)
    bow: Bow = field(default_factory=Bow)
    drag: float = 0.02
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    wind_gust: float = 0.0
    speed_noise: float = 0.01
    direction_noise: float = 0.002
    reference_speed: float = REFERENCE_SPEED
    position_tolerance: float = 1e-3
    velocity_tolerance: float = 5e-3
    max_flight_time: float = 3.0
    grasp_tolerance: float = 0.015
    nock_tolerance: float = 0.02

    def __post_init__(self) -> None:
        if not isinstance(self.scene, SceneConfig):
            raise ConfigError(f"scene must be a SceneConfig, got {self.scene!r}")
        if not isinstance(self.bow, Bow):
            raise ConfigError(f"bow must be a sim.bow.Bow, got {self.bow!r}")
        if self.bow.arrow_mass != self.scene.arrow_mass:
            raise ConfigError(
                f"the bow's arrow mass {self.bow.arrow_mass} kg differs from the scene's "
                f"{self.scene.arrow_mass} kg; set both to the same value"
            )
        wind = finite_vector("wind", self.wind, ConfigError, unit="m/s")
        object.__setattr__(self, "wind", tuple(wind.tolist()))
        bounds = {
            "drag": (0.0, 10.0),
            "wind_gust": (0.0, 50.0),
            "speed_noise": (0.0, 1.0),
            "direction_noise": (0.0, 1.0),
            "reference_speed": (1e-3, MAX_REFERENCE_SPEED),
            "position_tolerance": (1e-6, 0.5),
            "velocity_tolerance": (1e-6, 5.0),
            "max_flight_time": (0.01, 60.0),
            "grasp_tolerance": (1e-4, 0.1),
            "nock_tolerance": (1e-4, 0.1),
        }
        for name, (low, high) in bounds.items():
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ConfigError(f"{name} must be a finite number, got {value!r}")
            if not low <= value <= high:
                raise ConfigError(f"{name} must be in [{low}, {high}], got {value!r}")
            object.__setattr__(self, name, float(value))

    @classmethod
    def from_dict(cls, values: dict[str, object]) -> WorldConfig:
        """The config from `to_dict`'s output (nested scene and bow dicts accepted).

        Raises:
            ConfigError: an unknown parameter name or an invalid value.
        """
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown world parameters {unknown}; valid: {sorted(known)}")
        kwargs = dict(values)
        try:
            if isinstance(kwargs.get("scene"), dict):
                kwargs["scene"] = SceneConfig(**kwargs["scene"])  # type: ignore[arg-type]  # a dict (isinstance above)
            if isinstance(kwargs.get("bow"), dict):
                kwargs["bow"] = Bow(**kwargs["bow"])  # type: ignore[arg-type]  # a dict (isinstance above)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"invalid scene or bow parameters: {exc}") from exc
        return cls(**kwargs)  # type: ignore[arg-type]  # WorldConfig checks the values

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly copy of the parameters."""
        out: dict[str, object] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, SceneConfig):
                value = value.to_dict()
            elif isinstance(value, Bow):
                value = {g.name: getattr(value, g.name) for g in fields(value)}
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out


class ArcheryWorld:
    """The simulated iCub archer: seeded, steppable, with a blocking `release`.

    Args:
        config: world parameters (defaults if None).
        model: a model built by `sim.scene.build_scene(config.scene)`, to share one build
            between worlds; built here if None.
    """

    def __init__(
        self, config: WorldConfig | None = None, model: mujoco.MjModel | None = None
    ) -> None:
        self.config = WorldConfig() if config is None else config
        if model is None:
            model = build_scene(self.config.scene)
        elif abs(model.opt.timestep - self.config.scene.timestep) > 1e-15:
            raise ConfigError(
                f"the model's timestep {model.opt.timestep} s differs from the scene config's "
                f"{self.config.scene.timestep} s; build the model with build_scene(config.scene)"
            )
        self.physics = ScenePhysics(model)
        self._dt = self.physics.timestep
        self._centre = target_centre(self.config.scene.target_distance)
        self._parts = tuple(PARTS)
        self._slices: dict[str, slice] = {}
        start = 0
        for part in self._parts:
            self._slices[part] = slice(start, start + len(PARTS[part]))
            start += len(PARTS[part])
        self._act = np.concatenate([self.physics.actuator_indices(p) for p in self._parts])
        # Software limits: the URDF limits shrunk by the stops' margin (see SceneConfig).
        margin = np.concatenate([self.physics.joint_margins(p) for p in self._parts])
        self._lower = (
            np.concatenate([self.physics.joint_limits(p)[0] for p in self._parts]) + margin
        )
        self._upper = (
            np.concatenate([self.physics.joint_limits(p)[1] for p in self._parts]) - margin
        )
        self._qadr = np.concatenate([self.physics.qpos_indices(p) for p in self._parts])
        self._dadr = np.concatenate([self.physics.dof_indices(p) for p in self._parts])
        self._home = np.concatenate([home_of(p) for p in self._parts])
        self._target = self._home.copy()
        self._reference = self._home.copy()
        self._speed = np.full(self._home.size, self.config.reference_speed)
        self._ramping = False
        # the buffers of `_advance_setpoints`, and the servos' controls (a view of the data)
        self._step, self._low, self._delta = (np.empty(self._home.size) for _ in range(3))
        self._ctrl = self.physics.data.ctrl
        self._sources: list[SetpointSource] = []  # trajectories playing (`play`)
        self._rng = np.random.default_rng()  # fresh entropy until reset(seed) is called
        self._arrow = ArrowState.STOWED
        self._flight: ArrowFlight | None = None
        self._landing: Landing | None = None
        self._hold_pose: tuple[np.ndarray, np.ndarray] | None = None
        self.whole: WholeShot | None = None
        if self.config.scene.shot == "whole":
            self.whole = WholeShot(
                self.physics, self.config.grasp_tolerance, self.config.nock_tolerance
            )
        self.reset()

    # -- episode ----------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> None:
        """Restore the home posture at rest, time 0, the arrow stowed; reseed if `seed` given.

        Without a seed the noise stream continues (from fresh entropy if never seeded), as in
        Gymnasium.

        Raises:
            StateError: an arrow is in flight (let it land first).
        """
        if self._arrow is ArrowState.FLYING:
            raise StateError("cannot reset while an arrow is flying; step until it lands first")
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        physics = self.physics
        physics.reset()
        self._target = self._home.copy()
        self._reference = self._home.copy()
        self._speed[:] = self.config.reference_speed
        self._ramping = False
        self._sources.clear()
        physics.data.qpos[self._qadr] = self._home
        physics.data.ctrl[self._act] = self._home
        self._flight = None
        self._landing = None
        self._stow()
        if self.whole is not None:
            self.whole.reset()
        physics.forward()

    # -- joints -----------------------------------------------------------------------------
    def _part(self, part: object) -> slice:
        if not isinstance(part, str) or part not in self._slices:
            raise CommandError(f"unknown part {part!r}; parts: {', '.join(self._parts)}")
        return self._slices[part]

    def _vector(self, part: str, values: object, what: str) -> np.ndarray:
        names = PARTS[part]
        try:
            array = np.asarray(values, dtype=float)
        except (TypeError, ValueError) as exc:
            raise CommandError(
                f"{part} {what} must be {len(names)} numbers, got {values!r}"
            ) from exc
        if array.shape != (len(names),):
            raise CommandError(
                f"{part} {what} must have {len(names)} values ({', '.join(names)}), "
                f"got shape {array.shape}"
            )
        if not np.all(np.isfinite(array)):
            raise CommandError(f"{part} {what} must be finite, got {array.tolist()}")
        return array

    @property
    def parts(self) -> tuple[str, ...]:
        """The controlled parts, e.g. ("torso", "left_arm", "right_arm")."""
        return self._parts

    def joint_names(self, part: str) -> tuple[str, ...]:
        """Joint names of `part` in YARP order."""
        self._part(part)
        return PARTS[part]

    def joint_limits(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) software limits of `part`'s joints (rad): targets are clamped to these.

        They lie `SceneConfig.limit_margin` inside the URDF limits, which joints never pass.
        """
        s = self._part(part)
        return self._lower[s].copy(), self._upper[s].copy()

    def joint_positions(self, part: str) -> np.ndarray:
        """Joint angles of `part` (rad)."""
        return self.physics.data.qpos[self._qadr[self._part(part)]].copy()

    def joint_velocities(self, part: str) -> np.ndarray:
        """Joint velocities of `part` (rad/s)."""
        return self.physics.data.qvel[self._dadr[self._part(part)]].copy()

    def joint_targets(self, part: str) -> np.ndarray:
        """Current (clamped) position targets of `part` (rad)."""
        return self._target[self._part(part)].copy()

    def set_joint_targets(self, part: str, values: object) -> np.ndarray:
        """Command `part`'s joints to `values` (rad, YARP order), clamped to the joint limits.

        The servos' setpoints then move toward the targets at the reference speeds.

        Returns:
            The targets actually applied (rad), after clamping.

        Raises:
            CommandError: unknown part, wrong number of values, non-finite value.
        """
        s = self._part(part)
        array = self._vector(part, values, "targets")
        clamped = np.clip(array, self._lower[s], self._upper[s])
        self._target[s] = clamped
        self._ramping = True
        return clamped.copy()

    def hold(self, part: str) -> np.ndarray:
        """Stop `part` where it is: its targets *and* its servos' setpoints become the measured
        positions (clamped to the limits), so the setpoints do not first ramp back from where
        they had run ahead. The joints then come to rest within the servos' settling time.

        Returns:
            The positions held (rad).
        """
        s = self._part(part)
        held = np.clip(self.physics.data.qpos[self._qadr[s]], self._lower[s], self._upper[s])
        self._target[s] = held
        self._reference[s] = held
        self.physics.data.ctrl[self._act[s]] = held
        return held.copy()

    def reference_speeds(self, part: str) -> np.ndarray:
        """Reference speeds of `part`'s joints (rad/s)."""
        return self._speed[self._part(part)].copy()

    def set_reference_speeds(self, part: str, speeds: object) -> np.ndarray:
        """Set how fast `part`'s setpoints move toward their targets (rad/s, 0 < each ≤ 2).

        Raises:
            CommandError: unknown part, wrong number of values, non-finite or non-positive value.
        """
        s = self._part(part)
        array = self._vector(part, speeds, "reference speeds")
        if np.any(array <= 0) or np.any(array > MAX_REFERENCE_SPEED):
            raise CommandError(
                f"{part} reference speeds must be in (0, {MAX_REFERENCE_SPEED}] rad/s, "
                f"got {array.tolist()}"
            )
        self._speed[s] = array
        return array.copy()

    def motion_done(self, part: str | None = None) -> bool:
        """True when every setpoint has reached its target and every joint has settled there.

        With `part`, only that part's joints are checked (iCub's per-controlboard
        checkMotionDone); position within `position_tolerance` (rad), speed below
        `velocity_tolerance` (rad/s).
        """
        if part is None:
            if self._ramping or self._playing(None):
                return False
            s = slice(None)
        else:
            s = self._part(part)
            if self._ramping and not np.array_equal(self._reference[s], self._target[s]):
                return False
            if self._playing(s):
                return False
        data = self.physics.data
        error = np.max(np.abs(data.qpos[self._qadr[s]] - self._target[s]))
        speed = np.max(np.abs(data.qvel[self._dadr[s]]))
        return bool(
            error < self.config.position_tolerance and speed < self.config.velocity_tolerance
        )

    # -- time -------------------------------------------------------------------------------
    @property
    def sim_time(self) -> float:
        """Simulated time since the last reset (s)."""
        return self.physics.time

    @property
    def timestep(self) -> float:
        """Physics timestep (s)."""
        return self._dt

    def step(self, duration: float | None = None) -> Landing | None:
        """Advance the simulation by `duration` seconds (one timestep if None).

        The duration is rounded to a whole number of timesteps (at least one).

        Returns:
            The landing, if an arrow landed during this call; else None.

        Raises:
            CommandError: the duration is negative or not finite.
        """
        if duration is None:
            n = 1
        else:
            if not isinstance(duration, int | float) or not math.isfinite(duration) or duration < 0:
                raise CommandError(
                    f"duration must be a finite number of seconds >= 0, got {duration!r}"
                )
            n = max(1, round(duration / self._dt))
        landed = None
        physics = self.physics
        data = physics.data
        model = physics.model
        flight = self._flight
        if self._ramping:  # the speeds hold for the whole call: the per-step bounds, once
            np.multiply(self._speed, self._dt, out=self._step)
            np.negative(self._step, out=self._low)
        sources = self._sources
        for _ in range(n):
            for source in sources:
                self._drive(source, physics.time + self._dt)
            if self._ramping:
                self._advance_setpoints()
            if flight is not None:
                flight.before_step()
            mujoco.mj_step(model, data)
            if flight is not None:
                landing = flight.after_step()
                if landing is not None:
                    landed = self._landed(landing)
                    flight = None
        self._hold_arrow()
        return landed

    def _advance_setpoints(self) -> None:
        """Move every setpoint one step toward its target, by at most speed × dt. It runs before
        each physics step of a motion, so it is `np.clip(target − reference, −step, step)`
        spelled out on kept buffers (the same operations, the same bits): 3× cheaper. The
        bounds ±step (rad: speed × dt) are those `step` computed for its call."""
        step, delta = self._step, self._delta
        np.subtract(self._target, self._reference, out=delta)
        np.maximum(delta, self._low, out=delta)
        np.minimum(delta, step, out=delta)
        self._reference += delta
        if (self._reference == self._target).all():
            self._ramping = False
        self._ctrl[self._act] = self._reference

    # -- trajectories -----------------------------------------------------------------------
    def joint_indices(self, part: str, names: Sequence[str] | None = None) -> np.ndarray:
        """Where `part`'s joints (`names`, YARP order when None) sit in the world's joint
        vector, the indices a `SetpointSource` names.

        Raises:
            CommandError: unknown part or joint name.
        """
        s = self._part(part)
        joints = PARTS[part]
        if names is None:
            return np.arange(s.start, s.stop)
        unknown = [n for n in names if n not in joints]
        if unknown:
            raise CommandError(f"{part} has no joint {unknown[0]!r}; joints: {', '.join(joints)}")
        return np.array([s.start + joints.index(n) for n in names], dtype=int)

    def setpoints_of(self, joints: np.ndarray) -> np.ndarray:
        """The servos' setpoints (rad) of the joints at `joints` (`joint_indices`)."""
        return self._reference[joints].copy()

    def positions_of(self, joints: np.ndarray) -> np.ndarray:
        """The measured angles (rad) of the joints at `joints` (`joint_indices`)."""
        return self.physics.data.qpos[self._qadr[joints]].copy()

    def play(self, source: SetpointSource) -> None:
        """From the next step on, `source` sets its joints' setpoints (and targets) before every
        physics step, clamped to the limits, until `unplay`; its parts are not done moving
        meanwhile."""
        self._sources.append(source)

    def unplay(self, source: SetpointSource) -> None:
        """Stop playing `source` (its joints keep the setpoints it last gave)."""
        if source in self._sources:
            self._sources.remove(source)

    def _playing(self, s: slice | None) -> bool:
        if s is None:
            return bool(self._sources)
        return any(
            bool(np.any((source.joints >= s.start) & (source.joints < s.stop)))
            for source in self._sources
        )

    def _drive(self, source: SetpointSource, sim_time: float) -> None:
        joints = source.joints
        values = np.clip(source.setpoints(sim_time), self._lower[joints], self._upper[joints])
        self._target[joints] = values
        self._reference[joints] = values
        self._ctrl[self._act[joints]] = values

    # -- the arrow --------------------------------------------------------------------------
    @property
    def arrow_state(self) -> ArrowState:
        """Where the arrow is: stowed, nocked, flying or landed."""
        return self._arrow

    @property
    def arrow_falling(self) -> bool:
        """True while a dropped arrow falls (it lies still once on the floor)."""
        return self._arrow is ArrowState.DROPPED and self._hold_pose is None

    @property
    def landing(self) -> Landing | None:
        """The last shot's landing since the last reset, if any."""
        return self._landing

    def _stow(self) -> None:
        self._hold(*self.physics.stowed_arrow_pose())
        self._arrow = ArrowState.STOWED
        if self.whole is not None:  # the holder's weld holds it
            self._hold_pose = None
            self.physics.set_arrow_force(np.zeros(3))
            self.physics.data.eq_active[:] = self.physics.model.eq_active0

    def _hold(self, tip: np.ndarray, quat: np.ndarray) -> None:
        physics = self.physics
        self._hold_pose = (tip, quat)
        physics.set_arrow_pose(tip, quat)
        physics.set_arrow_velocity(np.zeros(3))
        physics.set_arrow_force(-physics.arrow_mass * physics.gravity)

    def _hold_arrow(self) -> None:
        """Re-pin a held arrow: on the hands when nocked, else where it was left."""
        if self.whole is not None:
            self._hold_whole(self.whole)
            return
        if self._arrow is ArrowState.FLYING:
            return
        if self._arrow is ArrowState.NOCKED:
            self.physics.kinematics()
            bow, string = self.physics.hand_positions()
            self._hold(bow, arrow_quat(bow - string))
        elif self._hold_pose is not None:
            self._hold(*self._hold_pose)

    def _hold_whole(self, whole: WholeShot) -> None:
        """The whole shot's pins: the string's nocking point, a nocked arrow; a dropped arrow
        lies where it met the floor."""
        self.physics.kinematics()
        whole.pin()
        if self._arrow is ArrowState.DROPPED:
            if self._hold_pose is None:
                tip, quat = self.physics.arrow_pose()
                floor = -self.config.scene.root_height
                if tip[2] > floor:
                    return
                tip[2] = floor
                self._hold_pose = (tip, quat)
            self._hold(*self._hold_pose)
        elif self._arrow is ArrowState.LANDED and self._hold_pose is not None:
            self._hold(*self._hold_pose)

    def grasp(self) -> float:
        """Whole shot: close the right hand's fingers on the arrow in its holder (a landed or
        dropped arrow is first replaced by the holder's next one).

        Returns:
            The grasp site's distance from the shaft (m), within `grasp_tolerance`.

        Raises:
            StateError: not a whole-shot world, an arrow is in the hand, on the string or in
                flight. GraspMissed: the hand is farther than `grasp_tolerance` from the shaft;
                the arrow stays in its holder.
        """
        whole = self._whole_shot()
        if self._arrow is not ArrowState.STOWED:
            if self._arrow not in (ArrowState.LANDED, ArrowState.DROPPED):
                raise StateError(f"the arrow is {self._arrow.value}; only one is taken at a time")
            self._stow()
        distance = whole.grasp()
        self._arrow = ArrowState.GRASPED
        self._hold_pose = None
        return distance

    def _whole_shot(self) -> WholeShot:
        if self.whole is None:
            raise StateError("the world's shot is 'posture': grasping needs shot 'whole'")
        return self.whole

    def hand_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """(bow hand, string hand) positions now (m): sites `l_hand_dh_frame`, `r_hand_dh_frame`."""
        self.physics.kinematics()
        return self.physics.hand_positions()

    def theta(self) -> np.ndarray:
        """θ = p_string − p_bow now (m), the paper's policy parameter as actually reached."""
        bow, string = self.hand_positions()
        return string - bow

    def nock(self) -> float:
        """Take a fresh arrow onto the bow: tip at the bow hand, pointing away from the string hand.

        A landed arrow is taken back; the nocked arrow follows the hands until `release`. In the
        whole shot the grasped arrow's nock goes onto the string instead (`sim.whole_shot`).

        Returns:
            The nock's distance from the string (m): 0 for the posture shot.

        Raises:
            StateError: an arrow is in flight (whole shot: no arrow is in the hand).
            NockMissed: whole shot, the nock is farther than `nock_tolerance` from the string.
        """
        if self._arrow is ArrowState.FLYING:
            raise StateError("an arrow is in flight; wait for it to land before nocking another")
        if self.whole is not None:
            if self._arrow is not ArrowState.GRASPED:
                raise StateError(
                    f"the arrow is {self._arrow.value}, not in the hand; grasp it first"
                )
            distance = self.whole.nock()
            self._arrow = ArrowState.NOCKED
            return distance
        self._arrow = ArrowState.NOCKED
        self._hold_arrow()
        return 0.0

    def launch(self) -> Launch:
        """Release the string: the arrow starts flying; advance it with `step`. In the whole
        shot the fingers open, and the arrow leaves from where it lies, its θ the nock's from the
        bow hand (`sim.whole_shot`); a grasped arrow not on the string falls.

        Raises:
            StateError: no arrow is nocked. NoArrowDirection: the hands coincide.
            ArrowDropped: whole shot, the arrow was in the hand but not on the string.
        """
        if self.whole is not None and self._arrow is ArrowState.GRASPED:
            try:
                self.whole.release()
            except ArrowDropped:
                self._arrow = ArrowState.DROPPED
                self._hold_pose = None
                self.physics.set_arrow_force(np.zeros(3))
                raise
        if self._arrow is not ArrowState.NOCKED:
            raise StateError(
                f"no arrow is nocked (the arrow is {self._arrow.value}); call nock() first"
            )
        cfg = self.config
        rng = self._rng
        bow, string = self.hand_positions()
        theta = string - bow  # θ measured, once: the launch's and the reply's; in the whole
        start = bow
        if self.whole is not None:
            start, theta = self.whole.release()  # shot, the arrow's: its nock's from the bow hand
        velocity = launch_velocity(
            theta, cfg.bow, rng, speed_noise=cfg.speed_noise, direction_noise=cfg.direction_noise
        )
        wind = self._draw_wind()
        launch = Launch(
            position=start,
            velocity=velocity,
            theta=theta,
            wind=wind,
            sim_time=self.physics.time,
        )
        scene = cfg.scene
        self._flight = ArrowFlight(
            self.physics,
            launch,
            drag=cfg.drag,
            plane_x=-scene.target_distance,
            centre=self._centre,
            face_radius=TARGET_DIAMETER / 2,
            floor_z=-scene.root_height,
            max_flight_time=cfg.max_flight_time,
        )
        self._arrow = ArrowState.FLYING
        self._hold_pose = None
        return launch

    def _draw_wind(self) -> np.ndarray:
        """The wind of a shot (m/s): the constant wind plus this shot's gust."""
        cfg = self.config
        return np.asarray(cfg.wind) + cfg.wind_gust * self._rng.standard_normal(3)

    def skip_shots(self, count: int) -> None:
        """Advance the shot noise as `count` launches would, without shooting: after
        `reset(seed)` and `skip_shots(n)` the next launch draws the noise of shot n + 1 of a
        world reset with the same seed (to replay one shot of a session).

        Raises:
            CommandError: count is not an integer >= 0.
        """
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise CommandError(f"count must be an integer >= 0, got {count!r}")
        cfg = self.config
        for _ in range(count):
            launch_velocity(
                START_THETA,
                cfg.bow,
                self._rng,
                speed_noise=cfg.speed_noise,
                direction_noise=cfg.direction_noise,
            )
            self._draw_wind()

    def release(self) -> Landing:
        """Release and simulate the flight to its end; the robot keeps moving meanwhile.

        Returns:
            The landing: hit with r on the target face, or a miss with its reason.

        Raises:
            StateError: no arrow is nocked. NoArrowDirection: the hands coincide.
        """
        self.launch()
        while True:
            landing = self.step(0.01)
            if landing is not None:
                return landing

    def _landed(self, landing: Landing) -> Landing:
        self._flight = None
        self._landing = landing
        self._arrow = ArrowState.LANDED
        self._hold_pose = self.physics.arrow_pose()
        return landing

    # -- rendering ----------------------------------------------------------------------------
    def qpos(self) -> np.ndarray:
        """The full MuJoCo position vector (robot joints and arrow pose): all a renderer needs."""
        return self.physics.qpos()

    @property
    def model(self) -> mujoco.MjModel:
        """The compiled scene."""
        return self.physics.model
