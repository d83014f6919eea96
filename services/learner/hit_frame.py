"""`hit.png` beside a session's journal: the measured frame of its latest hit, with the
detection drawn and a caption, drawn once.

Drawing a hit's frame costs the detector its colour maps at full resolution and a PNG of twice
the frame's width, and the learner a PNG decode and encode: tens of ms of CPU, for a picture
the next hit replaces. So a hit only marks itself as the latest; its picture is asked of the
detector (by the measurement's seq: the detector keeps its last `KEPT_FRAMES` measured frames)
when the session ends, or earlier, before the detector would drop that frame (`SAVE_AFTER`
attempts later, with room for measurements of other clients). A resumed session starts from the
latest hit its journal holds, whose frame the detector may still keep (a learner restarted
right after a hit).
"""

from __future__ import annotations

import logging
from pathlib import Path

from archery.protocol.journal_records import DoneRecord
from archery.protocol.verbs.detector import KEPT_FRAMES
from archery.services.learner.errors import RigError
from archery.services.learner.journal import JournalState
from archery.services.learner.report import caption_png, hit_caption
from archery.services.learner.rig_protocol import Measurement, Rig, Shot

__all__ = ["SAVE_AFTER", "LatestHit"]

log = logging.getLogger("archery.learner")
SAVE_AFTER = KEPT_FRAMES // 2  # attempts after a hit: its frame is saved before the next one


class LatestHit:
    """The latest hit of a session not yet saved as `directory/hit.png`.

    Args:
        rig: asks the detector for the hit's frame (`Rig.hit_frame`).
        directory: the session's folder.
        session_id: named in the caption.
    """

    def __init__(self, rig: Rig, directory: Path, session_id: str) -> None:
        self.rig = rig
        self.directory = directory
        self.session_id = session_id
        self.path: Path | None = None  # hit.png once saved
        self._pending: tuple[Shot, Measurement, DoneRecord] | None = None
        self._attempts = 0  # attempts started since the pending hit

    def hit(self, shot: Shot, measurement: Measurement, record: DoneRecord) -> None:
        """`record` is a hit (`shot`, measured as `measurement`): it replaces any earlier one
        unsaved."""
        self._pending = (shot, measurement, record)
        self._attempts = 0

    def resumed(self, state: JournalState) -> None:
        """A resumed session: its journal's latest hit is pending, if the detector's reply
        was journaled with it (its seq names the frame)."""
        hits = [d for d in state.done if d.hit and d.detection is not None]
        if hits:
            done = hits[-1]
            shot = Shot(done.shot or 0, 0.0, 0.0, done.outcome or "")
            self.hit(shot, Measurement("ok", list(done.r_m), dict(done.detection or {})), done)

    def attempt(self) -> None:
        """An attempt starts (it may measure): save the pending hit's frame once `SAVE_AFTER`
        attempts have started since it, while the detector still keeps it."""
        if self._pending is not None:
            self._attempts += 1
            if self._attempts >= SAVE_AFTER:
                self.save()

    def save(self) -> None:
        """Write the pending hit's frame, captioned, to `hit.png` (nothing if none is pending);
        a frame the detector no longer has, or a file that cannot be written, is logged."""
        if self._pending is None:
            return
        (shot, measurement, record), self._pending = self._pending, None
        try:
            png = self.rig.hit_frame(shot, measurement)
        except RigError as exc:
            log.warning("no frame of the hit of rollout %d: %s", record.rollout, exc.message)
            return
        if png is None:
            return
        path = self.directory / "hit.png"
        try:
            path.write_bytes(caption_png(png, hit_caption(self.session_id, record)))
        except (OSError, ValueError) as exc:
            log.warning("could not save the hit frame: %s", exc)
            return
        self.path = path
