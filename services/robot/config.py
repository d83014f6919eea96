"""The robot service's frozen, validated configuration and its command-line flags."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field, replace

from protocol.errors import ConfigError
from protocol.netflags import NetConfig
from protocol.service import config_number
from sim.bow import BowError
from sim.errors import SimError
from sim.world import WorldConfig

__all__ = ["RobotConfig", "add_robot_arguments", "config_from_args", "parse_vector3"]


@dataclass(frozen=True)
class RobotConfig:
    """Everything `archery robot` needs.

    Attributes:
        net: network settings (the common flags).
        world: the simulated robot, bow and shot (`sim.world.WorldConfig`).
        seed: seed of the shot noise at start-up (`reset {"seed"}` reseeds); None: fresh entropy.
        rtf: real-time factor: 1.0 paces simulated time with the wall clock (for watching),
            0 runs as fast as possible and only while something moves (see `simloop`).
        state_rate: joint state streams per simulated second (Hz).
        world_rate: world state messages per simulated second (Hz); also one after each landing.
        watchdog: a command stream (commands overtaking unfinished moves) with no command for
            this long (wall s) freezes the part at its measured positions; 0 switches it off.
        limit_tolerance: a command up to this far beyond a joint limit is clamped; further is
            rejected (rad).
        batch_window: at rtf 0, commands arriving within this long (wall s) of the one that woke
            the idle simulation start together, at the same simulated time.
        job_timeout: longest wait of an RPC for the simulation thread (wall s).
    """

    net: NetConfig = field(default_factory=NetConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    seed: int | None = 0
    rtf: float = 0.0
    state_rate: float = 50.0
    world_rate: float = 30.0
    watchdog: float = 0.5
    limit_tolerance: float = 0.02
    batch_window: float = 0.01
    job_timeout: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.net, NetConfig):
            raise ConfigError(f"net must be a NetConfig, got {self.net!r}")
        if not isinstance(self.world, WorldConfig):
            raise ConfigError(f"world must be a sim.world.WorldConfig, got {self.world!r}")
        if self.seed is not None and (
            isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0
        ):
            raise ConfigError(f"--seed must be an integer >= 0, got {self.seed!r}")
        bounds = {
            "rtf": (0.0, 100.0),
            "state_rate": (0.1, 1000.0),
            "world_rate": (0.1, 1000.0),
            "watchdog": (0.0, 60.0),
            "limit_tolerance": (0.0, 0.5),
            "batch_window": (0.0, 1.0),
            "job_timeout": (0.1, 600.0),
        }
        for name, (low, high) in bounds.items():
            flag = "--" + name.replace("_", "-")
            object.__setattr__(self, name, config_number(flag, getattr(self, name), low, high))


def parse_vector3(text: str, flag: str) -> tuple[float, float, float]:
    """Parse "X,Y,Z" into three finite floats.

    Raises:
        ConfigError: not three comma-separated finite numbers; the message names the flag.
    """
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{flag} must be three numbers X,Y,Z (m/s), got {text!r}")
    return values  # type: ignore[return-value]


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the robot's own flags."""
    defaults = RobotConfig()
    world = defaults.world
    parser.add_argument("--seed", type=int, default=0, help="seed of the shot noise (default 0)")
    parser.add_argument(
        "--rtf",
        type=float,
        default=defaults.rtf,
        help="real-time factor: 1 = wall-clock pace, 0 = as fast as possible (default 0)",
    )
    parser.add_argument(
        "--wind", default=None, metavar="VX,VY,VZ", help="constant wind (m/s, root frame)"
    )
    parser.add_argument("--drag", type=float, default=world.drag, help="drag K (1/m)")
    parser.add_argument(
        "--bow-stiffness", type=float, default=world.bow.stiffness, help="bow stiffness (N/m)"
    )
    parser.add_argument(
        "--state-rate", type=float, default=defaults.state_rate, help="joint states per sim s"
    )
    parser.add_argument(
        "--world-rate", type=float, default=defaults.world_rate, help="world states per sim s"
    )
    parser.add_argument(
        "--watchdog",
        type=float,
        default=defaults.watchdog,
        help="stale command stream timeout (wall s, 0 = off)",
    )
    parser.add_argument(
        "--limit-tolerance",
        type=float,
        default=defaults.limit_tolerance,
        help="commands this far beyond a limit are clamped, further rejected (rad)",
    )


def config_from_args(args: argparse.Namespace, net: NetConfig) -> RobotConfig:
    """Build the config from parsed flags.

    Raises:
        ConfigError: any invalid value; the message names the flag and its valid range.
    """
    base = WorldConfig()
    try:
        bow = replace(base.bow, stiffness=args.bow_stiffness)
    except BowError as exc:
        raise ConfigError(f"--bow-stiffness: {exc}") from None
    wind = base.wind if args.wind is None else parse_vector3(args.wind, "--wind")
    try:
        world = replace(base, bow=bow, wind=wind, drag=args.drag)
    except SimError as exc:
        raise ConfigError(f"invalid world setting: {exc}") from None
    return RobotConfig(
        net=net,
        world=world,
        seed=args.seed,
        rtf=args.rtf,
        state_rate=args.state_rate,
        world_rate=args.world_rate,
        watchdog=args.watchdog,
        limit_tolerance=args.limit_tolerance,
    )
