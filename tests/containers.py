"""The project's containers driven for real, for `make compose` and tests/test_containers.py: a
Docker engine and a client that builds with BuildKit, each image built once (on the official
base, or on a local stand-in where no registry answers), docker-compose projects run to their
end and torn down, and the checks made before any container starts (a missing secret, a taken
port).

    python -m tests.containers          # `make compose`: the checks, then the container tests
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tests.composefile import read_compose

__all__ = [
    "IMAGE_LIMIT",
    "OFFICIAL_BASE",
    "STANDIN_BASE",
    "TARGETS",
    "Compose",
    "EngineMissing",
    "base_image",
    "build_client",
    "build_images",
    "copy_context",
    "engine_problem",
    "missing_secret",
    "port_problem",
]

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "docker-compose.yml"
TARGETS = ("router", "robot", "camera", "detector", "controller", "learner", "foxglove")
OFFICIAL_BASE = "python:3.11-slim-bookworm"
STANDIN_BASE = "archery-base:bookworm"
CA_BUNDLES = ("/etc/ssl/certs/ca-certificates.crt",)
IMAGE_LIMIT = 800_000_000  # bytes: the most one image may take, as `docker images` counts it
REQUIRED = "ARCHERY_CONTAINERS"  # =required: a missing engine fails the tests instead of skipping


class EngineMissing(RuntimeError):
    """No Docker engine (or no client able to build) on this machine."""


def _run(
    cmd: Sequence[str | Path], timeout: float = 60, **kw: object
) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(c) for c in cmd],
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,  # type: ignore[call-overload]  # run's keyword arguments, passed through
    )


def engine_problem() -> str | None:
    """None when a Docker engine answers and docker-compose is installed; else why not, in one
    line (what to install or start)."""
    if shutil.which("docker") is None:
        return "no Docker engine: `docker` is not installed (Debian: apt-get install docker.io)"
    if shutil.which("docker-compose") is None:
        return "`docker-compose` is not installed (Debian: apt-get install docker-compose)"
    try:
        info = _run(["docker", "info", "--format", "{{.ServerVersion}}"], timeout=30)
    except subprocess.TimeoutExpired:
        return "no Docker engine: `docker info` did not answer within 30 s"
    if info.returncode != 0 or not info.stdout.strip():
        reason = (info.stderr.strip().splitlines() or ["no answer"])[-1]
        return f"no Docker engine answers ({reason}); start dockerd"
    return None


def build_client() -> tuple[list[str], dict[str, str]]:
    """The command that builds with BuildKit and the environment it needs: a `docker` on PATH
    with the buildx plugin, else one from before Docker 23, whose BuildKit is built in.

    Raises:
        EngineMissing: no such client on PATH.
    """
    seen: set[str] = set()
    for folder in os.environ.get("PATH", "").split(os.pathsep):
        path = Path(folder) / "docker"
        if not path.is_file() or str(path.resolve()) in seen:
            continue
        seen.add(str(path.resolve()))
        if _run([path, "buildx", "version"]).returncode == 0:
            return [str(path), "buildx", "build", "--load"], {}
        version = _run([path, "version", "--format", "{{.Client.Version}}"]).stdout.strip()
        match = re.match(r"(\d+)\.", version)
        if match and int(match[1]) < 23:
            return [str(path), "build"], {"DOCKER_BUILDKIT": "1"}
    raise EngineMissing(
        "no docker client on PATH builds with BuildKit: install the buildx plugin, or use "
        "Debian's docker.io (its client has BuildKit built in)"
    )


def image_exists(tag: str) -> bool:
    """Whether the engine holds the image `tag`."""
    return _run(["docker", "image", "inspect", tag]).returncode == 0


def base_image() -> str:
    """The official base image where it is here or can be pulled; else the local stand-in
    (docker/standin-base.sh, built once and kept)."""
    if image_exists(OFFICIAL_BASE) or _run(["docker", "pull", OFFICIAL_BASE], 600).returncode == 0:
        return OFFICIAL_BASE
    made = _run([ROOT / "docker" / "standin-base.sh", STANDIN_BASE], timeout=1800)
    if made.returncode != 0:
        raise EngineMissing(f"the stand-in base image could not be built: {made.stderr[-2000:]}")
    return STANDIN_BASE


def build_images(
    base: str, targets: Sequence[str] = TARGETS, context: Path = ROOT, tag: str = "latest"
) -> dict[str, float]:
    """Build `archery-TARGET:TAG` for each target from `context`; the seconds each took.

    Raises:
        subprocess.CalledProcessError: a build failed (its output is in the exception).
    """
    command, env = build_client()
    secret: list[str] = []
    bundle = os.environ.get("SSL_CERT_FILE") or next(
        (b for b in CA_BUNDLES if Path(b).is_file()), None
    )
    if bundle:
        secret = ["--secret", f"id=pip-ca,src={bundle}"]
    seconds: dict[str, float] = {}
    for target in targets:
        start = time.perf_counter()
        name = f"archery-{target}:{tag}"
        subprocess.run(
            [*command, "--target", target, "--build-arg", f"BASE={base}", *secret, "-t", name, "."],
            cwd=context,
            env=os.environ | env,
            check=True,
            capture_output=True,
            text=True,
            timeout=1800,
        )
        seconds[target] = time.perf_counter() - start
    return seconds


def copy_context(dest: Path) -> Path:
    """Copy the files git tracks (as they are in the working tree; links as links) to `dest`: a
    build context to change without touching the repository. Returns `dest`."""
    tracked = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    for name in tracked:
        source = ROOT / name
        if source.is_symlink():  # the import package's links to the folders: kept as links
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            (dest / name).symlink_to(source.readlink())
        elif source.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)
    return dest


def image_size(tag: str) -> int:
    """The image's size in bytes, as `docker images` counts it."""
    out = _run(["docker", "image", "inspect", tag, "--format", "{{.Size}}"]).stdout
    return int(out.strip())


