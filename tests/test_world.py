"""Tests of ArcheryWorld: joint control, limits, nock and release, impact ground truth, seeding."""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from archery.protocol.errors import ArcheryError, BadRequest, ConfigError
from archery.sim.arrow import Landing, Outcome, drag_acceleration
from archery.sim.bow import Bow
from archery.sim.errors import CommandError, SimError, StateError
from archery.sim.geometry import BOW_HAND, START_THETA, TARGET_DISTANCE, target_centre
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import BOW_HAND_SITE, STRING_HAND_SITE, SceneConfig
from archery.sim.world import ArcheryWorld, ArrowState, WorldConfig
from tests.postures import archery_posture
from tests.world_steps import move_until_done

SCENE = SceneConfig(meshes=False)
EXACT = {"drag": 0.0, "speed_noise": 0.0, "direction_noise": 0.0}
GRAVITY = np.array([0.0, 0.0, -9.81])
PLANE_X = -TARGET_DISTANCE
CENTRE = target_centre(TARGET_DISTANCE)


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_scene(SCENE)


def _aim_theta(length: float = 0.17) -> np.ndarray:
    """θ of that length that a drag-free arrow from BOW_HAND needs to hit the target centre."""
    speed = Bow().launch_speed(np.array([length, 0.0, 0.0]))
    distance = BOW_HAND[0] - PLANE_X
    drop = 0.5 * 9.81 * (distance / speed) ** 2
    elevation = math.atan2(drop, distance)
    return length * np.array([math.cos(elevation), 0.0, -math.sin(elevation)])


@pytest.fixture(scope="module")
def postures(model: mujoco.MjModel) -> dict[str, dict[str, np.ndarray]]:
    return {
        name: archery_posture(model, BOW_HAND, BOW_HAND + theta, tolerance=5e-3)
        for name, theta in {
            "start": START_THETA,
            "aim": _aim_theta(),
            "aim_wider": _aim_theta() + np.array([0.02, 0.01, -0.01]),
        }.items()
    }


def _world(model: mujoco.MjModel, **overrides: object) -> ArcheryWorld:
    return ArcheryWorld(WorldConfig(scene=SCENE, **overrides), model=model)  # type: ignore[arg-type]  # overrides of any WorldConfig field


def _go(world: ArcheryWorld, posture: dict[str, np.ndarray]) -> None:
    for part, values in posture.items():
        world.set_joint_targets(part, values)
    assert move_until_done(world, timeout=15.0)


def _servo_setpoints(world: ArcheryWorld, part: str) -> np.ndarray:
    """The position-servo setpoints of `part` (rad) in the world's MuJoCo data."""
    physics = world.physics
    return physics.data.ctrl[physics.actuator_indices(part)].copy()


def _closed_form(bow: np.ndarray, string: np.ndarray) -> tuple[np.ndarray, float]:
    """Drag-free impact offset r (m) and flight time (s), computed independently of the sim."""
    velocity = Bow().launch_velocity(string - bow)
    t = (bow[0] - PLANE_X) / -velocity[0]
    point = bow + velocity * t + 0.5 * GRAVITY * t**2
    return point[1:] - CENTRE[1:], t


# -- joints --------------------------------------------------------------------------------


def test_reset_restores_home_at_rest_with_the_arrow_stowed(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model)
    home = {part: world.joint_positions(part) for part in world.parts}
    _go(world, postures["start"])
    world.nock()
    world.reset(seed=1)
    assert world.sim_time == 0.0
    assert world.arrow_state is ArrowState.STOWED and world.landing is None
    for part in world.parts:
        np.testing.assert_array_equal(world.joint_positions(part), home[part])
        np.testing.assert_array_equal(world.joint_velocities(part), 0.0)
        np.testing.assert_array_equal(world.joint_targets(part), home[part])
    assert world.motion_done()


def test_a_commanded_posture_is_reached(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model)
    posture = postures["start"]
    _go(world, posture)
    assert world.motion_done()
    for part, values in posture.items():
        assert np.max(np.abs(world.joint_positions(part) - values)) < 1e-3
        assert np.max(np.abs(world.joint_velocities(part))) < 5e-3
    bow, string = world.hand_positions()
    assert np.linalg.norm(bow - BOW_HAND) < 6e-3
    assert np.linalg.norm(string - (BOW_HAND + START_THETA)) < 6e-3
    # Gravity is compensated: a second later the joints sit on their targets, still.
    world.step(1.0)
    for part, values in posture.items():
        assert np.max(np.abs(world.joint_positions(part) - values)) < 1e-5
        assert np.max(np.abs(world.joint_velocities(part))) < 1e-4


