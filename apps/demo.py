"""The demo (`make demo`): start the mesh, learn with ARCHER until the 5 cm ring is hit, show it.

It starts a router and the five services on this machine (as `archery up` does, on a free
port), runs one session as `archery learn` does with a live table per rollout (θ, r, distance,
hit), stops everything cleanly, and prints where the session's files are: `runs/<session>/`
with `journal.jsonl`, `report.png` (impacts on the target face and distance per rollout) and
`hit.png` (the camera frame of the final hit with the detector's overlay), and `shot.mp4` with
its contact sheet `shot.png` (the hit seen from the side, `archery film`). With `--shot whole`
every rollout grasps, nocks and draws its arrow, and the film shows that movement as
`runs/logs/whole-shot.mcap`, recorded meanwhile, saw it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.table import Table

from archery.apps.film.film import film_hit, film_ready, hit_video
from archery.apps.learn.client import learner_call, start_args
from archery.apps.learn.follow import SessionLost, follow, result_line
from archery.apps.up.command import start_observer
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher, LaunchError
from archery.mesh.cliargs import ArgumentParser, check_writable_dir, count, seconds
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.exit_status import for_error
from archery.protocol.journal_records import AbortedRecord, DoneRecord
from archery.protocol.messages import Rollout
from archery.services.learner.algorithms.registry import ALGORITHMS

__all__ = ["main"]


class Progress:
    """A rich table with one row per finished attempt."""

    def __init__(self, title: str) -> None:
        self.table = Table(title=title, expand=False)
        for name, justify in (
            ("rollout", "right"),
            ("θ x, y, z (cm)", "left"),
            ("r right, up (cm)", "left"),
            ("|r| (cm)", "right"),
            ("", "left"),
        ):
            self.table.add_column(name, justify=justify, no_wrap=True)  # type: ignore[arg-type]  # rich's JustifyMethod literals
        self.done = 0

    def add(self, message: Rollout) -> None:
        """Add the row of a done or aborted attempt."""
        record = message.record
        theta = ", ".join(f"{100 * v:.2f}" for v in record.theta)
        if isinstance(record, AbortedRecord):
            self.table.add_row("–", theta, "–", "–", f"[yellow]aborted {record.note()[:60]}")
        elif isinstance(record, DoneRecord):
            self.done += 1
            r = record.r_m
            distance = 100 * (r[0] ** 2 + r[1] ** 2) ** 0.5
            mark = "[bold green]HIT" if record.hit else ""
            style = "bold green" if record.hit else ""
            self.table.add_row(
                str(self.done),
                theta,
                f"{100 * r[0]:+.1f}, {100 * r[1]:+.1f}",
                f"[{style}]{distance:.1f}" if style else f"{distance:.1f}",
                mark,
            )


#: The robot's real-time factor for the whole shot: at rtf 0 its world states, which the film
#: of the movement is made of, go out at most `--world-rate` times per wall second; paced, at
#: `--world-rate` per simulated second, so the movement films smoothly, 4× faster than life.
WHOLE_SHOT_RTF = 4.0


def _shot_flags(shot: str) -> list[str]:
    """The robot's flags for `shot` (posture, or whole: paced at `WHOLE_SHOT_RTF`)."""
    return ["--shot", shot] + (["--rtf", f"{WHOLE_SHOT_RTF:g}"] if shot == "whole" else [])


def run_demo(args: argparse.Namespace, console: Console) -> int:
    """Start the mesh, run the session with a live table, stop the mesh; the exit status."""
    endpoint = args.endpoint or free_tcp_endpoint()
    runs = Path(args.runs)
    launcher = Launcher(
        endpoint,
        "icubSim",
        runs / "logs",
        {
            "robot": ["--seed", str(args.seed), *_shot_flags(args.shot)],
            "learner": ["--runs", str(runs)],
        },
    )
    with console.status(f"starting a router on {endpoint} and {', '.join(SERVICES)} …"):
        try:
            took = launcher.up(args.timeout)
        except (LaunchError, ConfigError) as exc:
            console.print(f"[red]archery demo: {exc}")
            return for_error(exc.code)
    console.print(f"mesh up in {took:.1f} s: router on {endpoint}, {', '.join(SERVICES)}")
    recording = recorder = None
    if args.shot == "whole":  # the film shows the movement as recorded: the journal has θ only
        recording = runs / "logs" / "whole-shot.mcap"
        robot = launcher.net.robot
        argv = ["record", "--out", str(recording), "--no-transforms", "--force"]
        argv += [f"{robot}/world/state:o", f"{robot}/learner/rollout:o"]
        try:
            recorder = start_observer(launcher, "recorder", argv, b"archery record: recording")
        except LaunchError as exc:
            console.print(f"[red]archery demo: {exc}")
            launcher.stop_all()
            return 1
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)  # also: their ports are known to this node
            request = {"algo": args.algo, "rollouts": args.rollouts, "seed": args.seed}
            status = learner_call(node, "start", start_args(request), timeout=60)
            session = status["session"]
            progress = Progress(f"{args.algo}: session {session}")
            start = time.monotonic()
            with Live(progress.table, console=console, refresh_per_second=8):
                final = follow(node, session, rollouts, progress.add)
            console.print()  # the table's last line ends here when output is not a terminal
            wall = time.monotonic() - start
    except (ArcheryError, SessionLost) as exc:
        console.print(f"[red]archery demo: {exc}")
        dead = launcher.first_exit()
        if dead is not None:
            console.print(launcher.describe_exit(dead))
        return 1
    finally:
        with console.status("stopping the services …"):
            if recorder is not None:
                recorder.terminate()  # the recording is closed before the film reads it
                recorder.wait(60)
            codes = launcher.stop_all()
    video = hit_video(final)
    final["video"] = None if video is None else str(video)
    outcome = _summary(console, final, wall, codes)  # the result first: filming cannot lose it
    if video is not None and film_hit(final, recording=recording):
        print(
            f"archery demo: the hit filmed into {video}", file=sys.stderr
        )  # stdout ends with the result
    return outcome


