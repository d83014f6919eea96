"""The paths `start` takes (`resume`, `from_journal`) stay inside the learner's runs folder:
`archery learner` over a real router is asked to read devices, FIFOs, files outside its folder,
symlinks leading out and huge sparse files. Each is a `bad_request` naming the rule, nothing
blocks, nothing says whether a file outside exists, and the learner answers afterwards. Good
paths (relative, absolute, a session id) get past the check: with no robot about, `start` then
stops at `service_missing`."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from archery.apps.learn import learn
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.services.learner import service as learner_service
from archery.services.learner.config import LearnerServiceConfig, SessionConfig
from archery.services.learner.journal import MAX_JOURNAL_BYTES
from archery.services.learner.session import Session
from tests.conftest import serving
from tests.rpc import rpc_call
from tests.test_learner_service_session import FakeRig

OUTSIDE = "is outside the learner's runs folder"
NOT_REGULAR = "is not a regular file: a journal must be one (not a FIFO, device, socket"
TOO_BIG = f"a journal holds at most {MAX_JOURNAL_BYTES} bytes"
FIELDS = ("resume", "from_journal")


@pytest.fixture(scope="module")
def outside(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder beside the runs folder, with a journal of its own (a readable one)."""
    folder = tmp_path_factory.mktemp("outside")
    _finished_session(folder, "theirs")
    return folder


@pytest.fixture
def runs(tmp_path: Path, outside: Path) -> Path:
    """The learner's runs folder: a finished session `s1`, a FIFO (also as a session's
    journal), a journal that is a directory, a sparse file past the bound, and symlinks out of
    the folder and within it."""
    runs = tmp_path / "runs"
    _finished_session(runs, "s1")
    os.mkfifo(runs / "fifo")
    (runs / "piped").mkdir()
    os.mkfifo(runs / "piped" / "journal.jsonl")
    (runs / "nested" / "journal.jsonl").mkdir(parents=True)
    with open(runs / "huge.jsonl", "wb") as f:
        f.truncate(16 * 1024**3)  # 16 GiB, no block written
    (runs / "out").symlink_to(outside / "theirs" / "journal.jsonl")
    (runs / "out_dir").symlink_to(outside / "theirs")
    (runs / "within").symlink_to(runs / "s1")
    return runs


def _finished_session(runs: Path, name: str) -> None:
    config = SessionConfig(algorithm="archer", rollouts=3, until_hit=False, seed=1)
    Session.create(config, FakeRig(), runs, session_id=name).run(threading.Event())


@pytest.fixture
def learner(net: NetConfig, runs: Path) -> Iterator[Node]:
    """The learner service alone (no robot: `start` past its checks says service_missing)."""
    config = LearnerServiceConfig(net=net, runs=runs, start_wait=0)
    with serving(learner_service.run, config), Node(None, net) as node:
        node.wait_alive(["learner"], 30)
        yield node


def _start(node: Node, args: dict[str, Any]) -> RpcError:
    """`start` with `args`, which must fail; its error."""
    with pytest.raises(RpcError) as info:
        rpc_call(node, node.keys.learner_rpc(), "start", args, timeout=20)
    return info.value


def _listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize(
    ("path", "rule"),
    [
        ("/dev/zero", OUTSIDE),
        ("/etc/shadow", OUTSIDE),
        ("/nonexistent/journal.jsonl", OUTSIDE),
        ("../x", OUTSIDE),
        ("s1/../../outside", OUTSIDE),
        ("out", OUTSIDE),  # a symlink inside, leading out
        ("out_dir", OUTSIDE),
        ("fifo", NOT_REGULAR),
        ("piped", NOT_REGULAR),  # a session directory whose journal is a FIFO
        ("nested", NOT_REGULAR),  # a session directory whose journal is a directory
        ("huge.jsonl", TOO_BIG),
    ],
)
def test_a_path_out_of_bounds_is_a_bad_request(
    learner: Node, runs: Path, field: str, path: str, rule: str
) -> None:
    before = _listing(runs)
    error = _start(learner, {field: path})  # a FIFO would wedge a blocking read: a timeout
    assert error.code == "bad_request", error
    assert rule in str(error) and f"{field} {path!r}" in str(error)
    assert rpc_call(learner, learner.keys.learner_rpc(), "status", timeout=10) == {"state": "idle"}
    assert _listing(runs) == before  # nothing journaled, nothing touched


def test_nothing_tells_whether_a_file_outside_exists(learner: Node, outside: Path) -> None:
    for field in FIELDS:
        there = outside / "theirs" / "journal.jsonl"
        assert there.is_file()
        messages = [
            str(_start(learner, {field: str(path)})).replace(str(path), "PATH")
            for path in (there, outside / "theirs" / "nothing.jsonl", outside / "theirs")
        ]
        assert len(set(messages)) == 1 and OUTSIDE in messages[0]


def test_paths_inside_the_runs_folder_are_taken(learner: Node, runs: Path) -> None:
    # Past the path's checks, `start` goes on to the services (none here) and stops there.
    journal = runs / "s1" / "journal.jsonl"
    for args in (
        {"resume": "s1"},
        {"resume": "s1/journal.jsonl"},
        {"resume": str(journal)},
        {"resume": "within"},  # a symlink that stays inside
        {"from_journal": "s1"},
        {"from_journal": str(journal)},
        {"from_journal": "within/journal.jsonl"},
    ):
        error = _start(learner, args)
        assert error.code == "service_missing", (args, error)
    for field in FIELDS:
        missing = _start(learner, {field: "nosuch/journal.jsonl"})
        assert missing.code == "bad_journal" and "cannot read journal" in str(missing)


def test_learn_sends_a_journal_found_here_as_an_absolute_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _finished_session(tmp_path / "runs", "s1")
    monkeypatch.chdir(tmp_path)
    parser = learn.build_parser()
    here = learn.start_request(parser.parse_args(["--resume", "runs/s1/journal.jsonl"]))
    assert here == {"resume": str(tmp_path / "runs" / "s1" / "journal.jsonl")}
    elsewhere = learn.start_request(parser.parse_args(["--resume", "s2/journal.jsonl"]))
    assert elsewhere == {"resume": "s2/journal.jsonl"}  # the learner's runs folder's to find


def test_a_huge_path_is_quoted_short(learner: Node) -> None:
    for field in FIELDS:
        for path in ("x" * 10 * 1024 * 1024, "/" + "y" * 10 * 1024 * 1024):
            error = _start(learner, {field: path})
            assert error.code in ("bad_journal", "bad_request") and len(str(error)) < 1000
    assert rpc_call(learner, learner.keys.learner_rpc(), "status", timeout=10) == {"state": "idle"}
