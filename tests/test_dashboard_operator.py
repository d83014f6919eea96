"""`archery dashboard` and the operator's requests (a real robot's arrow put on the string by
hand): the state carries the request the learner's status shows; read-only (the default) the
page has no Confirm button and `/api/confirm` is not served; with `--operator` a POST of the
page's (its token, its own origin) confirms the request number it names through the learner's
`confirm`, a stale number gets the learner's refusal, and nothing else reaches the learner. A
stand-in learner serves `status` and `confirm` over a real router with the learner's own
`OperatorDesk`; the page itself is checked in a headless Chromium."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import msgspec
import pytest

from archery.apps.dashboard.server import TOKEN_HEADER, Dashboard, bind
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.verbs.learner import (
    LEARNER_VERBS,
    ConfirmArgs,
    LearnerStatusReply,
    OperatorRequest,
)
from archery.services.learner.operator_desk import OperatorAbsent, OperatorDesk
from tests.rpc import some_verbs
from tests.test_dashboard import browser
from tests.test_dashboard_hardening import Answer, bound, request, token_of, wait_for

NOCK = "put an arrow on the string of the left hand's bow"


class StandIn:
    """A learner whose session waits for the operator (`ask`), serving `status` (its request
    in `operator`) and `confirm` (the learner's `OperatorDesk`), each `confirm` call kept."""

    def __init__(self, node: Node, *, serve_confirm: bool = True) -> None:
        self.desk = OperatorDesk(limit=600)
        self.calls: list[ConfirmArgs] = []
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []
        handlers: dict[str, Callable[[Any], Any]] = {"status": self._status}
        if serve_confirm:
            handlers["confirm"] = self._confirm
        node.serve(node.keys.learner_rpc(), some_verbs(LEARNER_VERBS, handlers))
        node.ready()

    def _status(self, _: object) -> LearnerStatusReply:
        return LearnerStatusReply(
            state="running", session="s1", rollouts=2, budget=10, operator=self.desk.pending
        )

    def _confirm(self, args: ConfirmArgs) -> OperatorRequest:
        self.calls.append(args)
        return self.desk.confirm(args.request)

    def ask(self, message: str = NOCK) -> OperatorRequest:
        """The session asks the operator for a nock (on a thread, as the session does); the
        request once it waits."""
        before = self.desk.pending

        def wait() -> None:
            with contextlib.suppress(OperatorAbsent):  # the test ended first
                self.desk.ask("nock", message, self.stop)

        thread = threading.Thread(target=wait, daemon=True)
        thread.start()
        self.threads.append(thread)
        wait_for(lambda: self.desk.pending not in (None, before), "the request waits")
        pending = self.desk.pending
        assert pending is not None
        return pending

    def close(self) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(timeout=10)


@contextmanager
def stand_in(net: NetConfig, *, serve_confirm: bool = True) -> Iterator[StandIn]:
    with Node("learner", net) as node:
        learner = StandIn(node, serve_confirm=serve_confirm)
        try:
            yield learner
        finally:
            learner.close()


def state_of(dash: Dashboard) -> dict[str, Any]:
    status, _, body = request(dash, "/api/state")
    assert status == 200, body
    state: dict[str, Any] = json.loads(body)
    return state


def wait_state(dash: Dashboard, ready: Callable[[dict[str, Any]], bool], what: str) -> dict:
    """The dashboard's state once `ready(state)` holds."""
    seen: list[dict[str, Any]] = []

    def check() -> bool:
        seen[:] = [state_of(dash)]
        return ready(seen[0])

    wait_for(check, what)
    return seen[0]


def asked(request_: OperatorRequest) -> Callable[[dict[str, Any]], bool]:
    return lambda state: state["learner"].get("operator") == msgspec.to_builtins(request_)


def confirm(
    dash: Dashboard, query: str, *, token: str | None = None, headers: dict[str, str] | None = None
) -> Answer:
    """POST /api/confirm?QUERY as the page does: with the page's token (unless `token`)."""
    sent = {TOKEN_HEADER: token_of(dash) if token is None else token, **(headers or {})}
    return request(dash, f"/api/confirm?{query}", method="POST", headers=sent)


def test_the_state_carries_the_operator_s_request(net: NetConfig) -> None:
    with stand_in(net) as learner, Dashboard(net, bind("127.0.0.1", 0)) as dash:
        waiting = learner.ask()
        state = wait_state(dash, asked(waiting), "the learner's request in the state")
        assert state["operator"] is False  # read-only: the page shows no button
        shown = state["learner"]["operator"]
        assert shown["request"] == 1 and shown["verb"] == "nock" and shown["message"] == NOCK
        assert shown["limit"] == 600 and shown["since"] == waiting.since
        assert dash.watch().snapshot()["learner"]["operator"] == shown
        learner.desk.confirm(1)  # by the terminal, say: the banner goes
        wait_state(dash, lambda s: "operator" not in s["learner"], "the request gone")


def test_read_only_does_not_serve_confirm(net: NetConfig) -> None:
    with stand_in(net) as learner, Dashboard(net, bind("127.0.0.1", 0)) as dash:
        waiting = learner.ask()
        wait_state(dash, asked(waiting), "the learner's request in the state")
        for query in ("request=1", f"robot={net.robot}&request=1", ""):
            status, _, body = confirm(dash, query)
            assert status == 404, (query, body)
        status, _, _ = request(dash, "/api/confirm?request=1")
        assert status == 404  # no command path at all: not even a 405
        assert learner.calls == [] and learner.desk.pending == waiting


def test_the_operator_s_dashboard_confirms_the_request_its_page_names(net: NetConfig) -> None:
    with (
        stand_in(net) as learner,
        Dashboard(net, bind("127.0.0.1", 0), operator=True) as dash,
    ):
        first = learner.ask()
        assert wait_state(dash, asked(first), "the request in the state")["operator"] is True
        address, port = bound(dash)
        refused = [
            confirm(dash, "request=1", token=""),
            confirm(dash, "request=1", token="not-the-token"),
            confirm(dash, "request=1", headers={"Origin": "http://evil.example"}),
            confirm(dash, "request=1", headers={"Origin": f"http://evil.example:{port}"}),
        ]
        assert [status for status, _, _ in refused] == [403, 403, 403, 403], refused
        foreign_host = request(
            dash,
            "/api/confirm?request=1",
            method="POST",
            host="evil.example",
            headers={TOKEN_HEADER: token_of(dash)},
        )
        assert foreign_host[0] == 421
        too_long = confirm(dash, "request=1", headers={"Content-Length": "100000"})
        assert too_long[0] == 413
        for query in ("", "request=0", "request=x", "request=1&request=1", "request=-1"):
            status, _, body = confirm(dash, query)
            assert status == 400 and b"request=N" in body, (query, body)
        assert request(dash, "/api/confirm?request=1")[0] == 405  # a GET changes nothing
        assert learner.calls == [] and learner.desk.pending == first

        origin = {"Origin": f"http://{address}:{port}"}  # the page's own
        status, headers, body = confirm(dash, f"robot={net.robot}&request=1", headers=origin)
        assert (status, headers["Content-Type"]) == (200, "application/json"), body
        assert json.loads(body) == msgspec.to_builtins(first)
        assert learner.calls == [ConfirmArgs(request=1)]
        learner.threads[0].join(timeout=10)
        assert not learner.threads[0].is_alive()  # the session goes on
        wait_state(dash, lambda s: "operator" not in s["learner"], "the banner gone")

        # a click on request 1 the page still showed while request 2 came: refused
        second = learner.ask()
        status, _, body = confirm(dash, "request=1")
        assert status == 409, body
        assert b"request 1 is not the one waiting: request 2" in body
        assert learner.desk.pending == second
        assert confirm(dash, "request=2")[0] == 200
        status, _, body = confirm(dash, "request=2")  # twice: nothing waits any more
        assert status == 409 and b"no request of the operator is waiting" in body, body
        assert learner.calls == [ConfirmArgs(request=n) for n in (1, 1, 2, 2)]


def test_a_learner_that_cannot_confirm_is_a_gateway_error(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.1", 0), operator=True) as dash:
        status, _, body = confirm(dash, "request=1")  # no learner at all
        assert status == 504 and b"learner/rpc:i" in body, body
        with stand_in(net, serve_confirm=False) as learner:  # a learner without `confirm`
            waiting = learner.ask()
            wait_state(dash, asked(waiting), "the request in the state")
            status, _, body = confirm(dash, "request=1")
            assert status == 502 and b"does not serve confirm" in body, body


def test_the_command_line_s_operator_flag(net: NetConfig) -> None:
    """`archery dashboard --operator` serves the button and `/api/confirm`; without it, neither."""
    for flags, mode in (((), "read-only"), (("--operator",), "operator")):
        proc = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "dashboard", "--connect", net.connect[0],
             "--robot", net.robot, "--port", "0", "--nice", "0", *flags],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            line = proc.stdout.readline()
            assert line.startswith("archery dashboard: serving http://127.0.0.1:"), line
            assert f"(robot {net.robot}, {mode}" in line, line
            url = line.split()[3]
            with urllib.request.urlopen(url + "api/state", timeout=30) as answer:
                assert json.loads(answer.read())["operator"] is bool(flags)
            post = urllib.request.Request(url + "api/confirm?request=1", method="POST")
            with urllib.request.urlopen(url + "api/robots", timeout=30) as answer:
                post.add_header(TOKEN_HEADER, answer.headers[TOKEN_HEADER])
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(post, timeout=30)
            assert refused.value.code == (504 if flags else 404)  # no learner: not there
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err


@pytest.mark.parametrize("operator", [False, True])
def test_the_page_shows_the_request_and_an_operator_s_button(
    net: NetConfig, operator: bool
) -> None:
    with (
        stand_in(net) as learner,
        Dashboard(net, bind("127.0.0.1", 0), operator=operator) as dash,
        browser() as page,
    ):
        learner.ask()
        page.goto(dash.url)
        banner = page.locator("#operator-panel")
        banner.wait_for(state="visible", timeout=30_000)
        text = page.locator("#operator-request").inner_text()
        assert text.startswith(f"The session waits for the operator: {NOCK} (request 1, since ")
        assert text.endswith(", waits up to 600 s)"), text
        since = text.split("since ")[1].split(",")[0]
        assert len(since) == 8 and since.count(":") == 2, since
        button = page.locator("#confirm")
        if not operator:
            assert button.is_hidden() and learner.calls == []
            return
        assert button.is_visible() and button.get_attribute("data-request") == "1"
        button.click()
        banner.wait_for(state="hidden", timeout=30_000)
        assert learner.calls == [ConfirmArgs(request=1)] and learner.desk.pending is None
        second = learner.ask()
        page.wait_for_function(
            "document.getElementById('confirm').dataset.request === '2'", timeout=30_000
        )
        assert "request 2" in page.locator("#operator-request").inner_text()
        assert learner.desk.pending == second
