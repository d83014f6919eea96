"""The dashboard's one command, `archery dashboard --operator` only: `POST /api/confirm?robot=R
&request=N` (the page's Confirm button) tells the learner the operator did what the session
waits for (`learner/rpc:i confirm`, `ConfirmArgs(request=N)`: the number the page showed, so a
click on a request already gone never confirms a newer one). `confirm` makes the call and its
HTTP answer: 200 with the request confirmed (JSON), 400 for a bad request number, 409 with the
learner's word when it refuses (nothing waits, another request does), 504 when nothing answers
in time, 502 for any other failure of the call. `add_operator_arg` is the flag and
`node_settings` the node's identity: `operator` with it, else `viewer` (no `confirm` granted).
"""

from __future__ import annotations

import argparse
import json
from http import HTTPStatus

import msgspec

from archery.apps.dashboard.watch import MeshWatch
from archery.mesh.acl import OPERATOR, VIEWER
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ArcheryError, BadRequest, ConfigError, RpcTimeout
from archery.protocol.verbs.learner import CONFIRM, ConfirmArgs

__all__ = ["CONFIRM_PATH", "CONFIRM_TIMEOUT", "add_operator_arg", "confirm", "node_settings"]

CONFIRM_PATH = "/api/confirm"
CONFIRM_TIMEOUT = 5.0  # s: the learner's `confirm` never waits; more is a learner gone or stuck

Answer = tuple[HTTPStatus, bytes, str]  # status, body, content type


def add_operator_arg(parser: argparse._ActionsContainer) -> None:
    """`--operator`: the dashboard's Confirm button."""
    parser.add_argument(
        "--operator",
        action="store_true",
        help="show a Confirm button with the operator's request the session waits for (an "
        "arrow put on the string by hand) and tell the learner when it is pressed (in secure "
        "mode: as the operator identity); without it the page only shows the request",
    )


def node_settings(args: argparse.Namespace) -> NetConfig:
    """The dashboard node's settings: identity `operator` with `--operator`, else `viewer`.

    Raises:
        ConfigError: `--operator` in secure mode with another `--identity`.
    """
    net = NetConfig.from_args(args).with_identity(OPERATOR if args.operator else VIEWER)
    if args.operator and net.secure and net.identity != OPERATOR:
        raise ConfigError(
            f"--operator in secure mode runs as identity {OPERATOR!r}, not {net.identity!r}"
        )
    return net


def _line(status: HTTPStatus, text: str) -> Answer:
    return status, (text + "\n").encode(), "text/plain; charset=utf-8"


def _number(values: list[str] | None) -> int | None:
    """The request number of the query (`request=N`, a whole number from 1), or None."""
    if not values or len(values) != 1:
        return None
    text = values[0]
    if not (text.isascii() and text.isdigit()) or len(text) > 18 or int(text) < 1:
        return None
    return int(text)


def confirm(
    watch: MeshWatch, query: dict[str, list[str]], *, timeout: float = CONFIRM_TIMEOUT
) -> Answer:
    """Confirm the request `query["request"]` of `watch`'s robot's learner; the HTTP answer."""
    number = _number(query.get("request"))
    if number is None:
        return _line(
            HTTPStatus.BAD_REQUEST,
            "give request=N: the number of the operator's request the page shows",
        )
    try:
        reply = watch.node.call_typed(
            watch.keys.learner_rpc(), CONFIRM, ConfirmArgs(request=number), timeout=timeout
        )
    except RpcTimeout as exc:
        return _line(HTTPStatus.GATEWAY_TIMEOUT, f"the learner did not answer: {exc}")
    except ArcheryError as exc:
        if exc.code == BadRequest.code:
            return _line(HTTPStatus.CONFLICT, str(exc))
        return _line(HTTPStatus.BAD_GATEWAY, f"the learner's confirm failed: {exc}")
    watch.status_soon()  # the page's banner goes as soon as the learner says so
    return HTTPStatus.OK, json.dumps(msgspec.to_builtins(reply)).encode(), "application/json"
