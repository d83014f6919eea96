"""Offline tools for real photos: `archery calibrate` (fit a colour model from marked pixels) and
`archery detect` (find the target centre and the arrow tip, one JSON line per image).

`archery detect IMAGE...` prints, per image, `{"image": path, "target": {"px": [x, y],
"confidence": c} or null, "arrow": … or null, "r_m": [right, up] or null, "rings": [ellipse,
...]}` (pixels: column, row; r in metres, the mesh's convention: arrow − centre, r[0] to the
right, r[1] up; rings: the fitted ring ellipses, inner → outer, see `rings.Ellipse.to_dict`),
with a progress bar on stderr for several images. Exit status 0 whatever is seen, 2 for bad
input (unreadable image, malformed pixels or model file) with the reason on stderr; with several
images an unreadable one gives `{"image": path, "error": reason}` and the others are measured.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from archery.apps.progress import progress_bar
from archery.mesh.cliargs import (
    ArgumentParser,
    add_force_arg,
    check_output_file,
    count,
    int_in,
)
from archery.protocol.errors import ArcheryError
from archery.services.detector.calibration import fit_from_marks, load_pixels
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.config import add_settings_arguments, settings_from_args
from archery.services.detector.detect import Detector, check_image
from archery.services.detector.errors import ImageError
from archery.services.detector.overlay import draw_overlay
from archery.services.detector.whitebalance import apply_gains

__all__ = [
    "calibrate_main",
    "detect_main",
    "read_rgb",
    "write_png",
]


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3).

    Raises:
        ImageError: missing, not an image, or of an unusable size.
    """
    if not Path(path).is_file():  # before OpenCV, which would warn on stderr too
        what = "a folder, not a file" if Path(path).is_dir() else "no such file"
        raise ImageError(f"cannot read an image from {str(path)!r}: {what}")
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
    parser.add_argument("--out", required=True, help="colour model file to write (.json)")
    add_force_arg(parser, "an existing --out file")
    parser.add_argument(
        "--max-components",
        type=int_in(1, 10, "a number of components"),
        default=5,
        help="largest K tried by BIC (1..10, default 5)",
    )
    parser.add_argument("--seed", type=count, default=0, help="seed of the GMM fits (>= 0)")
    args = parser.parse_args(argv)
    try:
        check_output_file(args.out, "--out", (".json",), force=args.force)
        rgb = read_rgb(args.image)
        fitted = fit_from_marks(
            rgb, load_pixels(args.pixels), max_components=args.max_components, seed=args.seed
        )
        model = fitted.model
        model.save(args.out)
    except (ArcheryError, OSError) as exc:
        print(f"archery calibrate: {exc}", file=sys.stderr)
        return 2
    summary = {
        "model": args.out,
        **model.summary(),
        "target_pixels": fitted.target_pixels,
        "arrow_pixels": fitted.arrow_pixels,
        "white_rgb": model.white_rgb,
    }
    print(json.dumps(summary))
    return 0


def _detect_one(
    detector: Detector, image: str, overlay: Path | None, rgb: np.ndarray | None = None
) -> dict[str, object]:
    """The JSON line of one image, read unless `rgb` is given (raises ArcheryError for bad
    input)."""
    rgb = read_rgb(image) if rgb is None else rgb
    detection = detector.detect(rgb)
    if overlay is not None:  # the pixels the model keeps, under the light it was found in
        shown = rgb if detection.gains is None else apply_gains(rgb, np.asarray(detection.gains))
        write_png(overlay, draw_overlay(rgb, detection, detector.memberships(shown)))
    return {
        "image": image,
        **detection.to_json(),
        "rings": [ring.to_dict() for ring in detection.rings],
    }


def detect_main(argv: list[str] | None = None) -> int:
    """`archery detect IMAGE... --model MODEL.json [--overlay OUT]`: one JSON line per image."""
    parser = ArgumentParser(
        prog="archery detect",
        description="find the target centre and the arrow tip in images (paper Section III-C)",
    )
    parser.add_argument("image", nargs="+", help="image files (PNG, JPEG, ...)")
    parser.add_argument("--model", required=True, help="colour model from `archery calibrate`")
    parser.add_argument(
        "--overlay",
        help="write the image and its filtered pixels with the detection and the fitted rings "
        "(PNG; with several images, a folder that gets IMAGE-NAME.png each)",
    )
    add_force_arg(parser, "existing overlay files")
    parser.add_argument(
        "--no-progress", action="store_true", help="no progress bar for several images"
    )
    add_settings_arguments(parser)
    args = parser.parse_args(argv)
    several = len(args.image) > 1
    first = None
    try:
        overlays = _overlays(args.image, args.overlay, force=args.force)
        if not several:  # a missing image is named before a missing model, as it always was
            first = read_rgb(args.image[0])
        detector = Detector(ColourModel.load(args.model), settings_from_args(args))
    except ArcheryError as exc:
        print(f"archery detect: {exc}", file=sys.stderr)
        return 2
    status = 0
    with _progress(len(args.image), enabled=several and not args.no_progress) as advance:
        for image, overlay in zip(args.image, overlays, strict=True):
            try:
                line = _detect_one(detector, image, overlay, first)
            except ArcheryError as exc:
                print(f"archery detect: {exc}", file=sys.stderr)
                status = 2
                if not several:
                    return status
                line = {"image": image, "error": str(exc)}
            print(json.dumps(line), flush=True)
            advance()
    return status


def _overlays(images: list[str], overlay: str | None, *, force: bool) -> list[Path | None]:
    """Each image's overlay file: `overlay` itself for one image; for several, IMAGE-NAME.png
    in the folder `overlay` (a/x.jpg, b/x.jpg → x.png, x-2.png). Each is checked as an output
    (`mesh.cliargs.check_output_file`) before any image is read.

    Raises:
        ConfigError, ImageError: one line naming --overlay and what to give instead.
    """
    if overlay is None:
        return [None] * len(images)
    if len(images) == 1:
        return [check_output_file(overlay, "--overlay", (".png",), force=force)]
    if not Path(overlay).is_dir():
        raise ImageError(f"--overlay {overlay!r} must be a folder for several images")
    stems: dict[str, int] = {}
    paths: list[Path | None] = []
    for image in images:
        stem = Path(image).stem
        stems[stem] = stems.get(stem, 0) + 1
        name = stem if stems[stem] == 1 else f"{stem}-{stems[stem]}"
        path = Path(overlay) / f"{name}.png"
        check_output_file(path, "--overlay", (".png",), force=force)
        paths.append(path)
    return paths


@contextlib.contextmanager
def _progress(total: int, *, enabled: bool) -> Iterator[Callable[[], None]]:
    """A progress bar on stderr (rich) over `total` images; yields the step function."""
    if not enabled:
        yield lambda: None
        return
    with progress_bar() as bar:
        task = bar.add_task("images", total=total)
        yield lambda: bar.advance(task)
