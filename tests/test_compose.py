"""docker-compose.yml and the Dockerfile, checked without a Docker engine: one image per process
(a Dockerfile target each, built by one service only), a router, one container per process,
every command an `archery` verb whose flags parse, every process connected to the router by name
and checked healthy by liveliness. tests/test_containers.py runs them for real."""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

import archery.mesh.router
import archery.mesh.service
from archery.apps.cli import VERBS
from archery.apps.learn.learn import build_parser, start_request
from archery.apps.up.launch_config import SERVICES
from archery.mesh.credentials import DEFAULT_HOSTS
from tests.composefile import read_compose

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return read_compose(ROOT / "docker-compose.yml")


def _plain(compose: dict[str, Any]) -> dict[str, Any]:
    return {n: s for n, s in compose["services"].items() if "profiles" not in s}


def _profile(compose: dict[str, Any], name: str) -> dict[str, Any]:
    return {n: s for n, s in compose["services"].items() if s.get("profiles") == [name]}


def _secure(compose: dict[str, Any]) -> dict[str, Any]:
    return _profile(compose, "secure")


TARGETS = re.findall(r"^FROM \S+ AS (\w+)$", (ROOT / "Dockerfile").read_text(), re.M)


def test_services_and_images(compose: dict[str, Any]) -> None:
    services = _plain(compose)
    assert set(services) == {"router", *SERVICES, "demo"}
    secure = _secure(compose)
    assert set(secure) == {f"{n}-secure" for n in services}
    fleet = _profile(compose, "fleet")
    watch = _profile(compose, "watch")
    assert set(watch) == {"watch"}
    assert set(services) | set(secure) | set(fleet) | set(watch) == set(compose["services"])
    built: dict[str, str] = {}
    for name, service in compose["services"].items():
        image = service["image"]
        assert re.fullmatch(r"archery-(\w+):latest", image), name
        if "build" in service:  # each image is built by one service, with its target
            target = service["build"]["target"]
            assert image == f"archery-{target}:latest" and target in TARGETS, name
            assert image not in built, f"{image} built by {built.get(image)} and {name}"
            built[image] = name
        command = service["command"]
        assert command[0] == "archery" and command[1] in VERBS, name
        assert service["user"] == "${ARCHERY_USER:-1000:1000}", name
    assert set(built) == {f"archery-{t}:latest" for t in ("router", *SERVICES, "foxglove")}
    assert {s["image"] for s in compose["services"].values()} <= set(built)
    for name in SERVICES:
        assert services[name]["command"][1] == name
        assert services[name]["image"] == f"archery-{name}:latest"
        assert services[name]["depends_on"] == {"router": {"condition": "service_healthy"}}
    assert services["demo"]["command"][1] == "learn"
    assert "--require-hit" in services["demo"]["command"]
    assert services["demo"]["depends_on"] == {
        n: {"condition": "service_healthy"} for n in ("router", *SERVICES)
    }


def test_every_process_has_a_liveliness_health_check(compose: dict[str, Any]) -> None:
    """A container is healthy when its service holds its liveliness token (`archery alive NAME`
    through its router); a router when it answers."""
    for name, service in compose["services"].items():
        if service["command"][1] in ("learn", "experiment", "foxglove"):
            assert "healthcheck" not in service, name  # a client of the mesh: no token
            continue
        test = service["healthcheck"]["test"]
        assert test[:3] == ["CMD", "archery", "alive"], name
        verb = service["command"][1]
        command = service["command"]
        if verb == "router":
            assert test[3] == "--connect" and "127.0.0.1:7447" in test[4], name
        else:
            assert test[3] == verb, name
            assert test[test.index("--connect") + 1] == command[command.index("--connect") + 1]
            if "--robot" in command:
                assert test[test.index("--robot") + 1] == command[command.index("--robot") + 1]


def test_everyone_meets_at_the_router_by_name(compose: dict[str, Any]) -> None:
    services = _plain(compose)
    router = services["router"]["command"]
    listen = router[router.index("--listen") + 1]
    port = listen.rsplit(":", 1)[1]
    assert listen == f"tcp/0.0.0.0:{port}"
    # the host's loopback only
    assert services["router"]["ports"] == [f"127.0.0.1:${{ARCHERY_PORT:-{port}}}:{port}"]
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
    assert router["ports"] == ["127.0.0.1:${ARCHERY_SECURE_PORT:-7448}:7447"]
    for name, service in services.items():
        command = service["command"]
        identity = {"router-secure": "router", "demo-secure": "operator"}.get(
            name, name.removesuffix("-secure")
        )
        if name != "router-secure":
            assert command[command.index("--connect") + 1] == "tls/router-secure:7447", name
            assert command[command.index("--secure") + 1] == "/secrets", name
            assert "router-secure" in service["depends_on"]
        if "healthcheck" in service:
            test = service["healthcheck"]["test"]
            assert test[test.index("--identity") + 1] == identity, name
        prefix = "${ARCHERY_SECRETS:-./secrets}/"
        secrets = [v for v in service["volumes"] if v.startswith(prefix)]
        wanted = {"ca.pem", f"{identity}.pem", f"{identity}.key"}
        if name == "router-secure":
            wanted.add("acl.json5")
        assert {v.split(":/")[0].removeprefix(prefix) for v in secrets} == wanted, name
        assert all(v.endswith(":ro") for v in secrets), name
    assert "router-secure" in DEFAULT_HOSTS  # the router's certificate names its host


