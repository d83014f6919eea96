"""docker-compose.yml and the Dockerfile, checked without a Docker engine: one image, a router,
one container per process, every command an `archery` verb whose flags parse, every process
connected to the router by name."""

from __future__ import annotations

import contextlib
import importlib
import json
import re
import threading
from pathlib import Path
from typing import Any

import pytest

import protocol.router
import protocol.service
from protocol.credentials import DEFAULT_HOSTS
from services.cli import VERBS
from services.launcher import SERVICES
from services.learner.tools.learn import build_parser, start_request

ROOT = Path(__file__).resolve().parents[1]
_LINE = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w-]*):(?: (?P<value>.+))?$")


def read_compose(path: Path) -> dict[str, Any]:
    """Read the compose file's YAML subset: nested `key:` blocks whose leaves are JSON values.

    Anything else (anchors, block lists, bare strings) is an error, so what this reads is what
    a YAML parser reads."""
    root: dict[str, Any] = {}
    stack: list[tuple[int, dict[str, Any]]] = [(-1, root)]
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        match = _LINE.match(line)
        assert match, f"{path.name} line {number} is outside the subset: {line!r}"
        indent = len(match["indent"])
        while indent <= stack[-1][0]:
            stack.pop()
        parent = stack[-1][1]
        assert match["key"] not in parent, f"line {number}: {match['key']!r} repeated"
        if match["value"] is None:
            parent[match["key"]] = child = {}
            stack.append((indent, child))
        else:
            parent[match["key"]] = json.loads(match["value"])
    return root


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return read_compose(ROOT / "docker-compose.yml")


def _plain(compose: dict[str, Any]) -> dict[str, Any]:
    return {n: s for n, s in compose["services"].items() if "profiles" not in s}


def _secure(compose: dict[str, Any]) -> dict[str, Any]:
    return {n: s for n, s in compose["services"].items() if s.get("profiles") == ["secure"]}


def test_services_and_image(compose: dict[str, Any]) -> None:
    services = _plain(compose)
    assert set(services) == {"router", *SERVICES, "demo"}
    secure = _secure(compose)
    assert set(secure) == {f"{n}-secure" for n in services}
    assert set(services) | set(secure) == set(compose["services"])
    for name, service in services.items():
        assert service["build"] == "." and service["image"] == "archery:latest", name
        command = service["command"]
        assert command[0] == "archery" and command[1] in VERBS, name
    for name in SERVICES:
        assert services[name]["command"][1] == name
        assert services[name]["depends_on"] == ["router"]
    assert services["demo"]["command"][1] == "learn"
    assert set(services["demo"]["depends_on"]) == {"router", *SERVICES}
    for name in ("robot", "camera"):  # they render or build MuJoCo scenes
        assert services[name]["environment"]["MUJOCO_GL"] == "egl"


def test_everyone_meets_at_the_router_by_name(compose: dict[str, Any]) -> None:
    services = _plain(compose)
    router = services["router"]["command"]
    listen = router[router.index("--listen") + 1]
    port = listen.rsplit(":", 1)[1]
    assert listen == f"tcp/0.0.0.0:{port}"
    assert services["router"]["ports"] == [f"127.0.0.1:{port}:{port}"]  # the host's loopback
    for name, service in services.items():
        if name == "router":
            continue
        command = service["command"]
        assert command[command.index("--connect") + 1] == f"tcp/router:{port}", name
        assert "--listen" not in command


