"""Benchmark of the YARP body: the whole learning loop through YARP only (mesh B) against the
same loop on the simulated robot's own mesh (mesh A), in the same run.

Run `python -m benchmarks.bench_yarp_body [--repeats 5] [--seeds 10]`. Started once for the
whole run, all on loopback: YARP's own `yarpserver` (a configuration folder of the run's own,
`YARP_IP=127.0.0.1`); mesh A, the five services with the simulated iCub at rtf 1 (`archery up
--rtf 1`: `archery robot --rtf 1`); `archery yarp --operator` on mesh A's robot as the YARP
robot /icubSim; mesh B, the five services with `archery robot --body yarp --remote /icubSim
--archery-rpc /icubSim/archery/rpc:i`, `archery camera --source yarp:/icubSim/cam/target:o` and
a detector whose colour model is fitted on mesh A's camera's calibration frame and marks. Both
meshes drive the same simulated robot, mesh B through YARP's ports only, so both run at rtf 1.

Each repeat runs one ARCHER session (learner's `start`, cap 15 rollouts, ended at the first
hit of the 5 cm ring) per seed on each mesh, A and B alternating which goes first from one
session pair to the next (A, B, B, A, ...). Per mesh (median [min, max]):

- wall time per rollout: the median of a session's done → done times (its first rollout, with
  the reset and the move from home, left out), pooled over a repeat's sessions; B / A per
  repeat (goal ≤ 1.5×);
- rollouts to the 5 cm ring over every session of the run (seeds 0 … N − 1; a session that
  misses counted as cap + 1): goal, the same median on both meshes;
- CPU per rollout (user + system, psutil) of the mesh's robot process: mesh B's YARP body
  against mesh A's own robot, over a repeat's sessions divided by their rollouts; B / A per
  repeat (no goal). Also the CPU per rollout of mesh A's robot and the bridge while mesh B's
  sessions run (what serving YARP costs the other side).

A line on stderr per session. `--smoke`: 1 repeat, seeds 0–1.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from archery.apps.learn.client import learner_call, start_args
from archery.apps.learn.follow import follow
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.apps.yarp.command import READY
from archery.apps.yarp.network import free_server_port
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.mesh.subscription import Subscription
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Rollout
from archery.protocol.verbs.camera import CALIBRATION
from archery.services.detector.calibration import fit_from_marks, parse_pixels
from archery.services.learner.journal import read_records
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

__all__ = ["main"]

PREFIX = "/icubSim"
CAP = 15  # rollouts per session at most
WARM_UP_SEED = 1000  # one untimed 2-rollout session per mesh before the repeats
MESHES = ("A", "B")
CLI = [sys.executable, "-m", "archery.apps.cli"]
ROOT = Path(__file__).resolve().parents[1]


def _commit() -> str:
    """The tree's commit, "+ changes" when its tracked files differ from it (a `git archive`
    of a commit: "not a git checkout")."""

    def git(*args: str) -> str:
        run = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
        return run.stdout.strip() if run.returncode == 0 else ""

    commit = git("rev-parse", "--short", "HEAD")
    if not commit:
        return "not a git checkout"
    return commit + (" + changes" if git("status", "--porcelain", "--untracked-files=no") else "")


def _cpu(pid: int) -> float:
    times = psutil.Process(pid).cpu_times()
    return float(times.user + times.system)


def _pid(launcher: Launcher, name: str) -> int:
    child = launcher.children[name]
    assert child.proc is not None
    return child.proc.pid


class YarpServer:
    """YARP's own name server on 127.0.0.1, as a user configures it: a configuration folder that
    names it and `YARP_IP=127.0.0.1`, in this process's environment (the launchers' children
    inherit it) and in this process's YARP network, until `close`."""

    def __init__(self, folder: Path) -> None:
        import yarp

        self.yarp = yarp
        self.port = free_server_port("127.0.0.1")
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "yarp.conf").write_text(f"127.0.0.1 {self.port} yarp\n")
        wanted = {"YARP_CONFIG_HOME": str(folder), "YARP_IP": "127.0.0.1"}
        self.server = subprocess.Popen(
            [str(Path(sys.executable).parent / "yarpserver"), "--read", "--socket", str(self.port)],
            env={**os.environ, **wanted},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # YARP's launcher script and the server it runs: one group
        )
        self.started = False
        deadline = time.monotonic() + 30
        while not self._answers():
            if time.monotonic() > deadline or self.server.poll() is not None:
                os.killpg(self.server.pid, signal.SIGKILL)
                self.server.wait()
                raise RuntimeError(f"yarpserver did not start on 127.0.0.1:{self.port}")
            time.sleep(0.05)
        os.environ.update(wanted)
        yarp.Network.init()
        self.started = True
        contact = yarp.Contact("/root", "tcp", "127.0.0.1", self.port)
        yarp.Network.setNameServerContact(contact)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # YARP's handler would reap our children

    def _answers(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                return True
        except OSError:
            return False

    def close(self) -> None:
        if self.started:
            self.yarp.Network.fini()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.server.pid, signal.SIGTERM)
        try:
            self.server.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(self.server.pid, signal.SIGKILL)
            self.server.wait()