def test_joint_limits_are_never_exceeded_even_when_commanded_beyond(model: mujoco.MjModel) -> None:
    world = _world(model, reference_speed=2.0)
    physics = world.physics
    for side in (1.0, -1.0):  # every joint to beyond its upper, then beyond its lower limit
        for part in world.parts:
            low, high = world.joint_limits(part)
            wanted = (high + 1.0) if side > 0 else (low - 1.0)
            applied = world.set_joint_targets(part, wanted)
            np.testing.assert_array_equal(applied, high if side > 0 else low)
            np.testing.assert_array_equal(world.joint_targets(part), applied)
        for _ in range(round(3.0 / world.timestep)):
            world.step()
            for part in world.parts:
                urdf_low, urdf_high = physics.joint_limits(part)
                q = world.joint_positions(part)
                assert np.all(q >= urdf_low) and np.all(q <= urdf_high), (part, q)
        assert world.motion_done()
    for part in world.parts:
        low, high = world.joint_limits(part)
        urdf_low, urdf_high = physics.joint_limits(part)
        assert np.all(low > urdf_low) and np.all(high < urdf_high)


def test_setpoints_move_at_the_reference_speed(model: mujoco.MjModel) -> None:
    world = _world(model)
    speed = 0.3
    world.set_reference_speeds("left_arm", np.full(7, speed))
    np.testing.assert_array_equal(world.reference_speeds("left_arm"), speed)
    start = world.joint_positions("left_arm")
    target = start.copy()
    target[3] += 0.6  # elbow: 2 s at 0.3 rad/s
    world.set_joint_targets("left_arm", target)
    previous = _servo_setpoints(world, "left_arm")
    steps = 0
    while not np.array_equal(_servo_setpoints(world, "left_arm"), target):
        world.step()
        steps += 1
        controls = _servo_setpoints(world, "left_arm")
        assert np.max(np.abs(controls - previous)) <= speed * world.timestep + 1e-12
        previous = controls
    assert steps * world.timestep == pytest.approx(0.6 / speed, abs=2 * world.timestep)
    assert move_until_done(world)


# -- the shot ------------------------------------------------------------------------------


def test_nocked_arrow_sits_on_the_hands_and_follows_them(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model)
    world.nock()
    assert world.arrow_state is ArrowState.NOCKED
    for posture in (postures["start"], postures["aim"]):
        for part, values in posture.items():
            world.set_joint_targets(part, values)
        while not world.motion_done():
            world.step(0.05)
            bow, string = world.hand_positions()
            tip, quat = world.physics.arrow_pose()
            np.testing.assert_allclose(tip, bow, atol=1e-12)
            axis = np.empty(3)
            mujoco.mju_rotVecQuat(axis, np.array([1.0, 0.0, 0.0]), quat)
            np.testing.assert_allclose(
                axis, (bow - string) / np.linalg.norm(bow - string), atol=1e-9
            )


def test_release_lands_on_the_closed_form_ballistic_point(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model, **EXACT)
    _go(world, postures["aim"])
    world.nock()
    bow, string = world.hand_positions()
    landing = world.release()
    expected_r, expected_t = _closed_form(bow, string)
    np.testing.assert_array_equal(landing.launch.position, bow)
    np.testing.assert_allclose(
        landing.launch.velocity, Bow().launch_velocity(string - bow), rtol=1e-12
    )
    assert landing.outcome is Outcome.TARGET and landing.hit and landing.reason is None
    assert landing.r is not None
    np.testing.assert_allclose(landing.r, expected_r, atol=2e-4)  # metres
    assert np.linalg.norm(landing.r) < 0.25
    assert landing.flight_time == pytest.approx(expected_t, abs=1e-4)
    assert landing.point[0] == PLANE_X
    assert landing.sim_time == pytest.approx(landing.launch.sim_time + landing.flight_time)
    # The arrow sticks there: tip on the plane at r, and it does not move afterwards.
    tip, quat = world.physics.arrow_pose()
    np.testing.assert_allclose(tip[1:] - CENTRE[1:], landing.r, atol=1e-12)
    world.step(1.0)
    tip_after, quat_after = world.physics.arrow_pose()
    np.testing.assert_allclose(tip_after, tip, atol=1e-9)
    np.testing.assert_allclose(quat_after, quat, atol=1e-9)
    assert world.arrow_state is ArrowState.LANDED and world.landing is landing