def test_fleet_profile_crosses_only_the_routers_link(compose: dict[str, Any]) -> None:
    """Robots on `robots`, the experiment on `lab`, the two routers linked over `link`."""
    fleet = _profile(compose, "fleet")
    networks = compose["networks"]
    assert all(networks[n] == {"internal": True} for n in ("robots", "lab", "link"))
    assert fleet["router-robots"]["networks"] == ["robots", "link"]
    lab = fleet["router-lab"]
    assert lab["networks"] == ["lab", "link"]
    assert lab["command"][lab["command"].index("--connect") + 1] == "tcp/router-robots:7447"
    stacks: dict[str, set[str]] = {}
    for name, service in fleet.items():
        command = service["command"]
        if name.startswith("router-"):
            continue
        if command[1] == "experiment":
            assert service["networks"] == ["lab"]
            assert command[command.index("--connect") + 1] == "tcp/router-lab:7447"
            continue
        assert service["networks"] == ["robots"], name
        assert command[command.index("--connect") + 1] == "tcp/router-robots:7447", name
        stacks.setdefault(command[command.index("--robot") + 1], set()).add(command[1])
    assert stacks == {
        p: {"robot", "camera", "detector", "controller"} for p in ("icubSim1", "icubSim2")
    }
    experiment = fleet["experiment"]["command"]
    assert experiment[experiment.index("--robots") + 1] == "icubSim1,icubSim2"


def test_watch_profile_serves_foxglove_on_the_hosts_loopback(compose: dict[str, Any]) -> None:
    """`archery foxglove`, read-only, published on the host's loopback only, on the same port as
    inside, so what a browser sends through the published port passes the server's Host check."""
    from archery.apps.foxglove.command import build_parser as foxglove_parser
    from archery.apps.foxglove.upgrade import UpgradeRules, parse_head

    watch = _profile(compose, "watch")["watch"]
    assert watch["image"] == "archery-foxglove:latest"
    assert watch["build"] == {"context": ".", "target": "foxglove"}
    port = "${ARCHERY_FOXGLOVE_PORT:-8765}"  # the same on both sides (the Host check)
    command = [port.split("-")[1].rstrip("}") if a == port else a for a in watch["command"]]
    args = foxglove_parser().parse_args(command[2:])
    assert args.connect == ["tcp/router:7447"] and not args.operator
    assert args.host == "0.0.0.0"  # inside the container; the host publishes loopback only
    assert args.insecure_network  # the container network is the trust boundary
    assert args.port == 8765 and watch["command"][watch["command"].index("--port") + 1] == port
    assert watch["ports"] == [f"127.0.0.1:{port}:{port}"]
    assert set(watch["depends_on"]) == {"router", "robot"}
    rules = UpgradeRules(args.host, args.port)
    for host in (f"localhost:{args.port}", f"127.0.0.1:{args.port}"):
        head = f"GET / HTTP/1.1\r\nHost: {host}\r\n\r\n".encode()
        assert rules.refusal(parse_head(head)) is None, host
    head = f"GET / HTTP/1.1\r\nHost: evil.example:{args.port}\r\n\r\n".encode()
    refused = rules.refusal(parse_head(head))
    assert refused is not None and refused.status == 421


def test_learner_and_demo_share_the_runs(compose: dict[str, Any]) -> None:
    learner = compose["services"]["learner"]
    runs = learner["command"][learner["command"].index("--runs") + 1]
    assert learner["volumes"] == [f"${{ARCHERY_RUNS:-./runs}}:{runs}"]


