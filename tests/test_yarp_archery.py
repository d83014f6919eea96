"""A YARP robot's own archery verbs and world events for `archery robot --body yarp
--archery-rpc`: `services/robot/yarp_archery.ArcheryLink` against the bridge's `ArcheryPort`
(its `json VERB` form) and an events port of `event_bottle`s, all in YARP's own code on a
private loopback `yarpserver`; the robot behind the port is a stand-in that answers the
contract's typed replies."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from archery.apps.yarp.ports import ArcheryPort, event_bottle
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.messages import WorldEvent
from archery.protocol.verbs import robot as rv
from archery.services.robot.config import RobotConfig
from archery.services.robot.yarp_archery import ArcheryLink
from archery.sim.scene_config import SceneConfig
from tests.ros2_sdk import until
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

STATUS = rv.ArcheryStatusReply(
    sim_time=1.25,
    arrow="nocked",
    phase="nocked",
    shot=3,
    motion_done=True,
    seed=7,
    rtf=0.0,
    state_rate=50.0,
    world_rate=30.0,
    watchdog=0.1,
    limit_tolerance=0.02,
    timestep=0.001,
    counters={"left_arm": {"accepted": 4}},
    scene=SceneConfig().to_status(),
    world={"drag": 0.01, "wind": [0.0, 0.5, 0.0]},
)
RELEASE = rv.ReleaseReply(
    shot=3,
    outcome="landed",
    hit=True,
    reason="",
    sim_time=2.5,
    release_sim_time=1.5,
    flight_time=1.0,
    theta=[0.05, -0.1, 0.3],
)


class StandIn:
    """The robot behind the port: the contract's replies, and the calls it got."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, Any]] = []

    def call(self, verb: Any, args: Any = None, timeout: float | None = None) -> Any:
        self.calls.append((verb.name, args))
        if verb is rv.ARCHERY_STATUS:
            return STATUS
        if verb is rv.RELEASE:
            return RELEASE
        if verb is rv.RESET:
            return rv.ResetReply(sim_time=0.0, seed=args.seed, shot=0)
        if verb is rv.NOCK:
            raise ArcheryError("no arrow in the holder", code="nock_missed")
        return rv.GraspReply(arrow="a1", distance=0.002, tolerance=0.01, sim_time=0.5)


class Events:
    def __init__(self) -> None:
        self.got: list[tuple[str, int, float | None, list[float] | None, str]] = []

    def joint_state(self, *args: Any) -> None:
        pass

    def world_state(self, *args: Any) -> None:
        pass

    def event(
        self,
        kind: str,
        shot: int,
        sim_time: float | None,
        impact_m: list[float] | None = None,
        reason: str = "",
    ) -> None:
        self.got.append((kind, shot, sim_time, impact_m, reason))


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> Iterator[YarpSetup]:
    running = YarpSetup(yarp, tmp_path_factory.mktemp("yarp") / "conf")
    try:
        yield running
    finally:
        running.close()


def test_the_verbs_are_the_ports_typed_answers_and_the_events_are_forwarded(
    setup: YarpSetup,
) -> None:
    robot = StandIn()
    port = ArcheryPort(yarp, robot, "/bot", operator=True)  # type: ignore[arg-type]
    events_out = yarp.BufferedPortBottle()
    assert events_out.open("/bot/world/events:o")
    sink = Events()
    link = ArcheryLink(yarp, "/bot/archery/rpc:i", "/bot/world/events:o", sink, timeout=10)
    try:
        status = link.status()
        assert status == STATUS  # the nested scene and the dicts too: nothing lost
        assert link.release() == RELEASE
        assert link.reset(2**40) == rv.ResetReply(sim_time=0.0, seed=2**40, shot=0)
        assert link.reset().seed is None
        assert link.grasp().distance == pytest.approx(0.002)
        with pytest.raises(ArcheryError) as refused:
            link.nock()
        assert refused.value.code == "nock_missed"
        assert [name for name, _ in robot.calls] == [
            rv.ARCHERY_STATUS.name,
            rv.RELEASE.name,
            rv.RESET.name,
            rv.RESET.name,
            rv.GRASP.name,
            rv.NOCK.name,
        ]
        until(lambda: events_out.getOutputCount() == 1, "the link's events reader", timeout=5)
        for event in (
            WorldEvent(kind="released", shot=3),
            WorldEvent(kind="landed", shot=3, impact_m=[0.01, -0.02]),
            WorldEvent(kind="watchdog", shot=3, reason="left_arm"),
        ):
            event_bottle(events_out.prepare(), event)
            events_out.writeStrict()
        until(lambda: len(sink.got) == 3, "the three events forwarded", timeout=10)
        assert sink.got == [
            ("released", 3, None, None, ""),
            ("landed", 3, None, [0.01, -0.02], ""),
            ("watchdog", 3, None, None, "left_arm"),
        ]
    finally:
        link.close()
        events_out.close()
        port.close()


def test_a_read_only_port_refuses_and_a_missing_port_does_not_open(setup: YarpSetup) -> None:
    port = ArcheryPort(yarp, StandIn(), "/ro", operator=False)  # type: ignore[arg-type]
    link = ArcheryLink(yarp, "/ro/archery/rpc:i", "/ro/world/events:o", Events(), timeout=10)
    try:
        assert link.status() == STATUS
        with pytest.raises(ArcheryError) as refused:
            link.release()
        assert refused.value.code == "read_only"
    finally:
        link.close()
        port.close()
    with pytest.raises(ConfigError, match="no such port"):
        ArcheryLink(yarp, "/nobody/archery/rpc:i", "", Events(), timeout=1)


def test_the_flag_needs_a_yarp_body_and_a_port_name() -> None:
    assert RobotConfig(body="yarp", archery_rpc="/icubSim/archery/rpc:i").archery_rpc
    with pytest.raises(ConfigError, match="--archery-rpc"):
        RobotConfig(archery_rpc="/icubSim/archery/rpc:i")
    with pytest.raises(ConfigError, match="--archery-rpc"):
        RobotConfig(body="yarp", archery_rpc="no port")
