"""The learner's exceptions when a session runs, under the project's `ArcheryError` (codes for
RPC replies and abort records); a journal's are `services.learner.journal.JournalError`."""

from __future__ import annotations

from archery.protocol.errors import ArcheryError

__all__ = ["RigError", "ServiceLost", "SessionFailed"]


class RigError(ArcheryError):
    """A service replied with an error, or its reply made no sense."""

    code = "rpc_error"


class ServiceLost(RigError):
    """A service did not reply in time or is no longer alive; `service` names it."""

    code = "service_lost"

    def __init__(self, service: str, message: str) -> None:
        super().__init__(message)
        self.service = service


class SessionFailed(ArcheryError):
    """The session cannot go on (too many aborts, a service gone for good); resumable."""

    code = "session_failed"
