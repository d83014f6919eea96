"""Observation tools: `archery record` (MCAP), `archery replay` and `archery hz`.

`record` subscribes to key patterns (default `ROBOT/**`: every stream of the robot) and writes
each message into an MCAP file (`apps.topics.recording` says why the format is what it is).
`replay` publishes a recording back with its original timing (or `--rate` times faster), and
only what a replay may publish, whatever the file holds (it may have been crafted): the recorded
robot's output streams (`protocol.keys.OUTPUT_PORTS`), each carrying its port's message type,
under the robot prefix it is told; in secure mode it presents the `replay` identity, which the
router lets do just that (`mesh.acl`). With `--serve-grab` it also answers the camera's `grab`
verb from the frames it replays, so a fresh detector can measure them. `hz` prints each matching
key's message rate and bandwidth (like `ros2 topic hz` and `bw`).
"""

from __future__ import annotations

import collections
import itertools
import statistics
import sys
import threading
import time
from typing import Any

import msgspec
import zenoh

from archery.apps.topics.read_limits import add_max_bytes_arg
from archery.apps.topics.recording import (
    CALIBRATION_ATTACHMENT,
    CALIBRATION_MEDIA_TYPE,
    COMPRESSIONS,
    FrameSource,
    Recorder,
    Recording,
    open_recording,
)
from archery.mesh.acl import REPLAY, VIEWER
from archery.mesh.cliargs import (
    ArgumentParser,
    add_force_arg,
    check_output_file,
    count,
    seconds,
)
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.node import Node
from archery.mesh.patterns import check_pattern, stream_type
from archery.mesh.priority import add_nice_arg, lower_priority
from archery.mesh.rpc_server import caller_left
from archery.mesh.signals import shutdown_on_signals, wait_for_stop
from archery.protocol.codec import encode
from archery.protocol.errors import ArcheryError, BadRequest, ConfigError, KeyNameError, RpcTimeout
from archery.protocol.exit_status import for_error
from archery.protocol.keys import output_port, validate_robot
from archery.protocol.messages import Image, Message
from archery.protocol.text import shown
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs.camera import (
    CALIBRATION,
    CAMERA_VERBS,
    GRAB,
    MAX_GRAB_TIMEOUT,
    SCENE,
    STATUS,
    CalibrationReply,
    CameraStatusReply,
    GrabArgs,
    SceneReply,
)
from archery.protocol.verbs.robot import ARCHERY_STATUS

__all__ = ["hz_main", "record_main", "replay_main"]

RECEIVE_QUEUE = 1024  # samples Zenoh queues per recorded pattern before it waits for us


def _fail(prog: str, exc: ArcheryError, status: int) -> int:
    print(f"archery {prog}: {exc}", file=sys.stderr)
    return status


def _until(stop: threading.Event, done: threading.Event, duration: float | None) -> None:
    """Block until Ctrl-C/SIGTERM (`stop`), `done`, or `duration` s."""
    deadline = None if duration is None else time.monotonic() + duration
    while not stop.is_set() and not done.is_set():
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            return
        done.wait(0.1 if left is None else min(0.1, left))


# -- record ---------------------------------------------------------------------------------------


def _calibration(node: Node, exprs: list[zenoh.KeyExpr]) -> dict[str, tuple[str, bytes]]:
    """The camera's calibration frame and marks, to record beside its frames (so a replay can
    calibrate a fresh detector): asked when a pattern records the camera's frames; none (one
    line on stderr) when the camera does not give them (not alive, a real device)."""
    frames = node.keys.cam_frames()
    if not any(expr.includes(zenoh.KeyExpr(frames)) for expr in exprs):
        return {}
    try:
        marks = node.call_typed(node.keys.cam_rpc(), CALIBRATION, timeout=30)
    except ArcheryError as exc:
        print(f"archery record: no calibration marks recorded: {exc}", file=sys.stderr)
        return {}
    return {CALIBRATION_ATTACHMENT: (CALIBRATION_MEDIA_TYPE, msgspec.msgpack.encode(marks))}


