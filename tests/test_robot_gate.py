"""The gate of a part's commands without the mesh: leases (claim, renew, drop, expiry,
takeover), the raw-payload screen and the rate limit, on a clock the test moves; then the
simulation loop's use of it (commands, positionMove, setRefSpeeds, counters), each command's
lease checked once where it arrives."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from archery.protocol.codec import decode, encode
from archery.protocol.messages import JointCommand
from archery.protocol.parts import PARTS
from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import REJECTION_REASONS
from archery.services.robot.config import RobotConfig
from archery.services.robot.gate import NOT_OWNER, RATE_LIMITED, NotOwner, PartGate
from archery.services.robot.handlers import RobotHandlers
from archery.services.robot.simloop import SimLoop
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig

WORLD = WorldConfig(scene=SceneConfig(meshes=False))


class Clock:
    """Monotonic wall seconds that move only when the test says so."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _gate(rate: float = 0.0, burst: int = 1) -> tuple[PartGate, Clock]:
    clock = Clock()
    ids = (f"lease{k:04d}" for k in itertools.count())
    return PartGate("left_arm", rate, burst, clock=clock, new_id=lambda: next(ids)), clock


def _payload(lease: str = "") -> bytes:
    return encode(JointCommand(part="left_arm", position=[0.0] * 7, lease=lease))


def test_with_no_lease_anyone_commands_the_part() -> None:
    gate, _ = _gate()
    assert gate.screen(_payload()) is None
    assert gate.screen(_payload("whatever")) is None  # a stale lease id too
    assert gate.owner_refusal("") is None
    assert gate.holder() == (None, 0.0)


def test_while_a_lease_runs_only_its_commands_pass() -> None:
    gate, _ = _gate()
    lease, took_over = gate.claim("controller", 2.0)
    assert (lease.id, lease.owner, lease.ttl, took_over) == ("lease0000", "controller", 2.0, "")
    assert gate.screen(_payload(lease.id)) is None
    for other in ("", "lease9999"):
        reason, message = gate.screen(_payload(other)) or ("", "")
        assert reason == NOT_OWNER and "held by 'controller'" in message
        assert gate.owner_refusal(other) == message
    assert gate.owner_refusal(lease.id) is None
    assert NOT_OWNER in REJECTION_REASONS and RATE_LIMITED in REJECTION_REASONS


def test_another_owner_needs_a_takeover_the_same_owner_replaces_its_lease() -> None:
    gate, _ = _gate()
    first, _ = gate.claim("controller", 2.0)
    with pytest.raises(NotOwner, match=r"held by 'controller' for 2.00 s more.*takeover") as info:
        gate.claim("operator", 60.0)
    assert info.value.code == "not_owner"
    again, took_over = gate.claim("controller", 2.0)  # e.g. a restarted controller
    assert took_over == "" and again.id != first.id
    assert gate.owner_refusal(first.id) is not None  # the old lease is gone
    taken, took_over = gate.claim("operator", 60.0, takeover=True)
    assert took_over == "controller" and gate.holder()[0] == taken
    with pytest.raises(NotOwner, match="not the running one: left_arm is held by 'operator'"):
        gate.renew(again.id)
    with pytest.raises(NotOwner, match="held by 'operator'"):
        gate.drop(again.id)


def test_a_lease_lasts_its_ttl_from_the_last_renewal_then_ends() -> None:
    gate, clock = _gate()
    lease, _ = gate.claim("controller", 2.0)
    clock.now += 1.5
    assert gate.renew(lease.id).expires == pytest.approx(clock.now + 2.0)
    clock.now += 1.9
    held, left = gate.holder()
    assert held is not None and left == pytest.approx(0.1)
    assert gate.screen(_payload()) is not None
    clock.now += 0.1  # 2 s since the renewal: ended
    assert gate.holder() == (None, 0.0)
    assert gate.screen(_payload()) is None  # anyone again
    with pytest.raises(NotOwner, match="has ended: nobody holds the part"):
        gate.renew(lease.id)
    gate.drop(lease.id)  # dropping an ended lease does nothing


