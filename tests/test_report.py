"""`report.png` of a session: readable at 60 rollouts, aborted attempts and resumes marked."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    HeaderRecord,
    ProposedRecord,
    ResumedRecord,
)
from archery.services.learner.algorithms.registry import make_learner
from archery.services.learner.journal import Journal, JournalState, read_records
from archery.services.learner.report import (
    Interruptions,
    interruptions,
    report_figure,
    write_report,
)

THETA = [0.17, 0.0, -0.02]  # m


def _journal(
    directory: Path, rollouts: int, aborts: dict[int, list[str]], resumes: tuple[int, ...]
) -> Path:
    """A session of `rollouts` done rollouts; `aborts[p]` are the codes of the attempts aborted
    after done rollout p, `resumes` the done-rollout counts at which it was resumed."""
    learner = make_learner("power", np.array(THETA), rng=np.random.default_rng(3))
    header = HeaderRecord(
        session="s1",
        algorithm="power",
        seed=3,
        rollouts=rollouts,
        options=learner.options(),
        config={"hit_radius_m": 0.05},
        learner_state=learner.state_dict(),
    )
    rng = np.random.default_rng(0)
    index = 0
    with Journal.create(directory, header) as journal:
        for k in range(1, rollouts + 1):
            if k - 1 in resumes:
                journal.append(ResumedRecord(after=index))
            for code in aborts.get(k - 1, []):
                index += 1
                journal.append(ProposedRecord(index=index, theta=THETA))
                journal.append(
                    AbortedRecord(
                        index=index, theta=THETA, code=code, cause=code, retry_theta=THETA
                    )
                )
            index += 1
            journal.append(ProposedRecord(index=index, theta=THETA))
            r = rng.normal(0.0, 0.3 * np.exp(-k / 25) + 0.03, 2)
            distance = float(np.linalg.norm(r))
            journal.append(
                DoneRecord(
                    index=index,
                    rollout=k,
                    theta=THETA,
                    r_m=r.tolist(),
                    distance_m=distance,
                    hit=distance < 0.05,
                    truth_r_m=(r + 0.003).tolist(),
                    truth_distance_m=float(np.linalg.norm(r + 0.003)),
                    learner_state=learner.state_dict(),
                )
            )
    return directory / "journal.jsonl"


def _state(path: Path) -> JournalState:
    return JournalState.from_records(read_records(path)[0])


def test_aborts_and_resumes_are_placed_between_the_rollouts_they_fell_between(
    tmp_path: Path,
) -> None:
    aborts = {0: ["no_arrow"], 20: ["service_lost", "service_lost"], 41: ["no_arrow"]}
    path = _journal(tmp_path / "s1", 60, aborts, resumes=(20, 45))
    marks = interruptions(_state(path))
    assert marks == Interruptions(
        aborted=((0, "no_arrow"), (20, "service_lost"), (20, "service_lost"), (41, "no_arrow")),
        resumed=(20, 45),
    )


def test_a_session_without_interruptions_has_none(tmp_path: Path) -> None:
    marks = interruptions(_state(_journal(tmp_path / "s1", 5, {}, ())))
    assert marks == Interruptions(aborted=(), resumed=())


def test_the_report_of_a_60_rollout_session_with_aborts_and_resumes_is_written(
    tmp_path: Path,
) -> None:
    path = _journal(tmp_path / "s1", 60, {3: ["no_arrow"], 30: ["rig_error"]}, resumes=(30,))
    report = write_report(path)
    assert report == tmp_path / "s1" / "report.png"
    assert report.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and report.stat().st_size > 50_000


def _marker_boxes(ax: Any) -> list[Any]:
    """The display boxes (px) of every marker drawn in `ax`: each scatter point's and each line
    marker's square of side `sqrt(size)` pt (the marker's extent), edge included."""
    from matplotlib.collections import PathCollection
    from matplotlib.lines import Line2D
    from matplotlib.transforms import Bbox

    px = ax.figure.dpi / 72.0
    boxes = []
    for artist in ax.get_children():
        if isinstance(artist, PathCollection):
            points = artist.get_offset_transform().transform(artist.get_offsets())
            sizes = np.broadcast_to(artist.get_sizes(), (len(points),))
            for (x, y), size in zip(points, sizes, strict=True):
                half = 0.5 * np.sqrt(size) * px * 0.7  # the disc inside the marker's square
                boxes.append(Bbox.from_extents(x - half, y - half, x + half, y + half))
        elif isinstance(artist, Line2D) and artist.get_marker() not in ("", "None", None):
            data = np.column_stack(artist.get_data()).astype(float)
            for x, y in artist.get_transform().transform(data[np.isfinite(data).all(axis=1)]):
                half = 0.5 * artist.get_markersize() * px * 0.7
                boxes.append(Bbox.from_extents(x - half, y - half, x + half, y + half))
    return boxes


@pytest.mark.parametrize("rollouts", [8, 60])
def test_no_number_of_the_report_lies_on_a_marker(tmp_path: Path, rollouts: int) -> None:
    import matplotlib.pyplot as plt

    aborts = {3: ["no_arrow"], 5: ["rig_error"]}
    path = _journal(tmp_path / "s1", rollouts, aborts, resumes=(5,))
    fig = report_figure(_state(path))
    try:
        renderer = fig.canvas.get_renderer()
        face, curve = fig.axes[:2]
        numbers = [t for t in face.texts if t.get_text().isdigit()]
        assert {"1", str(rollouts)} <= {t.get_text() for t in numbers} or rollouts > 20
        assert len(numbers) >= min(rollouts, 6), [t.get_text() for t in numbers]
        assert {t.get_text() for t in curve.texts} == {"no_arrow", "rig_error"}
        for ax in (face, curve):
            markers = _marker_boxes(ax)
            assert markers
            boxes = [t.get_window_extent(renderer) for t in ax.texts]
            for text, box in zip(ax.texts, boxes, strict=True):
                covered = [m for m in markers if box.overlaps(m)]
                assert not covered, (text.get_text(), box, covered[:3])
            for i, box in enumerate(boxes):  # nor on each other
                assert not any(box.overlaps(other) for other in boxes[i + 1 :])
        legend = curve.get_legend().get_window_extent(renderer)
        assert legend.y1 < curve.get_window_extent(renderer).y0  # under the plot, off the data
    finally:
        plt.close(fig)


def test_a_long_session_reads_at_a_glance(tmp_path: Path) -> None:
    """3,000 rollouts (and aborts): one collection of markers per kind, a few numbers only."""
    learner = make_learner("archer", np.array(THETA), rng=np.random.default_rng(3))
    records: list[Any] = [
        HeaderRecord(
            session="s1",
            algorithm="archer",
            seed=3,
            rollouts=3000,
            options=learner.options(),
            config={"hit_radius_m": 0.05},
            learner_state=learner.state_dict(),
        )
    ]
    rng = np.random.default_rng(0)
    index = 0
    for k in range(1, 3001):
        if k % 97 == 0:  # an aborted attempt now and then
            index += 1
            records.append(ProposedRecord(session="s1", index=index, theta=THETA))
            records.append(
                AbortedRecord(
                    session="s1", index=index, theta=THETA, code="no_arrow", cause="x",
                    retry_theta=THETA,
                )
            )  # fmt: skip
        index += 1
        r = rng.normal(0.0, 0.08, 2)
        distance = float(np.linalg.norm(r))
        records.append(ProposedRecord(session="s1", index=index, theta=THETA))
        records.append(
            DoneRecord(
                session="s1", index=index, rollout=k, theta=THETA, r_m=r.tolist(),
                distance_m=distance, hit=distance < 0.05, truth_r_m=r.tolist(),
                truth_distance_m=distance,
            )
        )  # fmt: skip
    state = JournalState.from_records(records)
    assert sum(d.hit for d in state.done) > 100  # many hits: only the first few are numbered
    fig = report_figure(state)
    face, curve = fig.axes[:2]
    assert 3 <= len(face.texts) <= 3 + 5
    assert len(face.collections) <= 3  # measured, hits, true: not one per rollout
    assert len(curve.texts) == 0  # one code: named in the legend, not at each cross
    fig.savefig(tmp_path / "report.png")
    import matplotlib.pyplot as plt

    plt.close(fig)
    assert (tmp_path / "report.png").stat().st_size > 10_000
