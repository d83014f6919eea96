"""End to end over a real router with all five real services as processes (MuJoCo physics and
rendering, Pinocchio IK, the GMM detector): ARCHER reaches the 5 cm ring; the detector and,
separately, the learner are killed mid-session and every rollout is still journaled once."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from archery.apps.learn.follow import follow
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.mesh.subscription import Subscription
from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    JournalRecord,
    ProposedRecord,
)
from archery.protocol.messages import Rollout
from archery.services.learner.journal import read_records
from tests.conftest import archery
from tests.rpc import rpc_call

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("runs")


@pytest.fixture(scope="module")
def mesh(runs: Path) -> Iterator[Launcher]:
    """The router and the five services as child processes, for the whole module."""
    launcher = Launcher(
        free_tcp_endpoint(),
        f"e2e{os.getpid()}",
        runs / "logs",
        {"learner": ["--runs", str(runs), "--service-wait", "60"]},
    )
    launcher.up(120)
    yield launcher
    codes = launcher.stop_all()
    assert all(code == 0 for code in codes.values()), codes


@pytest.fixture
def client(mesh: Launcher) -> Iterator[tuple[Node, Subscription[Rollout]]]:
    with Node(None, mesh.net) as node:
        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        node.wait_alive(SERVICES, timeout=60)
        yield node, rollouts


def _start(node: Node, **request: Any) -> str:
    return str(rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"])


def _wait_done(rollouts: Subscription[Rollout], session: str, count: int) -> list[Rollout]:
    seen: list[Rollout] = []
    while sum(isinstance(m.record, DoneRecord) for m in seen) < count:
        message = rollouts.get(timeout=60)
        if message.record.session == session:
            seen.append(message)
    return seen


def _check_journal(path: Path, done: int) -> list[JournalRecord]:
    """Each attempt proposed once and finished once, in order; `done` rollouts done."""
    records = read_records(path)[0]
    proposed = [r.index for r in records if isinstance(r, ProposedRecord)]
    finished = [r.index for r in records if isinstance(r, DoneRecord | AbortedRecord)]
    assert proposed == list(range(1, len(proposed) + 1))
    assert finished == proposed
    assert [r.rollout for r in records if isinstance(r, DoneRecord)] == list(range(1, done + 1))
    return records


def test_archer_hits_the_5cm_ring(client: tuple[Node, Subscription[Rollout]]) -> None:
    node, rollouts = client
    session = _start(node, algo="archer", seed=0, rollouts=15)
    final = follow(node, session, rollouts, lambda m: None)
    assert final["state"] == "finished" and final["ended"] == "hit", final
    assert final["hit_at"] <= 15 and final["final_distance_m"] < 0.05
    records = _check_journal(Path(final["journal"]), final["rollouts"])
    last = [r for r in records if isinstance(r, DoneRecord)][-1]
    # The detector's r agrees with the robot's ground truth (logged, never told).
    assert np.linalg.norm(np.subtract(last.r_m, last.truth_r_m)) < 0.02
    assert Path(final["report"]).stat().st_size > 10_000
    assert Path(final["hit_frame"]).stat().st_size > 10_000


def test_detector_killed_mid_session(
    mesh: Launcher, client: tuple[Node, Subscription[Rollout]]
) -> None:
    node, rollouts = client
    session = _start(node, algo="archer", seed=1, rollouts=6, until_hit=False)
    _wait_done(rollouts, session, 2)
    mesh.kill("detector")
    mesh.start("detector")
    final = follow(node, session, rollouts, lambda m: None)
    assert final["state"] == "finished" and final["rollouts"] == 6, final
    records = _check_journal(Path(final["journal"]), 6)
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert any(r.code == "service_lost" and "detector" in r.cause for r in aborted), aborted
    mesh.wait_alive(["detector"], 60)


def test_learner_killed_mid_session(
    mesh: Launcher, client: tuple[Node, Subscription[Rollout]]
) -> None:
    _, rollouts = client
    net = ["--connect", mesh.endpoint, "--robot", mesh.net.robot]
    learn = ["learn", "--algo", "archer", "--seed", "2", "--rollouts", "6", "--no-until-hit"]
    learn += ["--lost-wait", "5"]  # nothing restarts this learner: no need to wait long for it
    proc = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", *learn, *net],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = rollouts.get(timeout=60)
        _wait_done(rollouts, first.record.session, 2)
        mesh.kill("learner")
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, err
    lost = json.loads(out.strip().splitlines()[-1])
    assert lost["session"] == first.record.session and lost["status"] == "lost"
    assert f"archery learn --resume` {lost['journal']}" in err
    before = read_records(Path(lost["journal"]))[0]
    # The counts of the last line are the journal's, not those of the session's start.
    assert lost["rollouts"] == sum(isinstance(r, DoneRecord) for r in before) >= 2
    mesh.start("learner")
    result = archery("learn", "--resume", lost["journal"], *net, timeout=120)
    assert result.returncode == 0, result.stderr
    final = json.loads(result.stdout.strip().splitlines()[-1])
    assert final["session"] == first.record.session and final["status"] == "finished"
    assert final["rollouts"] == 6
    records = _check_journal(Path(lost["journal"]), 6)
    assert records[: len(before)] == before  # nothing journaled was changed
    assert [r.kind for r in records].count("resumed") == 1