def test_a_dropped_lease_frees_the_part() -> None:
    gate, _ = _gate()
    lease, _ = gate.claim("operator", 60.0)
    gate.drop(lease.id)
    assert gate.holder() == (None, 0.0) and gate.screen(_payload()) is None


def test_the_rate_limit_admits_a_burst_then_the_rate() -> None:
    gate, clock = _gate(rate=100.0, burst=5)
    payload = _payload()
    assert [gate.screen(payload) is None for _ in range(7)] == [True] * 5 + [False] * 2
    reason, message = gate.screen(payload) or ("", "")
    assert reason == RATE_LIMITED and "at most 100 commands/s" in message
    clock.now += 0.025  # two and a half commands' worth of time
    assert [gate.screen(payload) is None for _ in range(3)] == [True, True, False]
    clock.now += 10.0  # a long pause refills the burst, no more
    assert sum(gate.screen(payload) is None for _ in range(20)) == 5


def test_a_rival_flood_does_not_use_up_the_owner_s_budget() -> None:
    gate, _ = _gate(rate=100.0, burst=2)
    lease, _ = gate.claim("controller", 2.0)
    rival = _payload()
    assert all(gate.screen(rival) == (NOT_OWNER, gate.owner_refusal("")) for _ in range(1000))
    assert gate.screen(_payload(lease.id)) is None
    assert gate.screen(_payload(lease.id)) is None


def test_rate_zero_switches_the_limit_off() -> None:
    gate, _ = _gate(rate=0.0, burst=1)
    assert all(gate.screen(_payload()) is None for _ in range(1000))
    with pytest.raises(ValueError, match="burst"):
        PartGate("torso", 10.0, 0)
    with pytest.raises(ValueError, match="rate"):
        PartGate("torso", float("nan"), 1)


