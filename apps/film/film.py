"""`archery film SESSION [--rollout N]`: a video of one rollout, simulated again from the
session's journal, seen by a camera that frames the robot while it moves and follows the arrow
from the release to the target (`apps.film.framing`, rendered by `sim.scene_view`).

SESSION is a session's folder or its `journal.jsonl`; with `--recording FILE.mcap` (an `archery
record` of the session) the rollout is filmed as the recording saw it. Without `--rollout` it
films the session's first hit into `shot.mp4` beside the journal; `--rollout N` films done
rollout N into `rollout-N.mp4` (`--out`: .mp4, .mkv or .mov), its contact sheet beside it
(`.png`), its path printed on stdout. Exit status 2 (one line on stderr), before any rendering:
no such session, a journal of another version, no hit and no `--rollout`, a rollout it does not
have, a recording that does not cover it, an output `mesh.cliargs.check_output_file` refuses.
"""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from archery.apps.progress import progress_bar
from archery.apps.topics.read_limits import add_max_bytes_arg
from archery.mesh.cliargs import ArgumentParser, add_force_arg, check_output_file, count
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.exit_status import BAD_INPUT, OK, for_error
from archery.protocol.text import cut

if TYPE_CHECKING:  # imported where used: `learn` and `demo` import this module without MuJoCo
    from archery.apps.film.replay import FilmFrame, Rollout

__all__ = [
    "VIDEO_EXTENSIONS",
    "FilmResult",
    "check_video",
    "film_hit",
    "film_ready",
    "film_session",
    "hit_video",
    "main",
]

SHEET_THUMB = (480, 270)  # px, one contact-sheet frame
VIDEO_EXTENSIONS = (".mp4", ".mkv", ".mov")  # the containers that take `ShotVideo`'s H.264


@dataclass(frozen=True)
class FilmResult:
    """What was filmed: the video and contact sheet written, the video's frames, the replayed
    landing's distance from the journal's ground truth (m, None if unknown) and whether the
    journal recorded the robot's world (else the default world was used)."""

    video: Path
    sheet: Path
    frames: int
    landing_error_m: float | None
    recorded_world: bool


def _cm(values: list[float]) -> str:
    return ", ".join(f"{100 * v:+.1f}" for v in values)


def _lines(rollout: Rollout, frame: FilmFrame) -> list[str]:
    done, head = rollout.done, rollout.header
    lines = [
        f"{head.algorithm} · rollout {done.rollout} of {head.rollouts} · {frame.phase} · "
        f"t = {frame.sim_time:.2f} s",
        f"θ = ({_cm(done.theta)}) cm",
    ]
    if frame.phase == "impact":
        hit = "  HIT" if done.hit else ""
        lines.append(f"r = ({_cm(done.r_m)}) cm, |r| = {100 * done.distance_m:.1f} cm{hit}")
    return lines


