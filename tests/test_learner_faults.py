"""Faults a session lives through: any lost service (the detector's lost camera included) is
`service_lost` naming it, waited for in the same session with what it waits for shown, bounded
by `service_wait`, never counted as aborts in a row; no shot while a service is missing; late
replies and stale ground truth ignored; `archery learn --attach` and the journal's counts; the
journal invariants; and, with real processes, the camera killed mid-session and restarted."""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from archery.apps.learn import attach, follow, learn
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import RpcError, UpstreamLost
from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    HeaderRecord,
    JournalRecord,
    ProposedRecord,
    StoppedRecord,
)
from archery.protocol.messages import Rollout, WorldEvent
from archery.protocol.verbs import controller as cv
from archery.protocol.verbs.learner import LearnerStatusReply
from archery.services.detector import service as detector_service
from archery.services.detector.colour_model import ColourModel
from archery.services.learner import handlers as learner_handlers
from archery.services.learner import service as learner_service
from archery.services.learner.config import LearnerServiceConfig, SessionConfig
from archery.services.learner.errors import ServiceLost
from archery.services.learner.journal import JournalState, check_invariants, read_records
from archery.services.learner.rig import MeshRig
from archery.services.learner.rig_protocol import Measurement, PostureResult, Shot
from archery.services.learner.session import FINAL_STATES, Session
from tests.conftest import serving
from tests.rpc import rpc_call
from tests.test_learner_service_session import FakeRig


class FaultRig(FakeRig):
    """A FakeRig whose services vanish on cue and come back only when `back` is set.

    `lose_in` maps (attempt, step) to the service lost during that step ("posture" or "measure",
    where the call then fails with ServiceLost as the mesh rig reports it). A lost service is
    back at the next `wait_services`, or, with `hold`, once `back` is set. Every status seen
    while the session waits is kept in `seen_waiting`, and every shot notes what was missing.
    """

    def __init__(self, lose_in: dict[tuple[int, str], str] | None = None, hold: bool = False):
        super().__init__()
        self.lose_in = dict(lose_in or {})
        self.hold = hold
        self.back = threading.Event()
        self.session: Session | None = None
        self.seen_waiting: list[LearnerStatusReply] = []
        self.missing_at_shot: list[list[str]] = []
        self.lost_at: dict[str, float] = {}

    def _lose(self, service: str) -> None:
        self.gone.add(service)
        self.lost_at[service] = time.monotonic()

    def lost_ago(self, service: str) -> float | None:
        lost = self.lost_at.get(service)
        return None if lost is None or service not in self.gone else time.monotonic() - lost

    def wait_services(self, timeout: float, stop: threading.Event) -> bool:
        self.waits += 1
        if self.session is not None:
            self.seen_waiting.append(self.session.status())
        if self.hold and not self.back.wait(timeout):
            raise ServiceLost(", ".join(sorted(self.gone)), "still missing")
        self.gone.clear()
        return True

    def move_to(self, theta: np.ndarray) -> PostureResult:
        result = super().move_to(theta)
        service = self.lose_in.pop((self.attempts, "posture"), None)
        if service is not None:  # vanishes once the posture is reached, before the shot
            self._lose(service)
        return result

    def shoot(self) -> Shot:
        self.missing_at_shot.append(self.missing())
        return super().shoot()

    def measure(self, shot: Shot) -> Measurement:
        service = self.lose_in.pop((self.attempts, "measure"), None)
        if service is not None:
            self._lose(service)
            raise ServiceLost(service, f"the {service} did not answer")
        return super().measure(shot)


def _session(rig: FaultRig, runs: Path, config: SessionConfig, **kw: Any) -> Session:
    session = Session.create(config, rig, runs, session_id="s", **kw)
    rig.session = session
    return session


def _records(session: Session) -> list[JournalRecord]:
    return read_records(session.journal.path)[0]


