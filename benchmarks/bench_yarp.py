"""Benchmark of `archery yarp` against the mesh it bridges, with YARP's own code on the other side,
in plain mode and in secure mode (YARP's AuthHMAC with the deployment's key), and the time a
crashed bridge takes to answer again under `archery up --yarp`.

Run `python -m benchmarks.bench_yarp [--repeats 5] [--window 10] [--calls 20] [--plain |
--secure]`. Part 1: two meshes at once (`archery up`, rtf 1), one plain and one secure
(`archery keys init DIR`, `archery up --secure DIR` on a free `tls/` endpoint), each with
`archery yarp --operator` (in secure mode `--secure DIR`: every YARP connection authenticated)
running its own name server, and a YARP client of the benchmark's own per mode in a process of
its own (YARP reads its key once per process: the secure one's configuration folder holds
`DIR/yarp/auth.conf`). Each figure over `--repeats` repeats, the modes alternating within each
repeat, the order swapping (median [min, max]):

- the encoder stream: joint states a YARP reader gets on `/ROBOT/left_arm/state:o` and
  `stateExt:o` in a window, against those the mesh's own `state:o` delivers to a node's
  subscriber in the same window (goal ≥ 95 %);
- a `positionMove` round trip through YARP's `remote_controlboard` against the mesh's own
  `positionMove` verb, the two alternating call by call (goal ≤ 1.5×);
- the bridge's CPU (user + system) in a window with one YARP reader on each of its output
  ports against one with none, the two alternating (no goal).

Part 2: `archery up --yarp` (read-only bridge, its own name server; the restart policy's
defaults), plain and secure at once, each bridge crashed `--repeats` times with YARP 3.5's own
NULL dereference (`CONNECT` then `r` on `state:o`; in secure mode after YARP's handshake with
the key), the modes alternating. Each crash comes after the bridge has run `healthy_after`
(10 s), as a rare crash does: `up` then waits its first back-off (0.5 s) before the restart.
Timed from the crash's bytes sent to `remote_controlboard` (the key's client in secure mode)
reading the encoders again, polled once `up` says the bridge is back (goal ≤ 5 s).

`--smoke`: 1 repeat, 1 s windows, 3 calls, one crash per mode.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil

from archery.apps.up.restart_policy import RestartPolicy
from archery.apps.yarp.auth import YarpKey, authenticate, read_key
from archery.mesh.credentials import YARP_AUTH
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node, open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import SERVICES
from archery.protocol.verbs import robot as rv
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.yarp_setup import crash_output_port

__all__ = ["main"]

MODES = ("plain", "secure")
ROBOTS = {"plain": "benchyarp", "secure": "benchyarpsec"}  # one robot name per mesh
ARM = "left_arm"
ELBOW = 3
CLI = [sys.executable, "-m", "archery.apps.cli"]
ROOT = Path(__file__).resolve().parents[1]
SERVER = re.compile(r"name server ([\d.]+):(\d+)")
SAY = "@@ "  # a worker's answer line (YARP writes lines of its own to stdout)
POLICY = RestartPolicy()  # `archery up`'s defaults: what the crashes run under


def outputs(robot: str) -> list[str]:
    """The bridge's output ports."""
    return [
        *(f"/{robot}/{part}/{leaf}" for part in PARTS for leaf in ("state:o", "stateExt:o")),
        f"/{robot}/cam/target:o",
        f"/{robot}/detector/hit:o",
        f"/{robot}/world/events:o",
    ]


def _yarp_env(folder: Path) -> dict[str, str]:
    """The environment of a YARP process of the benchmark's: YARP's configuration in `folder`
    (private to the benchmark), its ports on loopback."""
    return {**os.environ, "YARP_CONFIG_HOME": str(folder), "YARP_IP": "127.0.0.1"}


def _folder(path: Path, server: tuple[str, int] | None, key: Path | None) -> Path:
    """A YARP configuration folder: the name server `server` and a copy of the key `key`, as a
    user installs them (either may be left out)."""
    path.mkdir(parents=True)
    if server is not None:
        (path / "yarp.conf").write_text(f"{server[0]} {server[1]} yarp\n")
    if key is not None:
        shutil.copy(key, path / "auth.conf")
    return path


