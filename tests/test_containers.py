"""The containers for real (`make compose`): the images build and each runs its process as a
non-root user, no key enters an image, `docker-compose up` runs the demo to a hit, the secure
profile too, the fleet profile runs an experiment across two networks whose routers link, and a
session survives a killed service and a restarted router; the watch profile's Foxglove server is
read by Foxglove's own client through the host's loopback. Skipped, with the reason, where no
Docker engine runs (`make compose` fails instead: ARCHERY_CONTAINERS=required)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from tests.composefile import read_compose
from tests.containers import (
    IMAGE_LIMIT,
    REQUIRED,
    ROOT,
    TARGETS,
    Compose,
    base_image,
    build_images,
    copy_context,
    engine_problem,
    image_size,
    journal_records,
    journals,
    missing_secret,
    port_problem,
)

pytestmark = [pytest.mark.containers, pytest.mark.slow, pytest.mark.timeout(1800)]

# What each image must import: every module of its process's packages. Left out on purpose: the
# recording modules (`record`/`replay` run on a host, `archery[record]`), the DMPs of `archery
# imitate` (`archery[imitate]`) and tests.postures (a fixture of the tests).
IMPORTS = {
    "router": ["archery.protocol"],
    "robot": ["archery.services.robot", "archery.sim"],
    "camera": ["archery.services.camera", "archery.sim"],
    "detector": ["archery.services.detector"],
    "controller": ["archery.services.controller"],
    "learner": ["archery.services.learner"],
    "foxglove": ["archery.apps.foxglove"],
}
NOT_IN_IMAGES = (
    "archery.apps.topics.image_records",
    "archery.apps.topics.json_image_records",
    "archery.apps.topics.observe",
    "archery.apps.topics.recording",
    "tests.postures",
)
_IMPORT_ALL = """
import importlib, os, pkgutil, sys
bad = []
for pkg in sys.argv[2:]:
    mod = importlib.import_module(pkg)
    for info in pkgutil.walk_packages(mod.__path__, pkg + "."):
        if info.name in sys.argv[1].split(","):
            continue
        try:
            importlib.import_module(info.name)
        except Exception as exc:
            bad.append(f"{info.name}: {type(exc).__name__}: {exc}")
