"""Tests of the analytic ballistic world (sim.ballistic)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.sim.ballistic import GRAVITY, BallisticWorld, Scenario, ScenarioError, ShotError
from archery.sim.bow import Bow
from archery.sim.geometry import BOW_HAND, START_THETA, TARGET_DISTANCE, target_centre

thetas_in_box = st.tuples(
    st.floats(0.12, 0.28), st.floats(-0.08, 0.08), st.floats(-0.08, 0.08)
).map(np.array)


def test_level_shot_drops_by_the_free_fall_formula() -> None:
    # θ straight backward: the arrow leaves level along −x at v = d·sqrt(η·k/m).
    theta = np.array([0.20, 0.0, 0.0])
    bow = Bow()
    v = (0.20 - bow.brace_height) * math.sqrt(bow.efficiency * bow.stiffness / bow.arrow_mass)
    t = (TARGET_DISTANCE + BOW_HAND[0]) / v
    shot = BallisticWorld().step(theta)
    assert shot.flight_time == pytest.approx(t, rel=1e-12)
    assert shot.r_true == pytest.approx([0.0, -0.5 * 9.81 * t * t], abs=1e-12)
    assert shot.point[0] == pytest.approx(-TARGET_DISTANCE)
    assert not shot.hit


def test_aiming_left_lands_left_and_up_lands_up() -> None:
    # r[0] is to the robot's right (+y): a string hand to the right (θ_y > 0) sends the arrow left.
    world = BallisticWorld()
    base = world.step(np.array([0.2, 0.0, 0.0])).r_true
    left = world.step(np.array([0.2, 0.01, 0.0])).r_true
    up = world.step(np.array([0.2, 0.0, -0.01])).r_true
    assert left[0] < base[0] and left[1] == pytest.approx(base[1], abs=1e-3)
    assert up[1] > base[1] and up[0] == pytest.approx(base[0], abs=1e-12)


def test_a_solution_exists_and_is_a_hit() -> None:
    # Aim straight at the centre's height and let a little elevation make up for the drop.
    world = BallisticWorld()
    theta = np.array([0.17, 0.0, 0.0])
    for _ in range(30):  # 1-D Newton on θ_z for r_z = 0
        r = world.step(theta).r_true[1]
        dr = (world.step(theta + np.array([0.0, 0.0, 1e-6])).r_true[1] - r) / 1e-6
        theta[2] -= r / dr
    shot = world.step(theta)
    assert shot.hit
    assert np.linalg.norm(shot.r_true) < 1e-9


@settings(max_examples=25, deadline=None)
@given(theta=thetas_in_box)
def test_rk4_with_vanishing_drag_matches_the_closed_form(theta: np.ndarray) -> None:
    closed = BallisticWorld().step(theta)
    integrated = BallisticWorld(Scenario(drag=1e-12)).step(theta)
    assert integrated.r_true == pytest.approx(closed.r_true, abs=1e-9)
    assert integrated.flight_time == pytest.approx(closed.flight_time, abs=1e-9)


@settings(max_examples=10, deadline=None)
@given(theta=thetas_in_box)
def test_rk4_converges_with_the_step(theta: np.ndarray) -> None:
    scenario = Scenario(drag=0.05, wind=(1.0, 3.0, -0.5))
    coarse = BallisticWorld(scenario, dt=2e-3).step(theta).r_true
    fine = BallisticWorld(scenario, dt=2.5e-4).step(theta).r_true
    assert coarse == pytest.approx(fine, abs=1e-8)


def test_drag_slows_the_arrow_and_crosswind_carries_it() -> None:
    theta = np.array(START_THETA)
    free = BallisticWorld().step(theta)
    dragged = BallisticWorld(Scenario(drag=0.05)).step(theta)
    windy = BallisticWorld(Scenario(drag=0.05, wind=(0.0, 3.0, 0.0))).step(theta)
    assert dragged.flight_time > free.flight_time
    assert dragged.r_true[1] < free.r_true[1]  # longer flight, more drop
    assert windy.r_true[0] > dragged.r_true[0]  # wind towards +y pushes the arrow right


def test_drag_matches_a_hand_integrated_horizontal_flight() -> None:
    # Without gravity along x and no wind, a level shot obeys dvx/dt = −K vx² exactly:
    # x(t) = ln(1 + K v0 t)/K, so the time to cover L is t = (exp(K L) − 1)/(K v0).
    scenario = Scenario(drag=0.2)
    world = BallisticWorld(scenario)
    theta = np.array([0.25, 0.0, 0.0])
    v0 = float(np.linalg.norm(world.launch(theta[None])[0]))
    length = TARGET_DISTANCE + BOW_HAND[0]
    expected = (math.exp(0.2 * length) - 1.0) / (0.2 * v0)
    # gravity adds a small vertical speed that couples through ‖v‖; the effect is below 1e-3.
    assert world.step(theta).flight_time == pytest.approx(expected, rel=2e-3)


def test_batch_and_single_shots_agree_bit_for_bit() -> None:
    world = BallisticWorld(Scenario(drag=0.03, wind=(0.5, -1.0, 0.0)))
    rng = np.random.default_rng(3)
    thetas = np.array(START_THETA) + 0.02 * rng.standard_normal((7, 3))
    batch = world.impacts(thetas)
    for i, theta in enumerate(thetas):
        single = world.impacts(theta[None])
        assert np.array_equal(single.r[0], batch.r[i])
        assert np.array_equal(single.points[0], batch.points[i])


def test_same_seed_same_observations_bit_for_bit() -> None:
    scenario = Scenario(noise=0.01)
    runs = []
    for _ in range(2):
        world = BallisticWorld(scenario)
        world.reset(42)
        runs.append([world.step(np.array(START_THETA)).r for _ in range(5)])
    assert all(np.array_equal(a, b) for a, b in zip(*runs, strict=True))
    other = BallisticWorld(scenario)
    other.reset(43)
    assert not np.array_equal(other.step(np.array(START_THETA)).r, runs[0][0])


def test_noise_has_the_requested_spread_and_truth_is_untouched() -> None:
    world = BallisticWorld(Scenario(noise=0.02))
    world.reset(0)
    shots = [world.step(np.array(START_THETA)) for _ in range(2000)]
    errors = np.array([s.r - s.r_true for s in shots])
    assert np.all(np.array([s.r_true for s in shots]) == shots[0].r_true)
    assert errors.std(axis=0) == pytest.approx([0.02, 0.02], rel=0.1)
    assert errors.mean(axis=0) == pytest.approx([0.0, 0.0], abs=0.002)


def test_trajectory_runs_from_the_bow_hand_to_the_impact() -> None:
    for scenario in (Scenario(), Scenario(drag=0.05, wind=(0.0, 2.0, 0.0))):
        world = BallisticWorld(scenario)
        path = world.trajectory(np.array(START_THETA), n_points=40)
        shot = world.step(np.array(START_THETA))
        assert len(path) >= 40
        assert path[0] == pytest.approx(BOW_HAND)
        assert path[-1] == pytest.approx(shot.point, abs=1e-9)
        assert np.all(np.diff(path[:, 0]) < 0)  # always moving towards the target


def test_a_farther_target_is_centred_on_its_own_plane() -> None:
    world = BallisticWorld(Scenario(distance=5.0))
    shot = world.step(np.array(START_THETA))
    assert shot.point[0] == pytest.approx(-5.0)
    assert world.centre == pytest.approx(target_centre(5.0))
    assert shot.r_true == pytest.approx(shot.point[1:] - target_centre(5.0)[1:])


def test_gravity_points_down() -> None:
    assert GRAVITY[2] < 0 and GRAVITY[0] == GRAVITY[1] == 0


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"distance": 0.3}, "distance 0.3"),
        ({"distance": float("nan")}, "distance"),
        ({"drag": -0.1}, "drag"),
        ({"noise": -1.0}, "noise"),
        ({"bow_stiffness": 0.0}, "bow_stiffness"),
        ({"wind": (1.0, 0.0, 0.0)}, "wind"),
        ({"wind": (1.0, 0.0)}, "wind"),
        ({"start": (0.1, float("inf"), 0.0)}, "start"),
    ],
)
def test_bad_scenarios_are_named(kwargs: dict, named: str) -> None:
    with pytest.raises(ScenarioError, match=named):
        Scenario(**kwargs)


def test_shots_that_cannot_fly_are_refused() -> None:
    world = BallisticWorld()
    with pytest.raises(ShotError, match="brace height"):
        world.step(np.array([0.05, 0.0, 0.0]))
    with pytest.raises(ShotError, match="away from the target"):
        world.step(np.array([-0.2, 0.0, 0.0]))
    with pytest.raises(ShotError, match="rows of 3"):
        world.impacts(np.array([0.2, 0.0]))
    with pytest.raises(ShotError, match="did not reach"):
        BallisticWorld(Scenario(drag=2.0, wind=(20.0, 0.0, 0.0)), max_time=0.5).step(
            np.array([0.2, 0.0, 0.0])
        )


def test_scenario_to_dict_is_plain() -> None:
    data = Scenario(drag=0.1, wind=(1, 2, 3)).to_dict()
    assert data["wind"] == [1.0, 2.0, 3.0] and data["start"] == list(START_THETA)
    assert Scenario(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}) == (
        Scenario(drag=0.1, wind=(1, 2, 3))
    )
