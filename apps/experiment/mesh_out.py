"""The files of an experiment on the mesh: its plan (the settings `--resume` compares), one
journal per session under `sessions/`, and the results read back from those journals."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from archery.apps.experiment.config import AlgorithmRun, ExperimentConfig, ExperimentError
from archery.protocol.errors import ArcheryError
from archery.protocol.journal_records import DoneRecord, EndRecord, JournalRecord, SessionRecord
from archery.services.learner.algorithms.power import Power
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.services.learner.config import SessionConfig
from archery.services.learner.journal import JOURNAL_NAME, JournalError, JournalState, read_records
from archery.services.learner.replay import rebuild_learner

__all__ = [
    "PLAN_NAME",
    "SESSIONS_DIR",
    "SessionItem",
    "journal_path",
    "prepare_out",
    "runs_from_journals",
    "session_config",
]


class FleetFailure(ArcheryError):
    """A session failed again and again on live robots: the experiment ends (resumable)."""

    code = "session_failed"


SESSIONS_DIR = "sessions"
PLAN_NAME = "experiment.json"  # the settings of the run, what --resume compares
PLAN_VERSION = 1


@dataclass(frozen=True)
class SessionItem:
    """One session of the experiment: an algorithm and the session number (0-based)."""

    algorithm: str
    session: int

    @property
    def name(self) -> str:
        """The session id and folder name, e.g. `archer-s07`."""
        return f"{self.algorithm}-s{self.session:02d}"


def session_config(config: ExperimentConfig, item: SessionItem) -> SessionConfig:
    """The learner session of `item`: the ballistic world's learner seed for that session
    number, the whole budget, the robot's start θ, `config`'s θ box (the robots' own, see
    `run_mesh_experiment`) and `--power-scale` for PoWER."""
    seed = int(config.seeds(item.session)[1].generate_state(1)[0])
    options = {}
    if config.power_scale is not None and ALGORITHMS[item.algorithm].cls is Power:
        options["return_scale"] = float(config.power_scale)
    return SessionConfig(
        algorithm=item.algorithm,
        rollouts=config.rollouts,
        seed=seed,
        until_hit=False,
        bounds=config.bounds,
        options=options,
    )


def journal_path(out: Path, item: SessionItem) -> Path:
    """Where `item`'s journal lives under the experiment folder `out`."""
    return out / SESSIONS_DIR / item.name / JOURNAL_NAME


def _plan(config: ExperimentConfig) -> dict[str, Any]:
    """The settings `--resume` must match; the θ box is the robots' (in each journal's header)."""
    run = {k: v for k, v in config.to_dict().items() if k != "bounds"}
    return {"version": PLAN_VERSION, "world": config.world, "run": run}


def prepare_out(out: Path, config: ExperimentConfig, resume: bool) -> None:
    """Write the run's settings into a fresh `out`, or (with `resume`) check that `out` holds
    an experiment with the same settings.

    Raises:
        ExperimentError: `out` holds another experiment (or, with `resume`, none, or one of
            other settings); the message names the first difference.
    """
    path = out / PLAN_NAME
    plan = _plan(config)
    if not resume:
        if path.exists():
            raise ExperimentError(
                f"--out {str(out)!r} holds an experiment already; continue it with --resume "
                f"{out}, or choose another --out"
            )
        out.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(plan, indent=2) + "\n")
        return
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        raise ExperimentError(
            f"--resume {str(out)!r}: no readable {PLAN_NAME} of an `archery experiment --world "
            f"mesh` there"
        ) from None
    if not isinstance(old, dict) or old.get("version") != PLAN_VERSION:
        raise ExperimentError(f"--resume {str(out)!r}: {path} is not a version {PLAN_VERSION} plan")
    flat_old = {"world": old.get("world"), **(old.get("run") or {})}
    flat_new = {"world": plan["world"], **plan["run"]}
    for key, value in flat_new.items():
        if flat_old.get(key) != value:
            raise ExperimentError(
                f"--resume {str(out)!r} ran {key} {flat_old.get(key)!r}, not {value!r}; give "
                f"the flags of that run"
            )


def session_records(path: Path) -> list[JournalRecord]:
    """The records of a session's journal (none when it has not started)."""
    return read_records(path)[0] if path.exists() else []


def session_ended(records: list[JournalRecord]) -> bool:
    """Whether the session's journal has its end record."""
    return any(isinstance(r, EndRecord) for r in records)


def runs_from_journals(config: ExperimentConfig, out: Path) -> dict[str, AlgorithmRun]:
    """Every algorithm's sessions read back from their journals (each must be finished).

    r_true is the robot's ground-truth impact where its event was received, else the
    detector's r; wall_time is the sum of the sessions' journal spans (robot-seconds).

    Raises:
        FleetFailure: a session's journal is missing, unfinished or short.
    """
    runs = {}
    n_s, n_r = config.sessions, config.rollouts
    for name in config.algorithms:
        thetas = np.empty((n_s, n_r, 3))
        r_obs, r_true = np.empty((n_s, n_r, 2)), np.empty((n_s, n_r, 2))
        wall, states = 0.0, []
        for s in range(n_s):
            path = journal_path(out, SessionItem(name, s))
            records = session_records(path)
            done = [r for r in records if isinstance(r, DoneRecord)]
            if not session_ended(records) or len(done) != n_r:
                raise FleetFailure(
                    f"session {path.parent.name} is unfinished ({len(done)} of {n_r} rollouts "
                    f"in {path})"
                )
            thetas[s] = [d.theta for d in done]
            r_obs[s] = [d.r_m for d in done]
            r_true[s] = [d.truth_r_m or d.r_m for d in done]
            stamps = [r.t for r in records if isinstance(r, SessionRecord)]
            wall += stamps[-1] - stamps[0]
            try:  # the checkpoint at its end, told its history
                learner, _ = rebuild_learner(JournalState.from_records(records, str(path)))
            except JournalError as exc:
                raise FleetFailure(f"session {path.parent.name}: {exc}") from None
            states.append(learner.state_dict())
        runs[name] = AlgorithmRun(name, thetas, r_obs, r_true, wall, tuple(states))
    return runs