def port_problem(port: int, host: str = "127.0.0.1") -> str | None:
    """None when `host:port` is free to publish; else one line naming it."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, port))
        except OSError:
            return f"port {host}:{port} is already taken on this host (set another one)"
    return None


def free_port() -> int:
    """A loopback TCP port that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def missing_secret(secrets: Path, profile: str = "secure") -> str | None:
    """None when every file the profile's containers mount from the secrets folder exists;
    else one line naming the first missing one (Docker would mount an empty folder instead)."""
    services = read_compose(COMPOSE_FILE)["services"]
    for name, service in services.items():
        if profile not in service.get("profiles", []):
            continue
        for volume in service.get("volumes", []):
            source = volume.split(":/", 1)[0]
            if "ARCHERY_SECRETS" not in source:
                continue
            path = secrets / source.rsplit("/", 1)[1]
            if not path.is_file():
                return (
                    f"{path} is missing (container {name}); make a deployment with "
                    f"`archery keys init {secrets}`"
                )
    return None


@dataclass
class Compose:
    """One docker-compose project of this repository's compose file, with its own name, ports,
    runs and secrets folders, run as the invoking user."""

    project: str
    runs: Path
    secrets: Path | None = None
    env: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.env = {
            "ARCHERY_USER": f"{os.getuid()}:{os.getgid()}",
            "ARCHERY_PORT": os.environ.get("ARCHERY_PORT") or str(free_port()),
            "ARCHERY_SECURE_PORT": os.environ.get("ARCHERY_SECURE_PORT") or str(free_port()),
            "ARCHERY_FOXGLOVE_PORT": os.environ.get("ARCHERY_FOXGLOVE_PORT") or str(free_port()),
            "ARCHERY_RUNS": str(self.runs),
            "ARCHERY_SECRETS": str(self.secrets or self.runs / "no-secrets"),
        } | self.env

    def __call__(
        self, *args: str, profiles: Sequence[str] = (), timeout: float = 600
    ) -> subprocess.CompletedProcess:
        """`docker-compose -p PROJECT -f FILE [--profile P]… ARGS…` (output captured)."""
        flags = [f for p in profiles for f in ("--profile", p)]
        return _run(
            ["docker-compose", "-p", self.project, "-f", COMPOSE_FILE, *flags, *args],
            timeout=timeout,
            env=os.environ | self.env,
        )

    def container(self, service: str) -> str:
        """The id of the (first) container of `service`, or '' if none exists."""
        out = self("ps", "-a", "-q", service).stdout.split()
        return out[0] if out else ""

    def inspect(self, service: str, template: str) -> str:
        """`docker inspect -f TEMPLATE` of the service's container (stripped)."""
        out = _run(["docker", "inspect", "-f", template, self.container(service)])
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    def wait_exit(self, service: str, timeout: float) -> int:
        """Block until the service's container exits; its exit status.

        Raises:
            subprocess.TimeoutExpired: it still runs after `timeout` s.
        """
        ident = self.container(service)
        assert ident, f"no container for {service}: {self('ps', '-a').stdout}"
        out = _run(["docker", "wait", ident], timeout=timeout).stdout
        return int(out.strip())

    def logs(self, *services: str) -> str:
        """The services' logs (the tail), for a failure message."""
        return self("logs", "--no-color", "--tail", "60", *services).stdout[-6000:]

    def down(self) -> None:
        """Remove every container, network and volume of the project, whatever profile."""
        self(
            "down",
            "--volumes",
            "--remove-orphans",
            profiles=("secure", "fleet", "watch"),
            timeout=300,
        )

    def leftovers(self) -> list[str]:
        """What the engine still holds of the project: containers, networks, volumes."""
        label = f"label=com.docker.compose.project={self.project}"
        out: list[str] = []
        for kind in ("container", "network", "volume"):
            listed = _run(
                [
                    "docker",
                    kind,
                    "ls",
                    "-q",
                    "--filter",
                    label,
                    *(["-a"] if kind == "container" else []),
                ]
            ).stdout.split()
            out += [f"{kind} {name}" for name in listed]
        return out

    @contextlib.contextmanager
    def running(self) -> Iterator[Compose]:
        """Tear the project down on leaving, whatever happened."""
        try:
            yield self
        finally:
            self.down()


def journals(runs: Path) -> list[Path]:
    """Every session journal under `runs`, oldest first."""
    return sorted(runs.glob("*/journal.jsonl"), key=lambda p: p.stat().st_mtime)


def journal_records(path: Path) -> list[dict]:
    """The records of a journal (JSON lines)."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def main(argv: Sequence[str] | None = None) -> int:
    """`make compose`: the engine check (one line, exit 1 without one), then the container tests
    with skipping turned into failure."""
    args = list(sys.argv[1:] if argv is None else argv)
    problem = engine_problem()
    if problem is None:
        for var in ("ARCHERY_PORT", "ARCHERY_SECURE_PORT", "ARCHERY_FOXGLOVE_PORT"):
            if os.environ.get(var):
                problem = port_problem(int(os.environ[var]))
                problem = problem and f"{problem}: {var}"
                if problem:
                    break
    if problem is not None:
        print(f"make compose: {problem}", file=sys.stderr)
        return 1
    import pytest

    os.environ[REQUIRED] = "required"
    return int(pytest.main(["-m", "containers", str(ROOT / "tests" / "test_containers.py"), *args]))


if __name__ == "__main__":
    sys.exit(main())