def test_concurrent_screens_count_every_token_once() -> None:
    gate, _ = _gate(rate=1e-9, burst=500)  # no refill worth counting: the burst only
    payload = _payload()
    admitted: list[int] = []

    def screen() -> None:
        admitted.append(sum(gate.screen(payload) is None for _ in range(400)))

    threads = [threading.Thread(target=screen) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(10)
    assert sum(admitted) == 500


# -- the simulation loop -----------------------------------------------------------------------
class NullSink:
    """Drops the loop's streams."""

    def joint_state(self, *args: Any) -> None:
        pass

    def world_state(self, *args: Any) -> None:
        pass

    def event(self, *args: Any) -> None:
        pass


@pytest.fixture
def loop() -> Iterator[SimLoop]:
    world = ArcheryWorld(WORLD)
    world.reset(0)
    sim = SimLoop(world, RobotConfig(world=WORLD, command_rate=1000.0, command_burst=3), NullSink())
    stop = threading.Event()
    thread = threading.Thread(target=sim.run, args=(stop,), daemon=True)
    thread.start()
    yield sim
    stop.set()
    thread.join(5)


def _wait_counted(sim: SimLoop, part: str, total: int) -> dict[str, Any]:
    """The part's counters once `total` commands are counted (accepted or rejected)."""
    for _ in range(2000):
        counters = sim.counters(part)
        if counters.accepted + counters.rejected >= total:
            return counters.rejected_by_reason | {"accepted": counters.accepted}
        threading.Event().wait(0.005)
    raise AssertionError(f"{part}: fewer than {total} commands counted: {sim.counters(part)}")


def _receive(sim: SimLoop, command: JointCommand) -> bool:
    """What the service's `command:i` subscription does with a message: screen its raw payload
    (the lease's one check), then decode it and hand it to the loop; whether it passed."""
    payload = encode(command)
    if not sim.leases.screen(command.part, payload):
        return False
    msg = decode(payload, JointCommand)
    sim.command(msg.part, msg.position, msg.names, msg.part, msg.batch, msg.lease)
    return True


def test_the_loop_obeys_only_the_holder_while_a_lease_runs(loop: SimLoop) -> None:
    handlers = RobotHandlers(loop, {})
    lease = loop.leases.claim("torso", "controller", 5.0)
    assert loop.leases.holder("torso").owner == "controller"
    assert not _receive(loop, JointCommand(part="torso", position=[0.0, 0.0, 0.1]))
    forged = JointCommand(part="torso", position=[0.0, 0.0, 0.1], lease="forged")
    assert not _receive(loop, forged)  # refused before decoding
    assert _receive(loop, JointCommand(part="torso", position=[0.0, 0.0, 0.2], lease=lease.lease))
    counted = _wait_counted(loop, "torso", 3)
    assert counted["accepted"] == 1 and counted[NOT_OWNER] == 2
    np.testing.assert_allclose(loop.targets("torso"), [0.0, 0.0, 0.2])
    with pytest.raises(NotOwner, match="held by 'controller'"):
        handlers.position_move("torso", rv.PositionMoveArgs(position=[0.0, 0.0, 0.3]))
    with pytest.raises(NotOwner, match="held by 'controller'"):
        handlers.set_ref_speeds("torso", rv.SetRefSpeedsArgs(speeds=1.0))
    move = rv.PositionMoveArgs(position=[0.0, 0.0, 0.3], lease=lease.lease)
    assert handlers.position_move("torso", move).position == [0.0, 0.0, 0.3]
    speeds = rv.SetRefSpeedsArgs(speeds=1.0, lease=lease.lease)
    assert handlers.set_ref_speeds("torso", speeds).speeds == [1.0] * 3
    assert loop.counters("torso").rejected_by_reason[NOT_OWNER] == 3  # the positionMove too
    assert "held by 'controller'" in loop.counters("torso").last_rejection
    assert loop.status().counters["torso"]["owner"] == "controller"
    loop.leases.drop("torso", lease.lease)
    anyone = rv.PositionMoveArgs(position=[0.0, 0.0, 0.0])
    assert handlers.position_move("torso", anyone).position == [0.0, 0.0, 0.0]  # anyone again
    assert loop.status().counters["torso"]["owner"] == ""


def test_a_command_s_lease_is_checked_once_where_it_arrives(
    loop: SimLoop, monkeypatch: pytest.MonkeyPatch
) -> None:
    lease = loop.leases.claim("torso", "controller", 5.0).lease
    consulted: list[str] = []
    running = PartGate._current

    def counted(gate: PartGate, now: float) -> Any:
        consulted.append(gate.part)
        return running(gate, now)

    monkeypatch.setattr(PartGate, "_current", counted)
    assert _receive(loop, JointCommand(part="torso", position=[0.0, 0.0, 0.2], lease=lease))
    assert _wait_counted(loop, "torso", 1)["accepted"] == 1
    assert consulted == ["torso"]  # at the screen, not again on its way to the simulation
    move = rv.PositionMoveArgs(position=[0.0, 0.0, 0.3], lease=lease)
    assert RobotHandlers(loop, {}).position_move("torso", move).position == [0.0, 0.0, 0.3]
    assert consulted == ["torso"] * 2  # a positionMove: by its handler, once


def test_the_running_id_outside_a_payload_s_lease_field_does_not_pass() -> None:
    gate, _ = _gate()
    lease, _ = gate.claim("controller", 2.0)
    elsewhere = (
        JointCommand(part="left_arm", position=[0.0], names=[lease.id]),  # its lease ""
        JointCommand(part="left_arm", position=[0.0] * 7, lease=lease.id + "0"),
    )
    for command in elsewhere:
        reason, message = gate.screen(encode(command)) or ("", "")
        assert reason == NOT_OWNER and "held by 'controller'" in message
    assert gate.screen(_payload(lease.id)) is None


def test_the_loop_drops_commands_over_the_rate_limit(loop: SimLoop) -> None:
    payload = encode(JointCommand(part="left_arm", position=[0.0] * len(PARTS["left_arm"])))
    admitted = sum(loop.leases.screen("left_arm", payload) for _ in range(1000))
    assert 3 <= admitted < 20  # the burst, and what 1000/s refilled meanwhile
    counters = loop.counters("left_arm")
    assert counters.rejected_by_reason[RATE_LIMITED] == 1000 - admitted
    assert "at most 1000 commands/s" in counters.last_rejection
