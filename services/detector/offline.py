"""Offline tools for real photos: `archery calibrate` (fit a colour model from marked pixels) and
`archery detect` (find the target centre and the arrow tip, print one JSON object).

`archery detect` prints `{"target": {"px": [x, y], "confidence": c} or null, "arrow": … or
null, "r_m": [right, up] or null}` (pixels: column, row; r in metres, the mesh's convention:
arrow − centre, r[0] to the right, r[1] up). Exit status 0 whatever is seen, 2 for bad input
(unreadable image, malformed pixels or model file) with the reason on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from protocol.cliargs import ArgumentParser
from protocol.errors import ArcheryError
from services.detector.calibration import load_pixels, sample_pixels
from services.detector.colour_model import ColourModel
from services.detector.detect import Detector, DetectorSettings, check_image
from services.detector.errors import ImageError
from services.detector.overlay import draw_overlay

__all__ = [
    "add_settings_arguments",
    "calibrate_main",
    "detect_main",
    "read_rgb",
    "settings_from_args",
    "write_png",
]


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3).

    Raises:
        ImageError: missing, not an image, or of an unusable size.
    """
    if not Path(path).is_file():  # before OpenCV, which would warn on stderr too
        raise ImageError(f"cannot read an image from {str(path)!r}: no such file")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ImageError(f"cannot read an image from {str(path)!r} (missing, or not an image)")
    return check_image(np.ascontiguousarray(bgr[:, :, ::-1]))


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write RGB pixels to a PNG file.

    Raises:
        ImageError: the file cannot be written.
    """
    if Path(path).suffix.lower() != ".png":
        raise ImageError(f"overlay path {str(path)!r} must end in .png")
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1])):
        raise ImageError(f"cannot write {str(path)!r} (does its folder exist?)")


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


def calibrate_main(argv: list[str] | None = None) -> int:
    """`archery calibrate IMAGE --pixels PIXELS.json --out MODEL.json`; prints a JSON summary."""
    parser = ArgumentParser(
        prog="archery calibrate",
        description="fit the target (and arrow tip) colour model from pixels marked on an image",
    )
    parser.add_argument("image", help="the image the pixels were marked on")
    parser.add_argument(
        "--pixels",
        required=True,
        help='PIXELS.json: {"target": [[x, y], {"rect": [x, y, w, h]}, ...], "arrow": [...]}',
    )
    parser.add_argument("--out", required=True, help="colour model file to write (JSON)")
    parser.add_argument("--max-components", type=int, default=5, help="largest K tried by BIC")
    parser.add_argument("--seed", type=int, default=0, help="seed of the GMM fits")
    args = parser.parse_args(argv)
    try:
        rgb = read_rgb(args.image)
        marks = load_pixels(args.pixels)
        target = sample_pixels(rgb, marks["target"], "target")
        arrow = sample_pixels(rgb, marks["arrow"], "arrow") if "arrow" in marks else None
        model = ColourModel.fit(target, arrow, max_components=args.max_components, seed=args.seed)
        model.save(args.out)
    except (ArcheryError, OSError) as exc:
        print(f"archery calibrate: {exc}", file=sys.stderr)
        return 2
    summary = {
        "model": args.out,
        **model.summary(),
        "target_pixels": len(target),
        "arrow_pixels": 0 if arrow is None else len(arrow),
    }
    print(json.dumps(summary))
    return 0


def detect_main(argv: list[str] | None = None) -> int:
    """`archery detect IMAGE --model MODEL.json [--overlay OUT.png]`: one JSON object."""
    parser = ArgumentParser(
        prog="archery detect",
        description="find the target centre and the arrow tip in an image (paper Section III-C)",
    )
    parser.add_argument("image")
    parser.add_argument("--model", required=True, help="colour model from `archery calibrate`")
    parser.add_argument(
        "--overlay", help="write the image and its filtered pixels with the detection (PNG)"
    )
    add_settings_arguments(parser)
    args = parser.parse_args(argv)
    try:
        rgb = read_rgb(args.image)
        detector = Detector(ColourModel.load(args.model), settings_from_args(args))
        memberships = detector.memberships(rgb)
        detection = detector.locate(*memberships)
        if args.overlay:
            write_png(args.overlay, draw_overlay(rgb, detection, memberships))
    except ArcheryError as exc:
        print(f"archery detect: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(detection.to_json()))
    return 0
