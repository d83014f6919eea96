"""The containers measured: image sizes against the one image of before, cold and warm builds,
`docker-compose up` to the demo's hit, the wall time per rollout in containers against
`archery up` on the same machine (interleaved repeats), and the fleet profile's rollouts/s
against the same fleet on one network.

    .venv/bin/python -m benchmarks.bench_containers [--repeats 5] [--rollouts 20]
        [--before COMMIT] [--parts build,sizes,up,rollout,fleet] [--smoke]

`sizes` builds the images with the build cache and reports each image's size against the
limit `make compose` enforces; `--smoke` is `sizes` and one 7-rollout session in containers
and on `archery up` (minutes once the images are cached; nothing recorded).

Needs a Docker engine (as `make compose` does); images are tagged archery-*:latest, the image
of before archery-before:bench.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from archery.apps.progress import progress_bar
from archery.mesh.router import free_tcp_endpoint, wait_for_endpoint
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.containers import (
    CA_BUNDLES,
    IMAGE_LIMIT,
    ROOT,
    TARGETS,
    Compose,
    base_image,
    build_client,
    build_images,
    copy_context,
    engine_problem,
    image_size,
    journal_records,
)

SERVICES = ("router", "robot", "camera", "detector", "controller", "learner")


def _before_image(commit: str, base: str) -> int:
    """Build the one image of `commit` (its Dockerfile, its base line pointed at `base`, pip
    given the CA bundle as the build secret); its size in bytes."""
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(
            ["git", "archive", commit], cwd=ROOT, capture_output=True, check=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        dockerfile = Path(tmp, "Dockerfile")
        text = dockerfile.read_text().replace("FROM python:3.11-slim-bookworm", f"FROM {base}")
        text = text.replace(
            "RUN pip install",
            "RUN --mount=type=secret,id=pip-ca PIP_CERT=/run/secrets/pip-ca pip install",
        )
        dockerfile.write_text(text)
        command, env = build_client()
        subprocess.run(
            [
                *command,
                "--secret",
                f"id=pip-ca,src={CA_BUNDLES[0]}",
                "-t",
                "archery-before:bench",
                ".",
            ],
            cwd=tmp,
            env=os.environ | env,
            check=True,
            capture_output=True,
        )
    return image_size("archery-before:bench")


def _per_rollout(journal: Path, skip: int) -> float:
    """Seconds per rollout between the `skip`-th and the last finished rollout of a journal."""
    done = [r["t"] for r in journal_records(journal) if r["record"] == "done"]
    return (done[-1] - done[skip - 1]) / (len(done) - skip)


def _learn_args(rollouts: int, seed: int) -> list[str]:
    return ["--rollouts", str(rollouts), "--no-until-hit", "--quiet", "--seed", str(seed)]


def _containers_session(runs: Path, rollouts: int, seed: int) -> float:
    """One session on the containers' mesh (started, used, torn down); s per rollout."""
    compose = Compose(f"archerybench{os.getpid()}", runs)
    with compose.running():
        up = compose("up", "-d", "--no-build", *SERVICES[1:], timeout=600)
        assert up.returncode == 0, up.stderr[-3000:]
        run = compose(
            "run", "--rm", "-T", "--no-deps", "demo", "archery", "learn", "--connect",
            "tcp/router:7447", *_learn_args(rollouts, seed), timeout=900,
        )  # fmt: skip
        assert run.returncode == 0, run.stderr[-3000:]
    journal = json.loads(run.stdout.strip().splitlines()[-1])["journal"]
    return _per_rollout(runs / Path(journal).relative_to("/app/runs"), 5)