def _robot_frames(node: Node, exprs: list[zenoh.KeyExpr]) -> FrameSource | None:
    """The 3D records' source (`apps.topics.robot_frames`) when a pattern records the robot's
    world state, built for the scene the robot runs (its status's `scene`; the default scene
    when the robot does not answer, said on stderr); None (one line on stderr) without MuJoCo."""
    world = node.keys.world_state()
    if not any(expr.includes(zenoh.KeyExpr(world)) for expr in exprs):
        return None
    try:
        from archery.apps.topics.robot_frames import RobotFrames
        from archery.sim.errors import SimError
        from archery.sim.scene_config import SceneConfig
    except ImportError as exc:
        print(f"archery record: no 3D records (transforms): {exc}", file=sys.stderr)
        return None
    scene = None
    try:
        status = node.call_typed(node.keys.archery_rpc(), ARCHERY_STATUS, timeout=3)
        scene = SceneConfig.of(status.scene)
    except ArcheryError as exc:
        print(f"archery record: transforms for the default scene: {exc}", file=sys.stderr)
    except (SimError, TypeError) as exc:
        print(f"archery record: transforms for the default scene: {exc}", file=sys.stderr)
    return RobotFrames(node.keys.robot, scene)


def record_main(argv: list[str] | None = None) -> int:
    """`archery record --out FILE.mcap [PATTERN ...]`: record streams until Ctrl-C."""
    parser = ArgumentParser(
        prog="archery record",
        description="record every message on the matching keys (default ROBOT/**) into an "
        "MCAP file, until Ctrl-C/SIGTERM, --duration or --count",
    )
    add_network_args(parser, default_mode="client")
    add_nice_arg(parser, 0)
    parser.add_argument("patterns", nargs="*", metavar="KEY_PATTERN", help="e.g. icubSim/**")
    parser.add_argument("--out", required=True, help="the MCAP file to write (.mcap)")
    add_force_arg(parser, "an existing recording")
    parser.add_argument("--duration", type=seconds, help="stop after this many seconds")
    parser.add_argument("--count", type=count, default=0, help="stop after N messages (0: no)")
    parser.add_argument(
        "--compression",
        choices=sorted(COMPRESSIONS),
        default="lz4",
        help="of each chunk (default lz4: the cheapest on a busy machine)",
    )
    parser.add_argument(
        "--no-transforms",
        action="store_true",
        help="leave out the robot's 3D records (its description, link transforms, joint states)",
    )
    parser.add_argument(
        "--flush-interval",
        type=seconds,
        default=1.0,
        help="close a chunk at least this often (s): what a crash may lose (default 1)",
    )
    args = parser.parse_args(argv)
    try:
        net = NetConfig.from_args(args).with_identity(VIEWER)
        patterns = args.patterns or [f"{net.robot}/**"]
        exprs = [check_pattern(p) for p in patterns]
        out = check_output_file(args.out, "--out", (".mcap",), force=args.force)
    except ArcheryError as exc:
        return _fail("record", exc, 2)
    lower_priority(args.nice)
    stop = shutdown_on_signals()
    try:
        with Node(None, net) as node:
            recorder = Recorder(
                out,
                net.robot,
                patterns,
                compression=args.compression,
                flush_interval=args.flush_interval,
                attachments=_calibration(node, exprs),
                frames=None if args.no_transforms else _robot_frames(node, exprs),
            )
            received = [0]
            done = threading.Event()

            def read(i: int, sub: zenoh.Subscriber) -> None:
                # Zenoh's thread only queues samples (no Python, no GIL): a busy recorder
                # never holds up the link, where the router would drop the frames it carries
                earlier = exprs[:i]
                for sample in sub:
                    key = sample.key_expr
                    if any(e.includes(key) for e in earlier):
                        continue  # the earlier pattern's subscriber has it
                    recorder.put(str(key), sample.payload.to_bytes())
                    received[0] += 1
                    if args.count and received[0] >= args.count:
                        done.set()

            subs = [
                node.session.declare_subscriber(expr, zenoh.handlers.FifoChannel(RECEIVE_QUEUE))
                for expr in exprs
            ]
            readers = [
                threading.Thread(target=read, args=(i, sub), name=f"record-{i}", daemon=True)
                for i, sub in enumerate(subs)
            ]
            for reader in readers:
                reader.start()
            print(f"archery record: recording {' '.join(patterns)} to {out}", flush=True)
            try:
                _until(stop, done, args.duration)
            finally:
                for sub in subs:
                    sub.undeclare()
                for reader in readers:
                    reader.join(10)
                stats = recorder.close()
    except ArcheryError as exc:
        return _fail("record", exc, 1)
    print(
        f"archery record: wrote {stats.total} messages on {len(stats.written)} keys to {out}"
        f" ({stats.malformed} malformed skipped, {stats.missing} missing by sequence number,"
        f" {stats.overflow} dropped by a full queue)",
        flush=True,
    )
    return 0