def test_camera_lost_mid_measure_is_waited_for_in_the_same_session(tmp_path: Path) -> None:
    # Lost three times in a row, yet max_aborts=2 does not fail the session: waiting is no fault.
    lose = {(2, "measure"): "camera", (3, "measure"): "camera", (4, "measure"): "camera"}
    rig = FaultRig(lose)
    session = _session(rig, tmp_path, SessionConfig(seed=2, max_aborts=2))
    status = session.run(threading.Event())
    assert status.state == "finished", status
    records = _records(session)
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert [(a.index, a.code) for a in aborted] == [
        (2, "service_lost"),
        (3, "service_lost"),
        (4, "service_lost"),
    ]
    assert all(a.cause.startswith("camera: ") for a in aborted)
    assert all(a.retry_theta == a.theta for a in aborted)
    waiting = [s for s in rig.seen_waiting if s.state == "waiting"]
    assert len(waiting) == 3
    for seen in waiting:
        assert seen.waiting_for == ["camera"]
        assert seen.cause.startswith("waiting for camera (lost ")
        assert seen.cause.endswith(" s ago)")
    assert "resumed" not in [r.kind for r in records]
    assert check_invariants(records) == []


def test_robot_lost_means_no_shot_while_it_is_missing(tmp_path: Path) -> None:
    rig = FaultRig({(2, "posture"): "robot"})
    session = _session(rig, tmp_path, SessionConfig(seed=1, until_hit=False, rollouts=4))
    assert session.run(threading.Event()).state == "finished"
    assert all(missing == [] for missing in rig.missing_at_shot)
    assert rig.shots == 4  # one per done rollout: the aborted attempt released nothing
    records = _records(session)
    (aborted,) = [r for r in records if isinstance(r, AbortedRecord)]
    assert aborted.code == "service_lost"
    assert aborted.cause == "robot: not alive before the shot; no arrow released"
    assert rig.seen_waiting[0].waiting_for == ["robot"]
    assert check_invariants(records) == []


def test_services_missing_before_an_attempt_are_waited_for_first(tmp_path: Path) -> None:
    rig = FaultRig(hold=True)
    session = _session(rig, tmp_path, SessionConfig(seed=1, until_hit=False, rollouts=3))
    rig._lose("detector")
    waiter = threading.Thread(target=session.run, args=(threading.Event(),))
    waiter.start()
    try:
        deadline = time.monotonic() + 10
        while not rig.seen_waiting and time.monotonic() < deadline:
            rig.back.wait(0.01)
        assert rig.seen_waiting and rig.seen_waiting[0].state == "waiting"
        assert rig.attempts == 0  # nothing proposed, moved or shot while it is missing
    finally:
        rig.back.set()
        waiter.join(10)
    assert session.status().state == "finished"
    assert session.journal.state.n_aborted == 0


def test_a_service_lost_for_good_fails_the_session_resumably(tmp_path: Path) -> None:
    rig = FaultRig({(2, "measure"): "camera"}, hold=True)  # the camera never comes back
    session = _session(rig, tmp_path, SessionConfig(seed=1), service_wait=0.3)
    status = session.run(threading.Event())
    assert status.state == "failed"
    assert status.cause.startswith("camera still not alive 0.3 s after a service was lost")
    records = _records(session)
    assert isinstance(records[-1], StoppedRecord) and records[-1].reason == "failed"
    assert check_invariants(records) == []
    resumed = Session.resume(session.journal.path, FakeRig())
    assert resumed.run(threading.Event()).state == "finished"
    assert check_invariants(_records(resumed)) == []


def test_a_stuck_service_that_stays_alive_is_bounded_by_service_wait(tmp_path: Path) -> None:
    class Stuck(FaultRig):
        def measure(self, shot: Shot) -> Measurement:
            raise ServiceLost("detector", "no reply within 20 s")

    session = _session(Stuck(), tmp_path, SessionConfig(seed=1), service_wait=0.2)
    status = session.run(threading.Event())
    assert status.state == "failed"
    assert "services kept failing 0.2 s after a service was lost" in status.cause
    assert check_invariants(_records(session)) == []


# -- journal invariants ----------------------------------------------------------------------------
def _r(kind: str, index: int, rollout: int = 1) -> JournalRecord:
    """A proposed, done or aborted record of attempt `index` (θ and r made up)."""
    theta = [0.17, 0.0, -0.02]
    if kind == "proposed":
        return ProposedRecord(session="s", index=index, theta=theta)
    if kind == "done":
        return DoneRecord(
            session="s",
            index=index,
            rollout=rollout,
            theta=theta,
            r_m=[0.0, 0.1],
            distance_m=0.1,
            hit=False,
        )
    return AbortedRecord(
        session="s", index=index, theta=theta, code="no_arrow", cause="", retry_theta=theta
    )


