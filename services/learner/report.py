"""The pictures of a session: `report.png` from its journal, a caption on the hit frame."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from archery.protocol.journal_records import AbortedRecord, DoneRecord, ResumedRecord
from archery.protocol.robotspec import HIT_RADIUS
from archery.services.learner.journal import JournalState, read_records
from archery.services.learner.label_placement import Label, place_labels

__all__ = [
    "Interruptions",
    "caption_png",
    "hit_caption",
    "interruptions",
    "plot_report",
    "report_figure",
    "write_report",
]

FACE_RADIUS = 0.25  # m, the target face (sim.geometry.TARGET_DIAMETER / 2)
RINGS = (0.25, 0.15, 0.10, HIT_RADIUS)  # m
LABELLED_FIRST = 8  # the face numbers the first rollouts, then every 10th, hits and the last
MANY = 20  # above this many rollouts the markers and labels get smaller
LONG = 200  # above this many, the face numbers only the first, the best, the last and hits
LONG_HITS = 5  # the first hits numbered in a long session


@dataclass(frozen=True)
class Interruptions:
    """Where a session was interrupted, on the done-rollout axis of the report.

    A position p means "after done rollout p" (0: before the first); the report draws it at
    p + 0.5, between two rollouts.

    Attributes:
        aborted: (position, code) of each aborted attempt, in order.
        resumed: position of each resume (the session was continued from its journal).
    """

    aborted: tuple[tuple[int, str], ...]
    resumed: tuple[int, ...]


def interruptions(state: JournalState) -> Interruptions:
    """The aborted attempts and resumes of a journal, placed between its done rollouts."""
    done, aborted, resumed = 0, [], []
    for record in state.records:
        if isinstance(record, DoneRecord):
            done += 1
        elif isinstance(record, AbortedRecord):
            aborted.append((done, record.code))
        elif isinstance(record, ResumedRecord):
            resumed.append(done)
    return Interruptions(tuple(aborted), tuple(resumed))


def hit_caption(session: str, done: DoneRecord) -> list[str]:
    """The caption of a hit's frame: the session, rollout, measured (and true) ‖r‖ and θ, in
    cm, and what the picture shows."""
    truth = done.truth_distance_m
    true = "" if truth is None else f" (true {100 * truth:.1f} cm)"
    return [
        f"session {session}, rollout {done.rollout}: hit, |r| = {100 * done.distance_m:.1f} cm"
        f"{true}",
        "theta = (" + ", ".join(f"{100 * v:.2f}" for v in done.theta) + ") cm. Left: the "
        "camera frame, right: the pixels of the colour models; red cross: target centre, blue "
        "circle: arrow tip",
    ]


def caption_png(png: bytes, lines: list[str]) -> bytes:
    """The PNG image with a dark band on top carrying `lines` in large white text.

    Raises:
        ValueError: `png` does not decode as an image.
    """
    import cv2

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError("the frame is not a decodable image")
    scale = max(1.0, image.shape[0] / 720)
    line_height = int(46 * scale)
    band = np.full((line_height * len(lines) + int(16 * scale), image.shape[1], 3), 32, np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(
            band,
            text,
            (int(16 * scale), int((i + 1) * line_height)),
            cv2.FONT_HERSHEY_SIMPLEX,
            1.15 * scale,
            (255, 255, 255),
            max(2, round(2 * scale)),
            cv2.LINE_AA,
        )
    ok, data = cv2.imencode(".png", np.vstack([band, image]))
    if not ok:
        raise ValueError("the captioned frame does not encode as PNG")
    return data.tobytes()


def plot_report(state: JournalState, path: Path) -> None:
    """`report.png` of `state` (`report_figure`) written to `path`."""
    import matplotlib.pyplot as plt

    fig = report_figure(state)
    fig.savefig(path)
    plt.close(fig)


def report_figure(state: JournalState) -> Any:
    """The figure of `report.png`: left, where each rollout's arrow met the target face
    (measured r, coloured by rollout, hits as stars; the robot's true impact as a hollow marker;
    numbered: the hits, the first and the last, the first 8 and every 10th, each where it covers
    no marker and no other number; past `LONG` rollouts only the first, the best, the last and
    the first `LONG_HITS` hits); right, the distance to the centre per rollout, measured and
    true, with the 5 cm ring, each aborted attempt (a red ×, between the rollouts it fell
    between, with its code) and each resume of the session (a dotted line); the legend under
    the plot, off the data. The caller closes it (`matplotlib.pyplot.close`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = state.done
    header = state.header
    radius = float(header.config.get("hit_radius_m", HIT_RADIUS))
    fig, (face, curve) = plt.subplots(
        1, 2, figsize=(13, 6.8), dpi=110, gridspec_kw={"width_ratios": [1.0, 1.25]}
    )
    for ring in RINGS:
        face.add_patch(plt.Circle((0, 0), 100 * ring, fill=False, color="0.35", lw=1))
    face.add_patch(plt.Circle((0, 0), 100 * radius, color="gold", alpha=0.35, lw=0))
    r = np.array([d.r_m for d in done]).reshape(-1, 2) * 100
    truth = [d.truth_r_m for d in done]
    hits = np.array([d.hit for d in done], dtype=bool)
    many = len(done) > MANY
    colours = plt.get_cmap("viridis")(np.linspace(0, 0.9, max(len(done), 1)))
    if len(done):
        width = 0.9 if not many else 0.6 if len(done) <= LONG else 0.25
        face.plot(r[:, 0], r[:, 1], "-", color="0.7", lw=width, zorder=1)
    # pt²; one collection per kind of marker, however many rollouts (later ones on top)
    areas = np.where(hits, 90 if many else 130, 28 if many else 55)
    for kind, marker in ((~hits, "o"), (hits, "*")):
        if kind.any():
            face.scatter(
                r[kind, 0],
                r[kind, 1],
                s=areas[kind],
                c=colours[kind],
                zorder=3,
                marker=marker,
                edgecolors="k",
                linewidths=0.3 if len(done) > LONG else 0.6,
            )
    known = np.array([t is not None for t in truth], dtype=bool)
    if known.any():
        true_r = 100 * np.array([t for t in truth if t is not None]).reshape(-1, 2)
        face.scatter(
            true_r[:, 0],
            true_r[:, 1],
            s=40,
            facecolors="none",
            edgecolors=colours[known],
            zorder=2,
            linewidths=1.2,
        )
    limit = max(100 * FACE_RADIUS + 3, float(np.abs(r).max()) + 4 if len(done) else 0)
    face.set_xlim(-limit, limit)
    face.set_ylim(-limit, limit)
    face.set_aspect("equal")
    face.set_xlabel("right of centre (cm)")
    face.set_ylabel("above centre (cm)")
    face.set_title(
        "arrow impacts on the target face, by rollout\n"
        "filled: measured by the detector, hollow: true (robot)"
    )
    face.grid(alpha=0.25)
    if many:  # the colour tells the order where numbers would overlap
        from matplotlib.colors import ListedColormap

        order = plt.cm.ScalarMappable(
            norm=plt.Normalize(0.5, len(done) + 0.5), cmap=ListedColormap(colours)
        )
        fig.colorbar(order, ax=face, fraction=0.04, pad=0.02, label="rollout")

    n = np.arange(1, len(done) + 1)
    measured = 100 * np.array([d.distance_m for d in done])
    true = np.array(
        [np.nan if d.truth_distance_m is None else 100 * d.truth_distance_m for d in done]
    )
    # (values, style, colour, line width, marker size, label): smaller when there are many
    lines = [(measured, "o-", "tab:blue", 2.0, 6.0, "measured by the detector")]
    if np.isfinite(true).any():
        lines.append((true, "s--", "tab:gray", 1.2, 5.0, "true (robot's ground truth)"))
    long = len(done) > LONG  # thousands of points: thin lines, no markers but the hits'
    for values, style, colour, width, size, label in lines:
        curve.plot(
            n,
            values,
            style.replace("o", "").replace("s", "") if long else style,
            color=colour,
            lw=0.5 if long else 0.75 * width if many else width,
            ms=0.6 * size if many else size,
            mfc=None if style == "o-" else "none",
            label=label,
        )
    if hits.any():
        curve.scatter(
            n[hits],
            measured[hits],
            s=40 if long else 150 if many else 220,
            marker="*",
            color="gold",
            edgecolors="k",
            zorder=4,
            label="hit",
        )
    curve.axhline(100 * radius, color="red", ls="--", lw=1.2, label=f"{100 * radius:g} cm ring")
    top = max(30.0, float(np.nanmax(measured)) * 1.1 if len(done) else 30.0)
    marks = interruptions(state)
    for i, position in enumerate(marks.resumed):
        curve.axvline(
            position + 0.5,
            color="tab:purple",
            ls=":",
            lw=1.6,
            label="session resumed" if i == 0 else None,
        )
    stacked: dict[int, int] = {}
    codes = {code for _, code in marks.aborted}
    one_code = next(iter(codes)) if len(codes) == 1 else None  # then named once, in the legend
    code_labels, crosses = [], []
    for position, code in marks.aborted:
        level = stacked.get(position, 0)  # several aborts between the same two rollouts stack
        stacked[position] = level + 1
        y = top * (0.03 + 0.05 * level)
        crosses.append((position + 0.5, y))
        if one_code is None and len(marks.aborted) <= LONG:
            code_labels.append(Label(code, (position + 0.5, y), radius_px=6.0, fontsize=7))
    if crosses:
        x, y = np.array(crosses).T
        curve.scatter(
            x,
            y,
            marker="x",
            s=60 if len(crosses) <= LONG else 20,
            color="red",
            linewidths=2 if len(crosses) <= LONG else 1,
            zorder=5,
            label=f"aborted attempt ({one_code or 'code'})",
        )
    curve.set_xlabel("rollout")
    curve.set_ylabel("distance of the arrow to the target centre (cm)")
    curve.set_xlim(0.5 if not marks.aborted else 0, max(len(done), 1) + 0.5)
    curve.set_ylim(0, top)
    curve.xaxis.get_major_locator().set_params(integer=True)
    curve.grid(alpha=0.3)
    # under the plot: a legend inside would cover the curve somewhere
    curve.legend(loc="upper center", bbox_to_anchor=(0.5, -0.11), fontsize=9, ncol=3)
    summary = state.summary()
    hit_at = summary["hit_at"]
    outcome = f"hit at rollout {hit_at}" if hit_at else f"no hit in {len(done)} rollouts"
    n_aborted = summary["aborted"]
    aborted = f", {n_aborted} aborted attempt{'s' * (n_aborted != 1)}" if n_aborted else ""
    n_resumed = len(marks.resumed)
    resumed = f", resumed {n_resumed} time{'s' * (n_resumed != 1)}" if n_resumed else ""
    curve.set_title(f"distance per rollout: {outcome}{aborted}{resumed}")
    fig.suptitle(f"session {state.session}: {header.algorithm}, seed {header.seed}", fontsize=13)
    fig.tight_layout()
    # the numbers last, on the final layout: each where it covers no marker
    px_per_pt = fig.dpi / 72.0
    last = len(done) - 1
    if len(done) > LONG:  # a number every 10th would be hundreds: the colour tells the order
        best = int(np.argmin(measured))
        numbered = {0, best, last, *np.flatnonzero(hits)[:LONG_HITS].tolist()}
    else:
        numbered = {
            k
            for k, d in enumerate(done)
            if d.rollout <= LABELLED_FIRST or d.rollout % 10 == 0 or hits[k] or k == last
        }
    wanted = sorted(numbered, key=lambda k: (not hits[k], k not in (0, last), k))
    place_labels(
        face,
        [
            Label(
                str(done[k].rollout),
                (float(r[k, 0]), float(r[k, 1])),
                radius_px=0.5 * math.sqrt(areas[k]) * px_per_pt,
                fontsize=8 if many else 10,
                weight="bold" if hits[k] else "normal",
            )
            for k in wanted
        ],
        over_markers=len(done) > LONG,
    )
    place_labels(curve, code_labels)
    return fig


def write_report(journal: Path) -> Path:
    """Read a journal and write `report.png` beside it; returns the figure's path."""
    records, _ = read_records(journal)
    state = JournalState.from_records(records, str(journal))
    path = journal.parent / "report.png"
    plot_report(state, path)
    return path
