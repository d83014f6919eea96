"""The mesh a drill runs against: `archery up`'s Launcher and Supervisor on loopback, and what a
drill observes of it.

`DrillMesh` starts a router and the five services as real child processes (as `archery up`
does), supervises them on a thread (`apps.up.supervisor.Supervisor`, every restart report
stamped with the wall time), and watches them from one anonymous node: every liveliness change
of the robot's services (`Tokens`), every `Rollout` the learner publishes, and the learner's
`status` polled while a session runs (`StatusWatch`), each stamped with `time.time()`, the clock
of the journal's `t`. Waits are on conditions (a token, a record, a status, an exit), never on
fixed sleeps.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import zenoh

from archery.apps.learn.client import learner_call, start_args
from archery.apps.up.launch_config import SERVICES, default_mesh
from archery.apps.up.launcher import Launcher
from archery.apps.up.restart_policy import RestartPolicy
from archery.apps.up.supervisor import GiveUp, Supervisor
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import ArcheryError, RpcTimeout
from archery.protocol.journal_records import DoneRecord, JournalRecord
from archery.protocol.messages import Rollout
from archery.services.learner.journal import read_records
from archery.services.learner.session import FINAL_STATES

__all__ = ["DRILL_POLICY", "DrillError", "DrillMesh", "Tokens"]

#: Restart policy of every child of a drill mesh: `up`'s default (on-failure, 0.5 s back-off)
#: with a budget the learner's 20 kills cannot spend and a back-off capped at 1 s.
DRILL_POLICY = RestartPolicy(budget=100, backoff=0.5, backoff_max=1.0)
WAIT = 90.0  # s: the longest any single condition of a drill is waited for


class DrillError(ArcheryError):
    """A condition a drill waits for did not come in time (the drill fails with this note)."""

    code = "drill_failed"


class Tokens:
    """Every liveliness change of one robot's services, stamped (wall s): (t, name, put?)."""

    def __init__(self, node: Node) -> None:
        self.events: list[tuple[float, str, bool]] = []
        self.cond = threading.Condition()
        self.sub = node.session.liveliness().declare_subscriber(
            node.keys.alive_all(), self._on, history=True
        )

    def _on(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.cond:
            self.events.append((time.time(), name, sample.kind == zenoh.SampleKind.PUT))
            self.cond.notify_all()

    def first(self, name: str, put: bool, after: float) -> float | None:
        """Time of the first change of `name` (put: came, else went) after `after`."""
        with self.cond:
            return next(
                (t for t, n, p in self.events if n == name and p == put and t > after), None
            )

    def wait(self, name: str, put: bool, after: float, timeout: float = WAIT) -> float:
        """Wait for that change; its time.

        Raises:
            DrillError: not seen within `timeout` s.
        """
        with self.cond:
            if not self.cond.wait_for(lambda: self.first(name, put, after), timeout):
                how = "come back" if put else "go"
                raise DrillError(f"{name}'s liveliness token did not {how} within {timeout:g} s")
        return self.first(name, put, after) or after


class StatusWatch:
    """The learner's status polled every `period` s on a thread: (t, state, waiting_for)."""

    def __init__(self, node: Node, period: float = 0.1) -> None:
        self.node = node
        self.period = period
        self.seen: list[tuple[float, str, list[str]]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="status-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                status = learner_call(self.node, "status", timeout=0.5)
            except ArcheryError:
                continue
            self.seen.append((time.time(), status["state"], list(status.get("waiting_for", []))))

    def first_waiting(self, service: str, after: float) -> float | None:
        """When the learner's status first listed `service` as waited for after `after`."""
        return next((t for t, s, w in self.seen if t > after and service in w), None)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


@dataclasses.dataclass
class SessionRun:
    """One session a drill runs: its id, journal and the rollouts it published (wall s, msg)."""

    session: str
    journal: Path
    published: list[tuple[float, Rollout]] = dataclasses.field(default_factory=list)

    def records(self) -> list[JournalRecord]:
        """The journal's records now."""
        return read_records(self.journal)[0]

    def published_done(self) -> list[int]:
        """Attempt indices of the done rollouts it published, in order."""
        return [m.record.index for _, m in self.published if isinstance(m.record, DoneRecord)]


class DrillMesh:
    """A router and the five services under supervision, plus the observers; a context manager.

    Args:
        workdir: logs go to `workdir/logs`, sessions to `workdir/runs`.
        robot: the robot prefix.
        start: start the router and services at once (False: the caller starts them, e.g. in a
            chosen order, then calls `observe`).
    """

    def __init__(self, workdir: Path, robot: str = "drill", start: bool = True) -> None:
        self.workdir = Path(workdir)
        base = default_mesh(
            free_tcp_endpoint(), robot, runs=str(self.workdir / "runs"), restart=DRILL_POLICY
        )
        learner = dataclasses.replace(
            base.services["learner"],
            args=(*base.services["learner"].args, "--no-report", "--service-wait", "120"),
        )
        mesh = dataclasses.replace(base, services={**base.services, "learner": learner})
        self.launcher = Launcher(logs=self.workdir / "logs", mesh=mesh)
        self.reports: list[tuple[float, str]] = []
        self.supervisor = Supervisor(self.launcher, report=self._report)
        self.outcome: list[GiveUp | None] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.node: Node | None = None
        self.tokens: Tokens | None = None
        self.status: StatusWatch | None = None
        self._runs: list[SessionRun] = []
        self._cond = threading.Condition()
        if start:
            self.launcher.up(WAIT)
            self.supervise()
            self.observe()

    # -- set-up ---------------------------------------------------------------------------------
    def _report(self, line: str) -> None:
        self.reports.append((time.time(), line))

    def supervise(self) -> None:
        """Start the supervisor's thread."""
        self._thread = threading.Thread(
            target=lambda: self.outcome.append(self.supervisor.run(self._stop)),
            name="supervisor",
            daemon=True,
        )
        self._thread.start()

    def observe(self) -> None:
        """Open the observing node (the router must listen) and start the observers."""
        self.node = Node(None, self.launcher.net)
        self.tokens = Tokens(self.node)
        self.node.subscribe(
            self.node.keys.learner_rollouts(), Rollout, mode="fifo", callback=self._on_rollout
        )
        self.status = StatusWatch(self.node)

    def _on_rollout(self, message: Rollout) -> None:
        with self._cond:
            for run in self._runs:
                if run.session == message.record.session:
                    run.published.append((time.time(), message))
            self._cond.notify_all()

    def close(self) -> None:
        """Stop the observers, the supervisor and every child."""
        if self.status is not None:
            self.status.close()
        if self.node is not None:
            self.node.close()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(30)
        self.launcher.stop_all()

    def __enter__(self) -> DrillMesh:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the children ---------------------------------------------------------------------------
    def pids(self) -> dict[str, int]:
        """Each child's process id now."""
        return {n: c.proc.pid for n, c in self.launcher.children.items() if c.proc is not None}

    def problems(self) -> list[str]:
        """What is wrong with the mesh now (empty: supervised, every child running)."""
        problems = [f"supervision ended: {o.line()}" for o in self.outcome if o is not None]
        if self._thread is None or not self._thread.is_alive():
            problems.append("the supervisor is not running")
        problems += [
            f"{n} is not running" for n, c in self.launcher.children.items() if c.returncode
        ]
        return problems

    def wait_alive(self, names: Iterable[str] = SERVICES, timeout: float = WAIT) -> float:
        """Wait by liveliness until the services are alive; the time they were."""
        assert self.node is not None
        try:
            self.node.wait_alive(names, timeout=timeout)
        except RpcTimeout as exc:
            raise DrillError(exc.message) from None
        return time.time()

    def wait_new_process(self, name: str, old_pid: int, timeout: float = WAIT) -> None:
        """Wait until the supervisor has started `name` again."""
        self.until(lambda: self.pids().get(name) != old_pid, f"{name} restarted", timeout)

    def until(self, condition: Callable[[], Any], what: str, timeout: float = WAIT) -> Any:
        """Wait until `condition()` is truthy (looked at on every rollout and every 50 ms).

        Raises:
            DrillError: not within `timeout` s.
        """
        deadline = time.monotonic() + timeout
        while True:
            value = condition()  # outside the lock: it may call the learner
            if value:
                return value
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DrillError(f"not {what} within {timeout:g} s")
            with self._cond:
                self._cond.wait(min(0.05, remaining))

    def supervisor_noticed(self, name: str, after: float) -> float | None:
        """When the supervisor reported `name`'s exit after `after`."""
        return next(
            (t for t, line in self.reports if t > after and line.startswith(f"{name} ")), None
        )

    def gone_at(self, name: str, after: float) -> float | None:
        """When the mesh first saw `name` go after `after`: its liveliness token going or the
        supervisor reporting its exit."""
        assert self.tokens is not None
        seen = [self.supervisor_noticed(name, after), self.tokens.first(name, False, after)]
        return min((t for t in seen if t is not None), default=None)

    # -- sessions -------------------------------------------------------------------------------
    def call(self, verb: str, args: dict[str, Any] | None = None, timeout: float = 60) -> Any:
        """Call a verb of the learner."""
        assert self.node is not None
        start = start_args(args) if verb == "start" and args is not None else None
        return learner_call(self.node, verb, start, timeout=timeout)

    def start_session(self, seed: int, rollouts: int = 10_000) -> SessionRun:
        """Start a session (no end at the first hit); wait until it runs."""
        request = {"algo": "archer", "seed": seed, "rollouts": rollouts, "until_hit": False}
        status = self.call("start", request)
        run = SessionRun(status["session"], Path(status["journal"]))
        with self._cond:
            self._runs.append(run)
        return run

    def resume(self, run: SessionRun, timeout: float = WAIT) -> None:
        """Resume the session with the learner's `start {resume}` (what `archery learn
        --resume` sends), once the learner is alive."""
        self.wait_alive(["learner"], timeout)
        self.call("start", {"resume": str(run.journal), "session": run.session}, timeout)

    def done_after(self, run: SessionRun, after: float) -> list[DoneRecord]:
        """The journal's done records of `run` written after `after` (wall s)."""
        return [r for r in run.records() if isinstance(r, DoneRecord) and r.t > after]

    def wait_done(self, run: SessionRun, count: int, after: float, timeout: float = WAIT) -> None:
        """Wait until `run` has published `count` done rollouts after `after` (wall s)."""

        def enough() -> bool:
            done = [t for t, m in run.published if isinstance(m.record, DoneRecord) and t > after]
            return len(done) >= count

        self.until(enough, f"{count} rollouts done", timeout)

    def stop_session(self, run: SessionRun, timeout: float = WAIT) -> dict[str, Any]:
        """Stop the session after its current rollout; its final status."""
        self.call("stop")
        return self.until(lambda: self._final(run), "the session stopped", timeout)

    def _final(self, run: SessionRun) -> dict[str, Any] | None:
        try:
            status = self.call("status", timeout=2)
        except ArcheryError:
            return None
        return (
            status
            if status.get("session") == run.session and (status["state"] in FINAL_STATES)
            else None
        )

    def wait_final(self, run: SessionRun, timeout: float = WAIT) -> dict[str, Any]:
        """Wait until the session has ended by itself (finished, stopped or failed)."""
        return self.until(lambda: self._final(run), "the session ended", timeout)
