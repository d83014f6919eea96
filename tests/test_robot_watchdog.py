"""The motion watchdog over the mesh: a command stream that stops mid-motion is held within
`watchdog` (0.1 s) of its last command, as the robot's own state stream shows; a single
positionMove is not a stream and runs to its end.

At rtf 1 (tested here) simulated time follows the wall clock, so the 0.1 wall s of the watchdog
are 0.1 simulated s of motion. At rtf 0 the moving simulation runs many times faster than the
wall clock: 0.1 wall s are seconds of simulated motion, so a stream's part has usually reached
its targets (and stopped on its own) before the watchdog could trip; the hold then only catches
targets further away than that.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from archery.protocol.messages import JointCommand, JointState
from tests import test_robot_service as mesh

robot = mesh.robot  # the fixture: the robot service in a thread, a client on the mesh
Client = mesh.Client

PART = "torso"
JOINT = 0  # torso_yaw: no gravity load, so the hold is the servo's alone
FAR = 0.8  # rad: 1.6 s away at the reference speed, the stream stops long before
SPEED = 0.5  # rad/s
RATE = 50.0  # Hz of the stream
WATCHDOG = 0.1  # wall s: the robot's default
STATE_RATE = 50.0  # Hz: the robot's joint states (its default state rate)
REST_SPEED = 0.02  # rad/s: a joint slower than this is at rest (streaming runs at 0.5)
REST_BAND = 0.01  # rad: a joint at rest stays this close to where it ends


def _recorder(client: Client) -> list[JointState]:
    """Every joint state of PART from now on, in arrival order."""
    states: list[JointState] = []
    client.node.subscribe(client.keys.state(PART), JointState, mode="fifo", callback=states.append)
    return states


def _now(client: Client) -> dict[str, int]:
    """The seq of the next state of PART (at rtf 1 sim time runs on, so `settle` cannot be used)."""
    return {PART: client.states[PART].wait_newer(5).seq}


def _stream(client: Client, count: int) -> float:
    """Send `count` commands towards FAR at RATE; the wall time (time.time()) of the last."""
    pub = client.commands[PART]
    target = [FAR, 0.0, 0.0]
    start = time.monotonic()
    last = 0.0
    for k in range(count):
        time.sleep(max(0.0, start + k / RATE - time.monotonic()))  # the stream's own pace
        pub.put(JointCommand(part=PART, position=target))
        last = time.time()
    return last


def test_a_stream_that_stops_mid_motion_is_held_within_the_watchdog(
    robot: Callable[..., Client],
) -> None:
    client = robot(rtf=1.0)
    assert client.archery("status")["watchdog"] == WATCHDOG
    client.part(PART, "setRefSpeeds", {"speeds": SPEED})
    _now(client)
    states = _recorder(client)
    last = _stream(client, 20)  # 0.4 s of commands overtaking the unfinished move
    event = client.event(timeout=5)
    assert event.kind == "watchdog" and event.reason.startswith(f"{PART}:"), event
    hold_latency = event.stamp - last
    assert WATCHDOG - 0.005 <= hold_latency <= WATCHDOG + 0.03, hold_latency

    def at_rest(msg: JointState) -> bool:
        return msg.stamp > event.stamp and abs(msg.velocity[JOINT]) < REST_SPEED

    client.states[PART].wait_newer(5, at_rest, after_seq=0)
    rest_seq = client.states[PART].wait_newer(5, lambda m: m.stamp > event.stamp + 0.5).seq
    after = [m for m in states if m.stamp > last and m.seq <= rest_seq]
    before = [m for m in states if m.stamp <= last]
    assert max(abs(m.velocity[JOINT]) for m in before) > 0.8 * SPEED  # it was streaming
    position = np.array([m.position[JOINT] for m in after])
    stamps = np.array([m.stamp for m in after])
    speeds = np.abs([m.velocity[JOINT] for m in after])
    # Held where it was: the joint went a few cm of its 0.8 rad after the last command: at most
    # the streaming speed for the hold latency, plus the state sampled up to one state period
    # (20 ms at 50 Hz) before the last command, plus the servo's overshoot (~7 mrad) ...
    at_last = before[-1].position[JOINT]
    travel = SPEED * (hold_latency + 1.0 / STATE_RATE) + 0.01
    assert np.all(np.abs(position - at_last) < travel), (travel, position - at_last)
    assert FAR - position[-1] > 0.4
    # ... and stopped there: the first state from which the joint stays slower than a tenth of
    # the streaming speed and within REST_BAND of where it ends (the servo, 40 ms time
    # constant, overshoots the held position by ~v/(e·ω) = 7 mrad and settles back).
    final = position[-1]
    still = [
        i
        for i in range(len(after))
        if np.all(speeds[i:] < 0.1 * SPEED) and np.all(np.abs(position[i:] - final) < REST_BAND)
    ]
    assert still, list(zip(stamps - last, position, speeds, strict=True))
    stop_latency = stamps[still[0]] - last
    assert stop_latency <= hold_latency + 0.1, stop_latency
    assert np.all(speeds[still[0] + 10 :] < 0.02), speeds  # 0.2 s later: ~0
    counters = client.part(PART, "counters")
    assert counters["watchdog_trips"] == 1 and not counters["streaming"]


def test_a_single_position_move_is_not_a_stream(robot: Callable[..., Client]) -> None:
    client = robot(rtf=1.0)
    client.part(PART, "setRefSpeeds", {"speeds": SPEED})
    after = _now(client)
    client.part(PART, "positionMove", {"position": [0.3, 0.0, 0.0]})  # 0.6 s ≫ the watchdog
    client.wait_reached({PART: np.array([0.3, 0.0, 0.0])}, after)
    counters = client.part(PART, "counters")
    assert counters["watchdog_trips"] == 0 and not counters["streaming"]
    assert client.events.received == 0  # no watchdog event


def test_one_command_after_a_settled_move_is_not_a_stream(robot: Callable[..., Client]) -> None:
    client = robot(rtf=1.0)
    client.part(PART, "setRefSpeeds", {"speeds": SPEED})
    after = _now(client)
    _stream(client, 1)
    client.wait_reached({PART: np.array([FAR, 0.0, 0.0])}, after, timeout=10)
    assert client.part(PART, "counters")["watchdog_trips"] == 0
