"""The pictures of a session: `report.png` from its journal, a caption on the hit frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from protocol.robotspec import HIT_RADIUS
from services.learner.journal import JournalState, read_records

__all__ = ["caption_png", "plot_report", "write_report"]

FACE_RADIUS = 0.25  # m, the target face (sim.geometry.TARGET_DIAMETER / 2)
RINGS = (0.25, 0.15, 0.10, HIT_RADIUS)  # m


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
    """`report.png`: left, where each rollout's arrow met the target face (measured r, numbered,
    hits in gold; the robot's true impact as a hollow marker); right, the distance to the centre
    per rollout, measured and true, with the 5 cm ring."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = state.done
    header = state.header
    radius = float(header["config"].get("hit_radius_m", HIT_RADIUS))
    fig, (face, curve) = plt.subplots(
        1, 2, figsize=(13, 6.2), dpi=110, gridspec_kw={"width_ratios": [1.0, 1.25]}
    )
    for ring in RINGS:
        face.add_patch(plt.Circle((0, 0), 100 * ring, fill=False, color="0.35", lw=1))
    face.add_patch(plt.Circle((0, 0), 100 * radius, color="gold", alpha=0.35, lw=0))
    r = np.array([d["r_m"] for d in done]).reshape(-1, 2) * 100
    truth = [d.get("truth_r_m") for d in done]
    hits = np.array([bool(d.get("hit")) for d in done], dtype=bool)
    colours = plt.get_cmap("viridis")(np.linspace(0, 0.9, max(len(done), 1)))
    if len(done):
        face.plot(r[:, 0], r[:, 1], "-", color="0.7", lw=0.9, zorder=1)
    for k, d in enumerate(done):
        x, y = r[k]
        face.scatter(
            x,
            y,
            s=130 if hits[k] else 55,
            color=colours[k],
            zorder=3,
            marker="*" if hits[k] else "o",
            edgecolors="k",
            linewidths=0.6,
        )
        face.annotate(
            str(d["rollout"]),
            (x, y),
            textcoords="offset points",
            xytext=(6, 5),
            fontsize=10,
            weight="bold" if hits[k] else "normal",
        )
        if truth[k] is not None:
            face.scatter(
                100 * truth[k][0],
                100 * truth[k][1],
                s=40,
                facecolors="none",
                edgecolors=colours[k],
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

    n = np.arange(1, len(done) + 1)
    measured = 100 * np.array([d["distance_m"] for d in done])
    true = np.array(
        [np.nan if d.get("truth_distance_m") is None else 100 * d["truth_distance_m"] for d in done]
    )
    curve.plot(n, measured, "o-", color="tab:blue", lw=2, label="measured by the detector")
    if np.isfinite(true).any():
        curve.plot(
            n,
            true,
            "s--",
            color="tab:gray",
            lw=1.2,
            ms=5,
            mfc="none",
            label="true (robot's ground truth)",
        )
    if hits.any():
        curve.scatter(
            n[hits],
            measured[hits],
            s=220,
            marker="*",
            color="gold",
            edgecolors="k",
            zorder=4,
            label="hit",
        )
    curve.axhline(100 * radius, color="red", ls="--", lw=1.2, label=f"{100 * radius:g} cm ring")
    curve.set_xlabel("rollout")
    curve.set_ylabel("distance of the arrow to the target centre (cm)")
    curve.set_xlim(0.5, max(len(done), 1) + 0.5)
    curve.set_ylim(0, max(30.0, float(np.nanmax(measured)) * 1.1 if len(done) else 30.0))
    curve.xaxis.get_major_locator().set_params(integer=True)
    curve.grid(alpha=0.3)
    curve.legend(loc="upper right")
    summary = state.summary()
    hit_at = summary["hit_at"]
    outcome = f"hit at rollout {hit_at}" if hit_at else f"no hit in {len(done)} rollouts"
    n_aborted = summary["aborted"]
    aborted = f", {n_aborted} aborted attempt{'s' * (n_aborted != 1)}" if n_aborted else ""
    curve.set_title(f"distance per rollout: {outcome}{aborted}")
    fig.suptitle(
        f"session {state.session}: {header['algorithm']}, seed {header['seed']}", fontsize=13
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_report(journal: Path) -> Path:
    """Read a journal and write `report.png` beside it; returns the figure's path."""
    records, _ = read_records(journal)
    state = JournalState.from_records(records, str(journal))
    path = journal.parent / "report.png"
    plot_report(state, path)
    return path
