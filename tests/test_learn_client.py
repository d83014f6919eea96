"""`archery learn` as robust as the mesh it follows, with real processes under supervision (what
`archery up` runs): the learner SIGKILLed under a running client (restarted, it is asked to
resume the session, and the client ends with the journal's truth), the router killed and
restarted under a running client (it waits and follows the same session on), and a full disk
(the journal's own error fails the session cleanly and no status counts a rollout the journal
lacks) — on a small tmpfs where this machine lets the tests mount one, and always with a
journal whose writes fail with ENOSPC."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import json
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from archery.apps.learn.follow import SessionLost, follow, journal_status
from archery.apps.up.launch_config import SERVICES, default_mesh
from archery.apps.up.launcher import Launcher
from archery.apps.up.restart_policy import RestartPolicy
from archery.apps.up.supervisor import GiveUp, Supervisor
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.mesh.subscription import Subscription
from archery.protocol.journal_records import DoneRecord, JournalRecord, StoppedRecord
from archery.protocol.messages import Rollout
from archery.services.learner import handlers as learner_handlers
from archery.services.learner import service as learner_service
from archery.services.learner.config import LearnerServiceConfig, SessionConfig
from archery.services.learner.journal import JournalState, check_invariants, read_records
from archery.services.learner.session import FINAL_STATES, Session
from tests.conftest import serving
from tests.rpc import rpc_call
from tests.test_learner_service_session import FakeRig

ROUTER_OUTAGE = 3.0  # s the supervisor waits before it restarts a killed router


# -- a journal on a full disk (injected) -------------------------------------------------------
class FullDisk(io.RawIOBase):
    """A journal's file that fills up: the `fill_at`-th write takes half its bytes, then every
    write fails with ENOSPC (as a full filesystem does)."""

    def __init__(self, file: io.RawIOBase, fill_at: int) -> None:
        super().__init__()
        self.file = file
        self.writes = 0
        self.fill_at = fill_at

    def writable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self.file.fileno()

    def write(self, data: Any) -> int:
        self.writes += 1
        if self.writes < self.fill_at:
            return int(self.file.write(data) or 0)
        if self.writes == self.fill_at:
            return int(self.file.write(bytes(data)[: len(data) // 2]) or 0)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def close(self) -> None:
        self.file.close()
        super().close()


def _done(records: list[JournalRecord]) -> int:
    return sum(isinstance(r, DoneRecord) for r in records)


@pytest.mark.parametrize("fill_at", [3, 4])  # 3: the second proposed record; 4: its done one
def test_a_full_disk_fails_the_session_with_the_journals_error(
    tmp_path: Path, fill_at: int
) -> None:
    config = SessionConfig(seed=1, rollouts=5, until_hit=False)
    session = Session.create(config, FakeRig(), tmp_path, session_id="s")
    journal = session.journal
    journal._file = FullDisk(journal._file, fill_at)
    status = session.run(threading.Event())
    assert status.state == "failed"
    cause = f"cannot write to journal {journal.path}: No space left on device"
    assert status.cause == cause, status.cause
    records = read_records(journal.path)[0]
    # the status counts what the file holds, no more: one rollout done, attempt 2 open or not
    assert status.rollouts == _done(records) == 1
    assert journal.state.records == records[-1:]  # it keeps only the last in memory
    assert not journal.path.read_bytes().endswith(b"\n")  # a torn last record, cut off on resume
    assert check_invariants(records, allow_open=True) == []
    assert not isinstance(records[-1], StoppedRecord)  # the failure could not be journaled
    journal.close()  # closed already: nothing to flush, nothing raised
    resumed = Session.resume(journal.path, FakeRig())
    assert resumed.run(threading.Event()).state == "finished"
    records = read_records(journal.path)[0]
    assert _done(records) == 5 and check_invariants(records) == []


def test_the_journal_status_of_a_session(tmp_path: Path) -> None:
    session = Session.create(
        SessionConfig(seed=1, rollouts=2, until_hit=False), FakeRig(), tmp_path
    )
    path = str(session.journal.path)
    assert journal_status(path) is None  # open: the session may go on
    assert journal_status(str(tmp_path / "nowhere.jsonl")) is None  # not readable here
    session.run(threading.Event())
    final = journal_status(path)
    assert final is not None
    assert (final["state"], final["cause"], final["rollouts"]) == ("finished", "budget", 2)
    assert final["session"] == session.session_id and final["journal"] == path
    stopped = Session.create(SessionConfig(seed=1), FakeRig(), tmp_path, session_id="stopped")
    stop = threading.Event()
    stop.set()
    stopped.run(stop)
    final = journal_status(str(stopped.journal.path))
    assert final is not None and (final["state"], final["cause"]) == ("stopped", "stop requested")


# -- following: a learner without the session, a learner or router gone ----------------------
def _open_journal(runs: Path, seed: int, run: bool = False) -> tuple[str, str]:
    """(session id, journal path) of a session over a fake rig: left open (as a crashed
    learner leaves it) or, with `run`, run to its end."""
    config = SessionConfig(seed=seed, rollouts=3, until_hit=False)
    session = Session.create(config, FakeRig(), runs)
    if run:
        session.run(threading.Event())
    session.journal.close()
    return session.session_id, str(session.journal.path)


def test_follow_resumes_the_session_a_restarted_learner_does_not_run(
    net: NetConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(learner_handlers, "MeshRig", lambda node, timeout: FakeRig())
    first, first_journal = _open_journal(tmp_path, 1)
    second, second_journal = _open_journal(tmp_path, 2)
    ended, ended_journal = _open_journal(tmp_path, 3, run=True)
    config = LearnerServiceConfig(net=net, runs=tmp_path, report=False)
    with serving(learner_service.run, config), Node(None, net) as node:
        node.wait_alive(["learner"], timeout=30)
        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        # The learner runs no session: without resume, following stops and says how to go on.
        with pytest.raises(SessionLost) as lost:
            follow(node, first, rollouts, lambda m: None, journal=first_journal)
        assert str(lost.value) == (
            f"session {first} is not running: the learner runs no session (it was restarted); "
            f"continue it with `archery learn --resume` {first_journal}"
        )
        # With resume, it is asked once to resume it, and the session is followed to its end.
        notes: list[str] = []
        seen: list[Rollout] = []
        final = follow(
            node,
            first,
            rollouts,
            seen.append,
            journal=first_journal,
            resume=True,
            note=notes.append,
        )
        assert final["session"] == first and final["state"] == "finished"
        assert final["rollouts"] == 3 and len(seen) == 6  # proposed and done, each rollout
        assert notes[0] == (
            f"  the learner runs no session (restarted?): asking it to resume session {first}; "
            "waiting up to 60 s for it (Ctrl-C to stop)"
        )
        # the count is the status after the resume: on a loaded machine the fast fake rig may
        # have finished a rollout already
        assert re.fullmatch(
            rf"  session {first} resumed from its journal: [0-3] of 3 rollouts done", notes[1]
        ), notes
        assert len(notes) == 2, notes
        # The learner runs another session: the session runs nowhere.
        with pytest.raises(SessionLost) as lost:
            follow(node, second, rollouts, lambda m: None, journal=second_journal, resume=True)
        assert str(lost.value) == (
            f"session {second} is not running: the learner runs session {first} now; continue "
            f"it with `archery learn --resume` {second_journal} once that one ends"
        )
        # A session that ended meanwhile: its journal's final status.
        final = follow(node, ended, rollouts, lambda m: None, journal=ended_journal, resume=True)
        assert (final["session"], final["state"], final["rollouts"]) == (ended, "finished", 3)
    assert [r.kind for r in read_records(Path(first_journal))[0]].count("resumed") == 1


def test_following_gives_up_in_bounded_time_saying_how_to_go_on() -> None:
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    try:
        with Node(None, NetConfig(connect=(endpoint,), robot="giveup")) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            # No learner on the mesh (gone, not restarted): the session needs resuming.
            started = time.monotonic()
            with pytest.raises(SessionLost) as lost:
                follow(node, "s1", rollouts, lambda m: None, gone_after=1.0, journal="j.jsonl")
            assert time.monotonic() - started < 30
            assert re.fullmatch(
                r"the learner has been gone for \d+ s during session s1 \(not restarted\); start "
                r"it \(`archery learner`, or `archery up`\) and continue the session with "
                r"`archery learn --resume` j\.jsonl",
                str(lost.value),
            ), lost.value
            # The router gone: the session may go on without this client.
            router.kill()
            router.wait(30)
            deadline = time.monotonic() + 30
            while list(node.session.info.routers_zid()):
                assert time.monotonic() < deadline
                threading.Event().wait(0.05)
            with pytest.raises(SessionLost) as lost:
                follow(node, "s1", rollouts, lambda m: None, gone_after=1.0, journal="j.jsonl")
            assert re.fullmatch(
                r"the router has been unreachable for \d+ s while following session s1; the "
                r"session goes on if its learner still runs it: follow it again with `archery "
                r"learn --attach s1` once the router is back",
                str(lost.value),
            ), lost.value
    finally:
        if router.poll() is None:
            router.kill()
        router.wait(30)


# -- real processes ---------------------------------------------------------------------------
@dataclasses.dataclass
class Mesh:
    launcher: Launcher
    node: Node
    runs: Path
    tmpfs: bool  # runs is a small tmpfs of its own
    lines: list[str]

    def pid(self, name: str) -> int:
        proc = self.launcher.children[name].proc
        assert proc is not None
        return proc.pid

    def wait_restarted(self, name: str, old_pid: int, timeout: float = 60) -> None:
        deadline = time.monotonic() + timeout
        while self.pid(name) == old_pid:
            assert time.monotonic() < deadline, f"{name} not restarted: {self.lines}"
            threading.Event().wait(0.05)

    def learn(self, *args: str) -> subprocess.Popen[str]:
        """A real `archery learn` client of this mesh (once the learner runs no session: a
        test that failed may have left one running)."""
        deadline = time.monotonic() + 120
        while True:
            status = rpc_call(self.node, self.node.keys.learner_rpc(), "status", timeout=10)
            if status["state"] in (*FINAL_STATES, "idle"):
                break
            assert time.monotonic() < deadline, status
            threading.Event().wait(0.2)
        net = ["--connect", self.launcher.endpoint, "--robot", self.launcher.net.robot]
        return subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "learn", *args, *net],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            stdin=subprocess.DEVNULL,
        )


def _mount_tmpfs(path: Path, size: str) -> bool:
    """Mount a tmpfs of `size` on `path` if this machine allows it (else leave it a directory)."""
    try:
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(path)],
            capture_output=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    """The five services and a router under a supervisor, as `archery up` runs them; the
    learner's runs directory a 16 MiB tmpfs when one can be mounted."""
    tmp = tmp_path_factory.mktemp("client")
    runs = tmp / "runs"
    runs.mkdir()
    tmpfs = _mount_tmpfs(runs, "16m")
    base = default_mesh(free_tcp_endpoint(), f"cli{os.getpid()}", runs=str(runs))
    router = dataclasses.replace(base.router, restart=RestartPolicy(backoff=ROUTER_OUTAGE))
    launcher = Launcher(logs=tmp / "logs", mesh=dataclasses.replace(base, router=router))
    lines: list[str] = []
    stop = threading.Event()
    outcome: list[GiveUp | None] = []
    try:
        launcher.up(120)
        supervisor = Supervisor(launcher, report=lines.append)
        thread = threading.Thread(target=lambda: outcome.append(supervisor.run(stop)), daemon=True)
        thread.start()
        with Node(None, launcher.net) as node:
            node.wait_alive(SERVICES, timeout=60)
            yield Mesh(launcher, node, runs, tmpfs, lines)
        stop.set()
        thread.join(30)
    finally:
        stop.set()
        launcher.stop_all()
        if tmpfs and subprocess.run(["umount", str(runs)], capture_output=True).returncode:
            subprocess.run(["umount", "-l", str(runs)], capture_output=True)
    assert outcome == [None], outcome  # no restart policy gave up


