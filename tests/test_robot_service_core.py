"""The robot service's core without the mesh: command rules, the simulation loop's timing,
watchdog, flight and streams against a recording sink."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import msgspec
import mujoco
import numpy as np
import pytest

from archery.protocol.errors import BadRequest
from archery.protocol.parts import PARTS
from archery.services.robot.commands import CommandRejected, PartLimits, check_command
from archery.services.robot.config import RobotConfig
from archery.services.robot.simloop import SimLoop
from archery.sim.errors import StateError
from archery.sim.geometry import BOW_HAND, START_THETA
from archery.sim.model_build import build_scene
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig
from tests.postures import archery_posture

WORLD = WorldConfig(scene=SceneConfig(meshes=False))
ARM = PartLimits(
    part="left_arm",
    names=PARTS["left_arm"],
    lower=(-1.0,) * 7,
    upper=(1.0,) * 7,
    tolerance=0.02,
)


# -- command rules ----------------------------------------------------------------------------


def test_a_full_command_is_accepted_unchanged() -> None:
    wanted = [0.1, -0.2, 0.3, 0.4, -0.5, 0.6, 0.0]
    targets, clamped = check_command(ARM, np.zeros(7), wanted, part="left_arm")
    np.testing.assert_array_equal(targets, wanted)
    assert not clamped


def test_a_named_subset_keeps_the_other_targets() -> None:
    current = np.full(7, 0.5)
    targets, _ = check_command(ARM, current, [0.1, -0.1], ["l_elbow", "l_shoulder_pitch"])
    expected = current.copy()
    expected[3], expected[0] = 0.1, -0.1
    np.testing.assert_array_equal(targets, expected)
    assert current[3] == 0.5  # the caller's array is not modified


def test_values_just_beyond_a_limit_are_clamped_onto_it() -> None:
    targets, clamped = check_command(ARM, np.zeros(7), [1.015, -1.02, 0, 0, 0, 0, 0])
    assert clamped
    assert targets[0] == 1.0 and targets[1] == -1.0


@pytest.mark.parametrize(
    ("position", "names", "part", "reason", "match"),
    [
        ([1.03, 0, 0, 0, 0, 0, 0], None, None, "out_of_range", r"l_shoulder_pitch = 1.03 rad"),
        ([0.0] * 6, None, None, "wrong_length", "takes 7 values"),
        ([0.0] * 8, None, None, "wrong_length", "takes 7 values"),
        ([0.0], ["r_elbow"], None, "unknown_joint", "no joint 'r_elbow'; its joints: l_"),
        ([0.0, 0.1], ["l_elbow", "l_elbow"], None, "duplicate_joint", "'l_elbow'"),
        ([0.0] * 7, None, "torso", "wrong_part", "for part 'torso' arrived on left_arm"),
        ([0.0] * 6 + [float("nan")], None, None, "bad_value", "finite"),
        (["a"] * 7, None, None, "bad_value", "numbers"),
        ("1234567", None, None, "wrong_length", "list of numbers"),
        ([0.0], ["l_elbow", "l_wrist_yaw"], None, "wrong_length", "2 names but 1 values"),
    ],
)
def test_bad_commands_are_rejected_with_a_reason(
    position: Any, names: Any, part: str | None, reason: str, match: str
) -> None:
    with pytest.raises(CommandRejected, match=match) as info:
        check_command(ARM, np.zeros(7), position, names, part)
    assert info.value.reason == reason
    assert isinstance(info.value, BadRequest) and info.value.code == "bad_request"


# -- the simulation loop ----------------------------------------------------------------------


class Recorder:
    """A sink that keeps everything the loop publishes, with the wall time it arrived; each
    joint state takes `latency` wall s to go out (a slow link)."""

    def __init__(self) -> None:
        self.latency = 0.0
        self.states: list[tuple[float, str, list[float], bool, float]] = []
        self.worlds: list[tuple[float, str, int, float]] = []
        self.events: list[tuple[str, int, float, list[float] | None, str]] = []
        self.lock = threading.Lock()

    def joint_state(
        self,
        part: str,
        names: tuple[str, ...],
        position: list[float],
        velocity: list[float],
        motion_done: bool,
        sim_time: float,
    ) -> None:
        assert names == PARTS[part] and len(position) == len(velocity) == len(names)
        time.sleep(self.latency)
        with self.lock:
            self.states.append((time.monotonic(), part, position, motion_done, sim_time))

    def world_state(self, qpos: np.ndarray, phase: str, shot: int, sim_time: float) -> None:
        with self.lock:
            self.worlds.append((time.monotonic(), phase, shot, sim_time))

    def event(
        self,
        kind: str,
        shot: int,
        sim_time: float,
        impact_m: list[float] | None = None,
        reason: str = "",
    ) -> None:
        with self.lock:
            self.events.append((kind, shot, sim_time, impact_m, reason))

    def wait_event(self, kind: str, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(e[0] == kind for e in self.events):
            assert time.monotonic() < deadline, f"no {kind} event in {self.events}"
            time.sleep(0.002)


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_scene(WORLD.scene)


@pytest.fixture(scope="module")
def aim_joints(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    return archery_posture(model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)


@pytest.fixture
def start(model: mujoco.MjModel) -> Iterator[Any]:
    """Starts a loop on its own thread: start(**config) -> (loop, recorder)."""
    with running_loops(model) as starter:
        yield starter


@contextlib.contextmanager
def running_loops(model: mujoco.MjModel) -> Iterator[Any]:
    """A starter of simulation loops on threads of their own, `WORLD` on `model`:
    start(**config) -> (loop, recorder); every loop is stopped and joined at the end."""
    running: list[tuple[threading.Event, threading.Thread]] = []

    def _start(**overrides: Any) -> tuple[SimLoop, Recorder]:
        world = ArcheryWorld(WORLD, model=model)
        world.reset(0)
        recorder = Recorder()
        loop = SimLoop(world, RobotConfig(world=WORLD, **overrides), recorder, seed=0)
        stop = threading.Event()
        thread = threading.Thread(target=loop.run, args=(stop,), daemon=True)
        thread.start()
        running.append((stop, thread))
        return loop, recorder

    yield _start
    for stop, thread in running:
        stop.set()
        thread.join(5)
        assert not thread.is_alive()


def _wait_moved(loop: SimLoop, timeout: float = 20.0) -> float:
    """Wait until a move ended at rest; the wall time it took (s)."""
    t0 = time.monotonic()
    while not loop.call(lambda: loop.world.motion_done() and loop.world.sim_time > 0):
        assert time.monotonic() < t0 + timeout, "the move did not end"
        time.sleep(0.002)
    return time.monotonic() - t0


def _go(loop: SimLoop, joints: dict[str, np.ndarray]) -> None:
    for part, values in joints.items():
        loop.command(part, values.tolist(), None, part, batch=len(joints))
    _wait_moved(loop)


def test_rtf0_time_stands_still_at_rest_but_the_streams_go_on(start: Any) -> None:
    loop, rec = start(state_rate=50.0)
    time.sleep(0.3)
    assert loop.status().sim_time == 0.0
    with rec.lock:
        torso = [s for s in rec.states if s[1] == "torso"]
    assert len(torso) >= 8  # repeated at ~50 Hz of wall time while idle
    assert all(s[4] == 0.0 and s[3] for s in torso)


def _torso_after(rec: Recorder, since: float, count: int, timeout: float = 10.0) -> list[float]:
    """Wait for `count` torso states published after wall time `since`; their wall times."""
    deadline = time.monotonic() + timeout
    while True:
        with rec.lock:
            stamps = [s[0] for s in rec.states if s[1] == "torso" and s[0] > since]
        if len(stamps) >= count:
            return stamps[:count]
        assert time.monotonic() < deadline, f"{len(stamps)} torso states of {count}"
        time.sleep(0.005)


def test_rtf0_at_rest_the_streams_fall_to_a_heartbeat_until_something_happens(start: Any) -> None:
    loop, rec = start(state_rate=50.0, world_rate=25.0, rest_rate=2.0, rest_after=0.3)
    first = _torso_after(rec, 0.0, 1)[0]  # the loop came to rest just before it
    quiet = _torso_after(rec, first + 0.3, 3)
    assert np.all(np.diff(quiet) >= 0.5 - 1e-3), np.diff(quiet)  # 2 Hz, not 50
    with rec.lock:
        worlds = [w[0] for w in rec.worlds if w[0] > first + 0.3]
    assert np.all(np.diff(worlds) >= 0.5 - 1e-3), np.diff(worlds)
    woken = time.monotonic()
    loop.set_ref_speeds("torso", 0.2)  # no motion, but activity: full rates at once
    lively = _torso_after(rec, woken, 5)
    assert np.all(np.diff(lively) >= 0.02 - 1e-3)
    assert lively[-1] - lively[0] < 4 * 0.5  # four heartbeats would take 2 s
    assert loop.status().sim_time == 0.0


def test_rtf0_moves_fast_and_streams_on_the_sim_time_grid_at_the_wall_rate(
    start: Any, aim_joints: dict[str, np.ndarray]
) -> None:
    loop, rec = start(state_rate=50.0, world_rate=25.0)
    t0 = time.monotonic()
    _go(loop, aim_joints)
    wall = time.monotonic() - t0
    sim = loop.status().sim_time
    assert sim > 1.0 and wall < sim / 5, (sim, wall)  # far faster than real time
    with rec.lock:
        moving = [s for s in rec.states if s[1] == "left_arm" and 0 < s[4] < sim]
        worlds = [w for w in rec.worlds if 0 < w[3] < sim]
        final = [s for s in rec.states if s[1] == "left_arm" and s[4] == pytest.approx(sim)]
        final_world = [w for w in rec.worlds if w[3] == pytest.approx(sim)]
    # Grid points of sim time, but at most one per period of wall time (not ~1,000 per wall s),
    # then the state that ends the motion at once.
    for stream, period in ((moving, 0.02), (worlds, 0.04)):
        grid = np.array([s[-1] for s in stream]) / period
        np.testing.assert_allclose(grid, np.round(grid), atol=1e-6)
        gaps = np.diff([s[0] for s in stream])
        assert np.all(gaps >= period - 2e-3), gaps
        assert len(stream) <= wall / period + 1
    assert final and final[0][3] and final_world


def test_rtf1_paces_sim_time_with_the_wall_clock(start: Any) -> None:
    loop, _ = start(rtf=1.0)
    time.sleep(0.1)
    t0, s0 = time.monotonic(), loop.status().sim_time
    time.sleep(0.5)
    t1, s1 = time.monotonic(), loop.status().sim_time
    assert (s1 - s0) == pytest.approx(t1 - t0, rel=0.2, abs=0.05)


def test_a_stale_stream_freezes_the_part_where_it_is(start: Any) -> None:
    loop, _ = start(rtf=1.0, watchdog=0.1)
    loop.set_ref_speeds("torso", 0.2)
    for k in range(5):  # a stream: commands 20 ms apart, the last one far away
        loop.command("torso", [0.0, 0.0, 0.05 * (k + 1)], None, "torso")
        time.sleep(0.02)
    assert loop.counters("torso").streaming
    time.sleep(0.35)  # stale after 0.1 s, while the slow setpoint is still on its way
    counters = loop.counters("torso")
    assert counters.watchdog_trips == 1 and not counters.streaming
    targets = np.array(loop.targets("torso"))
    assert 0.0 < targets[2] < 0.2  # frozen short of the last commanded 0.25 rad
    frozen = loop.positions("torso").position
    np.testing.assert_allclose(
        targets, np.clip(frozen, *loop.world.joint_limits("torso")), atol=0.03
    )


def test_a_single_move_outlives_the_watchdog(start: Any) -> None:
    loop, _ = start(rtf=1.0, watchdog=0.1)
    loop.set_ref_speeds("torso", 0.2)
    loop.command("torso", [0.0, 0.0, 0.08], None, "torso")
    time.sleep(0.3)
    assert not loop.motion_done("torso")  # still moving, longer than the watchdog
    np.testing.assert_allclose(loop.targets("torso"), [0.0, 0.0, 0.08])
    assert loop.counters("torso").watchdog_trips == 0


def test_reset_is_refused_during_a_flight(start: Any) -> None:
    loop, rec = start(rtf=1.0)
    loop.nock()  # from the home joint positions: a 0.38 s flight sideways to the ground
    result: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: result.update(msgspec.to_builtins(loop.release())))
    thread.start()
    rec.wait_event("released")
    with pytest.raises(StateError, match="flying"):
        loop.reset(1)
    thread.join(10)
    assert result["shot"] == 1 and result["flight_time"] > 0.05
    assert [e[0] for e in rec.events] == [
        "nocked",
        "released",
        "landed" if result["hit"] else "missed",
    ]
    assert loop.reset(1).sim_time == 0.0


def test_a_landing_is_published_at_once_and_the_reply_has_no_ground_truth(
    start: Any, aim_joints: dict[str, np.ndarray]
) -> None:
    loop, rec = start(world_rate=1.0)
    _go(loop, aim_joints)
    loop.nock()
    reply = msgspec.to_builtins(loop.release())
    assert not {"r", "point", "impact_m", "velocity"} & set(reply)
    kind, shot, sim_time, impact, reason = rec.events[-1]
    assert kind in ("landed", "missed") and shot == reply["shot"] == 1
    assert sim_time == reply["sim_time"] and reason == reply["reason"]
    assert impact is not None and len(impact) == 2
    after = [w for w in rec.worlds if w[3] >= sim_time]
    assert after and after[0][1] in ("stuck", "missed")  # within the slow 1 Hz world rate


def test_bad_rpc_arguments_are_refused(start: Any) -> None:
    loop, _ = start()
    with pytest.raises(BadRequest, match="seed must be an integer"):
        loop.reset(-1)
    with pytest.raises(BadRequest, match="reference speeds must be in"):
        loop.set_ref_speeds("left_arm", 5.0)
    with pytest.raises(CommandRejected, match="outside its limits"):
        loop.position_move("left_arm", [3.0] * 7)
    with pytest.raises(StateError, match="no arrow is nocked"):
        loop.release()
    assert loop.counters("left_arm").rejected_by_reason["out_of_range"] == 1


def test_motion_done_is_per_part(start: Any) -> None:
    loop, rec = start(rtf=1.0)
    loop.set_ref_speeds("left_arm", 0.2)
    loop.command("left_arm", [0.2], ["l_wrist_yaw"], "left_arm")  # a light, distal joint
    time.sleep(0.2)
    assert not loop.motion_done("left_arm")
    assert loop.motion_done("torso") and loop.motion_done("right_arm")
    with rec.lock:
        last = {s[1]: s[3] for s in rec.states}
    assert last == {"torso": True, "left_arm": False, "right_arm": True}


def test_moves_sent_one_after_another_are_not_a_stream(start: Any) -> None:
    loop, _ = start(watchdog=5.0)
    for k in range(3):  # each command after the previous move is done, as a controller does
        loop.command("torso", [0.0, 0.0, 0.05 * (k + 1)], None, "torso")
        _wait_moved(loop, 5)
        assert not loop.counters("torso").streaming
    assert loop.counters("torso").accepted == 3


def _first_motion(rec: Recorder, rest: dict[str, list[float]]) -> dict[str, float]:
    """Per part, the sim time of its first state away from where it rested."""
    with rec.lock:
        states = list(rec.states)
    return {
        part: min(s[4] for s in states if s[1] == part and not np.allclose(s[2], home, atol=1e-4))
        for part, home in rest.items()
    }


def test_an_announced_batch_starts_together_even_when_its_commands_trickle_in(
    start: Any, aim_joints: dict[str, np.ndarray]
) -> None:
    loop, rec = start(batch_window=1.0)
    rest = {part: loop.positions(part).position for part in aim_joints}
    for part, values in aim_joints.items():
        loop.command(part, values.tolist(), None, part, batch=len(aim_joints))
        time.sleep(0.05)  # a move at rtf 0 covers a simulated second in ~20 ms of wall time
    _wait_moved(loop)
    starts = _first_motion(rec, rest)
    assert len(set(starts.values())) == 1, starts


def test_a_command_without_a_batch_starts_at_once(start: Any) -> None:
    loop, _ = start(batch_window=1.0)
    loop.command("torso", [0.0, 0.0, 0.1], None, "torso")
    assert _wait_moved(loop) < 0.9  # a move takes ~20 ms here, never the 1 s a batch may wait


def test_an_incomplete_batch_starts_when_the_window_ends(start: Any) -> None:
    loop, _ = start(batch_window=0.3)
    before = loop.positions("torso")
    target = np.asarray(before.position) + np.array([0.0, 0.0, 0.1])  # 0.1 rad from its posture
    t0 = time.monotonic()
    loop.command("torso", target.tolist(), None, "torso", batch=3)  # the other two never come

    def arrived() -> bool:  # at rest at the target: not merely at rest, as before the move
        at = np.asarray(loop.positions("torso").position)
        return loop.call(loop.world.motion_done) and bool(abs(at[2] - target[2]) < 0.02)

    while not arrived():
        assert time.monotonic() < t0 + 20, "the move did not end"
        time.sleep(0.002)
    assert time.monotonic() - t0 >= 0.3, (before, loop.positions("torso"))
    np.testing.assert_allclose(loop.positions("torso").position, target, atol=0.02)


def test_a_release_after_a_batched_move_waits_for_no_batch(
    start: Any, aim_joints: dict[str, np.ndarray]
) -> None:
    loop, _ = start(batch_window=1.0)
    _go(loop, aim_joints)
    loop.nock()
    t0 = time.monotonic()
    loop.release()
    assert time.monotonic() - t0 < 0.9  # a flight takes ~5 ms here, never the batch window


def test_at_rtf0_a_release_replies_once_the_robot_rests_with_its_rest_published(
    start: Any, aim_joints: dict[str, np.ndarray]
) -> None:
    # a reply sooner would let the next command start at a simulated time, or from joint
    # positions, of the wall clock's choosing: same-seed sessions would part
    loop, rec = start()
    _go(loop, aim_joints)
    loop.nock()
    rec.latency = 0.02  # the rest's states take a while to go out: the reply waits for them
    reply = loop.release()
    with rec.lock:  # what was published by the time the reply came
        last = {part: s for s in rec.states if (part := s[1])}
    assert loop.call(lambda: loop.world.motion_done())  # at rest, not stepping: the reply waited
    resting = loop.call(lambda: loop.world.sim_time)
    assert reply.sim_time <= resting
    # the states of that rest, every part done at one simulated time, went out before the reply
    assert {s[4] for s in last.values()} == {resting} and all(s[3] for s in last.values())