HEADER = HeaderRecord(
    session="s", algorithm="archer", seed=0, rollouts=3, options={}, config={}, learner_state={}
)


@pytest.mark.parametrize(
    ("records", "violations"),
    [
        ([HEADER, _r("proposed", 1), _r("done", 1, rollout=1)], []),
        (
            [
                HEADER,
                _r("proposed", 1),
                _r("aborted", 1),
                _r("proposed", 2),
                _r("done", 2, rollout=1),
            ],
            [],
        ),
        ([HEADER, _r("proposed", 1)], ["attempts proposed but never ended: [1]"]),
        (
            [HEADER, _r("proposed", 1), _r("done", 1, rollout=1), _r("done", 1, rollout=2)],
            ["record 4: attempt 1 done after it was done already"],
        ),
        (
            [HEADER, _r("proposed", 1), _r("aborted", 1), _r("done", 1, rollout=1)],
            ["record 4: attempt 1 done after it was aborted already"],
        ),
        (
            [HEADER, _r("proposed", 1), _r("done", 1, rollout=1), _r("proposed", 3)],
            [
                "attempt indices not contiguous from 1: [1, 3]",
                "attempts proposed but never ended: [3]",
            ],
        ),
        (
            [HEADER, _r("done", 1, rollout=1)],
            ["record 2: done for attempt 1, never proposed"],
        ),
        (
            [HEADER, _r("proposed", 1), _r("done", 1, rollout=2)],
            ["done rollout numbers not contiguous from 1: [2]"],
        ),
        (
            [HEADER, _r("proposed", 1), _r("proposed", 1), _r("done", 1, rollout=1)],
            ["record 3: attempt 1 proposed again", "attempt indices not contiguous from 1: [1, 1]"],
        ),
    ],
)
def test_check_invariants(records: list[JournalRecord], violations: list[str]) -> None:
    assert check_invariants(records) == violations


def test_check_invariants_may_allow_the_last_attempt_open() -> None:
    running = [HEADER, _r("proposed", 1), _r("done", 1, rollout=1), _r("proposed", 2)]
    assert check_invariants(running, allow_open=True) == []
    assert check_invariants(running) == ["attempts proposed but never ended: [2]"]


# -- the mesh rig: lost upstream services, late replies, stale ground truth ------------------------
def _colour_model(path: Path) -> None:
    rng = np.random.default_rng(0)
    red = np.clip(rng.normal([200, 30, 30], 8, (400, 3)), 0, 255).astype(np.uint8)
    blue = np.clip(rng.normal([30, 40, 200], 8, (400, 3)), 0, 255).astype(np.uint8)
    ColourModel.fit(red, blue).save(str(path))


def test_detector_without_its_camera_is_service_lost_camera(net: NetConfig, tmp_path: Path) -> None:
    model = tmp_path / "model.json"
    _colour_model(model)
    config = detector_service.DetectorConfig(net=net, model=str(model), auto_calibrate=False)
    with serving(detector_service.run, config), Node("learner", net) as node:
        node.wait_alive(["detector"], timeout=30)
        # The detector's own reply: upstream_lost naming the camera.
        with pytest.raises(RpcError) as error:
            rpc_call(node, node.keys.detector_rpc(), "measure", {"timeout": 1.0}, timeout=10)
        assert isinstance(error.value, UpstreamLost) and error.value.service == "camera"
        # The rig makes it the loss of the camera, not an rpc error of the detector.
        rig = MeshRig(node, timeout=5.0)
        with pytest.raises(ServiceLost) as lost:
            rig.measure(Shot(1, 0.0, time.time(), "target"))
        assert lost.value.service == "camera" and lost.value.code == "service_lost"


def _fake_controller(node: Node, release: threading.Event, calls: list[list[float]]) -> None:
    def posture(args: cv.PostureArgs) -> cv.PostureReply:
        calls.append(list(args.theta))
        if len(calls) == 1:
            release.wait(30)  # the first posture answers only after its caller gave up
        theta = list(args.theta)
        return cv.PostureReply(
            q={},
            theta=theta,
            theta_achieved=theta,
            theta_measured=theta,
            relative_error_m=0.0,
            measured_error_m=0.0,
            reachable=True,
            bow_hand=[0.0, 0.0, 0.0],
            reached=True,
            reason="",
            wall_s=0.0,
            sim_time=0.0,
        )

    def status(args: Any) -> Any:
        raise RpcError("not in this test", code="unsupported")

    verbs = {"posture": posture, "status": status, "setTrajTime": status, "getTrajTime": status}
    node.serve(node.keys.cartesian_rpc("archery"), cv.ARCHERY_VERBS.bind_names(verbs))
    node.ready()


