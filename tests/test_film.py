"""`archery film`: a rollout simulated again from its journal and filmed (H.264, contact sheet);
the demo films its hit, and the replayed arrow lands where the journal says it did."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from archery.apps.film.film import SHEET_THUMB, film_hit, film_session, hit_video
from archery.apps.film.replay import ShotReplay, load_rollout
from archery.apps.film.video import caption
from archery.protocol.errors import BadRequest
from archery.services.learner.journal import read_records
from tests.conftest import archery

JOURNALS = Path(__file__).parent / "journals"


@pytest.fixture
def session(tmp_path: Path) -> Path:
    """A session folder with a journal of an older learner (no `rig` in its header)."""
    folder = tmp_path / "old-format"
    folder.mkdir()
    shutil.copy(JOURNALS / "old_format.jsonl", folder / "journal.jsonl")
    return folder


def _video(path: Path) -> tuple[str, int, tuple[int, int]]:
    """(codec, frames decoded, (width, height)) of a video file."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        return stream.codec_context.name, frames, (stream.width, stream.height)


def test_a_rollout_is_filmed_as_h264_with_its_contact_sheet(session: Path) -> None:
    result = film_session(session, 2, width=160, height=90, fps=10, quiet=True)
    assert result.video == session / "rollout-2.mp4" and result.sheet.suffix == ".png"
    assert not result.recorded_world  # the older journal: the default world
    codec, frames, size = _video(result.video)
    assert codec == "h264" and size == (160, 90) and frames == result.frames
    # the move, the nock, the flight (slowed down) and the impact held
    assert frames > 10 * 1.5
    with Image.open(result.sheet) as sheet:
        width, height = SHEET_THUMB
        assert sheet.size == (3 * width + 8, 2 * height + 4)


