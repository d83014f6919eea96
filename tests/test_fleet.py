"""A fleet of two MuJoCo iCubs across two linked routers: router A runs robot stack `icubSim1`
and the one learner (serving both robots), router B connects to A and runs stack `icubSim2`
(as a robot on another host would). One learner runs a session on each robot at once; the
Section IV experiment runs on both robots (`--world mesh`), survives a robot's death and
continues after being killed (`--resume`)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from archery.apps.experiment.experiment import main as experiment_main
from archery.apps.learn.follow import follow
from archery.apps.up.launch_config import SERVICES, MeshConfig, RobotSpec, RouterSpec, ServiceSpec
from archery.apps.up.launcher import Launcher
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, wait_for_endpoint
from archery.protocol.journal_records import DoneRecord, EndRecord, ResumedRecord
from archery.protocol.messages import Rollout, WorldEvent
from archery.services.learner.journal import check_invariants, read_records
from tests.conftest import archery
from tests.rpc import rpc_call

pytestmark = pytest.mark.slow

STACK = tuple(s for s in SERVICES if s != "learner")
ROBOTS = ("icubSim1", "icubSim2")
ALGOS = "archer,power"
SMALL = ("--sessions", "2", "--rollouts", "5", "--algo", ALGOS, "--no-progress")


def _mesh(endpoint: str, robot: str, runs: Path | None = None, fleet: str = "") -> MeshConfig:
    """One robot stack on `endpoint`; with `runs`, a router and the learner serving `fleet`
    too; without, no router (the stack joins a router that runs)."""
    services = STACK if runs is None else (*STACK, "learner")
    learner = () if runs is None else ("--runs", str(runs), "--fleet", fleet)
    return MeshConfig(
        RouterSpec(endpoint, runs is not None),
        (RobotSpec(robot, services),),
        {"robot": ServiceSpec(("--rtf", "0")), "learner": ServiceSpec(learner)},
    )


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Launcher]]:
    """Router A with icubSim1 and the learner; router B, linked to A, with icubSim2."""
    logs = tmp_path_factory.mktemp("fleet")
    a, b = free_tcp_endpoint(), free_tcp_endpoint()
    side_a = Launcher(logs=logs / "a", mesh=_mesh(a, ROBOTS[0], logs / "runs", ROBOTS[1]))
    side_a.up(120, services=[s for s in side_a.specs if s != "learner"])
    router_b = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "router", "--listen", b, "--connect", a],
        stdin=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    side_b = Launcher(logs=logs / "b", mesh=_mesh(b, ROBOTS[1]))
    try:
        wait_for_endpoint(b, 30)
        side_b.up(120)
        side_a.start("learner")
        side_a.wait_alive(["learner"], 60)
        yield {"a": side_a, "b": side_b}
    finally:
        side_b.stop_all()
        router_b.terminate()
        router_b.wait(30)
        side_a.stop_all()


def _net(fleet: dict[str, Launcher], robot: str = ROBOTS[0]) -> NetConfig:
    return NetConfig(connect=(fleet["a"].endpoint,), robot=robot)


def _shots(fleet: dict[str, Launcher]) -> dict[str, int]:
    shots = {}
    for robot in ROBOTS:
        with Node(None, _net(fleet, robot)) as node:
            shots[robot] = int(
                rpc_call(node, node.keys.archery_rpc(), "status", timeout=20)["shot"]
            )
    return shots


def _journals(out: Path) -> dict[str, list[dict]]:
    return {
        path.parent.name: read_records(path)[0]
        for path in sorted((out / "sessions").glob("*/journal.jsonl"))
    }


def _complete(out: Path, sessions: int = 2, rollouts: int = 5) -> dict[str, list[dict]]:
    """Every session's journal, each checked: finished, the whole budget, attempts once."""
    journals = _journals(out)
    assert len(journals) == sessions * len(ALGOS.split(","))
    for name, records in journals.items():
        assert isinstance(records[-1], EndRecord), name
        assert sum(isinstance(r, DoneRecord) for r in records) == rollouts, name
        assert check_invariants(records) == [], name
    return journals


