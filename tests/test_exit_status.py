"""One exit-status rule: 0 success, 1 a runtime failure, 2 bad input (also a remote service's
refusal of the request), 130 after Ctrl-C. The table of every verb's bad input is in
`tests/test_cli_errors.py`; here the rule itself and remote replies through `archery rpc`."""

from __future__ import annotations

from typing import Any

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import (
    ArcheryError,
    BadRequest,
    ConfigError,
    KeyNameError,
    RpcTimeout,
    Unreachable,
)
from archery.protocol.exit_status import BAD_INPUT, FAILURE, INTERRUPTED, for_error
from archery.protocol.verbs.robot import PART_VERBS
from tests.conftest import archery
from tests.rpc import some_verbs


@pytest.mark.parametrize(
    ("error", "status"),
    [
        (BadRequest("x"), BAD_INPUT),
        (ConfigError("x"), BAD_INPUT),
        (KeyNameError("x"), BAD_INPUT),
        (ArcheryError("x", code="unknown_verb"), BAD_INPUT),
        (ArcheryError("x", code="bad_journal"), BAD_INPUT),
        (Unreachable("x"), FAILURE),
        (RpcTimeout("x"), FAILURE),
        (ArcheryError("x", code="busy"), FAILURE),
        (ArcheryError("x", code="denied"), FAILURE),
        (ArcheryError("x", code="unavailable"), FAILURE),
        (ArcheryError("x", code="interrupted"), INTERRUPTED),
    ],
)
def test_each_error_code_has_its_status(error: ArcheryError, status: int) -> None:
    assert for_error(error.code) == status


def test_a_remote_refusal_is_bad_input_and_a_busy_service_a_failure(net: NetConfig) -> None:
    """A fake torso that knows only `positionMove` (refusing bad values) and is busy for
    `checkMotionDone`: an unknown remote verb and a refused request exit 2, a busy one 1."""

    def move(args: Any) -> Any:
        raise BadRequest("position 0 is beyond the joint's limit")

    def stop(args: Any) -> Any:
        raise ArcheryError("a move is being stopped already", code="busy")

    flags = ("--connect", net.connect[0], "--robot", net.robot)
    key = f"{net.robot}/torso/rpc:i"
    with Node("fake", net) as server:
        server.serve(key, some_verbs(PART_VERBS, {"positionMove": move, "checkMotionDone": stop}))
        server.ready()
        unknown = archery("rpc", key, "getLimits", *flags)
        refused = archery("rpc", key, "positionMove", '{"position": [0, 0, 0]}', *flags)
        busy = archery("rpc", key, "checkMotionDone", *flags)
    assert unknown.returncode == 2 and "does not serve getLimits" in unknown.stderr
    assert refused.returncode == 2 and "beyond the joint's limit" in refused.stderr
    assert busy.returncode == 1 and "being stopped already" in busy.stderr