# -- replay ---------------------------------------------------------------------------------------


class _Frames:
    """The frames a replay has published, for `grab`: the newest `keep` of them.

    A grab's times are read in the recording's clocks: `after_sim_time` against each frame's
    sim time, `after_stamp` against each frame's own stamp (when the camera captured it in the
    recorded session). Every rollout resets the simulated clock, so a sim time alone may match
    an earlier rollout's frame; the stamp of the measured frame (a detection's `frame_stamp`),
    or of the landing event the learner waited for, tells the rollouts apart.
    """

    def __init__(self, keep: int = 256) -> None:
        self._frames: collections.deque[Image] = collections.deque(maxlen=keep)
        self._dropped: float | None = None  # the stamp of the newest frame no longer kept
        self._cond = threading.Condition()

    def put(self, image: Image) -> None:
        with self._cond:
            if len(self._frames) == self._frames.maxlen:
                self._dropped = self._frames[0].stamp
            self._frames.append(image)
            self._cond.notify_all()

    def _dropped_fits(self, after_stamp: float | None) -> bool:
        """Whether a frame no longer kept might satisfy a grab for `after_stamp`."""
        return self._dropped is not None and (after_stamp is None or after_stamp <= self._dropped)

    def verbs(self, marks: CalibrationReply | None) -> ServedVerbs:
        """The camera's verbs as a replay answers them: `grab` from the replayed frames,
        `calibration` with the recorded calibration frame and marks (`marks`; None: the
        recording has none, which `calibration` says) and its frames in `status`."""

        def calibration(_: NoArgs) -> CalibrationReply:
            if marks is None:
                raise BadRequest(
                    "this recording has no calibration marks (the camera gave none when it was "
                    "recorded); give the detector the colour model of the recorded session "
                    "(`archery detector --model FILE`)"
                )
            return marks

        def status(_: NoArgs) -> CameraStatusReply:
            with self._cond:
                last = self._frames[-1] if self._frames else None
                count = len(self._frames)
            return CameraStatusReply(
                source="replay",
                width=last.width if last else 0,
                height=last.height if last else 0,
                rate=0.0,
                encoding=last.encoding if last else "",
                frames=count,
                renders=0,
                reuses=0,
                render_ms=None,
                errors=0,
                latest_sim_time=last.sim_time if last else None,
                scene=None,
                scene_from="replay",
            )

        def scene(_: NoArgs) -> SceneReply:
            raise BadRequest(
                "a replay serves the recorded camera frames only: it has no view of the robot "
                "(`archery film SESSION --recording FILE.mcap` films a recorded rollout)"
            )

        return CAMERA_VERBS.bind(
            GRAB.to(self.grab),
            CALIBRATION.to(calibration),
            STATUS.to(status),
            SCENE.to(scene),
        )

    def grab(self, grab: GrabArgs) -> Image:
        """The first frame (published so far, or within the timeout, never past its caller's
        own) with sim time ≥ `after_sim_time` and stamp ≥ `after_stamp`.

        Raises:
            RpcTimeout: no such frame published within the timeout.
            BadRequest: the frame asked for may be one of those no longer kept.
        """
        timeout = grab.timeout or 5.0

        def fits(image: Image) -> bool:
            if grab.after_stamp is not None and image.stamp < grab.after_stamp:
                return False
            if grab.after_sim_time is None:
                return True
            return image.sim_time is not None and image.sim_time >= grab.after_sim_time

        left = caller_left()  # never past the caller's own timeout
        wait = min(timeout, MAX_GRAB_TIMEOUT, max(0.0, left) if left is not None else timeout)
        deadline = time.monotonic() + wait
        with self._cond:
            while True:
                found = next((image for image in self._frames if fits(image)), None)
                if found is not None:
                    if found is self._frames[0] and self._dropped_fits(grab.after_stamp):
                        raise BadRequest(
                            f"the frame asked for (sim time >= {grab.after_sim_time}, stamp >= "
                            f"{grab.after_stamp}) may be among the replayed frames no longer "
                            f"kept (the newest {self._frames.maxlen} are)"
                        )
                    return found
                left = deadline - time.monotonic()
                if left <= 0:
                    raise RpcTimeout(
                        f"no replayed frame with sim time >= {grab.after_sim_time} and stamp >= "
                        f"{grab.after_stamp} within {timeout:g} s",
                    )
                self._cond.wait(left)


