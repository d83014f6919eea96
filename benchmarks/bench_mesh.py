"""Mesh benchmark: the protocol layer against raw zenoh-python, same router, same process run.

Every figure is a cost ratio, protocol / raw, taken per repeat and reported as the median over
repeats with its spread (min–max). Within a repeat, raw and protocol run in alternating blocks
(ABBA, the first side alternating between repeats), each block long enough to time and short
enough that machine noise (a shared 2-core machine) hits both sides alike.

- Frames: lossless RGB frames at 1280×720 and 640×480 from one session to another; the raw
  receiver copies each payload to `bytes` (what a real consumer does), the protocol receiver
  decodes and validates an `Image` (`Node.subscribe` with a callback; an `ImageView`, its pixels
  a view of the received payload). Figure: frames/s from the first `put` to the arrival of the
  block's last frame; cost ratio = raw fps / protocol fps.
- Streams: N = 1, 2, 4 camera streams at once through the router (N publisher/subscriber
  pairs, each publisher on its own thread at full speed, 1280×720); aggregate frames/s.
- RPC: round trips with a trivial handler and with a 1 ms handler (`time.sleep(0.001)` on
  both sides), on the keys of the protocol's calls: a call of VERB on the port PORT asks
  `PORT/VERB` and the server answers `PORT/*` (`protocol.keys.verb_key`, `verbs_key`), the
  raw querier and queryable alike. The raw queryable replies the request's payload (the same
  bytes as the protocol's request); the protocol serves a typed verb (`Node.call_typed`
  against `Node.serve`): the trivial one is a non-blocking verb, the 1 ms one blocking (it
  runs on the server's worker thread). Figures: median and p99 of the repeat's calls (ms).
- Secure: the same frames and RPC figures over a router in secure mode (mutual TLS with a
  fresh `archery keys init` deployment, the router enforcing its ACL), protocol-over-secure
  against raw-over-secure, with the deployment's identities (camera → operator, learner →
  detector) on their ACL-granted keys: the frames on `ROBOT/cam/target:o`, the calls on two
  verbs the ACL grants the learner on `ROBOT/detector/rpc:i` (`measure`, `frame`: served by
  the benchmark's trivial and 1 ms handlers), so both sides pass the same per-verb rules.

Goals (median over repeats): frames ≤ 1.15×, RPC median ≤ 1.2×, RPC p99 ≤ 1.5×.

Run: `python -m benchmarks.bench_mesh [--repeats 5] [--blocks 4] [--frames 40] [--calls 300]
[--slow-calls 60] [--no-secure]`. `--smoke` runs every part (plain and secure, 1 and 2
streams) once at its smallest budget: 1 repeat of 2 blocks per side, 2 frames per stream, 5
trivial and 2 slow calls per block, no 4-stream case; its ratios are noise, not figures (it
writes nothing; nothing does).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, TypeVar

import msgspec
import numpy as np
import zenoh

from archery.apps.progress import progress_bar
from archery.mesh.credentials import init_deployment
from archery.mesh.netflags import NetConfig, open_session
from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.codec import encode
from archery.protocol.keys import verb_key, verbs_key
from archery.protocol.messages import Image, RpcRequest
from archery.protocol.verbs import Args, Reply, Verb, VerbTable, names_caller
from benchmarks.echo_verbs import granted_verbs
from benchmarks.machine import cpu_model

ROBOT = "bench"
THETA = [0.17, 0.03, -0.03]
GOALS = {"fps": 1.15, "median": 1.2, "p99": 1.5}
T = TypeVar("T")
R = TypeVar("R")


class EchoArgs(Args, frozen=True):
    theta: Annotated[list[float], msgspec.Meta(max_length=16)]


class EchoReply(Reply, frozen=True):
    theta: list[float]


PLAIN_VERBS = ("echo", "work")  # (trivial, 1 ms) verb names on the plain router


def _verbs(trivial: str, slow: str) -> tuple[Verb, Verb, VerbTable]:
    """The trivial verb (non-blocking: θ at once), the 1 ms one (blocking) and their table."""
    fast = Verb(trivial, EchoArgs, EchoReply, "reply θ at once", blocking=False)
    work = Verb(slow, EchoArgs, EchoReply, "sleep 1 ms, then reply θ")
    return fast, work, VerbTable("bench", ("bench/rpc:i",), (fast, work))


def _granted_pair(caller: str, port: str) -> tuple[str, str]:
    """Two verbs the secure router's ACL lets `caller` call on the `rpc:i` port `port`
    (`echo_verbs.granted_verbs`): the secure figures' (trivial, 1 ms) verbs, on the same
    `PORT/VERB` keys as the product's calls."""
    names = granted_verbs(ROBOT, caller, port)
    if len(names) < 2:
        raise RuntimeError(f"the ACL grants {caller} fewer than two verbs on {port}: {names}")
    return names[0], names[1]


