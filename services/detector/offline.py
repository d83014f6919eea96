"""Offline tools for real photos: `archery calibrate` and `archery detect`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from protocol.errors import ArcheryError
from services.detector.calibration import load_pixels, sample_pixels
from services.detector.colour_model import ColourModel
from services.detector.detect import Detector, DetectorSettings
from services.detector.errors import ImageError
from services.detector.overlay import draw_overlay

__all__ = ["calibrate_main", "detect_main", "read_rgb"]


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8; raises ImageError when it cannot be read."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ImageError(f"cannot read an image from {str(path)!r} (missing, or not an image)")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def calibrate_main(argv: list[str] | None = None) -> int:
    """`archery calibrate IMAGE --pixels PIXELS.json --out MODEL.json`."""
    parser = argparse.ArgumentParser(
        prog="archery calibrate", description="fit the target/arrow colour model from marked pixels"
    )
    parser.add_argument("image")
    parser.add_argument("--pixels", required=True, help="PIXELS.json: target (and arrow) marks")
    parser.add_argument("--out", required=True, help="model file to write (JSON)")
    parser.add_argument("--max-components", type=int, default=5, help="largest K tried by BIC")
    args = parser.parse_args(argv)
    try:
        rgb = read_rgb(args.image)
        marks = load_pixels(args.pixels)
        target = sample_pixels(rgb, marks["target"], "target")
        arrow = sample_pixels(rgb, marks["arrow"], "arrow") if marks.get("arrow") else None
        model = ColourModel.fit(target, arrow, max_components=args.max_components)
        model.save(args.out)
    except ArcheryError as exc:
        print(f"archery calibrate: {exc}", file=sys.stderr)
        return 1
    summary = {
        "model": args.out,
        "target_components": model.target.n_components,
        "arrow_components": model.arrow.n_components if model.arrow else None,
        "target_pixels": len(target),
        "arrow_pixels": 0 if arrow is None else len(arrow),
    }
    print(json.dumps(summary))
    return 0


def detect_main(argv: list[str] | None = None) -> int:
    """`archery detect IMAGE --model MODEL.json [--overlay OUT.png]`: one JSON object."""
    parser = argparse.ArgumentParser(
        prog="archery detect", description="find the target centre and the arrow tip in an image"
    )
    parser.add_argument("image")
    parser.add_argument("--model", required=True, help="colour model from `archery calibrate`")
    parser.add_argument("--overlay", help="write the frame with the detection drawn (PNG)")
    parser.add_argument("--target-diameter", type=float, default=0.50, help="face diameter (m)")
    parser.add_argument(
        "--coloured-fraction",
        type=float,
        default=0.6,
        help="diameter of the calibrated colours over the face's (yellow+red+blue: 0.6)",
    )
    args = parser.parse_args(argv)
    try:
        rgb = read_rgb(args.image)
        settings = DetectorSettings(
            target_diameter_m=args.target_diameter, coloured_fraction=args.coloured_fraction
        )
        detection = Detector(ColourModel.load(args.model), settings).detect(rgb)
        if args.overlay and not cv2.imwrite(args.overlay, draw_overlay(rgb, detection)[:, :, ::-1]):
            raise ImageError(f"cannot write the overlay to {args.overlay!r} (use a .png path)")
    except ArcheryError as exc:
        print(f"archery detect: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(detection.to_json()))
    return 0