def _defaults(argv: list[str]) -> list[str]:
    """`argv` with each `${NAME:-default}` replaced by its default, as docker-compose does
    where NAME is not set."""
    return [re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", arg) for arg in argv]


def _parse_service(verb: str, argv: list[str], monkeypatch: pytest.MonkeyPatch) -> Any:
    """Run a service's main() with its flags but without serving: returns its config."""
    argv = _defaults(argv)
    module_name, func = VERBS[verb][0].split(":")
    module = importlib.import_module(module_name)
    real = archery.mesh.service.service_main  # not module.service_main: patched by an earlier call
    seen: list[Any] = []

    def dry(argv: Any, **kw: Any) -> int:
        return real(argv, **(kw | {"run": lambda config, stop: seen.append(config)}))

    monkeypatch.setattr(module, "service_main", dry)
    monkeypatch.setattr(archery.mesh.service, "shutdown_on_signals", threading.Event)
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
    monkeypatch.setattr(archery.mesh.router, "shutdown_on_signals", lambda: stop)
    monkeypatch.setattr(
        archery.mesh.router,
        "open_session",
        lambda net: opened.append(net) or contextlib.nullcontext(),
    )
    assert archery.mesh.router.main(services["router"]["command"][2:]) == 0
    assert opened[0].listen == ("tcp/0.0.0.0:7447",) and opened[0].mode == "router"
    assert archery.mesh.router.main(services["router-secure"]["command"][2:]) == 0
    assert opened[1].listen == ("tls/0.0.0.0:7447",) and opened[1].secure == "/secrets"
    assert opened[1].identity == "router"
    args = build_parser().parse_args(services["demo"]["command"][2:])
    assert start_request(args)["algo"] == "archer" and args.wait >= 60


def test_the_shot_is_a_variable_of_both_robots(
    compose: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("robot", "robot-secure"):
        argv = compose["services"][name]["command"]
        assert argv[argv.index("--shot") + 1] == "${ARCHERY_SHOT:-posture}"
        whole = [a.replace("${ARCHERY_SHOT:-posture}", "whole") for a in argv[2:]]
        assert _parse_service("robot", whole, monkeypatch).world.scene.shot == "whole"


def test_dockerfile() -> None:
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^ARG BASE=python:3\.11-slim-bookworm$", text, re.M)
    assert set(TARGETS) == {"base", "wheel", "router", *SERVICES, "foxglove"}
    assert "useradd --uid 1000" in text
    for target in ("router", *SERVICES, "foxglove"):  # every process runs as the unprivileged user
        stage = text.split(f" AS {target}\n", 1)[1].split("\nFROM ", 1)[0]
        assert "\nUSER archery\n" in stage, target
    lines = (ROOT / ".dockerignore").read_text().splitlines()
    ignored = [line for line in lines if line and not line.startswith("#")]
    assert ignored[0] == "*"  # only what is named goes in
    assert "**/*.key" in ignored


def test_gitignore_covers_the_secure_profiles_secrets() -> None:
    ignored = (ROOT / ".gitignore").read_text().split()
    assert "secrets/" in ignored and "*.key" in ignored


def test_the_subset_reader_refuses_what_it_does_not_know(tmp_path: Path) -> None:
    path = tmp_path / "c.yml"
    path.write_text("services:\n  a:\n    command: *anchor\n")
    with pytest.raises(json.JSONDecodeError):
        read_compose(path)
    path.write_text("services:\n  - a\n")
    with pytest.raises(AssertionError, match="outside the subset"):
        read_compose(path)


# -- `make compose` where no engine can run ----------------------------------------------------
def _make_compose(path: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """`python -m tests.containers` (what `make compose` runs) with PATH set to `path` only."""
    return subprocess.run(
        [sys.executable, "-m", "tests.containers", *args],
        env=os.environ | {"PATH": str(path)} | env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


NO_DOCKER = "no Docker engine: `docker` is not installed (Debian: apt-get install docker.io)"


def test_make_compose_without_docker_says_so_in_one_line(tmp_path: Path) -> None:
    run = _make_compose(tmp_path)
    assert run.returncode == 1
    assert run.stderr.splitlines() == [f"make compose: {NO_DOCKER}"]


def test_the_container_tests_skip_with_the_reason_without_docker(tmp_path: Path) -> None:
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-rs",
            "-p",
            "no:cacheprovider",
            "-m",
            "containers",
            str(ROOT / "tests" / "test_containers.py"),
        ],
        env=os.environ | {"PATH": str(tmp_path)},
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stdout[-2000:]
    assert "SKIPPED" in run.stdout and NO_DOCKER in run.stdout
    assert " passed" not in run.stdout.splitlines()[-1]


@pytest.mark.skipif(shutil.which("docker") is None, reason="no docker client here to point away")
def test_make_compose_names_what_is_missing_besides_the_client(tmp_path: Path) -> None:
    """A docker client without docker-compose; then both, with no engine answering."""
    (tmp_path / "docker").symlink_to(str(shutil.which("docker")))
    run = _make_compose(tmp_path)
    assert run.returncode == 1
    assert run.stderr.splitlines() == [
        "make compose: `docker-compose` is not installed (Debian: apt-get install docker-compose)"
    ]
    compose = shutil.which("docker-compose")
    if compose is None:
        return
    (tmp_path / "docker-compose").symlink_to(compose)
    dead = _make_compose(tmp_path, DOCKER_HOST=f"unix://{tmp_path}/no.sock")
    assert dead.returncode == 1
    (line,) = dead.stderr.splitlines()
    assert line.startswith("make compose: no Docker engine answers (") and "start dockerd" in line


def test_the_images_keep_the_icub_model_the_project_loads() -> None:
    from archery.protocol.robotspec import MODEL_NAME

    install = (ROOT / "docker" / "install.sh").read_text()
    assert f"prune_models.py {MODEL_NAME}\n" in install