def _echo(args: EchoArgs) -> EchoReply:
    return EchoReply(theta=args.theta)


def _work(args: EchoArgs) -> EchoReply:
    time.sleep(0.001)
    return EchoReply(theta=args.theta)


def _frame(width: int, height: int) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 255, (height, width, 3), np.uint8)


# -- streams --------------------------------------------------------------------------------------
class _Stream:
    """One publisher → subscriber pair; counts arrivals and keeps the last arrival's time."""

    _item: object
    _put: Callable[[object], object]
    _closers: tuple[Callable[[], object], ...]

    def __init__(self) -> None:
        self.count = 0
        self.last = 0.0
        self._cond = threading.Condition()

    def arrived(self) -> None:
        with self._cond:
            self.count += 1
            self.last = time.perf_counter()
            self._cond.notify_all()

    def send(self, frames: int) -> None:
        """Publish `frames` frames as fast as the (lossless) publisher takes them."""
        put, item = self._put, self._item
        for _ in range(frames):
            put(item)

    def wait(self, count: int) -> float:
        with self._cond:
            if not self._cond.wait_for(lambda: self.count >= count, timeout=60):
                raise RuntimeError(f"only {self.count} of {count} frames arrived")
            return self.last

    def close(self) -> None:
        for close in self._closers:
            close()


class RawStream(_Stream):
    """Raw bytes; the receiver copies each payload to `bytes` as a real consumer would."""

    def __init__(self, a: zenoh.Session, b: zenoh.Session, key: str, pixels: np.ndarray) -> None:
        super().__init__()
        self.payload = pixels.tobytes()
        self._sub = b.declare_subscriber(key, self._on_sample)
        self._pub = a.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        deadline = time.monotonic() + 10
        while not self._pub.matching_status.matching:
            if time.monotonic() > deadline:
                raise RuntimeError(f"no raw subscriber matched {key}")
            time.sleep(0.01)

        self._item, self._put = self.payload, self._pub.put
        self._closers = (self._pub.undeclare, self._sub.undeclare)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        sample.payload.to_bytes()
        self.arrived()


class NodeStream(_Stream):
    """`Image` messages: stamped, encoded, decoded and validated by the protocol layer."""

    def __init__(self, a: Node, b: Node, key: str, pixels: np.ndarray) -> None:
        super().__init__()
        self.image = Image.from_numpy(pixels)
        self._sub = b.subscribe(key, Image, mode="fifo", callback=self._on_image)
        self._pub: Publisher[Image] = a.publisher(key, Image, lossless=True)
        if not self._pub.wait_matched(10):
            raise RuntimeError(f"no protocol subscriber matched {key}")
        self._item, self._put = self.image, self._pub.put
        self._closers = (self._pub.close, self._sub.close)

    def _on_image(self, image: Image) -> None:
        self.arrived()


def _prime(streams: list[_Stream]) -> None:
    """One frame through each stream, so every route is in place before timing."""
    for stream in streams:
        for _ in range(50):
            stream.send(1)
            with stream._cond:
                if stream._cond.wait_for(lambda s=stream: s.count > 0, timeout=0.2):
                    break
        else:
            raise RuntimeError("a stream never delivered a frame")