def _session_of_the_client(rollouts: Subscription[Rollout], done: int) -> str:
    """The session whose rollouts come in (the client's), once `done` of them are done."""
    session, seen = None, 0
    while seen < done:
        record = rollouts.get(timeout=120).record
        session = session or record.session
        seen += record.session == session and isinstance(record, DoneRecord)
    assert session is not None
    return session


def _finished(proc: subprocess.Popen[str], timeout: float = 240) -> tuple[int, dict[str, Any], str]:
    """The client's exit status, final JSON line and stderr."""
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert out.strip(), err
    return proc.returncode, json.loads(out.strip().splitlines()[-1]), err


def _journal(line: dict[str, Any]) -> JournalState:
    return JournalState.from_records(read_records(Path(line["journal"]))[0], line["journal"])


@pytest.mark.slow
def test_learn_follows_its_session_across_a_learner_restart(mesh: Mesh) -> None:
    rollouts = mesh.node.subscribe(mesh.node.keys.learner_rollouts(), Rollout, mode="fifo")
    proc = mesh.learn("--algo", "archer", "--seed", "2", "--rollouts", "8", "--no-until-hit")
    session = _session_of_the_client(rollouts, 2)
    before = mesh.pid("learner")
    mesh.launcher.kill("learner")  # SIGKILL: the learner crashes mid-session
    mesh.wait_restarted("learner", before)
    code, line, err = _finished(proc)
    assert code == 0, err
    state = _journal(line)
    assert line["session"] == session == state.session and line["status"] == "finished"
    assert (line["rollouts"], line["aborted"]) == (len(state.done), len(state.aborted))
    assert line["rollouts"] == 8 and state.ended is not None
    assert line["final_distance_m"] == state.done[-1].distance_m
    assert [r.kind for r in state.records].count("resumed") == 1  # resumed once, when asked
    assert f"asking it to resume session {session}" in err, err
    assert check_invariants(state.records) == []
    assert "learner was killed by signal 9; restart 1 of 5" in " ".join(mesh.lines)