print(os.getuid(), len(bad))
print("\\n".join(bad), file=sys.stderr)
"""


def _engine() -> None:
    problem = engine_problem()
    if problem is not None:
        if os.environ.get(REQUIRED) == "required":
            pytest.fail(problem)
        pytest.skip(problem)


@pytest.fixture(scope="module")
def base() -> str:
    _engine()
    return base_image()


@pytest.fixture(scope="module")
def images(base: str) -> dict[str, float]:
    """Every image, built once for the module (seconds per target; cached layers are reused)."""
    return build_images(base)


def test_every_image_is_within_the_size_limit(images: dict[str, float]) -> None:
    sizes = {f"archery-{t}:latest": image_size(f"archery-{t}:latest") for t in TARGETS}
    print("image sizes: " + ", ".join(f"{tag} {size / 1e6:.0f} MB" for tag, size in sizes.items()))
    over = [
        f"{tag} is {size / 1e6:.0f} MB, over the {IMAGE_LIMIT / 1e6:.0f} MB limit"
        for tag, size in sizes.items()
        if size > IMAGE_LIMIT
    ]
    assert not over, "; ".join(over)


def test_each_image_imports_its_process_and_runs_unprivileged(images: dict[str, float]) -> None:
    for target in TARGETS:
        run = subprocess.run(
            [
                "docker",
                "run",
                "--rm",
                f"archery-{target}:latest",
                "python3",
                "-c",
                _IMPORT_ALL,
                ",".join(NOT_IN_IMAGES),
                *IMPORTS[target],
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, run.stderr
        uid, failures = run.stdout.split()
        assert failures == "0", f"{target}: {run.stderr}"
        assert uid != "0", f"{target} runs as root"


def test_the_controller_image_has_no_mujoco_or_opencv(images: dict[str, float]) -> None:
    """`archery[controller]` is Pinocchio without the simulator or the vision stack."""
    probe = "import importlib.util as u; print([m for m in ('mujoco','cv2') if u.find_spec(m)])"
    out = subprocess.run(
        ["docker", "run", "--rm", "archery-controller:latest", "python3", "-c", probe],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_no_key_enters_an_image(base: str, tmp_path: Path) -> None:
    """A deployment in secrets/ and a stray key beside the Dockerfile stay out of the image."""
    context = copy_context(tmp_path / "context")
    subprocess.run(
        [sys.executable, "-m", "archery.apps.cli", "keys", "init", str(context / "secrets")],
        check=True,
        capture_output=True,
        cwd=ROOT,
    )
    (context / "services" / "stray.key").write_text((context / "secrets" / "ca.key").read_text())
    build_images(base, ("learner",), context=context, tag="keycheck")
    try:
        find = subprocess.run(
            [
                "docker",
                "run",
                "--rm",
                "archery-learner:keycheck",
                "sh",
                "-c",
                "find / -xdev \\( -name '*.key' -o -name 'ca.pem' -o -name 'acl.json5' \\) -print;",
                "grep -rl 'PRIVATE KEY' /app /build /usr/local/lib/python3*/*-packages/services",
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
    finally:
        subprocess.run(["docker", "rmi", "-f", "archery-learner:keycheck"], capture_output=True)
    assert find.stdout.strip() == "", find.stdout


def test_missing_secret_and_taken_port_are_named_before_any_container(tmp_path: Path) -> None:
    _engine()  # the port is checked once an engine answers
    line = missing_secret(tmp_path / "secrets")
    assert line is not None and "secrets/ca.pem is missing" in line and "keys init" in line
    assert "\n" not in line
    with __import__("socket").socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        assert port_problem(port) == f"port 127.0.0.1:{port} is already taken on this host " + (
            "(set another one)"
        )
        run = subprocess.run(
            [sys.executable, "-m", "tests.containers"],
            env=os.environ | {"ARCHERY_PORT": str(port)},
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
        )
    assert run.returncode == 1
    assert run.stderr.count("\n") == 1 and f"127.0.0.1:{port}" in run.stderr, run.stderr


@pytest.fixture
def plain(images: dict[str, float], tmp_path: Path) -> Iterator[Compose]:
    runs = tmp_path / "runs"
    runs.mkdir()
    compose = Compose(f"archerytest{os.getpid()}", runs)
    with compose.running():
        yield compose
    assert compose.leftovers() == []


def _up(compose: Compose, exit_from: str, profile: str | None = None, timeout: float = 600) -> int:
    """`docker-compose up -d` of the profile's containers (or the plain ones: with a profile,
    compose would start those too) and the exit status of `exit_from` when it ends."""
    services = read_compose(ROOT / "docker-compose.yml")["services"]
    names = [n for n, s in services.items() if s.get("profiles", [None]) == [profile]]
    profiles = (profile,) if profile else ()
    up = compose("up", "-d", "--no-build", *names, profiles=profiles, timeout=timeout)
    assert up.returncode == 0, up.stderr[-4000:] + compose.logs()
    return compose.wait_exit(exit_from, timeout)


def _owned_by_me(path: Path) -> None:
    assert path.stat().st_uid == os.getuid(), f"{path} belongs to uid {path.stat().st_uid}"


def _session(compose: Compose, *flags: str) -> subprocess.Popen[str]:
    """`archery learn` in a one-off container of the learner's image, next to the services."""
    return subprocess.Popen(
        [
            "docker-compose",
            "-p",
            compose.project,
            "-f",
            str(ROOT / "docker-compose.yml"),
            "run",
            "--rm",
            "-T",
            "--no-deps",
            "demo",
            "archery",
            "learn",
            "--quiet",
            "--connect",
            "tcp/router:7447",
            *flags,
        ],
        env=os.environ | compose.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for_rollouts(runs: Path, known: set[Path], count: int, timeout: float) -> Path:
    """Block until a new journal under `runs` holds `count` finished rollouts; the journal."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for journal in set(journals(runs)) - known:
            done = [r for r in journal_records(journal) if r["record"] in ("done", "aborted")]
            if len(done) >= count:
                return journal
        time.sleep(0.1)
    raise AssertionError(f"no new session reached {count} rollouts in {timeout:g} s")


def _finished(proc: subprocess.Popen[str], rollouts: int) -> dict[str, object]:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-4000:]
    result = json.loads(out.strip().splitlines()[-1])
    assert result["status"] == "finished" and result["rollouts"] == rollouts, result
    return result


def test_compose_up_runs_the_demo_to_a_hit_and_survives_faults(plain: Compose) -> None:
    """The demo exits 0 only on a hit (`--require-hit`) and writes runs/ as the invoking user;
    then, on the same mesh, a session outlives a SIGKILLed controller (restarted by its policy)
    and a restarted router."""
    status = _up(plain, "demo")
    assert status == 0, plain.logs("demo", "learner")
    (journal,) = journals(plain.runs)
    records = journal_records(journal)
    assert records[-1]["record"] == "end"
    assert any(r["record"] == "done" and r.get("hit") for r in records), records[-2:]
    for path in (journal.parent, journal, journal.parent / "report.png"):
        _owned_by_me(path)

    for fault in ("kill", "router"):
        known = set(journals(plain.runs))
        proc = _session(plain, "--rollouts", "5", "--no-until-hit", "--seed", "3")
        _wait_for_rollouts(plain.runs, known, 1, timeout=300)
        if fault == "kill":  # the process dies as in a crash (`docker kill` would be a stop)
            os.kill(int(plain.inspect("controller", "{{.State.Pid}}")), signal.SIGKILL)
        else:
            subprocess.run(["docker", "restart", plain.container("router")], check=True)
        _finished(proc, 5)
    assert int(plain.inspect("controller", "{{.RestartCount}}")) >= 1


def test_the_whole_shot_runs_in_the_containers(images: dict[str, float], tmp_path: Path) -> None:
    """ARCHERY_SHOT=whole: the robot runs `--shot whole` and every rollout of a session grasps,
    nocks and draws its arrow, the controller's image playing the demonstration's movement and
    the learner's only asking for postures."""
    runs = tmp_path / "runs"
    runs.mkdir()
    compose = Compose(f"archerytestwhole{os.getpid()}", runs, env={"ARCHERY_SHOT": "whole"})
    services = ("router", "robot", "camera", "detector", "controller", "learner")
    with compose.running():
        up = compose("up", "-d", "--no-build", *services)
        assert up.returncode == 0, up.stderr[-4000:] + compose.logs()
        proc = _session(compose, "--rollouts", "3", "--no-until-hit", "--wait", "300")
        result = _finished(proc, 3)
        assert result["aborted"] == 0, result
    assert compose.leftovers() == []
    (journal,) = journals(runs)
    done = [r for r in journal_records(journal) if r["record"] == "done"]
    assert len(done) == 3 and all(r["timing"]["movement_sim_s"] > 12.0 for r in done), done


def test_the_watch_profile_serves_the_robot_to_foxglove(
    images: dict[str, float], tmp_path: Path
) -> None:
    """`--profile watch`: the Foxglove container beside the plain mesh, published on the host's
    loopback; Foxglove's own client reads the robot's description, joints and camera from it."""
    runs = tmp_path / "runs"
    runs.mkdir()
    compose = Compose(f"archerytestwatch{os.getpid()}", runs)
    url = f"ws://127.0.0.1:{compose.env['ARCHERY_FOXGLOVE_PORT']}/"
    with compose.running():
        up = compose("up", "-d", "--no-build", "router", "robot", "camera", "watch",
                     profiles=("watch",))  # fmt: skip
        assert up.returncode == 0, up.stderr[-4000:] + compose.logs()
        wants = ("/robot_description", "/joint_states", "/camera/image")
        lines = _foxglove_client(url, wants, timeout=300)
        assert compose.inspect("watch", "{{.State.Running}}") == "true", compose.logs("watch")
    assert compose.leftovers() == []
    topics = {m["topic"] for line in lines if "message" in line for m in [line["message"]]}
    assert set(wants) <= topics, (topics, lines[-3:])


def _foxglove_client(url: str, wants: Sequence[str], timeout: float) -> list[dict[str, Any]]:
    """Foxglove's own client (tests/foxglove_client) against `url`, retried while the server
    starts (connection refused) until `timeout`; its JSON lines once it has every wanted topic."""
    client = ROOT / "tests" / "foxglove_client"
    if not (client / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=client, check=True)
    argv = ["node", str(client / "client.mjs"), url, *(a for w in wants for a in ("--want", w))]
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        done = subprocess.run(
            [*argv, "--timeout", str(max(10, int(min(left, 120))))],
            capture_output=True,
            text=True,
            timeout=150,
        )
        if done.returncode == 0:
            return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
        if time.monotonic() > deadline:
            raise AssertionError(f"Foxglove's client got no answer: {done.stderr[-2000:]}")
        time.sleep(1)


def test_the_secure_profile_runs_the_demo_to_a_hit(
    images: dict[str, float], tmp_path: Path
) -> None:
    runs, secrets = tmp_path / "runs", tmp_path / "secrets"
    runs.mkdir()
    subprocess.run(
        [sys.executable, "-m", "archery.apps.cli", "keys", "init", str(secrets)],
        check=True,
        capture_output=True,
        cwd=ROOT,
    )
    assert missing_secret(secrets) is None
    compose = Compose(f"archerytestsecure{os.getpid()}", runs, secrets)
    with compose.running():
        status = _up(compose, "demo-secure", "secure")
        assert status == 0, compose.logs("demo-secure", "learner-secure", "router-secure")
    assert compose.leftovers() == []
    (journal,) = journals(runs)
    _owned_by_me(journal)


def test_the_fleet_profile_runs_an_experiment_across_two_networks(
    images: dict[str, float], tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    runs.mkdir()
    compose = Compose(f"archerytestfleet{os.getpid()}", runs)
    with compose.running():
        status = _up(compose, "experiment", "fleet")
        assert status == 0, compose.logs("experiment", "router-lab", "router-robots")
        networks = {
            name: compose.inspect(name, "{{json .NetworkSettings.Networks}}")
            for name in ("router-robots", "router-lab", "robot1", "experiment")
        }
    assert compose.leftovers() == []
    project = compose.project
    assert set(json.loads(networks["router-robots"])) == {f"{project}_robots", f"{project}_link"}
    assert set(json.loads(networks["router-lab"])) == {f"{project}_lab", f"{project}_link"}
    assert set(json.loads(networks["robot1"])) == {f"{project}_robots"}
    assert set(json.loads(networks["experiment"])) == {f"{project}_lab"}
    out = runs / "fleet-experiment"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["sessions"] == 2 and summary["run"]["rollouts"] == 4
    rows = list(csv.DictReader((out / "curves.csv").open()))
    for session in ("0", "1"):  # each session finished: it hit, or it used its whole budget
        mine = [r for r in rows if r["session"] == session]
        last = mine[-1]
        assert last["rollout"] == "4" or float(last["distance"]) <= 0.05, mine
