"""Long sessions: one session of `--rollouts` rollouts per learner at rtf 0 on `archery up` (with
its recorder, `--record`, and a dashboard polled as a browser would), on this tree and on an
earlier commit (`--before`, default: before the journal's checkpoints) in the same run, the
earlier one for as far as it gets.

    .venv/bin/python -m benchmarks.bench_long [--rollouts 10000] [--algos archer,power]
        [--before COMMIT] [--no-before] [--repeats 5] [--smoke]

Per session it reports: the journal's bytes per done rollout (and of the largest line), the
resident memory (RSS, MB) of every process of the mesh, the recorder's file and the dashboard at
each mark (`--marks`, default 1,000, 5,000 and 10,000 done rollouts), the wall time per rollout
over the first and the last 500 (from the journal's stamps; goal: last / first ≤ 1.1), and how
the session ended. Then, on each session's journal cut after done rollout `--resume-at` (default
9,000, or the session's last but one hundred when it ended sooner), the time to resume it
(`services.learner.session_setup.reopened_session` in a fresh process: read, check, rebuild the
learner; goal ≤ 5 s) and `archery report` on the whole journal, each `--repeats` times with the
trees interleaved. `--smoke`: 60-rollout sessions of ARCHER on this tree only, marks at 20, 40
and 60, windows of 20 and one repeat (seconds; nothing recorded). One session per learner and
tree: a 10,000-rollout session takes about 20 minutes here.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import psutil

from archery.mesh.netflags import NetConfig
from archery.mesh.node import open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Rollout
from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, interleaved, tree_at

__all__ = ["main"]

BEFORE = "ca34a87"  # before the checkpoints: every done record holds the learner's whole state
SERVICES = ("robot", "camera", "detector", "controller", "learner")
_RESUME = """
import shutil, sys, tempfile, time
from pathlib import Path
from archery.services.learner.session_setup import reopened_session
with tempfile.TemporaryDirectory() as tmp:
    path = Path(tmp) / "journal.jsonl"
    shutil.copy(sys.argv[1], path)
    start = time.perf_counter()
    journal, learner, config = reopened_session(path)
    took = time.perf_counter() - start
    journal.close()
print(took)
"""


def _free_port() -> int:
    return int(free_tcp_endpoint().rsplit(":", 1)[1])


def _rss_mb(proc: psutil.Process) -> float:
    try:
        return proc.memory_info().rss / 1e6
    except psutil.Error:
        return float("nan")


def _name(proc: psutil.Process) -> str:
    """The service a child of `archery up` runs (its verb), e.g. robot, router, record."""
    try:
        argv = proc.cmdline()
    except psutil.Error:
        return "?"
    verb = next((a for a in argv if a in (*SERVICES, "router", "record", "dashboard")), None)
    return verb or "up"


class _Poller(threading.Thread):
    """Asks the dashboard for its state every `period` s, as an open browser tab does."""

    def __init__(self, port: int, period: float = 2.0) -> None:
        super().__init__(daemon=True)
        self.url = f"http://127.0.0.1:{port}/api/state"
        self.period = period
        self.stop = threading.Event()
        self.answers = 0

    def run(self) -> None:
        while not self.stop.wait(self.period):
            try:
                with urllib.request.urlopen(self.url, timeout=10) as reply:
                    reply.read()
                self.answers += 1
            except OSError:
                pass


def _session(
    env: dict[str, str], folder: Path, algo: str, rollouts: int, marks: list[int]
) -> dict[str, Any]:
    """One long session on a fresh mesh of the tree `env` runs; its figures."""
    endpoint = free_tcp_endpoint()
    runs, mcap = folder / "runs", folder / "run.mcap"
    argv = [sys.executable, "-m", "archery.apps.cli"]
    quiet = {"stdin": subprocess.DEVNULL, "stdout": subprocess.DEVNULL, "env": env, "cwd": folder}
    up = subprocess.Popen(
        [*argv, "up", "--listen", endpoint, "--runs", str(runs), "--record", str(mcap)],
        stderr=subprocess.DEVNULL,
        **quiet,  # type: ignore[call-overload]
    )
    samples: dict[int, dict[str, float]] = {}
    count = [0]
    learn: subprocess.Popen[str] | None = None
    dashboard: subprocess.Popen[Any] | None = None
    poller: _Poller | None = None
    try:
        with open_node(NetConfig(connect=(endpoint,)), 60) as node:
            node.wait_alive(SERVICES, timeout=180)
            port = _free_port()
            dashboard = subprocess.Popen(
                [*argv, "dashboard", "--connect", endpoint, "--port", str(port)],
                stderr=subprocess.DEVNULL,
                **quiet,  # type: ignore[call-overload]
            )
            poller = _Poller(port)
            poller.start()
            watched = dashboard

            def on_rollout(message: Rollout) -> None:
                if isinstance(message.record, DoneRecord):
                    count[0] = message.record.rollout
                    if count[0] in marks:
                        samples[count[0]] = _sample(up, watched, mcap, runs)

            node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo", callback=on_rollout)
            learn = subprocess.Popen(
                [*argv, "learn", "--connect", endpoint, "--algo", algo, "--rollouts",
                 str(rollouts), "--no-until-hit", "--quiet", "--no-film", "--seed", "0"],
                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                text=True, env=env, cwd=folder,
            )  # fmt: skip
            out, err = learn.communicate()
            samples.setdefault(count[0], _sample(up, watched, mcap, runs))
    finally:
        if poller is not None:
            poller.stop.set()
        if learn is not None and learn.poll() is None:
            learn.kill()
        for proc in (dashboard, up):
            if proc is not None:
                proc.send_signal(signal.SIGINT)
                proc.wait(120)
    lines = [line for line in out.splitlines() if line.startswith("{")]
    result = json.loads(lines[-1]) if lines else {"status": "no result", "cause": err[-500:]}
    journal = next(runs.glob("*/journal.jsonl"))
    return {
        "algo": algo,
        "result": result,
        "journal": str(journal),
        "samples": samples,
        "dashboard_answers": 0 if poller is None else poller.answers,
    } | _journal_figures(journal)


def _sample(
    up: subprocess.Popen[Any], dashboard: subprocess.Popen[Any], mcap: Path, runs: Path
) -> dict[str, float]:
    """RSS (MB) of every process of the mesh and the dashboard; the recording's and the
    journal's sizes (MB)."""
    root = psutil.Process(up.pid)  # `up` itself holds the recorder (`--record`)
    procs = [*root.children(recursive=True), psutil.Process(dashboard.pid)]
    sample = {f"rss_{_name(p)}": _rss_mb(p) for p in procs} | {"rss_up+recorder": _rss_mb(root)}
    sample["mcap_mb"] = mcap.stat().st_size / 1e6 if mcap.exists() else 0.0
    journals = list(runs.glob("*/journal.jsonl"))
    sample["journal_mb"] = journals[0].stat().st_size / 1e6 if journals else 0.0
    return sample


