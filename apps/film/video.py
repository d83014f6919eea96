"""Writing a film: H.264 MP4 frames with a caption, and the six-frame contact sheet.

The encoder is PyAV's: its wheel ships FFmpeg's libraries with libx264, so frames go from
numpy to the MP4 in-process, with no ffmpeg program on the PATH and no pipe (imageio-ffmpeg
also ships an encoder, but as an ffmpeg executable fed through a pipe). yuv420p, which every
common player plays.
"""

from __future__ import annotations

from fractions import Fraction
from functools import cache
from pathlib import Path

import av
import numpy as np
from PIL import Image, ImageDraw, ImageFont

__all__ = ["Caption", "ShotVideo", "caption", "contact_sheet"]

Caption = list[str]


@cache
def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """DejaVu Sans (it has θ), from matplotlib's fonts; Pillow's own font otherwise."""
    try:
        from matplotlib import font_manager

        return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)
    except (ImportError, OSError):
        return ImageFont.load_default(size)


def caption(frame: np.ndarray, lines: Caption) -> np.ndarray:
    """`frame` (H, W, 3 uint8) with `lines` written on a dark band at its top left."""
    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image, "RGBA")
    size = max(12, frame.shape[0] // 24)
    font = _font(size)
    pad = size // 2
    widths = [draw.textlength(line, font=font) for line in lines]
    height = len(lines) * (size + pad // 2) + pad
    draw.rectangle((0, 0, max(widths, default=0) + 2 * pad, height), fill=(0, 0, 0, 150))
    for i, line in enumerate(lines):
        draw.text((pad, pad // 2 + i * (size + pad // 2)), line, font=font, fill=(255, 255, 255))
    return np.asarray(image)


class ShotVideo:
    """An H.264 MP4 file being written, frame by frame (even width and height, px).

    Args:
        path: the file (replaced).
        width, height: the frame size (px, even).
        fps: video frames per second.
    """

    def __init__(self, path: Path, width: int, height: int, fps: int) -> None:
        if width % 2 or height % 2:
            raise ValueError(f"H.264 needs an even frame size, got {width}x{height}")
        self.path = Path(path)
        self._container: av.container.OutputContainer | None = av.open(str(self.path), mode="w")
        stream = self._container.add_stream("libx264", rate=Fraction(fps))
        stream.width, stream.height = width, height
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "23", "preset": "veryfast"}
        self._stream = stream
        self.frames = 0

    def add(self, frame: np.ndarray, repeat: int = 1) -> None:
        """Append `frame` (H, W, 3 uint8 RGB) `repeat` times.

        Raises:
            ValueError: the video is closed.
        """
        if self._container is None:
            raise ValueError(f"{self.path} is closed")
        video = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
        for _ in range(repeat):
            self._container.mux(self._stream.encode(video))
            self.frames += 1

    def close(self) -> None:
        """Flush the encoder and close the file (idempotent)."""
        if self._container is None:
            return
        self._container.mux(self._stream.encode())
        self._container.close()
        self._container = None

    def __enter__(self) -> ShotVideo:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def contact_sheet(frames: list[np.ndarray], columns: int = 3) -> Image.Image:
    """The frames (each H, W, 3, equal sizes) tiled `columns` wide, 4 px apart on white."""
    if not frames:
        raise ValueError("a contact sheet needs at least one frame")
    h, w = frames[0].shape[:2]
    rows = -(-len(frames) // columns)
    gap = 4
    sheet = Image.new(
        "RGB", (columns * w + (columns - 1) * gap, rows * h + (rows - 1) * gap), "white"
    )
    for i, frame in enumerate(frames):
        sheet.paste(Image.fromarray(frame), ((i % columns) * (w + gap), (i // columns) * (h + gap)))
    return sheet
