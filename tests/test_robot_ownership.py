"""One owner per part and the rate limit, on real processes: `archery robot --rtf 1` and
`archery controller` as child processes, the rival publishers and the flooder in others (the
test's node, `tests.flooder`, `archery rpc` and `archery write`).

A move to θ (the controller's `posture` verb) at rtf 1 runs TRAJ_TIME wall seconds, so a rival
or a flood that starts once the arm moves lands while the controller holds the lease. The stall
of a flooded move is the longest wall-clock gap between two states of the left arm that bring it
closer to its targets (the states come every 20 ms).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.protocol.messages import JointCommand, JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import (
    COMMAND_BURST,
    COMMAND_RATE,
    CONTROLLER,
    LEASE_TTL,
    ROBOT,
    home_of,
)
from tests.conftest import archery
from tests.rpc import rpc_call

ARM = "left_arm"
THETA = [0.17, 0.03, -0.03]
TRAJ_TIME = 3.0  # s of sim time, wall s at rtf 1
FLOOD = 50_000
MAX_STALL = 0.5  # wall s
WAIT = 60.0  # wall s: the bound of every wait on a condition


def _spawn(verb: str, net: NetConfig, *flags: str) -> subprocess.Popen[bytes]:
    argv = [sys.executable, "-m", "archery.apps.cli", verb, "--connect", net.connect[0]]
    return subprocess.Popen([*argv, "--robot", net.robot, *flags], stdin=subprocess.DEVNULL)


def _until(condition: Callable[[], Any], what: str, timeout: float = WAIT) -> Any:
    """Poll `condition` until it returns something true; that value."""
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        assert time.monotonic() < deadline, f"{what} within {timeout:g} s"
        time.sleep(0.01)
    return value


@dataclass
class Rig:
    """The robot and controller processes and the test's node."""

    net: NetConfig
    node: Node
    robot: subprocess.Popen[bytes]
    controller: subprocess.Popen[bytes]
    states: list[tuple[float, list[float]]] = field(default_factory=list)  # (wall s, rad)

    def part(self, part: str, verb: str, args: dict[str, Any] | None = None) -> Any:
        return rpc_call(self.node, self.node.keys.part_rpc(part), verb, args, timeout=20)

    def counters(self, part: str = ARM) -> dict[str, int]:
        counters = self.part(part, "counters")
        return counters["rejected_by_reason"] | {"accepted": counters["accepted"]}

    def owner(self, part: str = ARM) -> str:
        return str(self.part(part, "getClaim")["owner"])

    def home(self) -> None:
        """Every part free and at home, the arm's state record empty."""
        for part in PARTS:
            if self.owner(part):
                lease = self.part(part, "claim", {"owner": "test", "takeover": True})["lease"]
                self.part(part, "dropClaim", {"lease": lease})
        rpc_call(self.node, self.node.keys.archery_rpc(), "reset", {"seed": 0}, timeout=30)
        home = np.array(home_of(ARM))

        def at_home() -> bool:
            return bool(self.states) and np.allclose(self.states[-1][1], home, atol=1e-4)

        _until(at_home, "the arm at home")
        self.states.clear()

    def move_to_theta(self) -> dict[str, Any]:
        return dict(
            rpc_call(
                self.node,
                self.node.keys.cartesian_rpc("archery"),
                "posture",
                {"theta": THETA, "timeout": WAIT},
                timeout=2 * WAIT,
            )
        )

    def move_to_theta_soon(self) -> Callable[[], dict[str, Any]]:
        """Start a move to θ on a thread; returns the call that waits for its reply."""
        result: dict[str, Any] = {}

        def run() -> None:
            try:
                result["reply"] = self.move_to_theta()
            except BaseException as exc:
                result["error"] = exc

        thread = threading.Thread(target=run, daemon=True)
        thread.start()

        def reply() -> dict[str, Any]:
            thread.join(3 * WAIT)
            if "error" in result:
                raise result["error"]
            return dict(result["reply"])

        return reply

    def start_controller(self) -> None:
        self.controller = _spawn("controller", self.net, "--traj-time", str(TRAJ_TIME))
        self.node.wait_alive([CONTROLLER], WAIT)


