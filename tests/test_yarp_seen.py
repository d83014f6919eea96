"""The bridge's frames' envelope stamps (`apps/yarp/ports.SeenClock`): when the simulated world
was in the state a frame shows, never when a render of an older world was sent again."""

from __future__ import annotations

import numpy as np

from archery.apps.yarp.ports import SeenClock
from archery.protocol.messages import Array, Image, WorldState


def _state(sim_time: float, stamp: float) -> WorldState:
    return WorldState(
        qpos=Array.from_numpy(np.zeros(3)),
        phase="idle",
        shot=0,
        sim_time=sim_time,
        stamp=stamp,
    )


def _frame(sim_time: float | None, stamp: float) -> Image:
    return Image(width=1, height=1, encoding="rgb8", data=b"\0\0\0", sim_time=sim_time, stamp=stamp)


def test_a_frame_is_stamped_when_its_world_was_current() -> None:
    clock = SeenClock(kept=4)
    assert clock.seen(_frame(1.0, 500.0)) == 500.0  # nothing known: its own stamp
    clock.state(_state(1.0, 100.0))
    clock.state(_state(1.0, 101.0))  # a heartbeat: the world still so at 101
    clock.state(_state(2.0, 102.0))
    assert clock.seen(_frame(1.0, 200.0)) == 101.0  # a render of 1.0 sent again at 200
    assert clock.seen(_frame(2.0, 200.0)) == 102.0
    assert clock.seen(_frame(1.5, 200.0)) == 101.0  # not recorded: a lower bound
    assert clock.seen(_frame(0.5, 200.0)) == 200.0  # older than all kept: its own stamp
    assert clock.seen(_frame(None, 7.0)) == 7.0
    clock.state(_state(0.0, 103.0))  # a reset: sim time starts over
    assert clock.seen(_frame(2.0, 200.0)) == 103.0
    for k in range(1, 10):
        clock.state(_state(float(k), 103.0 + k))
    assert clock.seen(_frame(9.0, 300.0)) == 112.0
