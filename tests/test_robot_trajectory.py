"""The robot's trajectories in its own loop, without the mesh: waypoints followed at their
simulated times, a bad trajectory (one faster than the joints' speed bound among them) refused
before anything moves, other moves refused while one plays, the aborts (path tolerance, a lease
taken over) holding the part where it is, and at rtf 0 the reply held until the robot rests."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np
import pytest

from archery.protocol.errors import ArcheryError, Busy
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import MAX_REFERENCE_SPEED, home_of
from archery.protocol.verbs import robot as rv
from archery.services.robot.follow import PATH_TOLERANCE, PartSpec
from archery.services.robot.simloop import SimLoop
from archery.services.robot.trajectory import BadTrajectory, plan_path
from archery.sim.errors import StateError
from archery.sim.model_build import build_scene
from tests.test_robot_service_core import WORLD, Recorder, running_loops

ARM = "right_arm"
HOME = np.array(home_of(ARM))
ELBOW = PARTS[ARM].index("r_elbow")


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_scene(WORLD.scene)


@pytest.fixture
def start(model: mujoco.MjModel) -> Iterator[Any]:
    """Starts a loop on its own thread: start(**config) -> (loop, recorder)."""
    with running_loops(model) as starter:
        yield starter


def _elbow_path(*angles: float, step: float = 0.5) -> rv.PartTrajectoryArgs:
    rows = []
    for angle in angles:
        row = HOME.copy()
        row[ELBOW] = angle
        rows.append(row.tolist())
    times = [step * (i + 1) for i in range(len(angles))]
    return rv.PartTrajectoryArgs(times=times, positions=rows)


def _play(loop: SimLoop, args: rv.PartTrajectoryArgs, lease: str = "") -> rv.TrajectoryReply:
    return loop.follow([PartSpec(ARM, None, lease)], args).result(30)


def _elbow_peak(rec: Recorder) -> tuple[float, float]:
    """(sim s, rad) of the right arm's state with the largest elbow angle."""
    with rec.lock:
        return max((s[2][ELBOW], s[4]) for s in rec.states if s[1] == ARM)[::-1]


def test_the_waypoints_are_passed_at_their_simulated_times(start: Any) -> None:
    loop, rec = start(rtf=2.0)  # states on the sim time grid (at rtf 0, on the wall clock's)
    middle = HOME[ELBOW] + 0.4  # up and back: the middle waypoint is the elbow's peak
    reply = _play(loop, _elbow_path(middle, HOME[ELBOW]))
    assert reply.parts == [ARM]
    assert reply.path_error < 0.15 and reply.goal_error <= 0.02
    # the trajectory took its 1 s of simulated time, then settled within the goal tolerance
    assert 1.0 <= reply.ended - reply.started < 1.1
    when, peak = _elbow_peak(rec)
    assert peak == pytest.approx(middle, abs=0.03)
    assert reply.started + 0.5 <= when <= reply.started + 0.65  # the servos lag a little
    assert loop.positions(ARM).position[ELBOW] == pytest.approx(HOME[ELBOW], abs=0.02)


def test_the_timing_holds_at_real_time_too(start: Any) -> None:
    loop, _ = start(rtf=4.0)
    reply = _play(loop, _elbow_path(HOME[ELBOW] + 0.3, step=1.0))
    assert 1.0 <= reply.ended - reply.started < 1.1


def test_at_rtf_0_the_reply_comes_at_rest_at_a_simulated_time_of_its_own(start: Any) -> None:
    # the next command (a release) then finds the joints settled where the simulation put
    # them, not where they were when the wall clock delivered it: same-seed runs stay identical
    ends = []
    for _ in range(2):
        loop, _ = start(rtf=0.0)
        reply = _play(loop, _elbow_path(HOME[ELBOW] + 0.3, step=0.4))
        assert loop.motion_done(ARM)
        ends.append((reply.ended, reply.goal_error, loop.positions(ARM).position))
    assert ends[0][0] == ends[1][0] and ends[0][1] == ends[1][1]
    assert np.array_equal(ends[0][2], ends[1][2])
    assert ends[0][1] < 0.02  # settled, nearer its goal than the tolerance that ended it