@pytest.mark.slow
def test_learn_follows_its_session_across_a_router_outage(mesh: Mesh) -> None:
    rollouts = mesh.node.subscribe(mesh.node.keys.learner_rollouts(), Rollout, mode="fifo")
    proc = mesh.learn("--algo", "archer", "--seed", "3", "--rollouts", "8", "--no-until-hit")
    session = _session_of_the_client(rollouts, 2)
    before = mesh.pid("router")
    mesh.launcher.kill("router")  # restarted on its endpoint after ROUTER_OUTAGE s
    mesh.wait_restarted("router", before)
    code, line, err = _finished(proc)
    assert code == 0, err
    state = _journal(line)
    assert line["session"] == session and line["status"] == "finished"
    assert line["rollouts"] == 8 == len(state.done) and state.ended is not None
    assert "resumed" not in [r.kind for r in state.records]  # the same session went on
    assert "the learner does not answer; waiting up to 30 s" in err, err
    assert "the learner answers again" in err, err
    assert "--resume" not in err and "--attach" not in err, err
    assert check_invariants(state.records) == []


def _fill(directory: Path) -> Path:
    """Fill the filesystem of `directory` up with one file; its path."""
    path = directory / "filler"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    chunk = 1 << 16
    try:
        while chunk:
            try:
                os.write(fd, bytes(chunk))
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
                chunk //= 2
    finally:
        os.close(fd)
    return path