class Setup:
    """The name server, mesh A (its robot at rtf 1), the bridge and mesh B, with a client node on
    each mesh, until `close`."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.yarp: YarpServer | None = None
        self.launchers: dict[str, Launcher] = {}
        self.bridge: subprocess.Popen[bytes] | None = None
        self.nodes: dict[str, Node] = {}
        self.feeds: dict[str, Subscription[Rollout]] = {}
        try:
            self._begin()
        except BaseException:
            self.close()
            raise

    def _begin(self) -> None:
        tmp = self.tmp
        t0 = time.monotonic()
        self.yarp = YarpServer(tmp / "yarp")  # before the launchers: their env names it
        a = Launcher(
            free_tcp_endpoint(),
            "meshA",
            tmp / "logs-a",
            {"robot": ["--rtf", "1"], "learner": ["--runs", str(tmp / "runs-a")]},
        )
        self.launchers["A"] = a
        a.up(180)
        model = self._calibrate(a)
        argv = [*CLI, "yarp", "--connect", a.endpoint, "--robot", "meshA",
                "--yarp-server", f"127.0.0.1:{self.yarp.port}", "--prefix", PREFIX,
                "--operator"]  # fmt: skip
        self.bridge_log = tmp / "bridge.log"
        with self.bridge_log.open("wb") as out:
            self.bridge = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120
        while READY not in self.bridge_log.read_text(errors="replace"):
            if self.bridge.poll() is not None or time.monotonic() > deadline:
                tail = self.bridge_log.read_text(errors="replace")[-2000:]
                raise RuntimeError(f"the bridge is not on YARP: {tail}")
            time.sleep(0.1)
        b = Launcher(
            free_tcp_endpoint(),
            "meshB",
            tmp / "logs-b",
            {
                "robot": ["--body", "yarp", "--remote", PREFIX,
                          "--archery-rpc", f"{PREFIX}/archery/rpc:i"],
                "camera": ["--source", f"yarp:{PREFIX}/cam/target:o"],
                "detector": ["--model", str(model)],
                "learner": ["--runs", str(tmp / "runs-b"), "--service-wait", "60"],
            },
        )  # fmt: skip
        self.launchers["B"] = b
        b.up(180)
        for mesh, launcher in self.launchers.items():
            node = Node(None, launcher.net)
            self.nodes[mesh] = node
            self.feeds[mesh] = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=60)
        self.startup = time.monotonic() - t0

    def _calibrate(self, a: Launcher) -> Path:
        """Mesh B's colour model: fitted, as a lab fits it for a real camera, on mesh A's
        camera's calibration frame with the target's and the arrow's pixels marked."""
        with Node(None, a.net) as node:
            marks = node.call_typed(node.keys.cam_rpc(), CALIBRATION, timeout=60)
        fitted = fit_from_marks(marks.image.to_numpy(), parse_pixels(marks.pixels, "marks"))
        path = self.tmp / "colour-model.json"
        fitted.model.save(path)
        return path

    def pids(self) -> dict[str, int]:
        """The processes whose CPU is measured (looked up again: a restart changes them)."""
        assert self.bridge is not None
        return {
            "robot A": _pid(self.launchers["A"], "robot"),
            "robot B": _pid(self.launchers["B"], "robot"),
            "bridge": self.bridge.pid,
        }

    def session(self, mesh: str, seed: int, cap: int = CAP) -> dict[str, Any]:
        """One ARCHER session on `mesh`: its final status, wall time, done → done times and the
        CPU the measured processes used meanwhile."""
        node, feed = self.nodes[mesh], self.feeds[mesh]
        pids = self.pids()
        cpu0 = {name: _cpu(pid) for name, pid in pids.items()}
        t0 = time.monotonic()
        request = {"algo": "archer", "seed": seed, "rollouts": cap}
        started = learner_call(node, "start", start_args(request), timeout=60)
        final = follow(node, str(started["session"]), feed, lambda m: None, poll=0.2)
        wall = time.monotonic() - t0
        cpu = {name: _cpu(pid) - cpu0[name] for name, pid in pids.items()}
        done = [r for r in read_records(Path(final["journal"]))[0] if isinstance(r, DoneRecord)]
        return {
            "mesh": mesh,
            "seed": seed,
            "final": final,
            "wall": wall,
            "rollouts": len(done),
            "steps": [b.t - a.t for a, b in itertools.pairwise(done)],
            "cpu": cpu,
        }

    def close(self) -> None:
        """The nodes, mesh B, the bridge, mesh A, the name server: in that order."""
        for node in self.nodes.values():
            with contextlib.suppress(Exception):
                node.close()
        if "B" in self.launchers:
            self.launchers["B"].stop_all()
        if self.bridge is not None and self.bridge.poll() is None:
            self.bridge.terminate()
            try:
                self.bridge.wait(60)
            except subprocess.TimeoutExpired:
                self.bridge.kill()
                self.bridge.wait()
        if "A" in self.launchers:
            self.launchers["A"].stop_all()
        if self.yarp is not None:
            self.yarp.close()