def test_one_learner_runs_a_session_on_each_robot_at_once(fleet: dict[str, Launcher]) -> None:
    with Node(None, _net(fleet, ROBOTS[0])) as one, Node(None, _net(fleet, ROBOTS[1])) as two:
        feeds = [n.subscribe(n.keys.learner_rollouts(), Rollout, mode="fifo") for n in (one, two)]
        request = {"algo": "archer", "until_hit": False, "seed": 1}
        first = rpc_call(
            one, one.keys.learner_rpc(), "start", request | {"rollouts": 40}, timeout=60
        )
        while not isinstance(feeds[0].get(timeout=120).record, DoneRecord):
            pass
        second = rpc_call(
            two, two.keys.learner_rpc(), "start", request | {"rollouts": 3}, timeout=60
        )
        final = follow(two, second["session"], feeds[1], lambda m: None, poll=0.2)
        assert (final["state"], final["rollouts"]) == ("finished", 3)
        status = rpc_call(one, one.keys.learner_rpc(), "status", timeout=20)
        assert (status["session"], status["state"]) == (first["session"], "running")
        rpc_call(one, one.keys.learner_rpc(), "stop", timeout=20)
        stopped = follow(one, first["session"], feeds[0], lambda m: None, poll=0.2)
        assert stopped["state"] == "stopped" and 0 < stopped["rollouts"] < 40
        learners = {Path(f["journal"]).parent.parent for f in (final, stopped)}
        assert len(learners) == 1  # one learner's runs folder holds both robots' sessions