@pytest.mark.parametrize(
    ("times", "rows", "match"),
    [
        ([0.5, 0.5], [HOME, HOME], "strictly increasing"),
        ([0.0, 0.5], [HOME, HOME], "> 0 s"),
        ([0.5], [np.where(np.arange(7) == ELBOW, 9.0, HOME)], "outside"),
        ([0.5], [HOME[:6]], "6 values for 7 joints"),
        ([0.5, 1.0], [HOME], "1 rows for 2 times"),
        ([500.0], [HOME], "past the bound"),
    ],
)
def test_a_bad_trajectory_is_refused_and_nothing_moves(
    start: Any, times: list[float], rows: list[Any], match: str
) -> None:
    loop, _ = start(rtf=0.0)
    before = loop.targets(ARM)
    args = rv.PartTrajectoryArgs(times=times, positions=[list(map(float, r)) for r in rows])
    with pytest.raises(BadTrajectory, match=match) as caught:
        _play(loop, args)
    assert caught.value.code == "bad_trajectory"
    assert loop.targets(ARM) == before and loop.motion_done(ARM)


def _elbow_limits(loop: SimLoop) -> tuple[float, float]:
    limits = loop.limits[ARM]
    return limits.lower[ELBOW], limits.upper[ELBOW]


def _refused_still(loop: SimLoop, args: rv.PartTrajectoryArgs | rv.TrajectoryArgs) -> str:
    """`args` refused `bad_trajectory` with nothing moved; its message."""
    before = loop.targets(ARM)
    with pytest.raises(BadTrajectory) as caught:
        loop.follow([PartSpec(ARM, None, "")], args).result(30)
    assert caught.value.code == "bad_trajectory"
    assert loop.targets(ARM) == before and loop.motion_done(ARM)
    assert loop.call(lambda: loop.world.setpoints_of(loop.world.joint_indices(ARM))).tolist() == (
        before
    )
    return caught.value.message


