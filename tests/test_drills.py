"""`archery drill`: the verdict from fabricated journals (a missing done, a duplicated done, a
broken invariant fail), the flags, and the quick drills against real processes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from archery.apps.drills import runner
from archery.apps.drills.order import start_order
from archery.apps.drills.verdict import DrillResult, Evidence, count_lost_duplicated, judge
from archery.apps.up.launch_config import SERVICES
from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    HeaderRecord,
    JournalRecord,
    ProposedRecord,
)

THETA = [0.17, 0.0, -0.02]
HEADER = HeaderRecord(
    session="s", algorithm="archer", seed=0, rollouts=3, options={}, config={}, learner_state={}
)


def _r(kind: str, index: int, rollout: int | None = None) -> JournalRecord:
    """A proposed, done (rollout number `rollout`) or aborted record of attempt `index`."""
    if kind == "proposed":
        return ProposedRecord(session="s", index=index, theta=THETA)
    if kind == "done":
        assert rollout is not None
        return DoneRecord(
            session="s",
            index=index,
            rollout=rollout,
            theta=THETA,
            r_m=[0.0, 0.1],
            distance_m=0.1,
            hit=False,
        )
    return AbortedRecord(
        session="s", index=index, theta=THETA, code="service_lost", cause="", retry_theta=THETA
    )


def _journal(*rollouts: tuple[int, str, int | None]) -> list[JournalRecord]:
    """A header, then per (index, outcome, rollout number) a proposed and its outcome."""
    records: list[JournalRecord] = [HEADER]
    for index, outcome, number in rollouts:
        records.append(_r("proposed", index))
        if outcome == "done":
            records.append(_r("done", index, rollout=number))
        elif outcome == "aborted":
            records.append(_r("aborted", index))
    return records


CLEAN = _journal((1, "done", 1), (2, "aborted", None), (3, "done", 2), (4, "done", 3))


def test_a_clean_session_passes() -> None:
    result = judge("d", [Evidence(CLEAN, [1, 3, 4])], recover_s=0.5, detect_s=0.1)
    assert result.passed and (result.lost, result.duplicated) == (0, 0)
    assert result.notes == []


def test_a_missing_done_is_a_lost_rollout() -> None:
    records = _journal((1, "done", 1), (2, "open", None), (3, "done", 2))
    result = judge("d", [Evidence(records)])
    assert not result.passed and result.lost == 1 and result.duplicated == 0
    assert any("never ended: [2]" in n for n in result.notes), result.notes


def test_a_published_done_the_journal_lacks_is_lost() -> None:
    assert count_lost_duplicated(Evidence(CLEAN, [1, 3, 4, 5])) == (1, 0)
    assert not judge("d", [Evidence(CLEAN, [1, 3, 4, 5])]).passed


def test_a_skipped_rollout_number_is_lost() -> None:
    records = _journal((1, "done", 1), (2, "done", 3))
    assert count_lost_duplicated(Evidence(records)) == (1, 0)


def test_a_duplicated_done_fails() -> None:
    records = [*CLEAN, _r("done", 4, rollout=3)]
    result = judge("d", [Evidence(records)])
    assert not result.passed and result.duplicated == 1 and result.lost == 0
    assert any("duplicated" in n for n in result.notes)
    assert any("journal: record" in n for n in result.notes), result.notes


def test_one_bad_session_of_several_fails_the_drill() -> None:
    bad = _journal((1, "done", 1), (2, "done", 1))
    result = judge("d", [Evidence(CLEAN), Evidence(bad)])
    assert not result.passed and result.duplicated == 1


def test_the_drills_own_problems_and_no_session_fail() -> None:
    assert not judge("d", [Evidence(CLEAN)], ["robot was restarted"]).passed
    assert not judge("d", []).passed


def test_the_table_shows_every_column() -> None:
    results = [
        DrillResult("kill-camera", True, 0.02, 0.5, 0, 0, ["back 1.0 s after the kill"]),
        DrillResult("kill-robot", False, None, None, 1, 2, ["1 rollout(s) lost"]),
    ]
    table = runner.render(results)
    assert [c.header for c in table.columns] == [
        "drill",
        "verdict",
        "detect (s)",
        "recover (s)",
        "lost",
        "dup",
        "notes",
    ]
    assert list(table.columns[1].cells) == ["[green]pass[/]", "[red]FAIL[/]"]
    assert list(table.columns[2].cells) == ["0.02", "—"]
    assert list(table.columns[5].cells) == ["0", "2"]


def test_goals_are_noted_not_verdicts() -> None:
    drill = runner.DRILLS["kill-camera"]
    result = DrillResult("kill-camera", True, 1.5, 6.0)
    runner._goals(drill, result)
    assert result.passed
    assert [n.split(":")[0] for n in result.notes] == ["goal missed", "goal missed"]


def test_start_orders_put_the_router_everywhere() -> None:
    orders = [start_order(k) for k in range(len(SERVICES) + 1)]
    assert [o.index("router") for o in orders] == list(range(len(SERVICES) + 1))
    assert all(sorted(o) == sorted([*SERVICES, "router"]) for o in orders)
    assert {o[0] for o in orders[1:]} == set(SERVICES)


def test_the_catalogue_has_every_drill_the_quick_set_and_bad_names_are_refused(
    capsys: pytest.CaptureFixture[str],
) -> None:
    names = set(runner.FULL)
    assert {f"kill-{s}" for s in SERVICES} | {f"freeze-{s}" for s in SERVICES} <= names
    assert {"router-2s", "router-15s", "flood-20000", "kill-learner-x20"} <= names
    assert set(runner.QUICK) <= set(runner.DRILLS)
    with pytest.raises(SystemExit) as exc:
        runner.main(["--only", "kill-nobody"])
    assert exc.value.code == 2
    assert "no drill 'kill-nobody'" in capsys.readouterr().err


@pytest.mark.slow
def test_quick_drills_pass(tmp_path: Path) -> None:
    out = tmp_path / "drills.json"
    status = runner.main(["--quick", "--workdir", str(tmp_path / "work"), "--json", str(out)])
    document = json.loads(out.read_text())
    drills = document["drills"]
    assert [d["name"] for d in drills] == list(runner.QUICK)
    for drill in drills:
        assert drill["passed"], drill
        assert (drill["lost"], drill["duplicated"]) == (0, 0), drill
        assert drill["recover_s"] is not None, drill
    assert status == 0 and document["passed"]