def test_experiment_on_two_robots_across_two_routers(
    fleet: dict[str, Launcher], tmp_path: Path
) -> None:
    before = _shots(fleet)
    out = tmp_path / "exp"
    result = archery(
        "experiment", "--world", "mesh", "--connect", fleet["a"].endpoint, *SMALL,
        "--out", str(out), timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "robots icubSim1, icubSim2" in result.stderr
    after = _shots(fleet)
    assert all(after[r] > before[r] for r in ROBOTS), (before, after)
    for name in ("summary.json", "curves.csv", "fig5.png", "fig6.png", "learners.json"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    ballistic = tmp_path / "ballistic"
    assert experiment_main([*SMALL, "--out", str(ballistic), "--no-figures"]) == 0
    reference = json.loads((ballistic / "summary.json").read_text())
    assert summary.keys() == reference.keys()
    assert summary["scenario"]["world"] == "mesh"
    with Node(None, _net(fleet)) as node:
        box = rpc_call(node, node.keys.cartesian_rpc("archery"), "status", timeout=20)
    assert summary["run"]["bounds"] == box["theta_box"]
    for name in ALGOS.split(","):
        assert summary["algorithms"][name].keys() == reference["algorithms"][name].keys()
    rows = (out / "curves.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 2 * 2 * 5
    _complete(out)

    other = archery(
        "experiment", "--world", "mesh", "--connect", fleet["a"].endpoint,
        "--sessions", "3", "--rollouts", "5", "--algo", ALGOS, "--resume", str(out),
    )  # fmt: skip
    assert other.returncode == 2
    assert other.stderr.strip().splitlines() == [
        f"archery experiment: error: --resume {str(out)!r} ran sessions 2, not 3; give the "
        f"flags of that run"
    ]


def test_resume_after_the_experiment_was_killed(fleet: dict[str, Launcher], tmp_path: Path) -> None:
    out = tmp_path / "exp"
    argv = [sys.executable, "-m", "archery.apps.cli", "experiment", "--world", "mesh"]
    argv += ["--connect", fleet["a"].endpoint, "--sessions", "3", "--rollouts", "5"]
    argv += ["--algo", ALGOS, "--no-progress"]
    proc = subprocess.Popen([*argv, "--out", str(out)], stderr=subprocess.DEVNULL)
    finished: dict[str, bytes] = {}
    try:
        changed = threading.Event()
        while proc.poll() is None and not finished:
            finished = {
                name: (out / "sessions" / name / "journal.jsonl").read_bytes()
                for name, records in _journals(out).items()
                if isinstance(records[-1], EndRecord)
            }
            changed.wait(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    assert finished, "the experiment ended before a session finished"
    assert not (out / "summary.json").exists()
    resumed = archery(*argv[3:], "--resume", str(out), timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    journals = _complete(out, sessions=3)
    for name, content in finished.items():
        assert (out / "sessions" / name / "journal.jsonl").read_bytes() == content, name
    assert any(isinstance(r, ResumedRecord) for records in journals.values() for r in records)
    assert json.loads((out / "summary.json").read_text())["run"]["sessions"] == 3


def test_bad_robot_and_no_robot_are_one_line(fleet: dict[str, Launcher], tmp_path: Path) -> None:
    common = ("experiment", "--world", "mesh", *SMALL)
    unknown = archery(
        *common, "--connect", fleet["a"].endpoint, "--robots", "icubSim1,nosuch",
        "--out", str(tmp_path / "a"),
    )  # fmt: skip
    assert unknown.returncode == 2
    assert unknown.stderr.strip().splitlines() == [
        "archery experiment: waiting up to 5 s for robots nosuch to be alive (Ctrl-C to stop)",
        "archery experiment: error: --robots: no robot 'nosuch' alive after 5 s; alive: "
        "icubSim1, icubSim2",
    ]
    alone = free_tcp_endpoint()
    router = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "router", "--listen", alone],
        stdin=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for_endpoint(alone, 30)
        none = archery(*common, "--connect", alone, "--out", str(tmp_path / "b"))
    finally:
        router.terminate()
        router.wait(30)
    assert none.returncode == 1
    lines = none.stderr.strip().splitlines()
    assert (
        lines[0] == "archery experiment: waiting up to 5 s for a robot on the mesh (Ctrl-C to stop)"
    )
    assert len(lines) == 2 and lines[1].startswith("archery experiment: no robot alive on the mesh")


def test_a_robot_killed_mid_experiment_costs_no_session(
    fleet: dict[str, Launcher], tmp_path: Path
) -> None:
    out = tmp_path / "exp"
    argv = [sys.executable, "-m", "archery.apps.cli", "experiment", "--world", "mesh"]
    argv += ["--connect", fleet["a"].endpoint, "--sessions", "3", "--rollouts", "5"]
    argv += ["--algo", ALGOS, "--no-progress", "--robot-wait", "2", "--out", str(out)]
    with Node(None, _net(fleet, ROBOTS[1])) as node:
        events = node.subscribe(node.keys.world_events(), WorldEvent, mode="fifo")
        proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
        try:
            while events.get(timeout=120).kind != "released":
                pass
            fleet["b"].kill("robot")  # SIGKILL, with an arrow of icubSim2 in flight
            _, err = proc.communicate(timeout=300)
        finally:
            proc.kill()
    try:
        assert proc.returncode == 0, err
        journals = _complete(out, sessions=3)
        assert any(isinstance(r, ResumedRecord) for records in journals.values() for r in records)
        assert "icubSim2 lost during session" in err
    finally:
        fleet["b"].start("robot")
        fleet["b"].wait_alive(["robot"], 60)


def test_up_with_two_robots_starts_two_stacks_and_one_learner(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    argv = [sys.executable, "-m", "archery.apps.cli", "up", "--robots", "2", "--listen", endpoint]
    argv += ["--runs", str(tmp_path / "runs"), "--logs", str(tmp_path / "logs")]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline(), proc.stdout.readline()]
        assert "all alive" in lines[1], (lines, proc.poll())
        assert "robot 'icubSim1', 'icubSim2'" in lines[1]
        assert f"--connect {endpoint} --robot icubSim1`" in lines[1]
        for robot in ROBOTS:
            with Node(None, NetConfig(connect=(endpoint,), robot=robot)) as node:
                node.wait_alive([*STACK, "learner"], timeout=30)
        logs = sorted(p.name for p in (tmp_path / "logs").glob("*.log"))
        assert logs == sorted(
            ["router.log", "learner@icubSim1.log"] + [f"{s}@{r}.log" for s in STACK for r in ROBOTS]
        )
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0
    assert "all stopped cleanly" in out
