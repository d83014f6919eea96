"""`archery report`: reports drawn after the fact from journals, and the paths it refuses."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from archery.apps.report import find_journals, main
from archery.services.learner.config import SessionConfig
from archery.services.learner.session import Session
from tests.test_learner_service_session import FakeRig


@pytest.fixture(scope="module")
def experiment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An experiment's folder: two finished sessions under sessions/, no report drawn."""
    root = tmp_path_factory.mktemp("experiment")
    for seed in (1, 2):
        session = Session.create(
            SessionConfig(seed=seed), FakeRig(), root / "sessions", session_id=f"s{seed}"
        )
        session.run(threading.Event())
    assert not list(root.glob("**/report.png"))
    return root


def test_every_session_of_an_experiment_gets_its_report(
    experiment: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(experiment), "--no-progress"]) == 0
    written = capsys.readouterr().out.split()
    assert written == [str(experiment / "sessions" / s / "report.png") for s in ("s1", "s2")]
    for path in written:
        assert Path(path).read_bytes().startswith(b"\x89PNG")


def test_a_bad_journal_is_named_and_the_others_are_still_drawn(
    experiment: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    torn = tmp_path / "torn" / "journal.jsonl"
    torn.parent.mkdir()
    torn.write_text("not json\n{}\n")
    other = tmp_path / "other.jsonl"
    other.write_text('{"record": "end"}\n')
    good = experiment / "sessions" / "s1"
    status = main([str(torn.parent), str(other), str(good), "--no-progress"])
    out, err = capsys.readouterr()
    assert status == 1
    assert out.split() == [str(good / "report.png")]
    lines = err.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"archery report: {torn}: ") and "line 1 is not JSON" in lines[0]
    assert lines[1].startswith(f"archery report: {other}: ")


def test_paths_without_journals_exit_2_before_drawing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(tmp_path / "missing")]) == 2
    assert "missing: no such file or folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty")]) == 2
    assert "no journal.jsonl in it" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError):
        find_journals(tmp_path / "empty")