def _hit(session: dict[str, Any], cap: int) -> int:
    """Rollouts to the 5 cm ring (cap + 1: missed within the cap)."""
    final = session["final"]
    hit = final.get("hit_at")
    return int(hit) if final.get("ended") == "hit" and hit is not None else cap + 1


def _line(session: dict[str, Any], repeat: int, repeats: int, cap: int) -> str:
    final, steps = session["final"], session["steps"]
    step = f"{statistics.median(steps) * 1e3:.0f} ms" if steps else "–"
    rollouts = max(session["rollouts"], 1)
    hit = _hit(session, cap)
    return (
        f"repeat {repeat + 1}/{repeats}, seed {session['seed']}, mesh {session['mesh']}: "
        f"{final['state']} {final.get('ended')}, {'hit at ' + str(hit) if hit <= cap else 'no hit'}"
        f", {session['rollouts']} rollouts in {session['wall']:.1f} s, {step} per rollout, robot "
        f"CPU {session['cpu']['robot ' + session['mesh']] / rollouts * 1e3:.0f} ms per rollout"
    )


def _per_repeat(sessions: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per mesh, one repeat's figures: wall per rollout (pooled done → done median), CPU per
    rollout of its robot, and (mesh B) of mesh A's robot and the bridge."""
    out: dict[str, dict[str, float]] = {}
    for mesh in MESHES:
        mine = [s for s in sessions if s["mesh"] == mesh]
        rollouts = sum(s["rollouts"] for s in mine)
        steps = [x for s in mine for x in s["steps"]]

        def cpu(name: str, of: list[dict[str, Any]] = mine, n: int = rollouts) -> float:
            return sum(s["cpu"][name] for s in of) / max(n, 1)

        out[mesh] = {
            "step": statistics.median(steps) if steps else float("nan"),
            "session": sum(s["wall"] for s in mine) / max(rollouts, 1),
            "cpu": cpu(f"robot {mesh}"),
            "cpu_robot_a": cpu("robot A"),
            "cpu_bridge": cpu("bridge"),
        }
    return out


def report(runs: list[list[dict[str, Any]]], cap: int) -> None:
    figures = [_per_repeat(r) for r in runs]
    a = [f["A"] for f in figures]
    b = [f["B"] for f in figures]
    every = [s for r in runs for s in r]
    print(f"\nbench_yarp_body results (median [min, max] over {len(runs)} repeats):")
    ratio = [y["step"] / x["step"] for x, y in zip(a, b, strict=True)]
    print(
        f"  wall per rollout (done → done), B (YARP body) / A (own robot), rtf 1: "
        f"×{median_spread(ratio, '.3f')} ({median_spread([y['step'] * 1e3 for y in b], '.0f')} "
        f"ms vs {median_spread([x['step'] * 1e3 for x in a], '.0f')} ms; goal ≤ 1.5×: "
        f"{'met' if statistics.median(ratio) <= 1.5 else 'NOT met'})"
    )
    whole = [y["session"] / x["session"] for x, y in zip(a, b, strict=True)]
    print(
        f"  session wall / rollouts (start and first rollout included), B / A: "
        f"×{median_spread(whole, '.3f')} ({median_spread([y['session'] for y in b], '.2f')} s vs "
        f"{median_spread([x['session'] for x in a], '.2f')} s)"
    )
    hits = {m: [_hit(s, cap) for s in every if s["mesh"] == m] for m in MESHES}
    seeds = sorted({s["seed"] for s in every})
    same = statistics.median(hits["A"]) == statistics.median(hits["B"])
    for mesh, name in (("B", "through YARP (mesh B)"), ("A", "on the own robot (mesh A)")):
        got = hits[mesh]
        print(
            f"  rollouts to the 5 cm ring, ARCHER seeds {seeds[0]}–{seeds[-1]} {name}: "
            f"{median_spread(got, 'g')}, {sum(h <= cap for h in got)}/{len(got)} hit within {cap}"
        )
    print(f"  same median: {'yes (goal met)' if same else 'no (goal NOT met)'}")
    cpu = [y["cpu"] / x["cpu"] for x, y in zip(a, b, strict=True)]
    print(
        f"  robot process CPU per rollout, YARP body (B) / own robot (A): "
        f"×{median_spread(cpu, '.3f')} ({median_spread([y['cpu'] * 1e3 for y in b], '.0f')} ms "
        f"vs {median_spread([x['cpu'] * 1e3 for x in a], '.0f')} ms; no goal)"
    )
    print(
        f"  while B's sessions run, per rollout: mesh A's robot "
        f"{median_spread([y['cpu_robot_a'] * 1e3 for y in b], '.0f')} ms CPU, the bridge "
        f"{median_spread([y['cpu_bridge'] * 1e3 for y in b], '.0f')} ms"
    )


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_yarp_body", description=__doc__
    )
    parser.add_argument("--repeats", type=int, default=5, help="repeats of every seed (≥ 5)")
    parser.add_argument("--seeds", type=int, default=10, help="ARCHER seeds 0 … N − 1")
    parser.add_argument("--smoke", action="store_true", help="1 repeat, seeds 0–1")
    parser.add_argument("--keep", metavar="DIR", help="keep the logs and journals in DIR")
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.seeds = 1, 2
    print(
        f"bench_yarp_body: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {cpu_model()}, "
        f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}, commit {_commit()}; "
        f"{args.repeats} repeats of ARCHER seeds 0–{args.seeds - 1}, cap {CAP}",
        flush=True,
    )
    begin = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench-yarp-body-") as folder:
        tmp = Path(args.keep or folder)
        tmp.mkdir(parents=True, exist_ok=True)
        setup = Setup(tmp)
        runs: list[list[dict[str, Any]]] = []
        try:
            print(f"  started in {setup.startup:.0f} s", file=sys.stderr, flush=True)
            for mesh in MESHES:  # untimed: each mesh's first session pays its warm-up
                setup.session(mesh, WARM_UP_SEED, 2)
            for repeat in range(args.repeats):
                sessions: list[dict[str, Any]] = []
                for seed in range(args.seeds):
                    for mesh in MESHES if (repeat + seed) % 2 == 0 else MESHES[::-1]:
                        session = setup.session(mesh, seed)
                        sessions.append(session)
                        print("  " + _line(session, repeat, args.repeats, CAP), file=sys.stderr,
                              flush=True)  # fmt: skip
                runs.append(sessions)
                got = _per_repeat(sessions)
                print(
                    f"  repeat {repeat + 1}: wall per rollout B / A ×"
                    f"{got['B']['step'] / got['A']['step']:.3f} ({got['B']['step'] * 1e3:.0f} vs "
                    f"{got['A']['step'] * 1e3:.0f} ms); robot CPU per rollout B / A ×"
                    f"{got['B']['cpu'] / got['A']['cpu']:.3f} ({got['B']['cpu'] * 1e3:.0f} vs "
                    f"{got['A']['cpu'] * 1e3:.0f} ms)",
                    flush=True,
                )
        finally:
            setup.close()
    report(runs, CAP)
    print(f"  run time {time.monotonic() - begin:.0f} s (start-up {setup.startup:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
