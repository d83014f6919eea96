"""The watchdog of streamed commands (wall clock, `command:i` only).

A command that arrives within `timeout` s of the part's previous one, while the part is still
moving toward that one, makes the part *streaming*: new targets overtake the old (interpolated
or teleoperated targets). A streaming part whose next command does not arrive within `timeout`
s is *stale* (`StreamWatchdog.stale`): the stream ends, and the simulation loop holds the part
at its measured positions if it still moves. Any other command (the first after a silence, or
one sent after the previous move was done, as a cartesian controller does) and every
`positionMove` is a move, followed to its end however long it takes.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

__all__ = ["CommandStream", "StreamWatchdog"]


@dataclass
class CommandStream:
    """One part's command stream."""

    last: float | None = None  # wall time (monotonic s) of the last accepted stream command
    streaming: bool = False


class StreamWatchdog:
    """The command streams of every part.

    Args:
        parts: the parts commands go to.
        timeout: a stream with no command for this long (wall s) is stale; 0 switches the
            watchdog off (no part is ever streaming).
    """

    def __init__(self, parts: Iterable[str], timeout: float) -> None:
        self.timeout = timeout
        self._streams = {part: CommandStream() for part in parts}

    def command(self, part: str, at: float, overtakes: bool) -> None:
        """An accepted `command:i` command for `part` at wall time `at` (s); `overtakes`: the
        part was still moving toward its previous targets."""
        stream = self._streams[part]
        recent = stream.last is not None and self.timeout > 0 and at - stream.last <= self.timeout
        stream.streaming = recent and overtakes
        stream.last = at

    def forget(self, part: str | None = None) -> None:
        """End `part`'s stream (every part's when None): a move or a reset replaced it."""
        for name in [part] if part is not None else list(self._streams):
            self._streams[name] = CommandStream()

    def streaming(self, part: str) -> bool:
        """True while `part` follows a command stream."""
        return self._streams[part].streaming

    def deadline(self) -> float | None:
        """The wall time (monotonic s) at which the next stream goes stale; None if none can.

        Timing (wall clock, measured from the command's arrival at the robot): the loop wakes
        at `deadline()` rather than at its next physics chunk, so the hold is applied `timeout`
        s (default 0.1) plus ~1 ms after the last command; the joints then decelerate on their
        servos (time constant 1/servo_bandwidth, 40 ms by default). At rtf 0 the simulation runs
        many times faster than the wall clock while something moves, so `timeout` wall seconds
        are many simulated ones: a streaming part usually reaches its targets before the
        watchdog can trip, and the watchdog only catches a stream whose targets lie further
        than that.
        """
        if self.timeout <= 0:
            return None
        lasts = [s.last for s in self._streams.values() if s.streaming and s.last is not None]
        return min(lasts) + self.timeout if lasts else None

    def stale(self, now: float) -> list[tuple[str, float]]:
        """End the streams with no command for longer than the timeout at wall time `now`. The
        simulation loop then holds each such part at its measured positions if it still moves
        (`ArcheryWorld.hold`: targets and servo setpoints both), counts a `watchdog_trips` and
        publishes a `watchdog` WorldEvent.

        Returns:
            (part, seconds since its last command) of each stream that ended.
        """
        if self.timeout <= 0:
            return []
        ended = []
        for part, stream in self._streams.items():
            if stream.streaming and stream.last is not None and now - stream.last >= self.timeout:
                stream.streaming = False
                ended.append((part, now - stream.last))
        return ended