def test_one_waypoint_at_1e_300_s_is_refused_and_nothing_moves(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    _, upper = _elbow_limits(loop)
    message = _refused_still(loop, _elbow_path(upper, step=1e-300))
    assert message.startswith("positions[0] moves right_arm.r_elbow at ")
    assert "from the setpoint at the start" in message
    assert f"over the maximum joint speed of {MAX_REFERENCE_SPEED:g} rad/s" in message


def test_a_limit_to_limit_swing_every_10_ms_is_refused(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    lower, upper = _elbow_limits(loop)
    swing = [upper if i % 2 else lower for i in range(rv.MAX_TRAJECTORY_POINTS)]  # 20 s
    message = _refused_still(loop, _elbow_path(*swing, step=0.01))
    # the first waypoint from home is already too fast: HOME to the lower limit in 10 ms
    speed = abs(lower - HOME[ELBOW]) / 0.01
    assert message.startswith(f"positions[0] moves right_arm.r_elbow at {speed:.4g} rad/s")
    times = [2.0 + 0.01 * i for i in range(len(swing))]  # the first at the lower limit, slowly
    slow_start = rv.PartTrajectoryArgs(times=times, positions=_elbow_path(*swing).positions)
    message = _refused_still(loop, slow_start)
    span = upper - lower
    assert message.startswith(f"positions[1] moves right_arm.r_elbow at {span / 0.01:.4g} rad/s")
    assert "from positions[0]" in message


def test_a_velocity_over_the_bound_is_refused(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    path = _elbow_path(HOME[ELBOW] + 0.2, HOME[ELBOW] + 0.4, step=1.0)  # 0.2 rad/s
    velocities = [[0.0] * 7, [0.0] * 7]
    velocities[0][ELBOW] = 1.5 * MAX_REFERENCE_SPEED
    args = rv.PartTrajectoryArgs(times=path.times, positions=path.positions, velocities=velocities)
    message = _refused_still(loop, args)
    assert message == (
        f"velocities[0] gives right_arm.r_elbow {1.5 * MAX_REFERENCE_SPEED:.4g} rad/s, over the "
        f"maximum joint speed of {MAX_REFERENCE_SPEED:g} rad/s"
    )


def test_several_parts_are_held_to_the_bound_too(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    left = list(home_of("left_arm"))
    left[PARTS["left_arm"].index("l_elbow")] += 0.5  # 0.5 rad in 0.1 s
    args = rv.TrajectoryArgs(
        parts=[rv.TrajectoryPart(part=ARM), rv.TrajectoryPart(part="left_arm")],
        times=[0.1],
        positions=[[*HOME.tolist(), *left]],
    )
    with pytest.raises(BadTrajectory, match=r"positions\[0\] moves left_arm.l_elbow at 5 rad/s"):
        loop.follow([PartSpec(ARM, None, ""), PartSpec("left_arm", None, "")], args).result(30)
    assert loop.motion_done("left_arm")


def test_a_trajectory_just_within_the_bound_is_played(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    fast = 0.95 * MAX_REFERENCE_SPEED  # the played path's peak: rest to rest, 1.875 × average
    out = HOME[ELBOW] + fast / 1.875 * 0.2
    path = _elbow_path(out, HOME[ELBOW], step=0.2)
    reply = _play(loop, path)
    assert reply.goal_error <= 0.02
    given = rv.PartTrajectoryArgs(
        times=path.times, positions=path.positions, velocities=[[0.0] * 7, [0.0] * 7]
    )
    assert _play(loop, given).goal_error <= 0.02
    twice = rv.PartTrajectoryArgs(  # the same average speed, its peak past the bound
        times=[0.2], positions=[_elbow_path(HOME[ELBOW] + fast * 0.2).positions[0]]
    )
    with pytest.raises(BadTrajectory, match=r"at up to 3\.56\d* rad/s \(quintic between"):
        _play(loop, twice)


def test_a_joint_of_another_part_is_refused(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    args = rv.PartTrajectoryArgs(times=[0.5], positions=[[0.1]], names=["l_elbow"])
    with pytest.raises(BadTrajectory, match="no joint 'l_elbow'"):
        loop.follow([PartSpec(ARM, ("l_elbow",), "")], args)


def test_a_nan_is_refused_by_the_path() -> None:
    with pytest.raises(BadTrajectory, match="finite"):
        plan_path(HOME, [0.5], [[float("nan")] * 7], None, HOME - 9, HOME + 9, PARTS[ARM], 120.0)


def test_other_moves_of_a_playing_part_are_refused_busy(start: Any) -> None:
    loop, _ = start(rtf=1.0)
    reply = loop.follow([PartSpec(ARM, None, "")], _elbow_path(HOME[ELBOW] + 0.3, step=2.0))
    with pytest.raises(Busy):
        loop.position_move(ARM, HOME.tolist())
    with pytest.raises(Busy):
        _play(loop, _elbow_path(HOME[ELBOW] + 0.1))
    loop.command(ARM, HOME.tolist(), None, ARM)
    assert loop.call(lambda: None) is None  # the command's job ran
    assert loop.counters(ARM).rejected_by_reason.get("busy") == 2  # the move and the command
    assert reply.result(30).goal_error <= 0.02


def test_a_part_that_falls_behind_aborts_and_is_held(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    args = rv.PartTrajectoryArgs(
        times=[0.45], positions=[_elbow_path(HOME[ELBOW] + 0.4).positions[0]], path_tolerance=1e-4
    )
    with pytest.raises(ArcheryError) as caught:
        _play(loop, args)
    assert caught.value.code == PATH_TOLERANCE
    held = np.array(loop.targets(ARM))
    assert abs(held[ELBOW] - HOME[ELBOW]) < 0.1  # stopped near where it was, not at the goal


def test_a_lease_taken_over_mid_trajectory_stops_the_part(start: Any) -> None:
    loop, _ = start(rtf=1.0)
    lease = loop.leases.claim(ARM, "controller", 30.0).lease
    reply = loop.follow([PartSpec(ARM, None, lease)], _elbow_path(HOME[ELBOW] + 0.6, step=3.0))
    loop.leases.claim(ARM, "operator", 30.0, takeover=True)
    with pytest.raises(ArcheryError) as caught:
        reply.result(30)
    assert caught.value.code == "not_owner"
    assert loop.targets(ARM)[ELBOW] < HOME[ELBOW] + 0.6 - 0.05


def test_actions_need_a_whole_shot_robot(start: Any) -> None:
    loop, _ = start(rtf=0.0)
    args = rv.TrajectoryArgs(
        parts=[rv.TrajectoryPart(part=ARM)],
        times=[0.5],
        positions=[HOME.tolist()],
        actions=(rv.TrajectoryAction(t=0.2, verb="grasp"),),
    )
    with pytest.raises(StateError, match="--shot whole"):
        loop.follow([PartSpec(ARM, None, "")], args).result(30)


def test_a_reset_aborts_a_playing_trajectory(start: Any) -> None:
    loop, _ = start(rtf=1.0)
    reply = loop.follow([PartSpec(ARM, None, "")], _elbow_path(HOME[ELBOW] + 0.3, step=5.0))
    loop.reset()
    with pytest.raises(StateError, match="reset"):
        reply.result(30)
    assert loop.motion_done(ARM) or loop.targets(ARM) == HOME.tolist()