@pytest.mark.slow
def test_a_full_disk_under_a_running_session(mesh: Mesh) -> None:
    if not mesh.tmpfs:
        pytest.skip("no tmpfs can be mounted here (the injected full disk above still runs)")
    rollouts = mesh.node.subscribe(mesh.node.keys.learner_rollouts(), Rollout, mode="fifo")
    proc = mesh.learn("--algo", "archer", "--seed", "4", "--rollouts", "12", "--no-until-hit")
    _session_of_the_client(rollouts, 2)
    filler = _fill(mesh.runs)
    try:
        code, line, err = _finished(proc)
        status = rpc_call(mesh.node, mesh.node.keys.learner_rpc(), "status", timeout=10)
    finally:
        filler.unlink()
    assert code == 1, err
    cause = f"cannot write to journal {line['journal']}: No space left on device"
    assert f"archery learn: session failed: {cause}" in err, err
    assert "internal error" not in err and "Traceback" not in err, err
    records = read_records(Path(line["journal"]))[0]
    done = _done(records)
    assert line["status"] == "failed" and line["rollouts"] == done < 12
    # The learner's status counts only what the journal holds.
    assert (status["state"], status["cause"], status["rollouts"]) == ("failed", cause, done)
    assert check_invariants(records, allow_open=True) == []
    # With room again, the session goes on from its journal (a torn last record cut off).
    resumed = mesh.learn("--resume", line["journal"])
    code, final, err = _finished(resumed)
    assert code == 0, err
    assert final["session"] == line["session"] and final["rollouts"] == 12
    state = _journal(final)
    assert state.records[: len(records)] == records and check_invariants(state.records) == []
    with contextlib.suppress(FileNotFoundError):
        filler.unlink()