def _frame_block(streams: list[_Stream], frames: int) -> float:
    """Aggregate frames/s of every stream sending `frames` at once (one thread per stream)."""
    targets = [s.count + frames for s in streams]
    threads = [threading.Thread(target=s.send, args=(frames,)) for s in streams[1:]]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    streams[0].send(frames)
    for thread in threads:
        thread.join()
    end = max(s.wait(t) for s, t in zip(streams, targets, strict=True))
    return len(streams) * frames / (end - start)


# -- rpc ------------------------------------------------------------------------------------------
class RawRpc:
    """A raw queryable replying the request's payload (after `delay` s) and a raw querier, on
    the keys of the protocol's calls: the queryable answers `PORT/*` (`verbs_key`), the querier
    asks `PORT/VERB` (`verb_key`), the keys the secure router's ACL grants per verb."""

    def __init__(
        self, a: zenoh.Session, b: zenoh.Session, port: str, verb: str, delay: float
    ) -> None:
        self.delay = delay
        self.payload = encode(RpcRequest(verb=verb, args={"theta": THETA}, stamp=time.time()))
        # the learner's call, as its node names itself on a verb that names its caller
        target = verb_key(port, verb, "learner" if names_caller(port, verb) else None)
        self._queryable = b.declare_queryable(verbs_key(port), self._on_query)
        self._querier = a.declare_querier(target, timeout=5.0)
        deadline = time.monotonic() + 10
        while not self._ok():
            if time.monotonic() > deadline:
                raise RuntimeError(f"no raw queryable answers {target}")
            time.sleep(0.01)

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        if self.delay:
            time.sleep(self.delay)
        query.reply(query.key_expr, payload)

    def _ok(self) -> bool:
        replies = list(self._querier.get(payload=self.payload))
        return (
            bool(replies)
            and replies[0].ok is not None
            and (
                replies[0].ok.payload.to_bytes() == self.payload  # from this echo, not another
            )
        )

    def call(self) -> None:
        if not self._ok():
            raise RuntimeError("a raw query got no reply")

    def close(self) -> None:
        self._querier.undeclare()
        self._queryable.undeclare()


class NodeRpc:
    """`Node.call_typed` against `Node.serve` of the trivial (non-blocking) or the 1 ms
    (blocking) verb of `names` (trivial, 1 ms)."""

    def __init__(
        self, client: Node, server: Node, key: str, delay: float, names: tuple[str, str]
    ) -> None:
        self.client, self.key = client, key
        fast, work, table = _verbs(*names)
        self.verb = work if delay else fast
        self.args = EchoArgs(theta=THETA)
        self._server = server.serve(key, table.bind_names({fast.name: _echo, work.name: _work}))
        deadline = time.monotonic() + 10
        while True:
            try:
                self.call()
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def call(self) -> None:
        if self.client.call_typed(self.key, self.verb, self.args, timeout=5.0).theta != THETA:
            raise RuntimeError("the echo changed θ")

    def close(self) -> None:
        self._server.close()


def _rpc_block(rpc: RawRpc | NodeRpc, calls: int) -> list[float]:
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        rpc.call()
        times.append((time.perf_counter() - t0) * 1e3)
    return times


# -- interleaving ---------------------------------------------------------------------------------
@dataclass
class Figure:
    """Per-repeat figures of one row: raw and protocol values, and the cost ratios."""

    name: str
    unit: str
    goal: float
    raw: list[float] = field(default_factory=list)
    ours: list[float] = field(default_factory=list)
    ratios: list[float] = field(default_factory=list)

    def add(self, raw: float, ours: float, *, higher_is_better: bool) -> None:
        self.raw.append(raw)
        self.ours.append(ours)
        self.ratios.append(raw / ours if higher_is_better else ours / raw)


def interleave(
    repeats: int, blocks: int, raw: Callable[[], object], ours: Callable[[], object], tick: Callable
) -> list[tuple[list[object], list[object]]]:
    """Per repeat, the raw and protocol results of `blocks` blocks each, in ABBA order."""
    out = []
    for r in range(repeats):
        got: dict[str, list[object]] = {"raw": [], "ours": []}
        for b in range(blocks):
            order = ("raw", "ours") if (b + r) % 2 == 0 else ("ours", "raw")
            for side in order:
                got[side].append((raw if side == "raw" else ours)())
                tick()
        out.append((got["raw"], got["ours"]))
    return out