def test_a_late_reply_never_reaches_the_next_call(net: NetConfig) -> None:
    release, calls = threading.Event(), []
    with Node("controller", net) as controller, Node("learner", net) as node:
        _fake_controller(controller, release, calls)
        node.wait_alive(["controller"], timeout=30)
        rig = MeshRig(node, timeout=0.5)
        with pytest.raises(ServiceLost) as lost:
            rig.move_to(np.array([0.1, 0.0, 0.0]))
        assert lost.value.service == "controller"
        release.set()  # the first reply is sent now, after the abort
        second = rig.move_to(np.array([0.2, 0.01, -0.02]))
        assert calls == [[0.1, 0.0, 0.0], [0.2, 0.01, -0.02]]
        assert second.theta_measured == [0.2, 0.01, -0.02]  # its own reply, not the late one


def test_ground_truth_ignores_an_earlier_robot_instances_shot(net: NetConfig) -> None:
    with Node("learner", net) as node, Node("robot", net) as robot:
        rig = MeshRig(node)
        events = robot.publisher(robot.keys.world_events(), WorldEvent, lossless=True)
        events.wait_matched(10)
        events.put(WorldEvent(kind="landed", shot=1, impact_m=[0.5, 0.5]))
        with rig._truth_cond:  # received before the next shot 1 (a restarted robot) is nocked
            rig._truth_cond.wait_for(lambda: 1 in rig._truth, timeout=10)
        shot = Shot(1, 0.0, time.time(), "target")
        assert rig.truth(shot) is None
        events.put(WorldEvent(kind="landed", shot=1, impact_m=[0.01, -0.02]))
        assert rig.truth(shot) == [0.01, -0.02]


# -- attach -------------------------------------------------------------------------------------
class GatedRig(FakeRig):
    """Blocks attempt 3's posture until `gate` is set."""

    def __init__(self) -> None:
        super().__init__()
        self.gate = threading.Event()

    def move_to(self, theta: np.ndarray) -> PostureResult:
        if self.attempts == 2:
            self.gate.wait(60)
        return super().move_to(theta)


@pytest.fixture
def gated_learner(
    net: NetConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[Node, GatedRig]]:
    """The learner service over the router with a gated fake rig; the gate opens once a client
    asks for the status (so an attaching client sees the session running)."""
    rig = GatedRig()
    monkeypatch.setattr(learner_handlers, "MeshRig", lambda node, timeout: rig)
    status = learner_handlers.LearnerHandlers.status

    def status_then_open(self: Any, args: Any) -> Any:
        reply = status(self, args)
        rig.gate.set()
        return reply

    monkeypatch.setattr(learner_handlers.LearnerHandlers, "status", status_then_open)
    config = LearnerServiceConfig(net=net, runs=tmp_path, report=False)
    with serving(learner_service.run, config), Node(None, net) as node:
        node.wait_alive(["learner"], timeout=30)
        yield node, rig


def _learn(net: NetConfig, *args: str) -> list[str]:
    return ["--connect", net.connect[0], "--robot", net.robot, *args]


@pytest.mark.parametrize("by", ["id", "journal"])
def test_attach_to_a_running_session_reports_the_journals_counts(
    gated_learner: tuple[Node, GatedRig],
    net: NetConfig,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    by: str,
) -> None:
    node, _ = gated_learner
    request = {"algo": "hill", "seed": 3, "rollouts": 5, "until_hit": False}
    started = rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=30)
    session = started["session"]
    with pytest.raises(RpcError, match=f"follow it with `archery learn --attach {session}`"):
        rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=30)
    target = session if by == "id" else str(Path(started["journal"]).parent)
    assert learn.main(_learn(net, "--attach", target)) == 0
    out, err = capsys.readouterr()
    assert f"attached to session {session} (running): " in err
    assert "attempt 5:" in err  # followed to the end
    line = json.loads(out.strip().splitlines()[-1])
    state = JournalState.from_records(read_records(Path(started["journal"]))[0])
    assert line["session"] == session and line["status"] == "finished"
    assert line["rollouts"] == 5 == len(state.done)
    assert (line["aborted"], line["hit_at"]) == (len(state.aborted), state.hit_at())
    assert line["final_distance_m"] == state.done[-1].distance_m
    assert check_invariants(state.records) == []
    # Attaching once it has ended prints the same line at once.
    assert learn.main(_learn(net, "--attach", target)) == 0
    assert json.loads(capsys.readouterr()[0].strip().splitlines()[-1]) == line