class _Channels:
    """Which of a recording's channels a replay publishes, and as which key.

    A channel is published when it is an output stream of the recorded robot (its key
    `SOURCE/...` one of `protocol.keys.OUTPUT_PORTS`) and holds that port's message type; it goes
    out as `TARGET/...`. Any other (a `command:i`, an `rpc:i`, a tap, another robot's key, Zenoh's
    admin space `@/...`) is skipped: counted, and named once on stderr.

    Args:
        source: the robot prefix the recording's keys carry (the recording's robot).
        target: the robot prefix to publish under (`--robot`; default the recording's).
    """

    def __init__(self, source: str, target: str) -> None:
        self.source = source
        self.target = target
        self._decided: dict[tuple[str, str], str | None] = {}  # (key, type) -> out key or None
        self.skipped = 0  # messages
        self.skipped_channels = 0

    def out_key(self, key: str, message: Message) -> str | None:
        """The key to publish `message` of channel `key` on, or None: skip it (said once per
        channel on stderr)."""
        kind = type(message).__name__
        decided = self._decided.get((key, kind), "")
        if decided == "":
            decided = self._decide(key, kind)
            self._decided[(key, kind)] = decided
        if decided is None:
            self.skipped += 1
        return decided

    def _decide(self, key: str, kind: str) -> str | None:
        port = output_port(key, self.source)
        if port is None:
            why = f"not an output stream of robot {self.source!r}"
        elif port.message != kind:
            why = f"it holds {kind} messages, not the port's {port.message}"
        else:
            return f"{self.target}/{key.split('/', 1)[1]}"
        self.skipped_channels += 1
        print(
            f"archery replay: skipped channel {shown(key)}: {why} (a replay publishes only the "
            f"robot's state:o, world, camera frame and event streams)",
            file=sys.stderr,
            flush=True,
        )
        return None