def test_release_with_drag_and_wind_matches_an_ode_solution(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    drag, wind = 0.05, np.array([1.0, -2.0, 0.5])
    world = _world(model, **{**EXACT, "drag": drag, "wind": tuple(wind)})
    _go(world, postures["aim"])
    world.nock()
    bow, string = world.hand_positions()
    landing = world.release()

    def rhs(_t: float, state: np.ndarray) -> np.ndarray:
        return np.concatenate([state[3:], GRAVITY + drag_acceleration(state[3:], wind, drag)])

    def plane(_t: float, state: np.ndarray) -> float:
        return state[0] - PLANE_X

    plane.terminal = True  # type: ignore[attr-defined]  # solve_ivp reads an event's terminal attribute
    start = np.concatenate([bow, Bow().launch_velocity(string - bow)])
    solution = solve_ivp(rhs, (0.0, 2.0), start, events=plane, rtol=1e-11, atol=1e-12)
    point = solution.y_events[0][0][:3]
    assert landing.r is not None
    np.testing.assert_allclose(landing.r, point[1:] - CENTRE[1:], atol=2e-3)
    # The drag and the wind really acted: the drag-free point is clearly elsewhere.
    free_r, _ = _closed_form(bow, string)
    assert np.linalg.norm(free_r - landing.r) > 0.01


def test_same_seed_gives_the_same_landing_bit_for_bit(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model, wind_gust=0.5)  # default drag and launch noise, plus gusts

    def rollout(seed: int) -> tuple[Landing, np.ndarray]:
        world.reset(seed=seed)
        _go(world, postures["aim"])
        world.nock()
        landing = world.release()
        return landing, world.qpos()

    first, qpos_first = rollout(5)
    second, qpos_second = rollout(5)
    other, _ = rollout(6)
    assert first.r is not None and second.r is not None and other.r is not None
    np.testing.assert_array_equal(first.r, second.r)
    np.testing.assert_array_equal(first.launch.velocity, second.launch.velocity)
    np.testing.assert_array_equal(first.launch.wind, second.launch.wind)
    assert first.sim_time == second.sim_time
    np.testing.assert_array_equal(qpos_first, qpos_second)
    assert not np.array_equal(first.r, other.r)


def test_launch_and_step_equal_release(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model)
    world.reset(seed=9)
    _go(world, postures["aim"])
    world.nock()
    blocking = world.release()
    world.reset(seed=9)
    _go(world, postures["aim"])
    world.nock()
    world.launch()
    assert world.arrow_state is ArrowState.FLYING
    landing = None
    while landing is None:
        landing = world.step(0.003)
    assert landing.r is not None and blocking.r is not None
    np.testing.assert_array_equal(landing.r, blocking.r)
    assert landing.sim_time == blocking.sim_time


def test_a_shot_without_draw_drops_to_the_ground(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model, bow=Bow(brace_height=0.5), **EXACT)  # the hands never pass the brace
    _go(world, postures["start"])
    world.nock()
    bow, _ = world.hand_positions()
    landing = world.release()
    assert landing.outcome is Outcome.GROUND and not landing.hit and landing.reason == "ground"
    assert landing.r is None
    assert landing.point[2] == -SCENE.root_height
    np.testing.assert_allclose(landing.point[:2], bow[:2], atol=1e-9)
    fall = math.sqrt(2 * (bow[2] + SCENE.root_height) / 9.81)
    assert landing.flight_time == pytest.approx(fall, abs=1e-4)


def test_a_shot_blown_off_the_face_is_a_miss_on_the_plane(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model, drag=0.05, wind=(0.0, 20.0, 0.0), speed_noise=0.0, direction_noise=0.0)
    _go(world, postures["aim"])
    world.nock()
    landing = world.release()
    assert landing.outcome is Outcome.OUTSIDE_FACE and landing.reason == "outside_face"
    assert landing.r is not None and landing.r[0] > 0.25  # blown to the robot's right
    assert landing.point[0] == PLANE_X


def test_a_flight_that_lasts_too_long_times_out(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model, max_flight_time=0.05, **EXACT)
    _go(world, postures["aim"])
    world.nock()
    landing = world.release()
    assert landing.outcome is Outcome.TIMEOUT and landing.r is None
    assert landing.flight_time == pytest.approx(0.05, abs=world.timestep)


def test_qpos_alone_reproduces_the_scene_for_a_renderer(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model)
    _go(world, postures["aim"])
    world.nock()
    world.release()
    copy = ScenePhysics(build_scene(SCENE))
    copy.data.qpos[:] = world.qpos()
    copy.kinematics()
    bow, string = world.hand_positions()
    np.testing.assert_array_equal(copy.site_position(BOW_HAND_SITE), bow)
    np.testing.assert_array_equal(copy.site_position(STRING_HAND_SITE), string)
    np.testing.assert_array_equal(copy.arrow_tip(), world.physics.arrow_tip())


# -- errors --------------------------------------------------------------------------------


def test_bad_commands_raise_clear_errors(model: mujoco.MjModel) -> None:
    world = _world(model)
    with pytest.raises(
        CommandError, match=r"unknown part 'neck'; parts: torso, left_arm, right_arm"
    ):
        world.set_joint_targets("neck", [0.0, 0.0, 0.0])
    with pytest.raises(CommandError, match=r"must have 7 values \(l_shoulder_pitch"):
        world.set_joint_targets("left_arm", [0.0] * 6)
    with pytest.raises(CommandError, match="must be finite"):
        world.set_joint_targets("torso", [0.0, float("nan"), 0.0])
    with pytest.raises(CommandError, match="must be 3 numbers"):
        world.set_joint_targets("torso", ["a", "b", "c"])
    with pytest.raises(CommandError, match="reference speeds"):
        world.set_reference_speeds("torso", [0.1, 0.0, 0.1])
    with pytest.raises(CommandError, match="duration"):
        world.step(-1.0)
    with pytest.raises(CommandError, match="duration"):
        world.step(float("inf"))
    # A rejected command changes nothing.
    np.testing.assert_array_equal(world.joint_targets("torso"), [0.0, 0.0, 0.0])


def test_shot_commands_in_the_wrong_state_raise(model: mujoco.MjModel) -> None:
    world = _world(model)
    with pytest.raises(StateError, match=r"no arrow is nocked \(the arrow is stowed\)"):
        world.release()
    world.nock()
    world.launch()
    with pytest.raises(StateError, match="cannot reset while an arrow is flying"):
        world.reset(seed=0)
    with pytest.raises(StateError, match="in flight"):
        world.nock()
    with pytest.raises(StateError, match="the arrow is flying"):
        world.launch()
    while world.step(0.01) is None:
        pass
    with pytest.raises(StateError, match="the arrow is landed"):
        world.release()
    world.reset(seed=0)  # allowed again once the arrow has landed
    assert issubclass(StateError, SimError) and issubclass(CommandError, SimError)
    assert issubclass(SimError, ArcheryError) and issubclass(CommandError, BadRequest)
    assert (StateError.code, CommandError.code, ConfigError.code) == (
        "bad_state",
        "bad_request",
        "bad_config",
    )


def test_world_config_is_validated(model: mujoco.MjModel) -> None:
    with pytest.raises(ConfigError, match="drag"):
        WorldConfig(scene=SCENE, drag=-0.1)
    with pytest.raises(ConfigError, match="wind"):
        WorldConfig(scene=SCENE, wind=(1.0, 2.0))  # type: ignore[arg-type]  # 2 components on purpose
    with pytest.raises(ConfigError, match="reference_speed"):
        WorldConfig(scene=SCENE, reference_speed=10.0)
    with pytest.raises(ConfigError, match="arrow mass"):
        WorldConfig(scene=SCENE, bow=Bow(arrow_mass=0.05))
    with pytest.raises(ConfigError, match="timestep"):
        ArcheryWorld(WorldConfig(scene=SceneConfig(meshes=False, timestep=0.001)), model=model)
    config = WorldConfig(scene=SCENE, drag=0.03, wind=(0.5, 0.0, 0.0))
    assert WorldConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ConfigError, match=r"unknown world parameters \['gravity'\]"):
        WorldConfig.from_dict({"gravity": 9.81})


