"""The detector service's frozen, validated configuration and its command-line flags."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

from archery.mesh.cliargs import check_writable_dir
from archery.mesh.configflags import add_config_args, check_bounds, config_from_args, flag
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ConfigError
from archery.protocol.robotspec import CAMERA_TIMEOUT
from archery.protocol.verbs import detector as dv
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import DetectorSettings
from archery.services.detector.errors import ModelFileError

__all__ = [
    "DetectorConfig",
    "add_arguments",
    "add_settings_arguments",
    "make_config",
    "settings_from_args",
]


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings.

    Attributes:
        net: network settings.
        model: colour model file (read at start if it exists, written by `calibrate`).
        settings: detection settings (target size, thresholds; flags shared with `archery
            detect`).
        auto_calibrate: without a model, calibrate from the camera's marks once it is alive.
        camera_timeout: default wait for a camera frame (s).
    """

    net: NetConfig = field(default_factory=NetConfig)
    model: str | None = flag(
        None, "colour model file (read if it exists, written on calibrate)", metavar="FILE"
    )
    settings: DetectorSettings = field(default_factory=DetectorSettings)
    auto_calibrate: bool = flag(
        True,
        "do not calibrate from the camera's marks when there is no model",
        name="--no-auto-calibrate",
    )
    camera_timeout: float = flag(
        CAMERA_TIMEOUT,
        "default wait for a camera frame",
        unit="wall s",
        low=0,
        high=dv.MAX_TIMEOUT,
        low_open=True,
    )

    def __post_init__(self) -> None:
        check_bounds(self)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the detector's own flags: the config's and the detection settings'."""
    add_config_args(parser, DetectorConfig)
    add_settings_arguments(parser)


def make_config(args: argparse.Namespace, net: NetConfig) -> DetectorConfig:
    """Build the config from parsed flags, checking the model file's place and contents.

    Raises:
        ConfigError: an invalid value; the message names the flag and what is valid.
    """
    if args.model:
        model = Path(args.model)
        if model.exists() and not model.is_file():
            raise ConfigError(f"--model {args.model!r} is not a file")
        check_writable_dir(model.parent, f"--model {args.model!r}: folder", create=False)
        if model.exists():
            try:
                ColourModel.load(args.model)
            except ModelFileError as exc:
                raise ConfigError(f"--model {args.model}: {exc}") from None
    config: DetectorConfig = config_from_args(
        DetectorConfig, args, net=net, settings=settings_from_args(args)
    )
    return config


def add_settings_arguments(parser: argparse.ArgumentParser) -> None:
    """The detection flags shared by `archery detect` and `archery detector`."""
    defaults = DetectorSettings()
    parser.add_argument(
        "--target-diameter",
        type=float,
        default=defaults.target_diameter_m,
        help="target face diameter (m)",
    )
    parser.add_argument(
        "--coloured-fraction",
        type=float,
        default=defaults.coloured_fraction,
        help="diameter of the calibrated colours over the face's (yellow+red+blue: 0.6)",
    )


def settings_from_args(args: argparse.Namespace) -> DetectorSettings:
    """Detection settings from the flags of `add_settings_arguments` (validated)."""
    return DetectorSettings(
        target_diameter_m=args.target_diameter, coloured_fraction=args.coloured_fraction
    )