def _pick(thumbs: list[tuple[str, object]]) -> list[object]:
    """Six thumbnails: the start and end of the move, the release, two of the flight and the
    impact; of the whole shot: the start, middle and end of the reach, grasp and carry, the
    end of the draw, the flight and the impact (a film without these phases: six evenly
    spread)."""
    by_phase: dict[str, list[object]] = {}
    for phase, thumb in thumbs:
        by_phase.setdefault(phase.split(" ")[0], []).append(thumb)
    move, release = by_phase.get("posture", []), by_phase.get("release", [])
    flight, impact = by_phase.get("flight", []), by_phase.get("impact", [])
    reach, draw = by_phase.get("reach,", []), by_phase.get("nock", [])  # the whole shot's
    if reach and draw and flight and impact:
        middle = reach[len(reach) // 2]
        return [reach[0], middle, reach[-1], draw[-1], flight[len(flight) // 2], impact[0]]
    if move and release and len(flight) >= 2 and impact:
        return [
            move[0],
            move[-1],
            release[0],
            flight[len(flight) // 3],
            flight[(2 * len(flight)) // 3],
            impact[0],
        ]
    every = [t for _, t in thumbs]
    return [every[round(i * (len(every) - 1) / 5)] for i in range(6)]


def check_video(video: Path, flag: str, *, force: bool) -> Path:
    """The contact sheet's path (`video` with `.png`), once `video` is a place to write a
    video (`mesh.cliargs.check_output_file`) and no sheet is there unless `force`.

    Raises:
        ConfigError: one line naming `flag` and the path.
    """
    check_output_file(video, flag, VIDEO_EXTENSIONS, force=force)
    sheet = video.with_suffix(".png")
    if sheet.is_dir() or (sheet.exists() and not force):
        raise ConfigError(
            f"{flag} {str(video)!r}: its contact sheet {str(sheet)!r} exists; give --force to "
            "replace it, or another name"
        )
    return sheet


def film_session(
    session: Path,
    rollout: int | None = None,
    *,
    out: Path | None = None,
    force: bool = True,
    width: int = 960,
    height: int = 540,
    fps: int = 30,
    quiet: bool = False,
    recording: Path | None = None,
    max_bytes: int | None = None,
) -> FilmResult:
    """Film rollout `rollout` (its first hit if None) of the session at `session`: simulated
    again from the journal, or as the MCAP `recording` saw it (`max_bytes`: the cap on what
    its chunks decompress to in all, `apps.topics.read_limits.total_cap`).

    From a recording, the rollout is the robot's world states between the rollout's records on
    `learner/rollout:o`, the flight as sampled (world states at the robot's world rate of
    simulated time). The posture move (the draw) and the nock play at real time, the release is
    held a moment, the flight slowed down ten times. The camera frames the robot's upper body
    until the release, then follows the arrow to the target (`apps.film.framing.ShotCamera`);
    every frame (`width` × `height` px) is captioned with the phase, the simulated time, θ
    and, from the impact on, the measured r. The contact sheet holds six frames from the move
    to the impact; unless `quiet`, a progress bar counts the frames on stderr. Unless `force`,
    an existing video or sheet is refused (`check_video`), before anything is rendered.

    Raises:
        ArcheryError (bad_journal, bad_request, bad_config): see the module's exit statuses.
    """
    import numpy as np
    from PIL import Image

    from archery.apps.film.framing import framed
    from archery.apps.film.recorded import RecordedShot
    from archery.apps.film.replay import ShotReplay, load_rollout
    from archery.apps.film.video import ShotVideo, caption, contact_sheet
    from archery.sim.scene_view import SceneView

    target = load_rollout(session, rollout)
    folder = session if session.is_dir() else session.parent
    name = "shot" if rollout is None else f"rollout-{target.done.rollout}"
    video_path = out or folder / f"{name}.mp4"
    sheet_path = check_video(video_path, "--out" if out else "the video", force=force)
    replay = ShotReplay(target)
    source: ShotReplay | RecordedShot = replay
    if recording is not None:
        whole = replay.world.config.scene.shot == "whole"
        source = RecordedShot(
            recording, target.header.session, target.done, max_bytes=max_bytes, whole=whole
        )
    thumbs: list[tuple[str, object]] = []
    with (
        SceneView(replay.world.config.scene, width=width, height=height) as view,
        ShotVideo(video_path, width, height, fps) as video,
        progress_bar(disable=quiet, transient=True) as bar,
    ):
        task = bar.add_task(f"filming rollout {target.done.rollout}", total=None)
        for frame, camera in framed(source.frames(fps), view.model, width, height):
            image = caption(view.render(frame.qpos, camera), _lines(target, frame))
            video.add(image, frame.repeat)
            small = Image.fromarray(image).resize(SHEET_THUMB, Image.Resampling.BILINEAR)
            thumbs.append((frame.phase, np.asarray(small)))
            bar.advance(task, frame.repeat)
        frames = video.frames
    contact_sheet(_pick(thumbs)).save(sheet_path, optimize=True)  # type: ignore[arg-type]
    if recording is not None:
        return FilmResult(video_path, sheet_path, frames, None, True)
    return FilmResult(
        video_path, sheet_path, frames, replay.landing_error_m(), replay.recorded_world
    )


def film_ready() -> None:
    """The preflight of a verb that films a hit after its session (`learn`, `demo`): the
    rendering backend starts (`sim.gl_backend.check`), so that a broken one fails before the
    session, not after it. Where MuJoCo is not installed (a learner-only install) there is
    nothing to check: filming then says it needs `archery[film]`.

    Raises:
        RenderBackendError: MuJoCo is installed and no rendering backend starts.
    """
    if importlib.util.find_spec("mujoco") is None:
        return
    from archery.sim.gl_backend import check

    check()


def hit_video(status: dict[str, Any]) -> Path | None:
    """Where `film_hit` writes the video of a finished session's hit (`shot.mp4` beside its
    journal), or None when there is nothing to film here: no hit, or the journal is not on
    this machine (then why, on stderr)."""
    journal = status.get("journal")
    if status.get("state") != "finished" or status.get("hit_at") is None or not journal:
        return None
    if not Path(journal).is_file():
        print(
            f"archery: the journal {journal} is not on this machine (the learner's runs folder): "
            f"film the hit where it is with `archery film SESSION`",
            file=sys.stderr,
        )
        return None
    return Path(journal).parent / "shot.mp4"


def film_hit(
    status: dict[str, Any], *, quiet: bool = False, recording: Path | None = None
) -> str | None:
    """Film a finished session's hit into `hit_video(status)`, as its `recording` saw it when
    given (the whole shot's movement is in the recording only), else simulated again from the
    journal; the video's path, or None.

    Filming comes after the session's result: any failure here (a rendering backend that does
    not start, a missing extra, a full disk, a bug) is one warning line on stderr, never an
    exception that would lose the result or change the session's exit status.
    """
    path = hit_video(status)
    if path is None:
        return None
    try:
        result = film_session(Path(status["journal"]), quiet=quiet, recording=recording)
    except Exception as exc:  # any failure: the session's result stands
        why = str(exc) if isinstance(exc, ArcheryError) else f"{type(exc).__name__}: {exc}"
        print(f"archery: warning: the hit was not filmed: {cut(why)}", file=sys.stderr)
        return None
    return str(result.video)


def main(argv: list[str] | None = None) -> int:
    """Film a rollout; exit status 0, or 2 on bad input (one line on stderr)."""
    parser = ArgumentParser(prog="archery film", description=__doc__)
    parser.add_argument("session", type=Path, help="a session's folder or its journal.jsonl")
    parser.add_argument("--rollout", type=count, default=None, help="done rollout N (1-based)")
    parser.add_argument(
        "--out", type=Path, default=None, help="the video: .mp4, .mkv, .mov (default: see above)"
    )
    add_force_arg(parser, "an existing video and its contact sheet")
    parser.add_argument(
        "--recording",
        type=Path,
        default=None,
        metavar="FILE.mcap",
        help="film the rollout as this recording of the session saw it (its world states)",
    )
    add_max_bytes_arg(parser)
    parser.add_argument("--width", type=count, default=960, help="frame width (px, even)")
    parser.add_argument("--height", type=count, default=540, help="frame height (px, even)")
    parser.add_argument("--fps", type=count, default=30, help="video frames per second")
    args = parser.parse_args(argv)
    if args.out is not None:
        try:
            check_video(args.out, "--out", force=args.force)
        except ConfigError as exc:
            print(f"archery film: {exc}", file=sys.stderr)
            return BAD_INPUT
    if (
        args.width % 2
        or args.height % 2
        or not (64 <= args.width <= 3840)
        or not (64 <= args.height <= 2160)
    ):
        print(
            f"archery film: the frame size must be even, 64..3840 x 64..2160 px, got "
            f"{args.width}x{args.height}",
            file=sys.stderr,
        )
        return BAD_INPUT
    if not 1 <= args.fps <= 120:
        print(f"archery film: --fps must be in 1..120, got {args.fps}", file=sys.stderr)
        return BAD_INPUT
    if args.rollout is not None and args.rollout < 1:
        print("archery film: --rollout counts from 1", file=sys.stderr)
        return BAD_INPUT
    from archery.sim.gl_backend import RenderBackendError, check

    try:
        check()
    except RenderBackendError as exc:
        print(f"archery film: {exc}", file=sys.stderr)
        return BAD_INPUT
    try:
        result = film_session(
            args.session,
            args.rollout,
            out=args.out,
            force=args.force,
            width=args.width,
            height=args.height,
            fps=args.fps,
            recording=args.recording,
            max_bytes=args.max_bytes,
        )
    except ArcheryError as exc:
        print(f"archery film: {exc}", file=sys.stderr)
        return for_error(exc.code)
    if not result.recorded_world:
        print(
            "archery film: the journal does not record the robot's world (an older learner): "
            "filmed with the default world",
            file=sys.stderr,
        )
    if result.landing_error_m is not None and result.landing_error_m > 0.01:
        print(
            f"archery film: the replayed arrow landed {100 * result.landing_error_m:.1f} cm "
            f"from the journal's landing",
            file=sys.stderr,
        )
    print(result.video)
    return OK


if __name__ == "__main__":
    sys.exit(main())