def _host_session(runs: Path, rollouts: int, seed: int) -> float:
    """One session on `archery up` on this machine (started, used, stopped); s per rollout."""
    endpoint = free_tcp_endpoint()
    archery = [sys.executable, "-m", "archery.apps.cli"]
    up = subprocess.Popen(
        [*archery, "up", "--listen", endpoint, "--runs", str(runs), "--log-level", "warn"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for_endpoint(endpoint, timeout=60)
        run = subprocess.run(
            [
                *archery,
                "learn",
                "--connect",
                endpoint,
                "--wait",
                "120",
                *_learn_args(rollouts, seed),
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert run.returncode == 0, run.stderr[-3000:]
    finally:
        up.send_signal(signal.SIGINT)
        up.wait(timeout=120)
    journal = json.loads(run.stdout.strip().splitlines()[-1])["journal"]
    return _per_rollout(Path(journal), 5)


def _up_to_hit(runs: Path, fresh: bool) -> float:
    """Seconds from `docker-compose up` to the demo's exit (0: a hit). `fresh`: no container
    exists before; else the stopped containers of the previous run are started again."""
    compose = Compose("archerybenchup", runs)
    if fresh:
        compose.down()
    start = time.perf_counter()
    up = compose(
        "up", "--no-build", "--abort-on-container-exit", "--exit-code-from", "demo", timeout=900
    )
    seconds = time.perf_counter() - start
    assert up.returncode == 0, up.stdout[-3000:]
    compose("stop", timeout=300)
    return seconds


def _fleet(runs: Path, one_network: bool, sessions: int, rollouts: int) -> float:
    """Rollouts/s of `archery experiment --world mesh` on the fleet profile: over the two
    routers' link, or (`one_network`) with the experiment on the robots' network and router."""
    compose = Compose(f"archerybenchfleet{os.getpid()}", runs)
    compose.env |= {
        "ARCHERY_FLEET_SESSIONS": str(sessions),
        "ARCHERY_FLEET_ROLLOUTS": str(rollouts),
        "ARCHERY_FLEET_ALGOS": "archer",
        "ARCHERY_FLEET_OUT": "fleet",
    }
    with compose.running():
        up = compose("up", "-d", "--no-build", "router-robots", "robot1", "camera1", "detector1",
                     "controller1", "robot2", "camera2", "detector2", "controller2",
                     "router-lab", profiles=("fleet",), timeout=600)  # fmt: skip
        assert up.returncode == 0, up.stderr[-3000:]
        network = ["--network", f"{compose.project}_robots"] if one_network else []
        connect = "tcp/router-robots:7447" if one_network else "tcp/router-lab:7447"
        start = time.perf_counter()
        run = subprocess.run(
            ["docker", "run", "--rm", *network, "-u", compose.env["ARCHERY_USER"]]
            + ([] if one_network else ["--network", f"{compose.project}_lab"])
            + ["-v", f"{runs}:/app/runs", "archery-learner:latest", "archery", "experiment"]
            + ["--world", "mesh", "--connect", connect, "--robots", "icubSim1,icubSim2"]
            + ["--algo", "archer", "--sessions", str(sessions), "--rollouts", str(rollouts)]
            + ["--no-progress", "--no-figures", "--out", f"/app/runs/f{start:.0f}"],
            capture_output=True,
            text=True,
            timeout=1800,
        )
        seconds = time.perf_counter() - start
        assert run.returncode == 0, run.stderr[-3000:]
    with (runs / f"f{start:.0f}" / "curves.csv").open() as curves:
        done = sum(1 for _ in curves) - 1  # sessions end at their hit
    return done / seconds


def _sizes_line() -> str:
    """Every image's size against the limit (`tests.containers.IMAGE_LIMIT`)."""
    sizes = {t: image_size(f"archery-{t}:latest") for t in TARGETS}
    largest = max(sizes, key=sizes.__getitem__)
    return (
        "- Image sizes: "
        + ", ".join(f"{t} {s / 1e6:.0f} MB" for t, s in sizes.items())
        + f"; largest {largest} {sizes[largest] / 1e6:.0f} MB (limit {IMAGE_LIMIT / 1e6:.0f} MB)"
    )


def _measure_up(runs: Path, repeats: int, quiet: bool) -> str:
    """`docker-compose up` to the demo's hit, fresh containers and stopped ones, interleaved."""
    fresh, warm = [], []
    with progress_bar(disable=quiet) as bar:
        task = bar.add_task("up to the hit (fresh, warm)", total=2 * repeats)
        for _ in range(repeats):
            fresh.append(_up_to_hit(runs, fresh=True))
            bar.advance(task)
            warm.append(_up_to_hit(runs, fresh=False))
            bar.advance(task)
    Compose("archerybenchup", runs).down()
    return (
        f"- `docker-compose up` to the demo's hit, {repeats} interleaved repeats: fresh "
        f"containers {median_spread(fresh, '.1f', ' s')}, stopped containers started again "
        f"{median_spread(warm, '.1f', ' s')}"
    )


def _measure_rollouts(runs: Path, repeats: int, rollouts: int, quiet: bool) -> str:
    """Wall time per rollout in containers and on `archery up`, alternating which goes first."""
    container, host, ratio = [], [], []
    with progress_bar(disable=quiet) as bar:
        task = bar.add_task("sessions (host, containers)", total=2 * repeats)
        for k in range(repeats):
            order = (("host", _host_session), ("containers", _containers_session))
            got = {}
            for name, session in order if k % 2 == 0 else order[::-1]:
                got[name] = session(runs / f"{name}{k}", rollouts, k)
                bar.advance(task)
            container.append(got["containers"])
            host.append(got["host"])
            ratio.append(got["containers"] / got["host"])
    return (
        f"- Wall time per rollout, rollouts 6–{rollouts} of an ARCHER session "
        f"(--no-until-hit), {repeats} interleaved repeats: containers "
        f"{median_spread([1000 * c for c in container], '.0f', ' ms')}, `archery up` "
        f"{median_spread([1000 * h for h in host], '.0f', ' ms')}; ratio "
        f"{median_spread(ratio, '.2f', '×')} (goal ≤ 1.10×)"
    )


def _measure_fleet(runs: Path, repeats: int, quiet: bool) -> str:
    """The fleet profile's rollouts/s across the routers' link and on one network."""
    fleet, one, ratio = [], [], []
    with progress_bar(disable=quiet) as bar:
        task = bar.add_task("fleet experiments (linked, one network)", total=2 * repeats)
        for k in range(repeats):
            for linked in (k % 2 == 0, k % 2 != 0):
                value = _fleet(runs / f"fleet{k}{linked}", not linked, 2, 6)
                (fleet if linked else one).append(value)
                bar.advance(task)
            ratio.append(fleet[-1] / one[-1])
    return (
        f"- Fleet profile (robot stacks icubSim1 and icubSim2, `experiment --world mesh`, 2 "
        f"ARCHER sessions of at most 6 rollouts, ending at the hit), {repeats} interleaved "
        f"repeats: across the routers' link {median_spread(fleet, '.2f', ' rollouts/s')}, on "
        f"one network and router {median_spread(one, '.2f', ' rollouts/s')}; ratio "
        f"{median_spread(ratio, '.2f', '×')}"
    )


class _Lines(list[str]):
    """The result lines, each printed (stdout) as soon as it is measured."""

    def __init__(self, *lines: str) -> None:
        super().__init__()
        for line in lines:
            self.append(line)

    def append(self, line: str) -> None:
        print(line, flush=True)
        super().append(line)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_containers", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rollouts", type=int, default=20, help="per session (default 20)")
    parser.add_argument("--before", default="a3f3eb1", help="the commit of the one image")
    parser.add_argument(
        "--parts",
        default="build,up,rollout,fleet",
        help="what to measure (default build,up,rollout,fleet; also: sizes)",
    )
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument(
        "--smoke", action="store_true", help="sizes, and one 7-rollout session of each kind"
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.parts, args.repeats, args.rollouts = "sizes,rollout", 1, 7
    problem = engine_problem()
    if problem:
        print(f"bench_containers: {problem}", file=sys.stderr)
        return 1
    base = base_image()
    lines = _Lines(
        f"- Date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        f"- Machine: {os.cpu_count()} cores, {cpu_model()}; base image {base} "
        f"({image_size(base) / 1e6:.0f} MB)",
    )
    parts = set(args.parts.split(","))
    if "build" in parts:
        before = _before_image(args.before, base)
        subprocess.run(["docker", "builder", "prune", "-af"], capture_output=True, check=True)
        for target in TARGETS:
            subprocess.run(["docker", "rmi", "-f", f"archery-{target}:latest"], capture_output=True)
        start = time.perf_counter()
        build_images(base)
        cold_s = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as tmp:  # a code change: the wheel stage again
            context = copy_context(Path(tmp))
            with (context / "protocol" / "errors.py").open("a") as file:
                file.write("# a change\n")
            start = time.perf_counter()
            build_images(base, context=context, tag="warm")
            warm_s = time.perf_counter() - start
        for target in TARGETS:
            subprocess.run(["docker", "rmi", "-f", f"archery-{target}:warm"], capture_output=True)
        lines.append(
            f"- Build of the six images: cold {cold_s:.0f} s (no build cache; pip's index on "
            f"this network), warm after a code change {warm_s:.0f} s"
        )
        sizes = {t: image_size(f"archery-{t}:latest") for t in TARGETS}
        lines.append(
            f"- Image size: before (one image, {args.before}) {before / 1e6:.0f} MB; after: "
            + ", ".join(f"{t} {s / 1e6:.0f} MB" for t, s in sizes.items())
            + f"; largest {max(sizes.values()) / 1e6:.0f} MB"
        )
    if "sizes" in parts:
        build_images(base)  # with the build cache: only what changed is built again
        lines.append(_sizes_line())
    with tempfile.TemporaryDirectory() as tmp:
        runs = Path(tmp)
        if "up" in parts:
            lines.append(_measure_up(runs / "up", args.repeats, args.no_progress))
        if "rollout" in parts:
            lines.append(_measure_rollouts(runs, args.repeats, args.rollouts, args.no_progress))
        if "fleet" in parts:
            lines.append(_measure_fleet(runs, args.repeats, args.no_progress))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