def _journal_figures(journal: Path) -> dict[str, Any]:
    """Bytes per done rollout, the largest line, and the done records' stamps (s)."""
    stamps, largest, size = [], 0, journal.stat().st_size
    with journal.open("rb") as file:
        for line in file:
            largest = max(largest, len(line))
            if b'"record":"done"' in line[:40]:
                stamps.append(json.loads(line)["t"])
    return {"bytes": size, "done": len(stamps), "largest_line": largest, "stamps": stamps}


def _per_rollout_ms(stamps: list[float], window: int) -> tuple[float, float]:
    """Wall time per rollout (ms) over the first and the last `window` done rollouts."""
    first = (stamps[window] - stamps[0]) / window
    last = (stamps[-1] - stamps[-window - 1]) / window
    return 1e3 * first, 1e3 * last


def _cut(journal: Path, rollout: int, dest: Path) -> Path:
    """A copy of `journal` up to its done rollout `rollout` (the learner killed right after)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    with journal.open("rb") as src, dest.open("wb") as out:
        for line in src:
            out.write(line)
            if b'"record":"done"' in line[:40] and json.loads(line)["rollout"] == rollout:
                break
    return dest


def _timed(argv: list[str], env: dict[str, str], cwd: Path) -> float:
    start = time.perf_counter()
    run = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, timeout=1800)
    if run.returncode != 0:
        raise RuntimeError(f"{argv[2:4]} failed: {run.stderr[-1000:]}")
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0 (1 if a session of this tree did not finish)."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_long", description=__doc__)
    parser.add_argument("--rollouts", type=int, default=10_000)
    parser.add_argument("--algos", default="archer,power")
    parser.add_argument("--before", default=BEFORE, help=f"the earlier commit (default {BEFORE})")
    parser.add_argument("--no-before", action="store_true", help="this tree only")
    parser.add_argument("--marks", default="1000,5000,10000", help="done rollouts to sample at")
    parser.add_argument("--window", type=int, default=500, help="rollouts per ms window")
    parser.add_argument("--resume-at", type=int, default=9000)
    parser.add_argument("--repeats", type=int, default=5, help="of the resume and report times")
    parser.add_argument("--smoke", action="store_true", help="60 ARCHER rollouts, this tree")
    args = parser.parse_args(argv)
    if args.smoke:
        args.rollouts, args.algos, args.no_before, args.marks = 60, "archer", True, "20,40,60"
        args.window, args.resume_at, args.repeats = 20, 50, 1
    marks = [int(m) for m in args.marks.split(",")]
    header()
    with tempfile.TemporaryDirectory(prefix="bench-long-") as tmp:
        trees = [("after", env_for(ROOT))]
        if not args.no_before:
            (Path(tmp) / "before-tree").mkdir()
            before = tree_at(args.before, Path(tmp) / "before-tree")
            trees.insert(0, ("before", env_for(before)))
        sessions: dict[tuple[str, str], dict[str, Any]] = {}
        for k, algo in enumerate(args.algos.split(",")):
            for name, env in trees if k % 2 == 0 else trees[::-1]:
                folder = Path(tmp) / f"{name}-{algo}"
                folder.mkdir()
                print(f"session: {algo} on {name} …", file=sys.stderr, flush=True)
                sessions[(name, algo)] = run = _session(env, folder, algo, args.rollouts, marks)
                _print_session(name, run, args.window)
        _print_times(sessions, dict(trees), args, Path(tmp))
        failed = [a for (n, a), s in sessions.items() if n == "after" and s["done"] < args.rollouts]
    return 1 if failed else 0


def _print_session(name: str, run: dict[str, Any], window: int) -> None:
    done, result = run["done"], run["result"]
    print(
        f"- {run['algo']} on {name}: {done} rollouts, {result.get('status')}"
        + (f" ({str(result.get('cause'))[:200]})" if result.get("status") != "finished" else "")
        + f"; journal {run['bytes'] / max(done, 1):.0f} B per rollout, largest line "
        f"{run['largest_line']} B; dashboard answered {run['dashboard_answers']} polls"
    )
    if done > 2 * window:
        first, last = _per_rollout_ms(run["stamps"], window)
        print(
            f"  ms per rollout: first {window} {first:.0f}, last {window} {last:.0f}: "
            f"×{last / first:.2f} (goal ≤ 1.1)"
        )
    for mark, sample in sorted(run["samples"].items()):
        rss = ", ".join(
            f"{k[4:]} {v:.0f}" for k, v in sorted(sample.items()) if k.startswith("rss")
        )
        print(
            f"  at {mark}: RSS MB {rss}; recording {sample['mcap_mb']:.0f} MB, journal "
            f"{sample['journal_mb']:.1f} MB"
        )


def _print_times(
    sessions: dict[tuple[str, str], dict[str, Any]],
    envs: dict[str, dict[str, str]],
    args: argparse.Namespace,
    tmp: Path,
) -> None:
    """Resume and report times, the trees interleaved per learner."""
    for algo in args.algos.split(","):
        cuts, times = {}, {}
        for name in envs:
            run = sessions[(name, algo)]
            at = min(args.resume_at, run["done"] - min(100, run["done"] // 2))
            cuts[name] = (at, _cut(Path(run["journal"]), at, tmp / f"cut-{name}-{algo}.jsonl"))
            times[name] = {"resume": [], "report": []}
        refused: dict[str, str] = {}
        for _, name, env in interleaved(args.repeats, list(envs.items())):
            at, cut = cuts[name]
            try:  # run in `tmp`: `python -c` puts its folder first on the path
                took = _run_out([sys.executable, "-c", _RESUME, str(cut)], env, tmp)
                times[name]["resume"].append(float(took))
            except RuntimeError as exc:  # e.g. a journal too big to take the rollouts left
                refused[name] = str(exc).strip().splitlines()[-1][:300]
            report = tmp / f"report-{name}-{algo}"
            shutil.rmtree(report, ignore_errors=True)
            report.mkdir()
            shutil.copy(sessions[(name, algo)]["journal"], report / "journal.jsonl")
            times[name]["report"].append(
                _timed(
                    [
                        sys.executable,
                        "-m",
                        "archery.apps.cli",
                        "report",
                        "--no-progress",
                        str(report),
                    ],
                    env,
                    tmp,
                )
            )
        for name in envs:
            at, _ = cuts[name]
            if name in refused:
                print(f"- {algo} on {name}: resume after {at} rollouts refused: {refused[name]}")
                times[name]["resume"] = [float("nan")]
            print(
                f"- {algo} on {name}: resume after {at} rollouts "
                f"{median_spread(times[name]['resume'], '.2f', ' s')} (goal ≤ 5 s); `archery "
                f"report` on the {sessions[(name, algo)]['done']}-rollout journal "
                f"{median_spread(times[name]['report'], '.1f', ' s')}; {args.repeats} repeats"
            )


def _run_out(argv: list[str], env: dict[str, str], cwd: Path) -> str:
    run = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, timeout=1800)
    if run.returncode != 0:
        raise RuntimeError(f"failed: {run.stderr[-1000:]}")
    return run.stdout.strip().splitlines()[-1]


if __name__ == "__main__":
    sys.exit(main())