class Lines:
    """A child's stdout line by line as it comes, each with the time it was read."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[tuple[float, str]] = []
        self.cond = threading.Condition()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self.cond:
                self.lines.append((time.monotonic(), line.rstrip("\n")))
                self.cond.notify_all()

    def wait(self, start: str, after: int = 0, timeout: float = 180) -> tuple[int, float, str]:
        """The first line from index `after` on that starts with `start`: (its index + 1, the
        time it was read, it)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for i, (at, line) in enumerate(self.lines[after:], start=after):
                    if line.startswith(start):
                        return i + 1, at, line
                left = deadline - time.monotonic()
                if left <= 0 or not self.reader.is_alive():  # late, or it said all it will
                    said = [line for _, line in self.lines[-5:]]
                    raise RuntimeError(f"no {start!r} from {self.proc.args!r}: {said}")
                self.cond.wait(min(left, 0.5))


def _server(line: str) -> tuple[str, int]:
    found = SERVER.search(line)
    if found is None:
        raise RuntimeError(f"no name server in {line!r}")
    return found[1], int(found[2])


class Deployment:
    """A mode's credentials and endpoint: plain (`tcp/`, no flags) or secure (`archery keys
    init` into `tmp`, `tls/`, `--secure DIR`)."""

    def __init__(self, mode: str, tmp: Path) -> None:
        self.mode, self.robot = mode, ROBOTS[mode]
        self.dir: Path | None = None
        self.flags: list[str] = []
        self.key: Path | None = None
        if mode == "secure":
            self.dir = tmp / "deploy"
            subprocess.run(
                [*CLI, "keys", "init", str(self.dir), "--robot", self.robot],
                check=True,
                capture_output=True,
                timeout=120,
            )
            self.flags, self.key = ["--secure", str(self.dir)], self.dir / YARP_AUTH

    def endpoint(self) -> str:
        tcp = free_tcp_endpoint()
        return tcp.replace("tcp/", "tls/") if self.dir is not None else tcp

    def yarp_key(self) -> YarpKey | None:
        return read_key(self.dir) if self.dir is not None else None