def test_secure_profile(compose: dict[str, Any]) -> None:
    """Mutual TLS to `router-secure`; each container mounts, read-only, the CA certificate and
    its own identity only (the router also the ACL), never the CA key."""
    services = _secure(compose)
    router = services["router-secure"]
    command = router["command"]
    assert command[command.index("--listen") + 1] == "tls/0.0.0.0:7447"
    assert command[command.index("--secure") + 1] == "/secrets"
    assert router["ports"] == ["127.0.0.1:7448:7447"]
    for name, service in services.items():
        command = service["command"]
        identity = {"router-secure": "router", "demo-secure": "operator"}.get(
            name, name.removesuffix("-secure")
        )
        if name != "router-secure":
            assert command[command.index("--connect") + 1] == "tls/router-secure:7447", name
            assert command[command.index("--secure") + 1] == "/secrets", name
            assert "router-secure" in service["depends_on"]
        secrets = [v for v in service["volumes"] if v.startswith("./secrets/")]
        wanted = {"ca.pem", f"{identity}.pem", f"{identity}.key"}
        if name == "router-secure":
            wanted.add("acl.json5")
        assert {v.split(":")[0].removeprefix("./secrets/") for v in secrets} == wanted, name
        assert all(v.endswith(":ro") for v in secrets), name
    assert "router-secure" in DEFAULT_HOSTS  # the router's certificate names its host


def test_learner_and_demo_share_the_runs(compose: dict[str, Any]) -> None:
    learner = compose["services"]["learner"]
    runs = learner["command"][learner["command"].index("--runs") + 1]
    assert learner["volumes"] == [f"./runs:{runs}"]


def _parse_service(verb: str, argv: list[str], monkeypatch: pytest.MonkeyPatch) -> Any:
    """Run a service's main() with its flags but without serving: returns its config."""
    module_name, func = VERBS[verb][0].split(":")
    module = importlib.import_module(module_name)
    real = protocol.service.service_main  # not module.service_main: patched by an earlier call
    seen: list[Any] = []

    def dry(argv: Any, **kw: Any) -> int:
        return real(argv, **(kw | {"run": lambda config, stop: seen.append(config)}))

    monkeypatch.setattr(module, "service_main", dry)
    monkeypatch.setattr(protocol.service, "shutdown_on_signals", threading.Event)
    assert getattr(module, func)(argv) == 0
    return seen[0]


def test_every_command_parses(compose: dict[str, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    services = compose["services"]
    for name in SERVICES:
        argv = services[name]["command"][2:]
        config = _parse_service(name, argv, monkeypatch)
        assert config.net.connect == ("tcp/router:7447",)
        argv = services[f"{name}-secure"]["command"][2:]
        config = _parse_service(name, argv, monkeypatch)
        assert config.net.connect == ("tls/router-secure:7447",)
        assert config.net.secure == "/secrets"
    # The router: parsed and configured, but no session opened.
    stop = threading.Event()
    stop.set()
    opened: list[Any] = []
    monkeypatch.setattr(protocol.router, "shutdown_on_signals", lambda: stop)
    monkeypatch.setattr(
        protocol.router, "open_session", lambda net: opened.append(net) or contextlib.nullcontext()
    )
    assert protocol.router.main(services["router"]["command"][2:]) == 0
    assert opened[0].listen == ("tcp/0.0.0.0:7447",) and opened[0].mode == "router"
    assert protocol.router.main(services["router-secure"]["command"][2:]) == 0
    assert opened[1].listen == ("tls/0.0.0.0:7447",) and opened[1].secure == "/secrets"
    assert opened[1].identity == "router"
    args = build_parser().parse_args(services["demo"]["command"][2:])
    assert start_request(args)["algo"] == "archer" and args.wait >= 60


def test_dockerfile() -> None:
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim", text, re.M)
    for package in ("protocol", "services", "sim"):
        assert f"COPY {package} ./{package}" in text
    assert "pip install --no-cache-dir ." in text and "MUJOCO_GL=egl" in text
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert "runs" in ignored and ".venv" in ignored


def test_the_subset_reader_refuses_what_it_does_not_know(tmp_path: Path) -> None:
    path = tmp_path / "c.yml"
    path.write_text("services:\n  a:\n    command: *anchor\n")
    with pytest.raises(json.JSONDecodeError):
        read_compose(path)
    path.write_text("services:\n  - a\n")
    with pytest.raises(AssertionError, match="outside the subset"):
        read_compose(path)
