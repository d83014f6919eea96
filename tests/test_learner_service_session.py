"""Session logic against a fake rig: the loop's order, aborts and their retry θ, waiting for lost
services, exact resume after a crash, stop, bad start requests, and the report figures."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from archery.protocol.errors import BadRequest
from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    EndRecord,
    JournalRecord,
    ProposedRecord,
)
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.config import SessionConfig
from archery.services.learner.errors import RigError, ServiceLost
from archery.services.learner.hit_frame import SAVE_AFTER
from archery.services.learner.journal import JournalError, JournalState, read_records
from archery.services.learner.report import interruptions, write_report
from archery.services.learner.rig_protocol import Measurement, PostureResult, Shot
from archery.services.learner.session import Session

BOX = THETA_BOX
# r (m) per θ (m) near the aim point, as measured on the MuJoCo robot.
GAIN = np.array([[-1.0, -11.0, -1.1], [2.3, -4.0, -11.8]])
AIM = np.array([0.16, 0.0, -0.018])
LAUNCH_OFFSET = np.array([2e-4, -1e-4, 5e-5])  # m: the hands at release, a little off the posture


class Crash(BaseException):
    """Stands for the learner process dying (nothing catches it)."""


class FakeRig:
    """The services as a linear world: r = GAIN (θ − AIM), deterministic per θ; failures on cue.

    `lose` maps an attempt number to the service that vanishes during it; `crash_at` raises
    `Crash` in that attempt's measure; arrows with ‖r‖ > 0.25 m are not seen (no_arrow).
    """

    services = ("robot", "camera", "detector", "controller")

    def __init__(self, lose: dict[int, str] | None = None, crash_at: int | None = None) -> None:
        self.lose = dict(lose or {})
        self.crash_at = crash_at
        self.attempts = 0
        self.calls: list[str] = []
        self.gone: set[str] = set()
        self.resets: list[int] = []
        self.theta = np.zeros(3)
        self.shots = 0
        self.waits = 0
        self.framed: list[int] = []  # the shots whose frame was asked for
        self.frame_error = False
        self.launched: list[list[float]] = []  # the θ (m) of each shot's release

    def follow_shot(self) -> str:
        """A linear world has no arms to drive: the posture shot."""
        return "posture"

    def missing(self) -> list[str]:
        return sorted(self.gone)

    def lost_ago(self, service: str) -> float | None:
        return 1.0 if service in self.gone else None

    def wait_services(self, timeout: float, stop: threading.Event) -> bool:
        self.waits += 1
        self.gone.clear()
        return True

    def theta_box(self) -> ThetaBox:
        return BOX

    def setup(self) -> dict[str, Any]:
        return {"world": {}, "shot": 0, "traj_time": 1.0}

    def reset(self, seed: int) -> None:
        self.resets.append(seed)

    def move_to(self, theta: np.ndarray) -> PostureResult:
        self.attempts += 1
        self.calls.append("posture")
        self.theta = np.array(theta)
        return PostureResult(True, "", list(theta), {"posture_s": 0.01})

    def shoot(self) -> Shot:
        self.calls.append("shoot")
        self.shots += 1
        launched = (self.theta + LAUNCH_OFFSET).tolist()  # the hands at the release
        self.launched.append(launched)
        return Shot(self.shots, 1.0, 0.0, "target", {"release_s": 0.01}, theta_launched=launched)

    def _r(self) -> np.ndarray:
        noise = np.random.default_rng(abs(hash(tuple(np.round(self.theta, 9))))).normal(0, 0.003, 2)
        return GAIN @ (self.theta - AIM) + noise

    def measure(self, shot: Shot) -> Measurement:
        self.calls.append("measure")
        if self.attempts in self.lose:
            service = self.lose.pop(self.attempts)
            self.gone.add(service)
            raise ServiceLost(service, f"no reply from {service}")
        if self.attempts == self.crash_at:
            raise Crash()
        r = self._r()
        if np.linalg.norm(r) > 0.25:
            return Measurement("no_arrow", None, {"status": "no_arrow"})
        return Measurement("ok", r.tolist(), {"status": "ok", "r_m": r.tolist()})

    def truth(self, shot: Shot) -> list[float] | None:
        return (GAIN @ (self.theta - AIM)).tolist()

    def hit_frame(self, shot: Shot, measurement: Measurement) -> bytes | None:
        self.framed.append(shot.shot)
        if self.frame_error:
            raise RigError("no kept frame of measurement 3", code="bad_request")
        return cv2.imencode(".png", np.full((72, 128, 3), 90, np.uint8))[1].tobytes()


def _kinds(path: Path) -> list[tuple[str, int | None]]:
    return [(r.kind, getattr(r, "index", None)) for r in read_records(path)[0]]


def _check_each_once(path: Path) -> None:
    """Every attempt proposed once and finished once, in order."""
    records = read_records(path)[0]
    proposed = [r.index for r in records if isinstance(r, ProposedRecord)]
    finished = [r.index for r in records if isinstance(r, DoneRecord | AbortedRecord)]
    assert proposed == list(range(1, len(proposed) + 1))
    assert finished == proposed


def _journaled(session: Session) -> JournalState:
    """Everything the session's journal file holds (a running session keeps only the last
    records in memory)."""
    return JournalState.from_records(read_records(session.journal.path)[0])


def _run(config: SessionConfig, rig: FakeRig, runs: Path, **kw: Any) -> Session:
    session = Session.create(config, rig, runs, session_id="s", **kw)
    session.run(threading.Event())
    return session


def test_archer_hits_and_journals_every_rollout(tmp_path: Path) -> None:
    rig = FakeRig()
    published: list[JournalRecord] = []
    session = _run(SessionConfig(seed=1), rig, tmp_path, on_record=published.append)
    status = session.status()
    assert status.state == "finished" and status.ended == "hit"
    assert isinstance(status.hit_at, int) and status.hit_at <= 8
    assert rig.calls[:3] == ["posture", "shoot", "measure"]
    assert rig.resets == [1]
    path = tmp_path / "s" / "journal.jsonl"
    _check_each_once(path)
    records = read_records(path)[0]
    assert isinstance(records[-1], EndRecord) and records[-1].reason == "hit"
    done = [r for r in records if isinstance(r, DoneRecord)]
    assert done[-1].hit and done[-1].distance_m < 0.05
    assert all(r.truth_r_m is not None for r in done)
    # θ proposed, reached by the controller and launched by the robot, each as its rig said
    proposed = {r.index: r.theta for r in records if isinstance(r, ProposedRecord)}
    assert [r.theta for r in done] == [proposed[r.index] for r in done]
    assert [r.theta_measured for r in done] == [r.theta for r in done]
    assert [r.theta_launched for r in done] == rig.launched
    assert all(r.theta_launched != r.theta for r in done)
    assert [r.kind for r in published] == [r.kind for r in records[1:]]
    assert isinstance(published[1], DoneRecord) and "journal_s" in (published[1].timing or {})
    assert (tmp_path / "s" / "hit.png").exists()


def test_only_the_latest_hit_is_drawn_once(tmp_path: Path) -> None:
    # past the hit: most rollouts hit, but a frame is asked for only where a hit is the
    # session's last or would be dropped by the detector before the next hit
    rig = FakeRig()
    session = _run(SessionConfig(seed=1, rollouts=25, until_hit=False), rig, tmp_path)
    done = [
        r for r in read_records(tmp_path / "s" / "journal.jsonl")[0] if isinstance(r, DoneRecord)
    ]
    hits = [r for r in done if r.hit]
    assert len(hits) > 10
    expected = [
        a.shot
        for a, b in zip(hits, [*hits[1:], None], strict=True)
        if b is None or b.index - a.index >= SAVE_AFTER
    ]
    assert rig.framed == expected and rig.framed[-1] == hits[-1].shot
    assert session.hit_frame_path == tmp_path / "s" / "hit.png"
    assert session.hit_frame_path.read_bytes().startswith(b"\x89PNG")


def test_a_hit_frame_the_detector_lost_is_logged_and_the_session_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rig = FakeRig()
    rig.frame_error = True
    session = _run(SessionConfig(seed=1), rig, tmp_path)
    assert session.status().ended == "hit" and len(rig.framed) == 1
    assert session.hit_frame_path is None and not (tmp_path / "s" / "hit.png").exists()
    assert "no frame of the hit of rollout" in caplog.text


def test_budget_ends_without_hit(tmp_path: Path) -> None:
    session = _run(SessionConfig(algorithm="hill", rollouts=3, seed=0), FakeRig(), tmp_path)
    assert session.status().ended == "budget" and session.status().rollouts == 3


def test_no_arrow_backs_off_and_never_invents_r(tmp_path: Path) -> None:
    # θ0 whose exploration scatters arrows off the face.
    config = SessionConfig(seed=4, theta0=(0.17, 0.015, -0.03), options={"explore_std": 0.01})
    rig = FakeRig()
    session = _run(config, rig, tmp_path)
    records = read_records(session.journal.path)[0]
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert aborted and all(r.code == "no_arrow" for r in aborted)
    done = [r for r in records if isinstance(r, DoneRecord)]
    told = {tuple(d.theta) for d in done}
    for a in aborted:
        assert tuple(a.theta) not in told  # the missed θ is never told
        following = next(
            r for r in records if isinstance(r, ProposedRecord) and r.index == a.index + 1
        )
        assert following.theta == a.retry_theta
        assert a.retry_theta != a.theta
    assert len(session.learner.thetas) == len(done)
    _check_each_once(session.journal.path)


def test_random_search_draws_again_after_a_miss_instead_of_backing_off(tmp_path: Path) -> None:
    # misses are frequent in this wide box: a long streak of them must not end the session
    config = SessionConfig(algorithm="random", rollouts=20, seed=3, max_aborts=100)
    session = _run(config, FakeRig(), tmp_path)
    records = read_records(session.journal.path)[0]
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert aborted and all(r.code == "no_arrow" for r in aborted)  # the box is wide: misses
    for a in aborted:
        fresh = np.random.default_rng([3, a.index]).uniform(BOX.low, BOX.high)
        np.testing.assert_allclose(a.retry_theta, fresh, atol=0)  # uniform in the box, …
        following = next(
            r for r in records if isinstance(r, ProposedRecord) and r.index == a.index + 1
        )
        assert following.theta == a.retry_theta  # … and run next
        assert a.cause.endswith("next θ drawn afresh")
    assert session.status().state == "finished"
    _check_each_once(session.journal.path)


def test_theta0_off_the_face_fails_at_once(tmp_path: Path) -> None:
    session = _run(
        SessionConfig(theta0=(0.17, 0.04, -0.03), options={"explore_std": 0.0}), FakeRig(), tmp_path
    )
    status = session.status()
    assert status.state == "failed" and "puts no arrow on the target face" in status.cause
    assert status.aborted == 1 and status.rollouts == 0


def test_lost_service_aborts_waits_and_reruns_same_theta(tmp_path: Path) -> None:
    rig = FakeRig(lose={2: "detector", 4: "robot"})
    session = _run(SessionConfig(seed=2), rig, tmp_path)
    records = read_records(session.journal.path)[0]
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert [a.code for a in aborted] == ["service_lost", "service_lost"]
    assert "detector" in aborted[0].cause and "robot" in aborted[1].cause
    for a in aborted:
        retry = next(r for r in records if isinstance(r, ProposedRecord) and r.index == a.index + 1)
        assert retry.theta == a.theta == a.retry_theta
    assert rig.waits == 2
    assert session.status().ended == "hit"
    marks = interruptions(_journaled(session))  # where report.png marks them
    assert [code for _, code in marks.aborted] == ["service_lost", "service_lost"]
    assert [p for p, _ in marks.aborted] == [
        sum(1 for r in records[: records.index(a)] if isinstance(r, DoneRecord)) for a in aborted
    ]
    _check_each_once(session.journal.path)


def test_resume_after_crash_is_exact(tmp_path: Path) -> None:
    config = SessionConfig(seed=5, until_hit=False, rollouts=8)
    reference = _run(config, FakeRig(), tmp_path / "ref")
    ref_thetas = [r.theta for r in _journaled(reference).done]

    crashed = Session.create(config, FakeRig(crash_at=4), tmp_path / "run", session_id="s")
    with pytest.raises(Crash):
        crashed.run(threading.Event())
    path = tmp_path / "run" / "s" / "journal.jsonl"
    assert _kinds(path)[-1] == ("proposed", 4)
    rig = FakeRig()
    with pytest.raises(JournalError, match="not 'other'"):
        Session.resume(path, rig, session="other")
    resumed = Session.resume(path.parent, rig, session="s")
    resumed.run(threading.Event())
    records = read_records(path)[0]
    assert [r.theta for r in records if isinstance(r, DoneRecord)] == ref_thetas
    assert [r.kind for r in records].count("resumed") == 1
    assert interruptions(JournalState.from_records(records)).resumed == (3,)  # report.png
    _check_each_once(path)
    assert isinstance(records[-1], EndRecord)
    with pytest.raises(JournalError, match="has ended"):
        Session.resume(path, FakeRig())


def test_a_resumed_session_draws_the_hit_its_journal_holds(tmp_path: Path) -> None:
    # a learner killed right after a hit, resumed and stopped at once: the hit's frame is asked
    config = SessionConfig(seed=1, until_hit=False, rollouts=30)
    reference = _run(config, FakeRig(), tmp_path / "ref")
    first = next(r for r in _journaled(reference).done if r.hit)
    crashed = Session.create(config, FakeRig(crash_at=first.index + 1), tmp_path, session_id="s")
    with pytest.raises(Crash):
        crashed.run(threading.Event())
    (tmp_path / "s" / "hit.png").unlink()  # as after SIGKILL: nothing ran on the way out
    rig, stop = FakeRig(), threading.Event()
    stop.set()
    resumed = Session.resume(tmp_path / "s", rig, session="s")
    assert resumed.run(stop).state == "stopped" and rig.calls == []
    assert rig.framed == [first.shot] and (tmp_path / "s" / "hit.png").exists()


def test_stop_then_resume(tmp_path: Path) -> None:
    stop = threading.Event()
    rig = FakeRig()
    published: list[JournalRecord] = []

    def on_record(record: JournalRecord) -> None:
        published.append(record)
        if isinstance(record, DoneRecord) and record.rollout == 2:
            stop.set()

    session = Session.create(
        SessionConfig(seed=3, until_hit=False, rollouts=4), rig, tmp_path, "s", on_record=on_record
    )
    assert session.run(stop).state == "stopped"
    assert len(_journaled(session).done) == 2
    resumed = Session.resume(tmp_path / "s", FakeRig())
    assert resumed.run(threading.Event()).ended == "budget"
    _check_each_once(tmp_path / "s" / "journal.jsonl")


def test_too_many_aborts_fail_the_session(tmp_path: Path) -> None:
    class Blind(FakeRig):
        def measure(self, shot: Shot) -> Measurement:
            return Measurement("no_target", None, {"status": "no_target", "reason": "dark"})

    session = _run(SessionConfig(max_aborts=3), Blind(), tmp_path)
    status = session.status()
    assert status.state == "failed" and "3 attempts in a row" in status.cause
    assert "no_target" in status.cause
    assert _kinds(session.journal.path)[-1] == ("stopped", None)
    # Resumed once the camera works again: the count of aborts in a row starts afresh.
    resumed = Session.resume(session.journal.path, FakeRig())
    assert resumed.run(threading.Event()).ended == "hit"
    _check_each_once(session.journal.path)


def test_rig_error_aborts_and_retries(tmp_path: Path) -> None:
    class Busy(FakeRig):
        def shoot(self) -> Shot:
            if self.attempts == 1:
                raise RigError("archery/rpc:i release: busy")
            return super().shoot()

    session = _run(SessionConfig(seed=1), Busy(), tmp_path)
    aborted = _journaled(session).aborted
    assert [a.code for a in aborted] == ["rpc_error"] and "busy" in aborted[0].cause
    assert session.status().ended == "hit"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ({"algo": "archerx"}, "unknown algorithm 'archerx'; valid algorithms: archer"),
        ({"rollouts": 0}, "rollouts must be an integer"),
        ({"seed": -1}, "seed must be"),
        ({"until_hit": "yes"}, "until_hit must be true or false"),
        ({"scenario": {"wind": 3}}, "scenario has no key 'wind'"),
        ({"scenario": {"theta0": [0.1, 0.2]}}, "theta0 must be a finite 3-vector"),
        ({"scenario": {"hit_radius": -0.1}}, "hit_radius must be in"),
        ({"scenario": {"bounds": {"low": [0, 0, 0]}}}, "bounds must be"),
        ({"scenario": {"bounds": {"low": [0.2, 0, 0], "high": [0.1, 0.1, 0.1]}}}, "low < high"),
        ({"speed": 3}, "start has no argument 'speed'"),
    ],
)
def test_bad_start_requests(args: dict[str, Any], message: str) -> None:
    with pytest.raises(BadRequest, match=message.replace("(", r"\(")):
        SessionConfig.from_request(args)


@pytest.mark.parametrize(
    ("config", "message"),
    [
        (SessionConfig(theta0=(0.30, 0.0, 0.0)), "outside the θ box"),
        (
            SessionConfig(bounds=ThetaBox(low=(0.1, -0.1, -0.1), high=(0.3, 0.1, 0.1))),
            "exceed the controller's θ box",
        ),
        (SessionConfig(options={"n_best": 1}), "options for 'archer'"),
        (SessionConfig(options={"colour": 1}), "invalid option"),
    ],
)
def test_bad_sessions_touch_nothing(tmp_path: Path, config: SessionConfig, message: str) -> None:
    with pytest.raises(BadRequest, match=message):
        Session.create(config, FakeRig(), tmp_path, "s")
    assert not (tmp_path / "s").exists()


def test_report(tmp_path: Path) -> None:
    session = _run(SessionConfig(seed=1), FakeRig(), tmp_path)
    path = write_report(session.journal.path)
    assert path == tmp_path / "s" / "report.png"
    assert path.stat().st_size > 10_000
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] > image.shape[0] > 400


def test_a_journal_of_the_old_random_hill_climber_is_refused_on_resume(tmp_path: Path) -> None:
    config = SessionConfig(algorithm="hill", seed=5, until_hit=False, rollouts=8)
    crashed = Session.create(config, FakeRig(crash_at=3), tmp_path, session_id="s")
    with pytest.raises(Crash):
        crashed.run(threading.Event())
    path = tmp_path / "s" / "journal.jsonl"
    # What the hill climber wrote when it was called "random".
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    for record in lines:
        if record["record"] == "header":
            record["algorithm"] = "random"
        if isinstance(record.get("learner_state"), dict):
            record["learner_state"]["algorithm"] = "random"
    path.write_text("".join(json.dumps(r) + "\n" for r in lines))
    with pytest.raises(JournalError, match=r"'random' named the hill climber.*now 'hill'"):
        Session.resume(path, FakeRig())
