"""The camera service's frozen, validated configuration and its command-line flags."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

from archery.mesh.configflags import add_config_args, check_bounds, config_from_args, flag
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ConfigError
from archery.protocol.robotspec import ROBOT_TIMEOUT
from archery.services.camera.sources import SourceSpec, parse_source

__all__ = ["ENCODINGS", "CameraConfig", "add_arguments", "make_config"]

ENCODINGS = ("rgb8_lz4", "rgb8", "jpeg", "png")


@dataclass(frozen=True)
class CameraConfig:
    """Camera settings.

    Attributes:
        net: network settings.
        source: where frames come from (`parse_source`).
        width, height: image size (px) of rendered frames, and asked of a device (`--size`).
        rate: frames published per wall second.
        rest_rate: frames per wall second at most while a rendered view is unchanged (the
            same pixels as the last frame sent: the robot's arms moving behind the camera, a
            target at rest); a changed view, a `grab` and a new subscriber get a frame at once.
        encoding: rgb8_lz4 (default: the raw pixels in one LZ4 block, lossless; a rendered
            1280x720 frame is ~55 kB instead of 2.7 MB through the router), rgb8 (raw), jpeg
            or png.
        robot_timeout: how long to wait for the robot's scene parameters at start (s).
        frame_timeout: how long a `yarp:` source waits for its name server and for a frame (s).
    """

    net: NetConfig = field(default_factory=NetConfig)
    source: SourceSpec = flag(
        SourceSpec("mujoco"),
        "mujoco (render the robot's scene), device:N, folder:PATH or yarp:/PORT (a YARP image "
        "port, e.g. yarp:/icub/cam/left) (default mujoco)",
        parse=parse_source,
    )
    width: int = flag(1280, "image width", unit="px", low=16, high=4096, name="--size", cli=False)
    height: int = flag(720, "image height", unit="px", low=16, high=4096, name="--size", cli=False)
    rate: float = flag(10.0, "frames per second", unit="frames/s", low=0.1, high=120)
    rest_rate: float = flag(
        1.0,
        "frames per second at most while the rendered view is unchanged",
        unit="frames/s",
        low=0.1,
        high=120,
    )
    encoding: str = flag(
        "rgb8_lz4",
        "rgb8_lz4 (lossless LZ4), rgb8 (raw), jpeg or png (lossy or slow)",
        choices=ENCODINGS,
    )
    robot_timeout: float = flag(
        ROBOT_TIMEOUT,
        "wait this long for the robot's scene parameters at start",
        unit="s",
        low=0,
        high=60,
    )
    frame_timeout: float = flag(
        5.0,
        "wait this long for a frame (and for YARP's name server) of a yarp: source",
        unit="s",
        low=0.1,
        high=60,
    )

    def __post_init__(self) -> None:
        check_bounds(self)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the camera's own flags: the config's and `--size`."""
    add_config_args(parser, CameraConfig)
    defaults = CameraConfig()
    parser.add_argument(
        "--size",
        default=f"{defaults.width}x{defaults.height}",
        metavar="WIDTHxHEIGHT",
        help="image size (px, 16..4096 each; default %(default)s)",
    )


def make_config(args: argparse.Namespace, net: NetConfig) -> CameraConfig:
    """Build the config from parsed flags.

    Raises:
        ConfigError: an invalid value; the message names the flag and what is valid; for
            rendered frames, a rendering backend that does not start (`sim.gl_backend.check`).
    """
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {args.size!r} is not WIDTHxHEIGHT, e.g. 1280x720") from None
    config: CameraConfig = config_from_args(CameraConfig, args, net=net, width=width, height=height)
    if config.source.kind == "mujoco":  # a backend that cannot start: exit 2 before serving
        from archery.sim.gl_backend import check

        check()
    return config