def replay_main(argv: list[str] | None = None) -> int:
    """`archery replay FILE.mcap [--rate R] [--keys PATTERN]`: publish a recording again."""
    parser = ArgumentParser(
        prog="archery replay",
        description="publish a recording's messages again with their original timing: the "
        "recorded robot's output streams only (state:o, world, camera frames, events), under "
        "--robot (default: the recording's robot); in secure mode as the identity `replay`",
    )
    add_network_args(parser, default_mode="client")
    parser.set_defaults(robot=None)  # None: the recording's robot
    parser.add_argument("file", help="an MCAP file written by `archery record`")
    parser.add_argument("--rate", type=seconds, default=1.0, help="speed factor (default 1)")
    parser.add_argument("--keys", help="replay only the keys matching this pattern")
    parser.add_argument(
        "--recover",
        action="store_true",
        help="replay a file cut short (a killed recorder): the messages of its complete chunks",
    )
    parser.add_argument(
        "--serve-grab",
        action="store_true",
        help="answer ROBOT/cam/rpc:i grab with the replayed frames (after_sim_time and "
        "after_stamp in the recording's clocks), and keep answering after the end until Ctrl-C",
    )
    add_max_bytes_arg(parser)
    args = parser.parse_args(argv)
    try:
        recording = open_recording(args.file, max_bytes=args.max_bytes)
        source = _rec_robot(recording)
        if args.robot is None:
            args.robot = source
        net = NetConfig.from_args(args).with_identity(REPLAY)
        if not recording.complete and not args.recover:
            raise ConfigError(
                f"{args.file!r} is cut short (no summary: was the recorder killed?); "
                f"--recover replays the messages of its complete chunks"
            )
        only = check_pattern(args.keys) if args.keys else None
    except ArcheryError as exc:
        return _fail("replay", exc, 2)
    stop = shutdown_on_signals()
    try:
        with Node(None, net) as node:
            frames = _Frames()
            if args.serve_grab:
                node.serve(node.keys.cam_rpc(), frames.verbs(_recorded_marks(recording)))
                print(f"archery replay: serving grab on {node.keys.cam_rpc()}", flush=True)
            channels = _Channels(source, net.robot)
            published, keys = _publish(node, recording, args, only, channels, frames, stop)
            skipped = (
                f" ({channels.skipped} messages on {channels.skipped_channels} channels skipped: "
                f"not the robot's output streams)"
                if channels.skipped_channels
                else ""
            )
            print(
                f"archery replay: published {published} messages on {len(keys)} keys{skipped}",
                flush=True,
            )
            if args.serve_grab:
                wait_for_stop(stop)
    except ArcheryError as exc:  # a malformed record found while publishing: bad input, 2
        return _fail("replay", exc, for_error(exc.code))
    if channels.skipped_channels and not published:
        print(
            f"archery replay: nothing replayed: {args.file!r} holds none of the robot's output "
            f"streams",
            file=sys.stderr,
        )
        return 2
    return 0


def _recorded_marks(recording: Recording) -> CalibrationReply | None:
    """The camera's calibration reply recorded with the frames, or None.

    Raises:
        ConfigError: the attachment is there but unreadable.
    """
    data = recording.attachment(CALIBRATION_ATTACHMENT)
    if data is None:
        return None
    try:
        return msgspec.msgpack.decode(data, type=CalibrationReply)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ConfigError(f"{recording.path}: its calibration attachment: {exc}") from None


def _rec_robot(recording: Recording) -> str:
    """The robot prefix the recording's keys carry (its metadata; `icubSim` when it has none).

    Raises:
        ConfigError: the metadata names no valid robot prefix.
    """
    robot = recording.metadata.get("robot") or "icubSim"
    try:
        return validate_robot(robot)
    except KeyNameError:
        raise ConfigError(
            f"{str(recording.path)!r} names no valid robot (its metadata says {shown(robot)})"
        ) from None