@pytest.fixture(scope="module")
def rig(router_endpoint: str) -> Iterator[Rig]:
    net = NetConfig(connect=(router_endpoint,), robot=f"own{os.getpid()}")
    robot = _spawn("robot", net, "--rtf", "1")
    controller = _spawn("controller", net, "--traj-time", str(TRAJ_TIME))
    node = Node(None, net)
    rig = Rig(net, node, robot, controller)
    node.subscribe(
        node.keys.state(ARM),
        JointState,
        callback=lambda m: rig.states.append((time.monotonic(), list(m.position))),
    )
    try:
        node.wait_alive([ROBOT, CONTROLLER], 120)
        yield rig
    finally:
        node.close()
        for proc in (rig.controller, robot):
            proc.terminate()
        for proc in (rig.controller, robot):
            try:
                assert proc.wait(20) in (0, -signal.SIGKILL)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture
def flooder(rig: Rig) -> Iterator[Callable[[], float]]:
    """flood() publishes FLOOD commands holding the arm where it is, from another process;
    returns how long the publishing took (wall s)."""
    argv = [sys.executable, "-m", "tests.flooder", rig.net.connect[0], rig.net.robot, ARM]
    proc = subprocess.Popen(
        [*argv, str(FLOOD)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdin is not None and proc.stdout is not None
    assert proc.stdout.readline().strip() == "ready"

    def flood() -> float:
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write("go\n")
        proc.stdin.flush()
        return float(proc.stdout.readline())

    yield flood
    proc.stdin.close()
    assert proc.wait(20) == 0


def _moving(rig: Rig) -> bool:
    """The arm has left home (by more than 1 mrad)."""
    home = np.array(home_of(ARM))
    return any(np.max(np.abs(np.array(q) - home)) > 1e-3 for _, q in list(rig.states))


def _worst_stall(rig: Rig, goal: np.ndarray, tolerance: float = 5e-3) -> float:
    """The longest wall gap between states that bring the arm closer to `goal` (rad), from its
    first move until it is within `tolerance` of it."""
    best, last, worst = float("inf"), None, 0.0
    for t, q in list(rig.states):
        distance = float(np.max(np.abs(np.array(q) - goal)))
        if distance < best - 1e-6:
            if last is not None:
                worst = max(worst, t - last)
            best, last = distance, t
            if distance <= tolerance:
                return worst
    raise AssertionError(f"the arm never got within {tolerance} rad of its targets")


def _arm_targets(reply: dict[str, Any]) -> np.ndarray:
    return np.array([reply["q"][j] for j in PARTS[ARM]])


def test_a_rival_publisher_during_a_move_changes_nothing_and_is_counted(rig: Rig) -> None:
    rig.home()
    before = rig.counters()
    reply = rig.move_to_theta_soon()
    _until(lambda: rig.owner() == CONTROLLER, "the controller's lease on the arm")
    rival = rig.node.publisher(rig.node.keys.command(ARM), JointCommand, lossless=True)
    assert rival.wait_matched(WAIT)
    sent = 500
    # the arm's latest state (the lease may be taken before a state arrives after the reset)
    where = _until(lambda: rig.states and rig.states[-1][1], "a state of the arm")
    for _ in range(sent):  # valid commands: hold the arm where it is
        rival.put(JointCommand(part=ARM, position=where))
    counted = _until(
        lambda: (c := rig.counters())["not_owner"] - before["not_owner"] >= sent and c,
        "the rival's commands counted",
    )
    assert rig.owner() == CONTROLLER  # all of them came while the controller held the arm
    done = reply()
    assert done["reached"] and done["reason"] == "" and done["measured_error_m"] < 1e-3
    after = rig.counters()
    assert counted["not_owner"] - before["not_owner"] == sent
    assert after["accepted"] - before["accepted"] == 1  # the controller's command only
    np.testing.assert_allclose(rig.part(ARM, "getTargets")["position"], _arm_targets(done))
    assert "held by 'controller'" in rig.part(ARM, "counters")["last_rejection"]
    _until(lambda: rig.owner() == "", "the controller dropping its lease")


def test_a_flood_of_50000_commands_stalls_a_move_by_at_most_half_a_second(
    rig: Rig, flooder: Callable[[], float]
) -> None:
    rig.home()
    before = rig.counters()
    reply = rig.move_to_theta_soon()
    _until(lambda: _moving(rig), "the arm moving")
    flood_s = flooder()
    done = reply()
    assert done["reached"], done["reason"]
    stall = _worst_stall(rig, _arm_targets(done))
    assert stall <= MAX_STALL, (stall, flood_s)
    after = rig.counters()
    assert after["not_owner"] - before["not_owner"] == FLOOD  # every one refused, none applied
    assert after["accepted"] - before["accepted"] == 1


def test_a_flood_with_no_lease_held_is_rate_limited_and_the_arm_stays_put(
    rig: Rig, flooder: Callable[[], float]
) -> None:
    rig.home()
    before = rig.counters()
    start = time.monotonic()
    flooder()
    after = _until(
        lambda: (
            (c := rig.counters())["accepted"] + c["rate_limited"]
            >= before["accepted"] + before["rate_limited"] + FLOOD
            and c
        ),
        "the flood counted",
    )
    elapsed = time.monotonic() - start
    accepted = after["accepted"] - before["accepted"]
    assert accepted + after["rate_limited"] - before["rate_limited"] == FLOOD
    assert 1 <= accepted <= COMMAND_BURST + COMMAND_RATE * elapsed
    stream = list(rig.states)  # the robot kept streaming (and its simulation running)
    arrivals = np.array([t for t, _ in stream if start <= t])
    assert arrivals[-1] - start >= elapsed - 0.1
    assert np.max(np.diff(np.concatenate([[start], arrivals]))) <= MAX_STALL
    home = np.array(home_of(ARM))
    assert max(np.max(np.abs(np.array(q) - home)) for _, q in stream) < 2e-3  # held


def test_a_lease_that_is_not_renewed_ends_and_frees_the_part(rig: Rig) -> None:
    rig.home()
    before = rig.counters()
    asked = time.monotonic()
    lease = rig.part(ARM, "claim", {"owner": "tester", "ttl": 0.5})
    assert lease["owner"] == "tester" and lease["ttl"] == 0.5 and lease["took_over"] == ""
    with pytest.raises(RpcError, match="held by 'tester'") as refused:
        rig.part(ARM, "claim", {"owner": "someone"})
    assert refused.value.code == "not_owner"
    hold = JointCommand(part=ARM, position=list(home_of(ARM)))
    publisher = rig.node.publisher(rig.node.keys.command(ARM), JointCommand, lossless=True)
    publisher.put(hold)
    _until(lambda: rig.counters()["not_owner"] > before["not_owner"], "a refusal counted")
    _until(lambda: rig.owner() == "", "the lease's end")
    assert time.monotonic() - asked >= 0.5
    with pytest.raises(RpcError, match="has ended: nobody holds the part") as ended:
        rig.part(ARM, "renewClaim", {"lease": lease["lease"]})
    assert ended.value.code == "not_owner"
    publisher.put(hold)  # anyone's again
    _until(lambda: rig.counters()["accepted"] > before["accepted"], "the command accepted")


def test_the_operator_takes_the_arm_over_mid_move(rig: Rig) -> None:
    rig.home()
    flags = ["--connect", rig.net.connect[0], "--robot", rig.net.robot]
    rpc_key, key = f"{rig.net.robot}/{ARM}/rpc:i", f"{rig.net.robot}/{ARM}/command:i"
    reply = rig.move_to_theta_soon()
    _until(lambda: rig.owner() == CONTROLLER, "the controller's lease on the arm")
    claim = '{"owner": "operator", "takeover": true, "ttl": 120}'
    took = archery("rpc", rpc_key, "claim", claim, *flags)
    assert took.returncode == 0, took.stderr
    lease = json.loads(took.stdout)
    assert lease["owner"] == "operator" and lease["took_over"] == CONTROLLER
    done = reply()  # the controller sees it at its next renewal and gives up the move
    assert not done["reached"]
    assert "left_arm was taken over during the move" in done["reason"], done["reason"]
    assert "held by 'operator'" in done["reason"]
    with pytest.raises(RpcError, match=r"cannot move left_arm: .* is held by 'operator'") as busy:
        rig.move_to_theta()
    assert busy.value.code == "not_owner"
    home = json.dumps({"part": ARM, "position": list(home_of(ARM))})
    refused = archery("write", key, home, *flags)
    assert refused.returncode == 1
    assert "refused by" in refused.stderr and "held by 'operator'" in refused.stderr
    leased = json.dumps({"part": ARM, "position": list(home_of(ARM)), "lease": lease["lease"]})
    accepted = archery("write", key, leased, *flags)
    assert accepted.returncode == 0, accepted.stderr
    free = rig.part(ARM, "dropClaim", {"lease": lease["lease"]})
    assert free == {"held": False, "owner": "", "ttl": 0.0, "expires_in": 0.0}
    assert rig.move_to_theta()["reached"]  # the controller's again


def test_a_dead_controller_s_lease_ends_by_itself(rig: Rig) -> None:
    rig.home()
    reply = rig.move_to_theta_soon()
    _until(lambda: rig.owner() == CONTROLLER, "the controller's lease on the arm")
    held = rig.part(ARM, "getClaim")
    assert held["ttl"] == LEASE_TTL and held["expires_in"] <= LEASE_TTL
    rig.controller.kill()
    rig.controller.wait(20)
    killed = time.monotonic()
    _until(lambda: rig.owner() == "", "the dead controller's lease ending")
    assert time.monotonic() - killed <= LEASE_TTL + 10.0
    with pytest.raises(RpcError):
        reply()
    rig.node.wait_gone(CONTROLLER, WAIT)
    rig.start_controller()
    rig.home()
    assert rig.move_to_theta()["reached"]


def test_set_ref_speeds_claims_the_part_in_the_same_round_trip(rig: Rig) -> None:
    rig.home()
    n = len(PARTS[ARM])
    took = rig.part(ARM, "setRefSpeeds", {"speeds": 0.3, "claim": {"owner": "tester"}})
    assert took["speeds"] == [0.3] * n and took["lease"]
    held = rig.part(ARM, "getClaim")
    assert held["owner"] == "tester" and held["ttl"] == LEASE_TTL
    with pytest.raises(RpcError, match="a lease or a claim, not both") as both:
        rig.part(
            ARM,
            "setRefSpeeds",
            {"speeds": 0.2, "lease": took["lease"], "claim": {"owner": "tester"}},
        )
    assert both.value.code == "bad_request"
    with pytest.raises(RpcError, match="held by 'tester'") as refused:
        rig.part(ARM, "setRefSpeeds", {"speeds": 0.1, "claim": {"owner": "someone"}})
    assert refused.value.code == "not_owner"
    assert rig.part(ARM, "getRefSpeeds")["speeds"] == [0.3] * n  # the refused call set nothing
    rig.part(ARM, "dropClaim", {"lease": took["lease"]})
    with pytest.raises(RpcError) as wrong:  # speeds of the wrong length: the new lease let go
        rig.part(ARM, "setRefSpeeds", {"speeds": [0.1] * (n + 1), "claim": {"owner": "tester"}})
    assert wrong.value.code == "bad_request"
    assert rig.owner() == ""
    assert rig.move_to_theta()["reached"]  # the controller claims and moves the arm as before
