"""When the simulation loop publishes and how fast simulated time runs.

Streams are scheduled in simulated time: joint states every 1/state_rate s, the world state
every 1/world_rate s, and physics advances in chunks that end on the next grid point (`chunk`).
At rtf 0 a grid point goes out only once its stream's period has passed in wall time too
(`due`); at rtf > 0 simulated time follows the wall clock (`wall_due`); at rest the unchanged
state is repeated in wall time (`beats`). Each method's docstring says why.
"""

from __future__ import annotations

import math
import time

__all__ = ["MAX_CHUNK", "MAX_IDLE_WAIT", "MAX_LAG", "Pacing"]

MAX_CHUNK = 0.02  # s of simulated time per physics chunk at most (bounds the jobs' latency)
MAX_IDLE_WAIT = 0.1  # s of wall time between idle checks of the stop flag and the watchdog
MAX_LAG = 0.25  # s of wall time behind the rtf schedule before re-anchoring


class Pacing:
    """The publication grid (sim time), the rtf schedule and the idle beats (wall time).

    Args:
        dt: the physics time step (s of sim time).
        state_rate, world_rate: joint states and world states per simulated second (Hz).
        rtf: real-time factor (> 0 for `wall_due`).
        rest_rate: beats per wall second of each stream once at rest for `rest_after` (Hz; a
            stream slower than this keeps its own rate); None: the streams' rates.
        rest_after: wall seconds after the last activity (`wake`) that the beats keep the
            streams' rates.
    """

    def __init__(
        self,
        dt: float,
        state_rate: float,
        world_rate: float,
        rtf: float,
        rest_rate: float | None = None,
        rest_after: float = 0.0,
    ) -> None:
        self.dt = dt
        self.rtf = rtf
        self.state_period = 1.0 / state_rate
        self.world_period = 1.0 / world_rate
        rest_period = 0.0 if rest_rate is None else 1.0 / rest_rate
        self._rest_periods = (
            max(self.state_period, rest_period),
            max(self.world_period, rest_period),
        )
        self.rest_after = rest_after
        self._max_chunk = max(1, round(MAX_CHUNK / dt))
        self._next_state = 0.0  # sim time of the next joint state publication
        self._next_world = 0.0
        self._sent_state = -math.inf  # wall time of the last publication
        self._sent_world = -math.inf
        self._lively_until = time.monotonic() + rest_after  # wall time the full-rate beats end
        self._anchor: tuple[float, float] | None = None  # (wall, sim) pair of the rtf schedule
        #: the last `due` reached a joint-state grid point (at rtf 0 also one that does not go
        #: out on the streams: the history keeps every one)
        self.on_state_grid = False

    # -- sim time ----------------------------------------------------------------------------
    def schedule(self, sim_time: float) -> None:
        """Publications on a grid of the periods from `sim_time` (its state goes out now)."""
        self._next_state = sim_time + self.state_period
        self._next_world = sim_time + self.world_period

    def chunk(self, sim_time: float) -> int:
        """Steps up to the next scheduled publication (at least 1, at most `MAX_CHUNK` s of sim
        time)."""
        ahead = min(self._next_state, self._next_world) - sim_time
        return min(self._max_chunk, max(1, math.ceil(ahead / self.dt - 1e-6)))

    def due(self, sim_time: float) -> tuple[bool, bool]:
        """After a chunk ending at `sim_time`: whether joint states and a world state are due
        (each grid point reached moves its grid on; at rtf 0 a grid point is due only once its
        stream's period has passed in wall time since the stream's last publication).

        Why at rtf 0: a moving world runs some 50× faster than the wall clock, so the grid would
        put out thousands of states per wall second that no subscriber can use and every one
        pays for (the robot, the router and each subscriber handle every message). A grid point
        then goes out at most state_rate and world_rate times per wall second, as at rest; the
        chunks, and so the physics, stay those of the grid, and the state that ends a motion
        goes out at once (the loop publishes it on coming to rest).
        """
        half = 0.5 * self.dt
        joints = self.on_state_grid = sim_time >= self._next_state - half
        if joints:
            self._next_state = max(self._next_state + self.state_period, sim_time + half)
        world = sim_time >= self._next_world - half
        if world:
            self._next_world = max(self._next_world + self.world_period, sim_time + half)
        if self.rtf == 0 and (joints or world):
            now = time.monotonic()
            joints = joints and now >= self._sent_state + self.state_period
            world = world and now >= self._sent_world + self.world_period
        return joints, world

    # -- wall time ---------------------------------------------------------------------------
    def wall_due(self, sim_time: float, steps: int) -> float:
        """The wall time (monotonic s) at which `steps` more steps from `sim_time` are due:
        simulated time advances at rtf × the wall clock; a simulation that falls more than
        `MAX_LAG` s behind re-anchors rather than racing to catch up."""
        now = time.monotonic()
        anchor = self._anchor
        if anchor is None or sim_time < anchor[1] or now - self._wall(anchor, sim_time) > MAX_LAG:
            anchor = self._anchor = (now, sim_time)
        return self._wall(anchor, sim_time + steps * self.dt)

    def _wall(self, anchor: tuple[float, float], sim_time: float) -> float:
        return anchor[0] + (sim_time - anchor[1]) / self.rtf

    def sent_joints(self) -> None:
        """Joint states went out: the next beat (and at rtf 0 the next grid point that goes
        out) is one period (wall) away."""
        self._sent_state = time.monotonic()

    def sent_world(self) -> None:
        """A world state went out: the next beat (and at rtf 0 the next grid point that goes
        out) is one period (wall) away."""
        self._sent_world = time.monotonic()

    def wake(self) -> None:
        """Something happened (a command, a move, a shot, a reset): the beats keep the streams'
        rates for `rest_after` wall seconds from now."""
        self._lively_until = time.monotonic() + self.rest_after

    def _beat_times(self) -> tuple[float, float, float]:
        """Now, and the wall times of the next joint state and world state beats."""
        now = time.monotonic()
        lively = now < self._lively_until
        state, world = (self.state_period, self.world_period) if lively else self._rest_periods
        return now, self._sent_state + state, self._sent_world + world

    def idle_wait(self) -> float:
        """How long (wall s) the resting loop may sleep before its next beat or check."""
        now, state, world = self._beat_times()
        return min(MAX_IDLE_WAIT, state - now, world - now)

    def beats(self) -> tuple[bool, bool]:
        """Whether a joint state and a world state beat are due now (at rest).

        At rest (rtf 0 and nothing moves) the unchanged state is repeated on the streams in
        wall time (*beats*), so subscribers still see a live robot: at the streams' rates for
        `rest_after` wall seconds after the last activity (`wake`: a command, a move, nock,
        release, reset, the end of a motion), then at `rest_rate` (a heartbeat, 10 Hz by
        default: five beats within the controller's 0.5 s freshness rule). Any activity brings
        the full rates back at once: the next beat is then one full period after the last one,
        usually already due.
        """
        now, state, world = self._beat_times()
        return now >= state, now >= world