@dataclass
class Plan:
    repeats: int
    blocks: int
    frames: int
    calls: int
    slow_calls: int


def _side(make: Callable[[], T], run: Callable[[T], R], fresh: bool) -> Callable[[], R]:
    """One side's block: `run` on the endpoints `make` builds, built once (plain) or anew for
    every block and closed after it (`fresh`: raw and protocol share the ACL-granted keys of
    the secure mesh, so only one side's endpoints may exist at a time)."""
    kept: list[T] = []

    def block() -> R:
        if fresh or not kept:
            kept[:] = [make()]
        try:
            return run(kept[0])
        finally:
            if fresh:
                kept.pop().close()  # type: ignore[attr-defined]  # the endpoints close

    def close() -> None:
        for item in kept:
            item.close()  # type: ignore[attr-defined]  # the endpoints close

    block.close = close  # type: ignore[attr-defined]  # a close function on the block
    return block


class _Streams(list):
    """Streams primed once built, closed together."""

    def __init__(self, streams: list[_Stream]) -> None:
        super().__init__(streams)
        _prime(streams)

    def close(self) -> None:
        for stream in self:
            stream.close()


def _run_sides(
    plan: Plan, sides: list[Callable[[], object]], tick: Callable[[], None]
) -> list[tuple[list[object], list[object]]]:
    """A warm-up block of each side, then the interleaved repeats; the endpoints closed."""
    try:
        for side in sides:
            side()
        return interleave(plan.repeats, plan.blocks, sides[0], sides[1], tick)
    finally:
        for side in sides:
            side.close()  # type: ignore[attr-defined]  # _side's blocks have close


def measure_frames(
    plan: Plan,
    fig: Figure,
    raw: Callable[[], list[_Stream]],
    ours: Callable[[], list[_Stream]],
    tick: Callable[[], None],
    fresh: bool = False,
) -> None:
    """Fill `fig` with per-repeat aggregate frames/s (after a warm-up block of each side)."""
    sides = [
        _side(lambda m=m: _Streams(m()), lambda s: _frame_block(s, plan.frames), fresh)
        for m in (raw, ours)
    ]
    results = _run_sides(plan, sides, tick)
    for raw_fps, our_fps in results:  # mean rate of the repeat's blocks (equal frame counts)
        fig.add(
            statistics.harmonic_mean(raw_fps),  # type: ignore[arg-type,type-var]  # a side's blocks return frame rates
            statistics.harmonic_mean(our_fps),  # type: ignore[arg-type,type-var]  # a side's blocks return frame rates
            higher_is_better=True,
        )


def measure_rpc(
    median: Figure,
    p99: Figure,
    raw: Callable[[], RawRpc],
    ours: Callable[[], NodeRpc],
    plan: Plan,
    calls: int,
    tick: Callable[[], None],
    fresh: bool = False,
) -> None:
    """Fill the median and p99 figures per repeat (after a warm-up block of each side)."""
    sides = [_side(m, lambda rpc: _rpc_block(rpc, calls), fresh) for m in (raw, ours)]
    results = _run_sides(plan, sides, tick)
    for raw_blocks, our_blocks in results:
        raw_t = [t for block in raw_blocks for t in block]  # type: ignore[attr-defined]  # a side's blocks return call times
        our_t = [t for block in our_blocks for t in block]  # type: ignore[attr-defined]  # a side's blocks return call times
        median.add(statistics.median(raw_t), statistics.median(our_t), higher_is_better=False)
        p99.add(
            float(np.percentile(raw_t, 99)),
            float(np.percentile(our_t, 99)),
            higher_is_better=False,
        )


# -- the meshes -----------------------------------------------------------------------------------
@dataclass
class Mesh:
    """Raw sessions and protocol nodes on one router: (a → b) for streams and calls."""

    raw_a: zenoh.Session
    raw_b: zenoh.Session
    node_a: Node
    node_b: Node

    def close(self) -> None:
        for node in (self.node_a, self.node_b):
            node.close()
        for session in (self.raw_a, self.raw_b):
            session.close()