class Worker:
    """The benchmark's YARP client (and, for part 1, a mesh node) in a process of its own,
    configured by `folder`; asked one JSON line at a time."""

    def __init__(self, folder: Path, log: Path, **spec: Any) -> None:
        self.log = log
        with log.open("w") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "benchmarks.bench_yarp", "--worker", json.dumps(spec)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
                env=_yarp_env(folder),
                cwd=ROOT,
            )
        self._answer()

    def _answer(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith(SAY):
                answer: dict[str, Any] = json.loads(line[len(SAY) :])
                if "error" in answer:
                    raise RuntimeError(f"the YARP client: {answer['error']}")
                return answer
        tail = self.log.read_text(errors="replace")[-800:]
        raise RuntimeError(f"the YARP client ended: {tail}")

    def ask(self, **command: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()
        return self._answer()

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, RuntimeError):
                self.ask(do="quit")
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(120)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Bridged:
    """Part 1 for one mode: the mesh, `archery yarp --operator` on a name server of its own,
    and the benchmark's YARP client, until `close`."""

    def __init__(self, mode: str, tmp: Path) -> None:
        self.mode = mode
        self.procs: list[subprocess.Popen[str]] = []
        self.worker: Worker | None = None
        try:
            self._begin(tmp)
        except BaseException:
            self.close()
            raise

    def _begin(self, tmp: Path) -> None:
        dep = Deployment(self.mode, tmp)
        endpoint = dep.endpoint()
        empty = _folder(tmp / "yarp-none", None, None)  # no name server configured: its own
        up = [*CLI, "up", "--listen", endpoint, "--robot", dep.robot, "--rtf", "1",
              "--logs", str(tmp / "logs"), "--runs", str(tmp / "runs"), *dep.flags]  # fmt: skip
        self.procs.append(
            subprocess.Popen(
                up,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
                env=_yarp_env(empty),
            )
        )
        Lines(self.procs[-1]).wait("archery up: all alive")
        bridge = [*CLI, "yarp", "--connect", endpoint, "--robot", dep.robot, "--operator",
                  *dep.flags]  # fmt: skip
        with (tmp / "bridge.log").open("w") as err:
            self.procs.append(
                subprocess.Popen(
                    bridge, stdout=subprocess.PIPE, stderr=err, text=True, env=_yarp_env(empty)
                )
            )
        ready = Lines(self.procs[-1]).wait("archery yarp: on YARP", timeout=120)[2]
        self.bridge = psutil.Process(self.procs[-1].pid)
        folder = _folder(tmp / "yarp-client", _server(ready), dep.key)
        self.worker = Worker(folder, tmp / "client.log", endpoint=endpoint, robot=dep.robot,
                             secure=str(dep.dir) if dep.dir else None)  # fmt: skip

    def repeat(self, window: float, calls: int, first: bool) -> dict[str, Any]:
        """One repeat's stream, round trips and CPU (readers first or not)."""
        assert self.worker is not None
        got = self.worker.ask(do="stream", window=window)
        got.update(self.worker.ask(do="trips", calls=calls))
        used = {}
        for readers in (first, not first):
            used[readers] = self.worker.ask(
                do="cpu", window=window, readers=readers, pid=self.bridge.pid
            )["cpu"]
        got.update(cpu_with=used[True], cpu_without=used[False])
        return got

    def close(self) -> None:
        """The client, the bridge, the mesh: in that order."""
        if self.worker is not None:
            self.worker.close()
        for proc in reversed(self.procs):
            _stop(proc)


class Supervised:
    """Part 2 for one mode: `archery up --yarp` (the bridge read-only, on a name server of its
    own) and the benchmark's YARP client, until `close`."""

    def __init__(self, mode: str, tmp: Path, budget: int | None) -> None:
        self.mode = mode
        self.worker: Worker | None = None
        self.dep = Deployment(mode, tmp)
        self.key = self.dep.yarp_key()
        empty = _folder(tmp / "yarp-none", None, None)
        extra = ["--restart-budget", str(budget)] if budget is not None else []
        self.proc = subprocess.Popen(
            [*CLI, "up", "--listen", self.dep.endpoint(), "--robot", self.dep.robot, "--rtf",
             "1", "--logs", str(tmp / "logs"), "--runs", str(tmp / "runs"), "--yarp",
             *extra, *self.dep.flags],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_yarp_env(empty),
        )  # fmt: skip
        self.out = Lines(self.proc)
        try:
            _, self.since, line = self.out.wait("archery up: on YARP")
            self.out.wait("archery up: all alive")
            self.server = _server(line)
            folder = _folder(tmp / "yarp-client", self.server, self.dep.key)
            self.worker = Worker(folder, tmp / "client.log", robot=self.dep.robot)
        except BaseException:
            self.close()
            raise

    def _connect(self, address: tuple[str, int]) -> socket.socket:
        """A connection to a YARP port or name server (after YARP's handshake, in secure mode)."""
        conn = socket.create_connection(address, timeout=5)
        if self.key is not None:
            authenticate(conn, self.key, time.monotonic() + 5)
            conn.settimeout(5)
        return conn

    def _address(self, name: str) -> tuple[str, int]:
        with self._connect(self.server) as conn:
            conn.sendall(f"NAME_SERVER query {name}\n".encode())
            answer = b""
            while b"*** end of message" not in answer:
                chunk = conn.recv(4096)
                if not chunk:
                    break
                answer += chunk
        words = answer.decode().split()
        return words[words.index("ip") + 1], int(words[words.index("port") + 1])

    def crash(self) -> dict[str, float]:
        """Crash the bridge once it has run `healthy_after`; the times (s from the crash) at
        which it was gone, `up` said it was back, and remote_controlboard read the encoders."""
        assert self.worker is not None
        while time.monotonic() - self.since < POLICY.healthy_after + 0.5:
            time.sleep(0.1)  # a rare crash: the bridge has run long enough to count as healthy
        bridge = next(
            c for c in psutil.Process(self.proc.pid).children() if "yarp" in c.cmdline()[3:5]
        )
        address = self._address(f"/{self.dep.robot}/{ARM}/state:o")
        mark = len(self.out.lines)
        with self._connect(address) as raw:
            crashed = time.monotonic()
            crash_output_port(raw)
        bridge.wait(30)
        gone = time.monotonic()
        after, _, killed = self.out.wait("archery up: yarp was killed by signal", mark, 60)
        delay = re.search(r", in ([\d.]+) s", killed)  # "restart 1 of 5 within 60 s, in 0.5 s"
        _, back, line = self.out.wait("archery up: yarp is back", after, 120)
        self.since, self.server = back, _server(line)
        host, port = self.server
        read = self.worker.ask(do="encoders", host=host, port=port, timeout=60)["at"]
        return {
            "gone": gone - crashed,
            "back": back - crashed,
            "encoders": read - crashed,
            "delay": float(delay[1]) if delay else math.nan,
        }

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
        _stop(self.proc)


# the worker: the benchmark's YARP client in a process of its own


def stream(yarp: Any, node: Node, robot: str, window: float) -> dict[str, float]:
    """Mesh states, YARP state:o vectors and stateExt:o bottles of the arm in one window."""
    counts = {"mesh": 0, "state": 0, "ext": 0}
    counting = threading.Event()

    def mesh(_: JointState) -> None:
        if counting.is_set():
            counts["mesh"] += 1

    sub = node.subscribe(node.keys.state(ARM), JointState, mode="fifo", callback=mesh)
    ports = {"state": yarp.BufferedPortVector(), "ext": yarp.BufferedPortBottle()}
    for key, port in ports.items():
        port.setStrict(True)  # every message, not only the newest
        port.open(f"/bench/{key}:i")
        leaf = "state:o" if key == "state" else "stateExt:o"
        yarp.Network.connect(f"/{robot}/{ARM}/{leaf}", f"/bench/{key}:i")
    stop = threading.Event()

    def read(key: str, port: Any) -> None:
        while not stop.is_set():
            if port.read(True) is not None and counting.is_set():
                counts[key] += 1

    threads = [threading.Thread(target=read, args=item, daemon=True) for item in ports.items()]
    for thread in threads:
        thread.start()
    time.sleep(1.0)  # the connections made and the first messages through
    counting.set()
    time.sleep(window)
    counting.clear()
    stop.set()
    for port in ports.values():
        port.interrupt()
    for thread in threads:
        thread.join(timeout=5)
    for port in ports.values():
        port.close()
    node.unsubscribe(sub)
    return {k: float(v) for k, v in counts.items()}


def _board(yarp: Any, robot: str, local: str) -> Any:
    """A remote_controlboard on the arm (its PolyDriver; not valid while it cannot open)."""
    options = yarp.Property()
    for k, value in (
        ("device", "remote_controlboard"),
        ("remote", f"/{robot}/{ARM}"),
        ("local", local),
    ):
        options.put(k, value)
    return yarp.PolyDriver(options)


def round_trips(yarp: Any, node: Node, robot: str, calls: int) -> dict[str, float]:
    """Median s of `calls` positionMove round trips through remote_controlboard and through
    the mesh's own verb, alternating call by call (the order swapping each pair), after one
    untimed pair. The board is opened for these calls only: YARP 3.5 (built without ACE) leaves
    the 2 s receive timeout of its AuthHMAC handshake on the socket, so in secure mode an RPC
    connection idle for 2 s is dropped by the port it reaches (TcpFace.cpp; TcpStream.h)."""
    driver = _board(yarp, robot, f"/bench/board{time.monotonic_ns()}")
    if not driver.isValid():
        raise RuntimeError("remote_controlboard did not open")
    try:
        return _round_trips(node, driver.viewIPositionControl(), calls)
    finally:
        driver.close()


def _round_trips(node: Node, board: Any, calls: int) -> dict[str, float]:
    key = node.keys.part_rpc(ARM)
    elbow = PARTS[ARM][ELBOW]
    times: dict[str, list[float]] = {"yarp": [], "mesh": []}
    for i in range(-1, calls):  # -1: the untimed pair
        goal = 50.0 + (i % 2) * 10.0  # deg: back and forth inside the elbow's range

        def by_yarp(goal: float = goal) -> None:
            if not board.positionMove(ELBOW, goal):
                raise RuntimeError("remote_controlboard's positionMove failed")

        def by_mesh(goal: float = goal) -> None:
            args = rv.PositionMoveArgs(position=[math.radians(goal)], names=[elbow])
            node.call_typed(key, rv.POSITION_MOVE, args)

        pair = [("yarp", by_yarp), ("mesh", by_mesh)]
        for name, call in pair if i % 2 == 0 else pair[::-1]:
            start = time.perf_counter()
            call()
            if i >= 0:
                times[name].append(time.perf_counter() - start)
    return {"yarp_s": statistics.median(times["yarp"]), "mesh_s": statistics.median(times["mesh"])}


def cpu(yarp: Any, robot: str, pid: int, window: float, readers: bool) -> float:
    """The bridge's CPU (s per s) in one window, with a reader on each output port or none."""
    bridge = psutil.Process(pid)

    def used() -> float:
        times = bridge.cpu_times()
        return float(times.user + times.system)

    ports = []
    if readers:
        for i, name in enumerate(outputs(robot)):
            port = yarp.BufferedPortImageRgb() if "cam" in name else yarp.BufferedPortBottle()
            port.open(f"/bench/reader{i}:i")
            port.setStrict(False)
            yarp.Network.connect(name, f"/bench/reader{i}:i")
            ports.append(port)
        time.sleep(1.0)
    before, start = used(), time.monotonic()
    time.sleep(window)
    rate = (used() - before) / (time.monotonic() - start)
    for port in ports:
        port.close()
    return rate


def encoders(yarp: Any, robot: str, server: tuple[str, int], timeout: float) -> float:
    """When (time.monotonic()) remote_controlboard, pointed at `server`, first read the arm's
    encoders: a new client tried every 50 ms until one opens and reads them."""
    yarp.Network.setNameServerContact(yarp.Contact("/root", "tcp", server[0], server[1]))
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        driver = _board(yarp, robot, f"/bench/encoders{time.monotonic_ns()}")
        try:
            if driver.isValid():
                board = driver.viewIEncoders()
                values = yarp.Vector(board.getAxes())
                while time.monotonic() < deadline:
                    if board.getEncoders(values.data()):
                        return time.monotonic()
                    time.sleep(0.01)
        finally:
            driver.close()
        time.sleep(0.05)
    raise RuntimeError(f"remote_controlboard read no encoders within {timeout} s")


def _say(answer: dict[str, Any]) -> None:
    print(SAY + json.dumps(answer), flush=True)


def worker(spec: dict[str, Any]) -> int:
    """The YARP client: answers the parent's commands, one JSON line each, until `quit`."""
    import yarp

    yarp.Network.init()
    robot = spec["robot"]
    node: Node | None = None
    try:
        if spec.get("endpoint"):
            secure = spec.get("secure")
            net = NetConfig(connect=(spec["endpoint"],), robot=robot, secure=secure,
                            identity="operator" if secure else None)  # fmt: skip
            node = open_node(net, 60)
            node.wait_alive(SERVICES, timeout=120)
        _say({"ready": True})
        for line in sys.stdin:
            command = json.loads(line)
            do = command["do"]
            try:
                if do == "quit":
                    _say({})
                    break
                if do == "stream":
                    assert node is not None
                    _say(stream(yarp, node, robot, command["window"]))
                elif do == "trips":
                    assert node is not None
                    _say(round_trips(yarp, node, robot, command["calls"]))
                elif do == "cpu":
                    rate = cpu(yarp, robot, command["pid"], command["window"], command["readers"])
                    _say({"cpu": rate})
                elif do == "encoders":
                    server = (command["host"], command["port"])
                    _say({"at": encoders(yarp, robot, server, command["timeout"])})
                else:
                    _say({"error": f"unknown command {do!r}"})
            except Exception as exc:  # told to the parent, which stops
                _say({"error": f"{do}: {exc!r}"})
    except Exception as exc:
        _say({"error": repr(exc)})
        return 1
    finally:
        if node is not None:
            node.close()
        yarp.Network.fini()
    return 0


# the benchmark


def part1(modes: list[str], tmp: Path, args: argparse.Namespace) -> dict[str, list[Any]]:
    """Stream, round trips and CPU per mode, the modes alternating in each repeat."""
    results: dict[str, list[Any]] = {mode: [] for mode in modes}
    setups: dict[str, Bridged] = {}
    try:
        for mode in modes:
            setups[mode] = Bridged(mode, tmp / f"part1-{mode}")
        for repeat in range(args.repeats):
            order = modes if repeat % 2 == 0 else modes[::-1]
            for mode in order:
                got = setups[mode].repeat(args.window, args.calls, first=repeat % 2 == 0)
                results[mode].append(got)
                print(
                    f"  repeat {repeat + 1}, {mode}: mesh {got['mesh'] / args.window:.1f}/s, "
                    f"state:o {got['state'] / got['mesh']:.3f}, stateExt:o "
                    f"{got['ext'] / got['mesh']:.3f}; positionMove {got['yarp_s'] * 1e3:.2f} ms "
                    f"vs {got['mesh_s'] * 1e3:.2f} ms; bridge CPU {got['cpu_with']:.3f} vs "
                    f"{got['cpu_without']:.3f} s/s",
                    flush=True,
                )
    finally:
        for setup in setups.values():
            setup.close()
    return results


def part2(modes: list[str], tmp: Path, repeats: int) -> dict[str, list[dict[str, float]]]:
    """Crash → encoders again per mode, the modes alternating."""
    budget = repeats if repeats > POLICY.budget else None  # the default holds 5 crashes
    results: dict[str, list[dict[str, float]]] = {mode: [] for mode in modes}
    setups: dict[str, Supervised] = {}
    try:
        for mode in modes:
            setups[mode] = Supervised(mode, tmp / f"part2-{mode}", budget)
        for repeat in range(repeats):
            for mode in modes if repeat % 2 == 0 else modes[::-1]:
                got = setups[mode].crash()
                results[mode].append(got)
                print(
                    f"  crash {repeat + 1}, {mode}: gone {got['gone']:.2f} s, up's back-off "
                    f"{got['delay']:g} s, back {got['back']:.2f} s, encoders read "
                    f"{got['encoders']:.2f} s after the crash",
                    flush=True,
                )
    finally:
        for setup in setups.values():
            setup.close()
    return results


def report(one: dict[str, list[Any]], two: dict[str, list[dict[str, float]]]) -> None:
    print("bench_yarp results (median [min, max] over repeats):")
    for mode, runs in one.items():
        state = [r["state"] / r["mesh"] for r in runs]
        ext = [r["ext"] / r["mesh"] for r in runs]
        print(
            f"  {mode}: encoder stream, state:o / mesh: {median_spread(state, '.3f')}; "
            f"stateExt:o / mesh: {median_spread(ext, '.3f')} (goal ≥ 0.95; mesh "
            f"{median_spread([r['mesh'] for r in runs], '.0f')} states per window)"
        )
        print(
            f"  {mode}: positionMove round trip, remote_controlboard / mesh: "
            f"{median_spread([r['yarp_s'] / r['mesh_s'] for r in runs], '.3f')}× "
            f"({median_spread([r['yarp_s'] * 1e3 for r in runs])} ms vs "
            f"{median_spread([r['mesh_s'] * 1e3 for r in runs])} ms; goal ≤ 1.5×)"
        )
        print(
            f"  {mode}: bridge CPU, a reader on each of its {len(outputs('x'))} output ports / "
            f"none: {median_spread([r['cpu_with'] / r['cpu_without'] for r in runs], '.2f')}× "
            f"({median_spread([r['cpu_with'] for r in runs], '.3f')} vs "
            f"{median_spread([r['cpu_without'] for r in runs], '.3f')} s of CPU per s)"
        )
    if "plain" in one and "secure" in one:
        pairs = zip(one["secure"], one["plain"], strict=True)
        ratio = [s["yarp_s"] / p["yarp_s"] for s, p in pairs]
        print(
            f"  remote_controlboard's positionMove, secure / plain: {median_spread(ratio, '.3f')}×"
        )
    for mode, runs in two.items():
        print(
            f"  {mode}: crash → remote_controlboard reads the encoders: "
            f"{median_spread([r['encoders'] for r in runs])} s (goal ≤ 5 s); of which the bridge "
            f"gone {median_spread([r['gone'] for r in runs])} s, `up`'s back-off "
            f"{median_spread([r['delay'] for r in runs], 'g')} s, `up` says it is back "
            f"{median_spread([r['back'] for r in runs])} s after the crash"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_yarp", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--window", type=float, default=10.0, help="s per stream/CPU window")
    parser.add_argument("--calls", type=int, default=20, help="round trips per repeat and path")
    only = parser.add_mutually_exclusive_group()
    only.add_argument("--plain", action="store_true", help="plain mode only")
    only.add_argument("--secure", action="store_true", help="secure mode only")
    parser.add_argument("--no-crash", action="store_true", help="skip part 2 (the crashes)")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--keep", metavar="DIR", help="keep the logs in DIR (a new folder)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        return worker(json.loads(args.worker))
    if args.smoke:
        args.repeats, args.window, args.calls = 1, 1.0, 3
    modes = ["plain"] if args.plain else ["secure"] if args.secure else list(MODES)
    print(f"bench_yarp: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {cpu_model()}, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; modes {', '.join(modes)}",
          flush=True)  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="bench-yarp-") as folder:
        tmp = Path(args.keep or folder)
        one = part1(modes, tmp, args)
        two = {} if args.no_crash else part2(modes, tmp, args.repeats)
    report(one, two)
    return 0


if __name__ == "__main__":
    sys.exit(main())
