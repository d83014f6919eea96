"""One rollout as an `archery record` recording saw it, as the states a film shows.

The recording holds the learner's `learner/rollout:o` records (an attempt's `proposed` record
opens it, its `done` record closes it) and the robot's `world/state:o` (its qpos, at the
robot's world rate of simulated time, and one after each landing). The rollout's frames are the
world states received between its proposed and done records, each shown for the simulated time
to the next one; a state of the flight is slowed down like a replayed shot's, so the flight is
as the recording sampled it. Times are seconds.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from archery.apps.film.replay import POSTURE, SLOW_MOTION, FilmFrame
from archery.apps.topics.recording import Recording, open_recording
from archery.protocol.errors import BadRequest
from archery.protocol.journal_records import DoneRecord, ProposedRecord
from archery.protocol.messages import Rollout, WorldState

__all__ = ["RecordedShot"]

_PHASES = {"idle": POSTURE, "nocked": "nock", "flying": "flight", "stuck": "impact"}
#: The whole shot's: the arrow is off the bow while the hand reaches, grasps and carries it;
#: the last shot's arrow stays on the target until then.
_WHOLE_PHASES = _PHASES | {"idle": "reach, grasp & carry", "nocked": "nock & draw"}
#: The whole shot's movement (some 12 s of simulated time, more with each waypoint's settling)
#: plays this many times faster than real time.
WHOLE_SPEEDUP = 4.0
_HOLD_IMPACT_S = 1.5  # s of video the last state is shown


class RecordedShot:
    """The world states of done rollout `done` of session `session` in the recording at `path`
    (`max_bytes`: the cap on what its chunks decompress to in all, as `open_recording`'s;
    `whole`: the robot ran the whole shot, whose phases the captions name).

    Raises:
        ConfigError: not a recording this version reads.
        BadRequest: the recording does not cover the rollout (no proposed or done record of
            it, or no world state between them).
    """

    def __init__(
        self,
        path: Path,
        session: str,
        done: DoneRecord,
        *,
        max_bytes: int | None = None,
        whole: bool = False,
    ) -> None:
        self._whole = whole
        self._phases = _WHOLE_PHASES if whole else _PHASES
        recording = open_recording(path, max_bytes=max_bytes)
        robot = recording.metadata.get("robot", "")
        opened = closed = None
        states: list[tuple[int, WorldState]] = []
        for key, message, log_time in _messages(recording, robot):
            if isinstance(message, Rollout) and message.record.session == session:
                record = message.record
                if isinstance(record, ProposedRecord) and record.index == done.index:
                    opened = log_time
                elif isinstance(record, DoneRecord) and record.index == done.index:
                    closed = log_time
            elif isinstance(message, WorldState) and key.endswith("/world/state:o"):
                states.append((log_time, message))
        if opened is None or closed is None:
            raise BadRequest(
                f"{path} does not cover rollout {done.rollout} of session {session} (its "
                f"learner/rollout:o records of attempt {done.index} are not in it)"
            )
        self.states = [s for t, s in states if opened <= t <= closed]
        if not self.states:
            raise BadRequest(
                f"{path} holds no world state of rollout {done.rollout} of session {session}"
            )

    def frames(self, fps: float) -> Iterator[FilmFrame]:
        """Each recorded state for the simulated time to the next (the flight slowed down; the
        whole shot's movement sped up, `WHOLE_SPEEDUP`)."""
        released = False
        owed = 0.0  # video frames owed to the states so far (a sped-up state may get none)
        for state, following in zip(self.states, [*self.states[1:], None], strict=True):
            phase = self._phases.get(state.phase, state.phase)
            released = released or state.phase == "flying"
            if self._whole and not released and state.phase in ("stuck", "missed"):
                phase = self._phases["idle"]  # the last shot's arrow, before this one's grasp
            t = state.sim_time or 0.0
            speed = WHOLE_SPEEDUP if self._whole and not released else 1.0
            if following is None:
                repeat = round(_HOLD_IMPACT_S * fps)
            else:
                dt = max(0.0, (following.sim_time or t) - t)
                speed = SLOW_MOTION if phase == "flight" else speed
                owed += dt * fps / speed
                repeat = round(owed)
                owed -= repeat
            if phase == "flight":
                phase = f"flight ×{SLOW_MOTION:g}"
            elif speed > 1.0 and following is not None:
                phase = f"{phase} ×{speed:g}"
            if repeat:
                yield FilmFrame(state.qpos.to_numpy(), t, phase, repeat=repeat, released=released)


def _messages(recording: Recording, robot: str) -> Iterator[tuple[str, object, int]]:
    """(key, message, log time) of the learner's rollouts and the robot's world states (no
    other message decoded), chunk by chunk within the reader's bounds; a file cut short is
    read as far as its complete records go."""
    topics = {f"{robot}/learner/rollout:o", f"{robot}/world/state:o"}
    yield from recording.messages(recover=not recording.complete, topics=topics)