def _publish(
    node: Node,
    recording: Recording,
    args: Any,
    only: zenoh.KeyExpr | None,
    channels: _Channels,
    frames: _Frames,
    stop: threading.Event,
) -> tuple[int, set[str]]:
    """Publish the recording's messages that `only` selects (None: all) and `channels` lets
    through, in their recorded timing (`args.rate` times faster); the frames also go to
    `frames` (for `--serve-grab`). Returns (messages published, keys published on)."""
    publishers: dict[str, zenoh.Publisher] = {}
    start = time.monotonic()
    first: int | None = None
    published = 0
    try:
        for key, message, log_time in recording.messages(recover=args.recover):
            if stop.is_set():
                break
            if only is not None and not _selects(only, key):
                continue
            out = channels.out_key(key, message)
            if out is None:
                continue
            first = log_time if first is None else first
            due = start + (log_time - first) / 1e9 / args.rate
            if stop.wait(min(max(0.0, due - time.monotonic()), threading.TIMEOUT_MAX)):
                break
            pub = publishers.get(out)
            if pub is None:
                pub = node.session.declare_publisher(
                    out,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                publishers[out] = pub
            if isinstance(message, Image):
                frames.put(message)
            pub.put(encode(message))
            published += 1
    finally:
        for pub in publishers.values():
            pub.undeclare()
    return published, set(publishers)


def _selects(only: zenoh.KeyExpr, key: str) -> bool:
    """Whether the `--keys` pattern covers the recorded key (False for no valid key)."""
    try:
        return bool(only.includes(zenoh.KeyExpr(key)))
    except zenoh.ZError:
        return False


# -- hz -------------------------------------------------------------------------------------------


class _Rates:
    """Arrival times and sizes per key."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.times: dict[str, list[float]] = collections.defaultdict(list)
        self.sizes: dict[str, int] = collections.defaultdict(int)

    def add(self, key: str, size: int) -> None:
        with self.lock:
            self.times[key].append(time.monotonic())
            self.sizes[key] += size

    def lines(self, since: float) -> list[str]:
        out = []
        with self.lock:
            items = [(k, list(v), self.sizes[k]) for k, v in sorted(self.times.items())]
        for key, times, size in items:
            span = max(time.monotonic() - since, 1e-9)
            gaps = [b - a for a, b in itertools.pairwise(times)]
            rate = (len(times) - 1) / (times[-1] - times[0]) if len(gaps) else 0.0
            jitter = (
                f"  gap min {min(gaps) * 1e3:.1f} max {max(gaps) * 1e3:.1f} "
                f"std {statistics.pstdev(gaps) * 1e3:.1f} ms"
                if gaps
                else ""
            )
            out.append(
                f"{key}  {rate:.2f} Hz  {size / span / 1e6:.3f} MB/s  "
                f"n={len(times)}  mean size {size / len(times) / 1e3:.1f} kB{jitter}"
            )
        return out


def hz_main(argv: list[str] | None = None) -> int:
    """`archery hz KEY_PATTERN`: message rate and bandwidth of each matching key."""
    parser = ArgumentParser(
        prog="archery hz",
        description="print each matching key's message rate (Hz) and bandwidth (MB/s)",
    )
    add_network_args(parser, default_mode="client")
    parser.add_argument("pattern", metavar="KEY_PATTERN")
    parser.add_argument("--duration", type=seconds, help="measure this long (s), then print")
    parser.add_argument("--count", type=count, default=0, help="stop after N messages (0: no)")
    parser.add_argument(
        "--window", type=seconds, default=1.0, help="print every N s while measuring (default 1)"
    )
    args = parser.parse_args(argv)
    try:
        net = NetConfig.from_args(args).with_identity(VIEWER)
        expr = check_pattern(args.pattern)
    except ArcheryError as exc:
        return _fail("hz", exc, 2)
    stop = shutdown_on_signals()
    rates = _Rates()
    done = threading.Event()
    seen = [0]

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if stream_type(key) is None or done.is_set():
            return
        rates.add(key, len(sample.payload))
        seen[0] += 1
        if args.count and seen[0] >= args.count:
            done.set()

    try:
        with Node(None, net) as node:
            start = time.monotonic()
            sub = node.session.declare_subscriber(expr, on_sample)
            try:
                end = None if args.duration is None else start + args.duration
                while not stop.is_set() and not done.is_set():
                    step = args.window if end is None else min(args.window, end - time.monotonic())
                    if step <= 0:
                        break
                    if done.wait(step):
                        break
                    if end is None or time.monotonic() < end:
                        for line in rates.lines(start):
                            print(line, flush=True)
            finally:
                sub.undeclare()
    except ArcheryError as exc:
        return _fail("hz", exc, 1)
    lines = rates.lines(start)
    if not lines:
        print(f"archery hz: no message on {args.pattern}", file=sys.stderr)
        return 1
    print("--- total", flush=True)
    for line in lines:
        print(line, flush=True)
    return 0
