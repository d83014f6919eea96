"""The robot's publication pacing at rest, on a clock the test turns: full-rate beats after any
activity, a heartbeat once the robot has rested `rest_after` wall seconds."""

from __future__ import annotations

import pytest

from archery.services.robot import pacing
from archery.services.robot.pacing import MAX_IDLE_WAIT, Pacing


class Clock:
    """A monotonic clock that only moves when told (s)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    fake = Clock()
    monkeypatch.setattr(pacing.time, "monotonic", fake)
    return fake


def _sent(p: Pacing) -> None:
    p.sent_joints()
    p.sent_world()


def test_beats_keep_the_full_rates_for_rest_after_then_fall_to_the_rest_rate(clock: Clock) -> None:
    p = Pacing(0.002, 50.0, 25.0, 0.0, rest_rate=10.0, rest_after=1.0)
    _sent(p)
    clock.now += 0.019
    assert p.beats() == (False, False)
    assert p.idle_wait() == pytest.approx(0.001)
    clock.now += 0.002
    assert p.beats() == (True, False)  # 50 Hz joint states
    clock.now += 0.020
    assert p.beats() == (True, True)  # 25 Hz world states
    clock.now = 101.5  # rested 1.5 s: the heartbeat
    _sent(p)
    clock.now += 0.05
    assert p.beats() == (False, False)
    assert p.idle_wait() == pytest.approx(0.05)
    clock.now += 0.051
    assert p.beats() == (True, True)


def test_any_activity_brings_the_full_rates_back_at_once(clock: Clock) -> None:
    p = Pacing(0.002, 50.0, 30.0, 0.0, rest_rate=10.0, rest_after=1.0)
    clock.now += 5.0
    _sent(p)
    clock.now += 0.04
    assert p.beats() == (False, False)
    p.wake()  # a command: both beats are overdue at the full rates
    assert p.beats() == (True, True)
    assert p.idle_wait() < 0
    _sent(p)
    clock.now += 0.9
    _sent(p)
    clock.now += 0.021
    assert p.beats() == (True, False)  # still within rest_after of the command
    clock.now += 0.2
    _sent(p)
    clock.now += 0.05
    assert p.beats() == (False, False)  # 1.17 s after it: the heartbeat again


def test_a_stream_slower_than_the_rest_rate_keeps_its_own(clock: Clock) -> None:
    p = Pacing(0.002, 50.0, 1.0, 0.0, rest_rate=10.0, rest_after=0.0)
    _sent(p)
    clock.now += 0.5
    assert p.beats() == (True, False)
    p.sent_joints()
    assert p.idle_wait() == pytest.approx(MAX_IDLE_WAIT)
    clock.now += 0.5
    assert p.beats() == (True, True)


def test_moving_at_rtf0_keeps_the_full_rates_whatever_the_rest(clock: Clock) -> None:
    p = Pacing(0.002, 50.0, 25.0, 0.0, rest_rate=1.0, rest_after=0.0)
    p.schedule(0.0)
    _sent(p)
    clock.now += 0.021
    assert p.due(0.02) == (True, False)  # one joint state period of wall time, not the rest's