def test_the_cli_films_the_first_hit_and_says_the_world_was_not_journaled(
    session: Path,
) -> None:
    done = archery(
        "film", str(session), "--width", "128", "--height", "72", "--fps", "8", timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(session / "shot.mp4")
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines[0] == (
        "archery film: the journal does not record the robot's world (an older learner): "
        "filmed with the default world"
    )
    # this session was resumed and its robot's settings are unknown: the replay says how far
    # its arrow landed from the journal's, if that is over 1 cm
    assert all(line.startswith("archery film: the replayed arrow landed") for line in lines[1:])
    assert (session / "shot.png").is_file()
    first_hit = next(
        r for r in read_records(session / "journal.jsonl")[0] if getattr(r, "hit", False)
    )
    assert load_rollout(session, None).done == first_hit


def test_a_hit_that_cannot_be_filmed_is_one_warning(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """After a session, filming fails as one warning line and returns None (the session's
    result stands): here the video's path is taken by a folder."""
    status = {"state": "finished", "hit_at": 1, "journal": str(session / "journal.jsonl")}
    assert hit_video(status) == session / "shot.mp4"
    (session / "shot.mp4").mkdir()
    assert film_hit(status, quiet=True) is None
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("archery: warning: the hit was not filmed:")
    assert hit_video({"state": "finished", "hit_at": None, "journal": status["journal"]}) is None


def test_a_session_without_a_hit_names_the_flag() -> None:
    with pytest.raises(BadRequest, match="no hit in its 0 rollouts; name one with --rollout N"):
        load_rollout(JOURNALS / "old_format_from.jsonl", None)


def test_captions_are_drawn_on_a_dark_band() -> None:
    frame = np.full((90, 160, 3), 200, dtype=np.uint8)
    drawn = caption(frame, ["θ = (+16.3, -0.0, -1.5) cm"])
    assert drawn.shape == frame.shape and drawn[2, 2].max() < 200  # the band
    assert (drawn[:20] == 255).any()  # white text
    assert np.array_equal(drawn[60:], frame[60:])  # the rest untouched


@pytest.mark.slow
def test_the_demo_films_its_hit_and_the_replay_lands_where_the_journal_says(
    tmp_path: Path,
) -> None:
    runs = tmp_path / "runs"
    demo = subprocess.run(
        [sys.executable, "-m", "archery.apps.cli", "demo", "--runs", str(runs), "--seed", "0"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert demo.returncode == 0, demo.stdout + demo.stderr
    line = json.loads(demo.stdout.strip().splitlines()[-1])
    video = Path(line["video"])
    assert video.name == "shot.mp4" and video.parent == Path(line["journal"]).parent
    codec, frames, _ = _video(video)
    assert codec == "h264" and frames > 30
    assert video.with_suffix(".png").is_file()
    # the journal holds the robot's world; the shot simulated again lands within 2 mm of the
    # robot's own landing (truth_r_m)
    rollout = load_rollout(video.parent, None)
    assert isinstance(rollout.header.rig, dict) and rollout.header.rig["world"]
    assert rollout.done.rollout == line["hit_at"]
    replay = ShotReplay(rollout)
    for _ in replay.frames(10):
        pass
    error = replay.landing_error_m()
    assert error is not None and error <= 0.002, error


def _recorded_session(session: Path, tmp_path: Path) -> tuple[Path, int]:
    """A recording of rollout 1 of the session: its learner records and the world states of
    a move, a nock and a flight (simulated here); and the video frames they make at 10 fps."""
    from archery.apps.topics.recording import Recorder
    from archery.protocol.codec import encode
    from archery.protocol.journal_records import DoneRecord, ProposedRecord
    from archery.protocol.messages import Array, Rollout, WorldState
    from archery.sim.scene_config import SceneConfig
    from archery.sim.world import ArcheryWorld, WorldConfig

    records = read_records(session / "journal.jsonl")[0]
    done = next(r for r in records if isinstance(r, DoneRecord) and r.rollout == 1)
    proposed = next(r for r in records if isinstance(r, ProposedRecord) and r.index == done.index)
    path = tmp_path / "session.mcap"
    recorder = Recorder(path, "icubSim", ["icubSim/**"])
    ns = 1_000_000_000

    def rollout(record: object, seq: int) -> None:
        message = Rollout(record=record, seq=seq)  # type: ignore[arg-type]  # a journal record
        recorder.put("icubSim/learner/rollout:o", encode(message), ns)

    rollout(proposed, 1)
    world = ArcheryWorld(WorldConfig(scene=SceneConfig(meshes=False)))
    world.reset(0)
    phases = ["idle"] * 10 + ["nocked"] * 3 + ["flying"] * 4 + ["stuck"]
    for seq, phase in enumerate(phases, start=1):
        ns += 10_000_000
        world.step(0.1 if phase != "flying" else 0.02)
        state = WorldState(
            qpos=Array.from_numpy(world.qpos()), phase=phase, seq=seq, sim_time=world.sim_time
        )
        recorder.put("icubSim/world/state:o", encode(state), ns)
    ns += 10_000_000
    rollout(msgspec_structs_replace(done), 2)
    ns += 10_000_000
    late = WorldState(qpos=Array.from_numpy(world.qpos()), seq=99, sim_time=99.0)
    recorder.put("icubSim/world/state:o", encode(late), ns)  # after the rollout: not filmed
    recorder.close()
    # each state for the sim time to the next at 10 fps: 10 idle states 0.1 s apart (1 frame
    # each), 2 nocked (1 each), the last nocked 0.02 s before the release (under a frame: not
    # shown), 3 flying 0.02 s apart slowed ten times (2 each), the last flying 0.1 s before it
    # sticks (10), the stuck arrow held 1.5 s (15)
    return path, 10 + 2 + 0 + 6 + 10 + 15


def msgspec_structs_replace(done: object) -> object:
    """A done record as the learner publishes it: without its learner state."""
    import msgspec

    return msgspec.structs.replace(done, learner_state=msgspec.UNSET)  # type: ignore[type-var]


def test_a_rollout_is_filmed_as_a_recording_saw_it(session: Path, tmp_path: Path) -> None:
    path, expected = _recorded_session(session, tmp_path)
    result = film_session(session, 1, width=160, height=90, fps=10, quiet=True, recording=path)
    codec, frames, _ = _video(result.video)
    assert codec == "h264" and frames == result.frames == expected
    # a rollout the recording does not cover: one line, exit status 2
    done = archery("film", str(session), "--rollout", "2", "--recording", str(path), timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"archery film: {path} does not cover rollout 2 of session old-format (its "
        f"learner/rollout:o records of attempt 3 are not in it)"
    ]


def test_a_whole_shot_is_filmed_with_its_phases_and_its_movement_sped_up(
    session: Path, tmp_path: Path
) -> None:
    from archery.apps.film.recorded import WHOLE_SPEEDUP, RecordedShot
    from archery.protocol.journal_records import DoneRecord

    path, _ = _recorded_session(session, tmp_path)
    done = next(r for r in read_records(session / "journal.jsonl")[0] if isinstance(r, DoneRecord))
    posture = list(RecordedShot(path, "old-format", done).frames(30))
    whole = list(RecordedShot(path, "old-format", done, whole=True).frames(30))
    phases = [f.phase for f in whole]
    assert phases[0] == f"reach, grasp & carry ×{WHOLE_SPEEDUP:g}"
    assert f"nock & draw ×{WHOLE_SPEEDUP:g}" in phases and phases[-1] == "impact"
    # the movement (1.22 s of states before the release) plays four times faster; the flight
    # and the impact as in any film
    moving = [f.repeat for f in whole if "×4" in f.phase]
    assert abs(sum(moving) - 1.22 * 30 / WHOLE_SPEEDUP) <= 1
    tail = [f.repeat for f in whole if f.phase.startswith(("flight", "impact"))]
    assert tail == [f.repeat for f in posture if f.phase.startswith(("flight", "impact"))]