def _summary(
    console: Console, final: dict[str, Any], wall: float, codes: dict[str, int | None]
) -> int:
    hit_at = final.get("hit_at")
    rollouts = final.get("rollouts")
    if final.get("state") == "finished" and hit_at is not None:
        console.print(
            f"[bold green]Hit the 5 cm ring at rollout {hit_at}[/] "
            f"({rollouts} rollouts, {final.get('aborted', 0)} aborted attempts, {wall:.1f} s; "
            f"final distance {100 * final['final_distance_m']:.1f} cm)."
        )
    else:
        console.print(
            f"[yellow]No hit: session {final.get('state')} after {rollouts} rollouts "
            f"{final.get('cause', '')}"
        )
    console.print(f"  journal:   {final.get('journal')}")
    console.print(f"  report:    {final.get('report')}")
    console.print(f"  hit frame: {final.get('hit_frame')}")
    console.print(f"  video:     {final.get('video')}")
    unclean = {n: c for n, c in codes.items() if c != 0}
    console.print(
        "services stopped cleanly" if not unclean else f"[yellow]unclean stops: {unclean}"
    )
    print(result_line(final), flush=True)
    return 0 if final.get("state") == "finished" and hit_at is not None and not unclean else 1


def _positive(text: str) -> int:
    value = count(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive integer")
    return value


def _check_demo_listen(endpoint: str) -> None:
    """Raise ConfigError unless the demo's router may listen on `endpoint`: a valid endpoint on
    this machine only (the demo takes neither --secure nor --insecure-network: a mesh that other
    machines reach is `archery up`'s, with `archery learn` beside it)."""
    try:
        NetConfig(connect=(), listen=(endpoint,), mode="router")
    except ConfigError as exc:
        if "plain mode trusts every peer" not in str(exc):
            raise
        raise ConfigError(
            f"--listen {endpoint}: the demo's mesh is for this machine only; give a loopback "
            "endpoint (e.g. tcp/127.0.0.1:7447), or, for a mesh other machines reach, run "
            "`archery up --secure DIR --listen tls/HOST:PORT` and `archery learn` beside it"
        ) from None


def main(argv: list[str] | None = None) -> int:
    """Run the demo; exit status 0 when the ring was hit and everything stopped cleanly."""
    parser = ArgumentParser(prog="archery demo", description=__doc__)
    parser.add_argument(
        "--algo", default="archer", choices=ALGORITHMS, help="the learner (default archer)"
    )
    parser.add_argument("--rollouts", type=_positive, default=30, help="budget of rollouts")
    parser.add_argument("--seed", type=count, default=0, help="seed of the learner and the shots")
    parser.add_argument("--runs", default="runs", help="where the session directory goes")
    parser.add_argument(
        "--shot",
        choices=("posture", "whole"),
        default="posture",
        help="posture (default: the arrow is placed on the string) or whole (every rollout "
        "grasps, nocks and draws it, the demonstration's movement as DMPs; the imitate extra)",
    )
    parser.add_argument(
        "--listen",
        "--endpoint",
        dest="endpoint",
        metavar="ENDPOINT",
        help="where the demo's router listens, tcp/HOST:PORT (default: a free local port)",
    )
    parser.add_argument("--timeout", type=seconds, default=120.0, help="start-up limit (s)")
    args = parser.parse_args(argv)
    try:
        if args.endpoint:
            _check_demo_listen(args.endpoint)
        check_writable_dir(Path(args.runs), "--runs", create=True)
        film_ready()  # the hit is filmed: a backend that cannot start fails now, not then
    except ConfigError as exc:
        print(f"archery demo: {exc}", file=sys.stderr)
        return 2
    console = Console()
    console.print(
        "[bold]archery demo[/]: a simulated iCub learns archery (Kormushev et al. 2010) "
        "over a Zenoh mesh"
    )
    return run_demo(args, console)


if __name__ == "__main__":
    sys.exit(main())
