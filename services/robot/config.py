"""The robot service's frozen, validated configuration and its command-line flags."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, replace

from archery.mesh.configflags import add_config_args, check_bounds, config_from_args, flag
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ConfigError
from archery.protocol.robotspec import COMMAND_BURST, COMMAND_RATE
from archery.protocol.text import shown
from archery.protocol.vectors import parse_vector
from archery.sim.bow import BowError
from archery.sim.errors import SimError
from archery.sim.scene_config import SHOTS
from archery.sim.world import WorldConfig

__all__ = ["BODIES", "RobotConfig", "add_arguments", "make_config"]

#: what `archery robot --body` serves: the simulated iCub, or a YARP robot's control boards
BODIES = ("mujoco", "yarp")
#: who tells a YARP body's arrow landing (`--landing`)
LANDINGS = ("events", "camera")


@dataclass(frozen=True)
class RobotConfig:
    """Everything `archery robot` needs.

    Attributes:
        net: network settings (the common flags).
        world: the simulated robot, bow and shot (`sim.world.WorldConfig`).
        seed: seed of the shot noise at start-up (`reset {"seed"}` reseeds); None: fresh entropy.
        rtf: real-time factor: 1.0 paces simulated time with the wall clock (for watching),
            0 runs as fast as possible and only while something moves (see `pacing`).
        state_rate: joint state streams per simulated second (Hz); at rtf 0 also at most this
            many per wall second.
        world_rate: world state messages per simulated second (Hz; at rtf 0 also at most this
            many per wall second); also one after each nock, release, landing and reset.
        rest_rate: at rtf 0, at rest (every part's motion done, no arrow in flight) and
            `rest_after` wall s after the last activity, each state stream repeats its
            unchanged state at this rate (Hz of wall time, a heartbeat; a slower stream keeps
            its own rate) instead of its full rate; any command, move, nock, release or reset
            brings the full rates back at once (see `pacing`).
        rest_after: wall seconds after the last activity (a command, a move's end, a shot, a
            reset) that a robot at rest keeps streaming at the full rates.
        watchdog: a command stream (commands overtaking unfinished moves) with no command for
            this long (wall s, from the last command's arrival) holds the part at its measured
            positions (`watchdog`); 0 switches it off.
        limit_tolerance: a command up to this far beyond a joint limit is clamped; further is
            rejected (rad).
        batch_window: at rtf 0, the longest wait (wall s) of a robot at rest for the rest of
            an announced batch of commands (`JointCommand.batch`), to start them together; a
            batch complete before then starts at once, so the window costs its length only
            when a batch stays incomplete (a sender that died mid-batch); a busy machine can
            hold a controller's three commands tens of ms apart.
        job_timeout: longest wait of an RPC for the simulation thread (wall s).
        command_rate: each part's `command:i` admits at most this many commands per wall
            second in the long run; the excess is dropped and counted (`rate_limited`), the
            part keeping its last accepted targets (see `gate`); 0 switches the limit off.
        command_burst: how many commands a part admits at once after a pause (the rate
            limit's bucket).
        body: what the robot serves: "mujoco", the simulated iCub (the default), or "yarp", a
            YARP robot's control boards (`yarp_loop`: joint states at `state_rate` per wall
            second, positionMove and the lease verbs; no archery verb, no world).
        remote: the YARP robot's name with `body` "yarp", e.g. /icubSim (its control boards
            REMOTE/PART); YARP's name server is the one YARP's configuration names.
        archery_rpc: with `body` "yarp", the robot's own archery RPC port (e.g.
            /icubSim/archery/rpc:i, `archery yarp --operator`'s): `status`, `reset`, `nock`,
            `release` and `grasp` are its answers (`yarp_archery`), and the robot's world
            events (REMOTE/world/events:o, when it exists) go to the mesh; "" (the default):
            those verbs are refused.
        landing: with `archery_rpc`, who tells the arrow's landing: "events" (the robot's
            release replies once landed, its world events forwarded) or "camera" (they are
            ignored: the detector tells it from the frames, as on a robot that does not see
            its arrows). A body without `archery_rpc` always leaves it to the camera.
        release_joint: with `body` "yarp" and no `archery_rpc`, the finger axis `release`
            opens (`yarp_shot`; "": `yarp_shot.RELEASE_JOINT` when the robot has it).
        release_open: the angle (degrees) `release` moves that finger to.
        hand_postures: a JSON file {verb: {axis: degrees}} of the hand postures of `grasp`,
            `nock` and `reset` (a verb without one is the operator's: `operator_needed`).
    """

    net: NetConfig = field(default_factory=NetConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    seed: int | None = flag(0, "seed of the shot noise", low=0)
    rtf: float = flag(
        0.0, "real-time factor: 1 = wall-clock pace, 0 = as fast as possible", low=0, high=100
    )
    state_rate: float = flag(50.0, "joint states per sim s", unit="Hz", low=0.1, high=1000)
    world_rate: float = flag(30.0, "world states per sim s", unit="Hz", low=0.1, high=1000)
    rest_rate: float = flag(
        10.0, "state heartbeats per wall s once at rest", unit="Hz", low=0.1, high=1000
    )
    rest_after: float = flag(
        1.0, "full-rate streams this long after the last activity", unit="wall s", low=0, high=60
    )
    watchdog: float = flag(
        0.1, "stale command stream timeout, 0 = off", unit="wall s", low=0, high=60
    )
    limit_tolerance: float = flag(
        0.02,
        "commands this far beyond a limit are clamped, further rejected",
        unit="rad",
        low=0,
        high=0.5,
    )
    batch_window: float = flag(
        0.5,
        "at rtf 0, longest wait for the rest of an announced command batch",
        unit="wall s",
        low=0,
        high=1,
    )
    job_timeout: float = flag(
        10.0, "longest wait of an RPC for the simulation thread", unit="wall s", low=0.1, high=600
    )
    command_rate: float = flag(
        COMMAND_RATE,
        "commands a part's command:i admits per second, the excess dropped; 0 = no limit",
        unit="per wall s",
        low=0,
        high=1e6,
    )
    command_burst: int = flag(
        COMMAND_BURST, "commands a part admits at once after a pause", low=1, high=1e6
    )
    body: str = flag(
        "mujoco",
        "the robot's body: the simulated iCub, or a YARP robot's control boards (--remote)",
        choices=BODIES,
    )
    remote: str = flag(
        "/icub", "the YARP robot's name with --body yarp (its boards REMOTE/PART)", metavar="NAME"
    )
    archery_rpc: str = flag(
        "",
        "with --body yarp, the robot's own archery RPC port (e.g. /icubSim/archery/rpc:i): its "
        "status, reset, nock, release and grasp answers, and its world events "
        "(REMOTE/world/events:o) forwarded; none: those verbs are refused",
        metavar="PORT",
    )
    landing: str = flag(
        "events",
        "with --archery-rpc, who tells the arrow's landing: the robot's events, or the camera "
        "(the robot's ignored, as on a robot that does not see its arrows)",
        choices=LANDINGS,
    )
    release_joint: str = flag(
        "",
        "with --body yarp and no --archery-rpc, the finger axis the release opens (default "
        "r_index_proximal when the robot has it)",
        metavar="AXIS",
    )
    release_open: float = flag(
        0.0, "the angle the release finger opens to", unit="degrees", low=-360, high=360
    )
    hand_postures: str = flag(
        "",
        "with --body yarp, a JSON file {grasp|nock|reset: {AXIS: degrees}}: the hand postures "
        "of those verbs (a verb without one is done by the operator and confirmed)",
        metavar="FILE",
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.body == "yarp" and not _yarp_name(self.remote):
            raise ConfigError(
                f"--remote {shown(self.remote)}: give the robot's YARP name, e.g. /icub"
            )
        if self.archery_rpc and (self.body != "yarp" or not _yarp_name(self.archery_rpc)):
            raise ConfigError(
                f"--archery-rpc {shown(self.archery_rpc)}: give a YARP port name, e.g. "
                "/icubSim/archery/rpc:i, with --body yarp"
            )
        if self.hand_postures:
            if self.body != "yarp":
                raise ConfigError("--hand-postures goes with --body yarp")
            from archery.services.robot.hand_postures import read_postures

            read_postures(self.hand_postures)  # before any work: the file and its shape


def _yarp_name(name: str) -> bool:
    """Whether `name` is a YARP port name: /, no trailing /, printable, no space."""
    return (
        name.startswith("/")
        and not name.endswith("/")
        and name.isprintable()
        and not any(c.isspace() for c in name)
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the robot's own flags: the config's and the world's (wind, drag, bow stiffness, the
    shot: posture or whole)."""
    world = WorldConfig()
    add_config_args(parser, RobotConfig)
    parser.add_argument(
        "--wind", default=None, metavar="VX,VY,VZ", help="constant wind (m/s, root frame)"
    )
    parser.add_argument("--drag", type=float, default=world.drag, help="drag K (1/m)")
    parser.add_argument(
        "--bow-stiffness", type=float, default=world.bow.stiffness, help="bow stiffness (N/m)"
    )
    parser.add_argument(
        "--shot",
        choices=SHOTS,
        default=world.scene.shot,
        help="posture: the arrow is put on the string (nock); whole: the right hand grasps it "
        "from its holder, nocks it, draws and releases (grasp, nock, release)",
    )


def make_config(args: argparse.Namespace, net: NetConfig) -> RobotConfig:
    """Build the config from parsed flags.

    Raises:
        ConfigError: any invalid value; the message names the flag and its valid range.
    """
    base = WorldConfig()
    try:
        bow = replace(base.bow, stiffness=args.bow_stiffness)
    except BowError as exc:
        raise ConfigError(f"--bow-stiffness: {exc}") from None
    wind = base.wind
    if args.wind is not None:
        wind = tuple(parse_vector("--wind", args.wind, ConfigError, unit="m/s").tolist())
    try:
        scene = replace(base.scene, shot=args.shot)
        world = replace(base, bow=bow, wind=wind, drag=args.drag, scene=scene)
    except (SimError, ConfigError) as exc:
        raise ConfigError(f"invalid world setting: {exc}") from None
    config: RobotConfig = config_from_args(RobotConfig, args, net=net, world=world)
    return config