def _plain_mesh(endpoint: str) -> Mesh:
    net = NetConfig(connect=(endpoint,), robot=ROBOT)
    return Mesh(open_session(net), open_session(net), Node(None, net), Node(None, net))


def _secure_nets(endpoint: str, deployment: str, a: str, b: str) -> tuple[NetConfig, NetConfig]:
    def net(identity: str) -> NetConfig:
        return NetConfig(connect=(endpoint,), robot=ROBOT, secure=deployment, identity=identity)

    return net(a), net(b)


def _secure_mesh(endpoint: str, deployment: str, a: str, b: str) -> Mesh:
    net_a, net_b = _secure_nets(endpoint, deployment, a, b)
    return Mesh(open_session(net_a), open_session(net_b), Node(None, net_a), Node(None, net_b))


def run_plain(plan: Plan, streams: list[int], tick: Callable[[], None]) -> list[Figure]:
    """Frames (two sizes), N streams and RPC through one plain router."""
    figures = []
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    mesh = _plain_mesh(endpoint)
    try:
        cases = [(1, 1280, 720), (1, 640, 480)] + [(n, 1280, 720) for n in streams if n != 1]
        for n, width, height in cases:
            name = f"{width}×{height} frames/s" if n == 1 else f"{n} streams 1280×720 fps"
            fig = Figure(name, "fps", GOALS["fps"])
            pixels = _frame(width, height)
            key = f"{ROBOT}/n{n}w{width}"

            def raw(key: str = key, pixels: np.ndarray = pixels, n: int = n) -> list[_Stream]:
                return [
                    RawStream(mesh.raw_a, mesh.raw_b, f"{key}/raw{i}", pixels) for i in range(n)
                ]

            def ours(key: str = key, pixels: np.ndarray = pixels, n: int = n) -> list[_Stream]:
                return [
                    NodeStream(mesh.node_a, mesh.node_b, f"{key}/ours{i}", pixels) for i in range(n)
                ]

            measure_frames(plan, fig, raw, ours, tick)
            figures.append(fig)
        for delay, calls, label in ((0.0, plan.calls, "trivial"), (0.001, plan.slow_calls, "1 ms")):
            median = Figure(f"RPC {label} median (ms)", "ms", GOALS["median"])
            p99 = Figure(f"RPC {label} p99 (ms)", "ms", GOALS["p99"])
            key = f"{ROBOT}/rpc{int(delay * 1e3)}"
            verb = PLAIN_VERBS[1 if delay else 0]
            measure_rpc(
                median,
                p99,
                lambda key=key, delay=delay, verb=verb: RawRpc(
                    mesh.raw_a, mesh.raw_b, f"{key}/raw", verb, delay
                ),
                lambda key=key, delay=delay: NodeRpc(
                    mesh.node_a, mesh.node_b, f"{key}/ours", delay, PLAIN_VERBS
                ),
                plan,
                calls,
                tick,
            )
            figures += [median, p99]
    finally:
        mesh.close()
        router.terminate()
        router.wait()
    return figures


def run_secure(plan: Plan, tick: Callable[[], None]) -> list[Figure]:
    """1280×720 frames and RPC through a secure router (tls + ACL), raw and protocol, each
    block on fresh endpoints (the two sides share the ACL-granted keys)."""
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        deployment = str(init_deployment(Path(tmp) / "deploy", robot=ROBOT))
        endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
        router = spawn_router(endpoint, secure=deployment)
        meshes: list[Mesh] = []
        try:
            cam = _secure_mesh(endpoint, deployment, "camera", "operator")
            meshes.append(cam)
            frames_key = cam.node_a.keys.cam_frames()  # the ACL grants camera → operator
            fig = Figure("secure 1280×720 frames/s", "fps", GOALS["fps"])
            pixels = _frame(1280, 720)
            measure_frames(
                plan,
                fig,
                lambda: [RawStream(cam.raw_a, cam.raw_b, frames_key, pixels)],
                lambda: [NodeStream(cam.node_a, cam.node_b, frames_key, pixels)],
                tick,
                fresh=True,
            )
            figures.append(fig)
            rpc = _secure_mesh(endpoint, deployment, "learner", "detector")
            meshes.append(rpc)
            rpc_key = rpc.node_a.keys.detector_rpc()  # learner calls, detector serves
            names = _granted_pair("learner", rpc_key)
            for delay, calls, label in (
                (0.0, plan.calls, "trivial"),
                (0.001, plan.slow_calls, "1 ms"),
            ):
                median = Figure(f"secure RPC {label} median", "ms", GOALS["median"])
                p99 = Figure(f"secure RPC {label} p99", "ms", GOALS["p99"])
                verb = names[1 if delay else 0]
                measure_rpc(
                    median,
                    p99,
                    lambda delay=delay, verb=verb: RawRpc(
                        rpc.raw_a, rpc.raw_b, rpc_key, verb, delay
                    ),
                    lambda delay=delay: NodeRpc(rpc.node_a, rpc.node_b, rpc_key, delay, names),
                    plan,
                    calls,
                    tick,
                    fresh=True,
                )
                figures += [median, p99]
        finally:
            for mesh in meshes:
                mesh.close()
            router.terminate()
            router.wait()
    return figures