def test_attach_to_a_session_that_does_not_run(
    gated_learner: tuple[Node, GatedRig], net: NetConfig, capsys: pytest.CaptureFixture[str]
) -> None:
    assert learn.main(_learn(net, "--attach", "20260101-000000-archer-s0-abcd")) == 1
    err = capsys.readouterr()[1]
    assert "session 20260101-000000-archer-s0-abcd is not running (the learner is idle)" in err
    assert "archery learn --resume" in err


def test_final_counts_come_from_the_journal(tmp_path: Path) -> None:
    session = _session(FaultRig(), tmp_path, SessionConfig(seed=2, until_hit=False, rollouts=3))
    session.run(threading.Event())
    stale = {"session": "s", "rollouts": 0, "aborted": 0, "journal": str(session.journal.path)}
    counted = attach.journal_counts(stale)
    assert (counted["rollouts"], counted["aborted"], counted["ended"]) == (3, 0, "budget")
    assert (
        counted["final_distance_m"] == session.journal.state.done[-1].distance_m
    )  # the last is kept
    unreadable = stale | {"journal": str(tmp_path / "elsewhere" / "journal.jsonl")}
    assert attach.journal_counts(unreadable) == unreadable  # the learner's own counts then


def test_waiting_lines() -> None:
    lines: list[str] = []
    show = attach.WaitingLines(lines.append, repeat=3600)
    waiting = {"state": "waiting", "waiting_for": ["camera"], "cause": "waiting for camera (lost"}
    show({"state": "running"})
    show(waiting | {"cause": "waiting for camera (lost 1.0 s ago)"})
    show(waiting | {"cause": "waiting for camera (lost 1.5 s ago)"})  # the same wait: not again
    show(waiting | {"waiting_for": ["camera", "robot"], "cause": "waiting for camera, robot"})
    show({"state": "running"})
    assert lines == [
        "  waiting for camera (lost 1.0 s ago)…",
        "  waiting for camera, robot…",
        "  every service is alive again: the session goes on",
    ]


# -- real processes -------------------------------------------------------------------------------
def _status_when(node: Node, condition: Any, timeout: float) -> dict[str, Any]:
    """The learner's status, polled until `condition` holds (fails on a final state)."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    while True:
        status = rpc_call(node, node.keys.learner_rpc(), "status", timeout=10)
        if condition(status):
            return status
        assert status["state"] not in FINAL_STATES and time.monotonic() < deadline, status
        pause.wait(0.2)


@pytest.mark.slow
def test_camera_killed_and_restarted_mid_session(tmp_path: Path) -> None:
    launcher = Launcher(
        free_tcp_endpoint(),
        f"faults{os.getpid()}",
        tmp_path / "logs",
        {"learner": ["--runs", str(tmp_path), "--service-wait", "120"]},
    )
    with launcher:
        launcher.up(120)
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=60)
            request = {"algo": "archer", "seed": 1, "rollouts": 4, "until_hit": False}
            session = rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)[
                "session"
            ]
            done = 0
            while done < 2:
                message = rollouts.get(timeout=120)
                record = message.record
                done += record.session == session and isinstance(record, DoneRecord)
            launcher.kill("camera")
            status = _status_when(node, lambda s: "camera" in s.get("waiting_for", []), 120)
            assert status["state"] == "waiting"
            assert status["cause"].startswith("waiting for camera (lost ")
            launcher.start("camera")
            final = follow.follow(node, session, rollouts, lambda m: None)
        codes = launcher.stop_all()
    assert all(code == 0 for code in codes.values()), codes
    assert final["state"] == "finished" and final["rollouts"] == 4, final
    records = read_records(Path(final["journal"]))[0]
    assert check_invariants(records) == []
    assert "resumed" not in [r.kind for r in records]
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert aborted and all(r.code == "service_lost" for r in aborted), aborted
    assert any(r.cause.startswith("camera") for r in aborted), aborted