def test_landing_serialises_to_plain_data(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    world = _world(model, **EXACT)
    _go(world, postures["aim"])
    world.nock()
    landing = world.release()
    data = landing.to_dict()
    assert data["outcome"] == "target" and data["hit"] is True
    assert data["r"] == landing.r.tolist()  # type: ignore[union-attr]  # a target landing has r
    assert data["launch"]["theta"] == landing.launch.theta.tolist()  # type: ignore[index]  # to_dict nests the launch dict
    json.dumps(data)


def test_skipped_shots_draw_the_noise_their_launches_would(
    model: mujoco.MjModel, postures: dict[str, dict[str, np.ndarray]]
) -> None:
    # three shots in a row, then the third again after skipping two: the same launch
    config = {"wind_gust": 0.5, "speed_noise": 0.05, "direction_noise": 0.01}
    world = _world(model, **config)
    world.reset(11)
    _go(world, postures["aim"])
    launches = []
    for _ in range(3):
        world.nock()
        launches.append(world.release().launch)
    again = _world(model, **config)
    again.reset(11)
    _go(again, postures["aim"])
    again.skip_shots(2)
    again.nock()
    third = again.release().launch
    # the gust is drawn after the launch's own three numbers: equal gusts, equal stream
    np.testing.assert_array_equal(third.wind, launches[2].wind)
    assert not np.array_equal(launches[1].wind, launches[2].wind)
    # the hands moved a little in the first world's flights: the velocities are close
    np.testing.assert_allclose(third.velocity, launches[2].velocity, atol=0.01)
    for bad in (-1, 1.5, True):
        with pytest.raises(CommandError, match="count must be an integer >= 0"):
            again.skip_shots(bad)  # type: ignore[arg-type]  # a wrong type on purpose