def report(figures: list[Figure]) -> None:
    """Print one row per figure: medians over repeats, the median ratio, its spread, goal."""
    head = f"{'figure':<28} {'raw':>9} {'protocol':>9} {'ratio':>7} {'spread':>12} {'goal':>8}"
    print(head)
    for fig in figures:
        ratio = statistics.median(fig.ratios)
        spread = f"{min(fig.ratios):.2f}–{max(fig.ratios):.2f}"
        verdict = "met" if ratio <= fig.goal else "NOT met"
        print(
            f"{fig.name:<28} {statistics.median(fig.raw):>9.3f} {statistics.median(fig.ours):>9.3f}"
            f" {ratio:>6.2f}× {spread:>12} ≤{fig.goal:.2f} {verdict}"
        )
    print(
        "ratio = protocol cost / raw cost per repeat (frames: raw fps / protocol fps; RPC: "
        "protocol ms / raw ms); raw and protocol columns are medians over repeats"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table of ratios."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_mesh", description=__doc__)
    for flag, default, what in (
        ("--repeats", 5, "interleaved repeats (≥ 5)"),
        ("--blocks", 4, "blocks per side and repeat"),
        ("--frames", 40, "frames per stream and block"),
        ("--calls", 300, "trivial calls per block"),
        ("--slow-calls", 60, "1 ms calls per block"),
    ):
        parser.add_argument(flag, type=int, default=default, help=what)
    parser.add_argument("--streams", default="1,2,4", help="simultaneous stream counts")
    parser.add_argument("--no-secure", action="store_true", help="skip the secure-mode figures")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="every part once at its smallest budget (seconds; ratios are noise, not figures)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.blocks, args.frames, args.calls, args.slow_calls = 1, 2, 2, 5, 2
        args.streams = "1,2"
    elif args.repeats < 5:
        parser.error("--repeats must be at least 5")
    if args.blocks < 2 or args.frames < 2 or args.calls < 2 or args.slow_calls < 2:
        parser.error("--blocks, --frames, --calls and --slow-calls must be at least 2")
    streams = [int(n) for n in args.streams.split(",")]
    plan = Plan(args.repeats, args.blocks, args.frames, args.calls, args.slow_calls)
    per_case = 2 * plan.repeats * plan.blocks
    plain_cases = 2 + sum(1 for n in streams if n != 1) + 2
    secure_cases = 0 if args.no_secure else 3
    figures: list[Figure] = []
    with progress_bar() as progress:
        task = progress.add_task("mesh benchmark", total=per_case * (plain_cases + secure_cases))

        def tick() -> None:
            progress.advance(task)

        figures += run_plain(plan, streams, tick)
        if not args.no_secure:
            figures += run_secure(plan, tick)
    print(f"\nmachine: {cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(
        f"{plan.repeats} repeats × {plan.blocks} ABBA blocks per side: {plan.frames} frames per "
        f"stream, {plan.calls} trivial / {plan.slow_calls} 1 ms calls per block; routers on "
        f"loopback (plain tcp/, secure tls/ + ACL)"
    )
    report(figures)
    if args.smoke:
        print("smoke run: the smallest budget, the ratios are noise and no figures")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
