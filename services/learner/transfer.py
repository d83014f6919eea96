"""Where a transferred session starts from: the last learner state of another session's journal.

`archery learn --from SESSION` (verb `start` with `from_journal`) names a session id under the
learner's runs directory, its directory or its journal file, inside that directory
(`services.learner.runs_folder`). The source must be a journal of
this version, of the same algorithm, with at least one done rollout; everything is checked
before the new session does any work.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from archery.protocol.errors import BadRequest
from archery.services.learner.algorithms.base import LearnerError
from archery.services.learner.algorithms.registry import check_transfer
from archery.services.learner.journal import JOURNAL_NAME, JournalError, JournalState, read_records
from archery.services.learner.replay import rebuild_learner
from archery.services.learner.runs_folder import journal_in_runs

__all__ = ["TransferSource", "load_source"]


@dataclass(frozen=True)
class TransferSource:
    """A previous session's learned model.

    Attributes:
        session: its session id.
        journal: its journal file.
        algorithm: its algorithm (a name of the registry).
        state: its learner's state after its last done rollout.
    """

    session: str
    journal: Path
    algorithm: str
    state: dict[str, Any]

    def header(self) -> dict[str, str]:
        """The new session's header field `from`."""
        return {"session": self.session, "journal": str(self.journal), "algo": self.algorithm}


def _journal_path(target: str, runs: Path | None) -> Path:
    """The journal of `target`: inside `runs` by its rules (`runs_folder.journal_in_runs`), or,
    without `runs` (a program's own path), a journal or its directory."""
    if runs is not None:
        return journal_in_runs(target, runs, "from_journal")
    path = Path(target)
    if path.is_dir():
        path = path / JOURNAL_NAME
    if not path.is_file():
        raise JournalError(f"--from {target!r}: no such journal")
    return path


def load_source(target: str, algorithm: str, runs: Path | None = None) -> TransferSource:
    """The learned model of the session `target`: with `runs` (the learner's runs folder, what
    the `start` verb gives), an id, directory or journal inside it
    (`runs_folder.journal_in_runs`); without, a directory or journal anywhere.

    Raises:
        BadRequest: `algorithm` cannot start from another session; with `runs`, a path
            outside it, not a regular file or too big.
        JournalError: no such journal, a broken one or one of another version, another algorithm,
            or no done rollout.
    """
    try:
        check_transfer(algorithm)
    except LearnerError as exc:
        raise BadRequest(str(exc)) from None
    path = _journal_path(target, runs)
    records, _ = read_records(path)
    state = JournalState.from_records(records, str(path))
    source_algorithm = state.header.algorithm
    if source_algorithm != algorithm:
        raise JournalError(
            f"--from {path}: session {state.session} ran {source_algorithm}, not {algorithm}; "
            f"a session starts only from one of its own algorithm"
        )
    if not state.done:
        raise JournalError(f"--from {path}: session {state.session} has no done rollout")
    learner_state = rebuild_learner(state)[0].state_dict()
    return TransferSource(state.session, path.resolve(), source_algorithm, learner_state)
