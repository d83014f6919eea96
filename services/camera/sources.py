"""Frame sources of the camera: the rendered scene, a real device (OpenCV) or an image folder.

Every source is used from one thread only (the camera's capture thread: GL contexts and
capture devices belong to the thread that opened them) and gives RGB uint8 frames.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from archery.protocol.errors import ArcheryError, ConfigError

__all__ = ["DeviceSource", "FolderSource", "SourceError", "SourceSpec", "parse_source"]

log = logging.getLogger("archery.camera")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class SourceError(ArcheryError):
    """A source that delivers no frame (device unplugged, unreadable files)."""

    code = "no_frame"


@dataclass(frozen=True)
class SourceSpec:
    """A parsed `--source`: kind "mujoco", "device" (index) or "folder" (path)."""

    kind: str
    index: int = 0
    path: str = ""


def parse_source(text: str) -> SourceSpec:
    """Parse `mujoco`, `device:N` or `folder:PATH`.

    Raises:
        ConfigError: anything else, or a folder that does not exist.
    """
    if text == "mujoco":
        return SourceSpec("mujoco")
    match = re.fullmatch(r"device:(\d+)", text)
    if match:
        return SourceSpec("device", index=int(match.group(1)))
    if text.startswith("folder:") and len(text) > len("folder:"):
        path = text[len("folder:") :]
        if not Path(path).is_dir():
            raise ConfigError(f"--source {text!r}: {path!r} is not a folder")
        if not any(p.suffix.lower() in IMAGE_SUFFIXES for p in Path(path).iterdir()):
            raise ConfigError(
                f"--source {text!r}: the folder holds no image ({', '.join(IMAGE_SUFFIXES)})"
            )
        return SourceSpec("folder", path=path)
    raise ConfigError(
        f"--source {text!r} is not one of mujoco, device:N (N = 0, 1, …), folder:PATH"
    )


class DeviceSource:
    """A real camera through OpenCV's VideoCapture, at the requested size (px).

    `capture` is the VideoCapture to use (a stand-in in tests); opened from `index` if None.
    """

    def __init__(self, index: int, width: int, height: int, capture: Any = None) -> None:
        self.index = index
        self._capture = cv2.VideoCapture(index) if capture is None else capture
        if not self._capture.isOpened():
            raise ConfigError(
                f"camera device {index} cannot be opened (is it connected? `ls /dev/video*` "
                f"lists the devices; use --source device:N with one of them)"
            )
        self._capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        self._capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        self._capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)

    def read(self, fresh: bool = False) -> np.ndarray:
        """The next frame (RGB); with `fresh`, one buffered frame is dropped first, so the frame
        returned was exposed after the call started.

        Raises:
            SourceError: the device delivered no frame.
        """
        if fresh:
            self._capture.grab()
        ok, bgr = self._capture.read()
        if not ok or bgr is None:
            raise SourceError(f"camera device {self.index} returned no frame")
        return np.ascontiguousarray(bgr[:, :, ::-1])

    def close(self) -> None:
        """Release the device."""
        self._capture.release()


class FolderSource:
    """Images of a folder, in name order, over and over (replaying real photos)."""

    def __init__(self, path: str) -> None:
        self.files = sorted(p for p in Path(path).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise ConfigError(f"folder {path!r} holds no image ({', '.join(IMAGE_SUFFIXES)})")
        self._next = 0

    def read(self, fresh: bool = False) -> np.ndarray:
        """The next image (RGB), read from disk now; unreadable files are skipped with a warning.

        Raises:
            SourceError: no file of the folder can be read.
        """
        for _ in range(len(self.files)):
            path = self.files[self._next]
            self._next = (self._next + 1) % len(self.files)
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is not None:
                return np.ascontiguousarray(bgr[:, :, ::-1])
            log.warning("skipping %s: not a readable image", path)
        raise SourceError(f"no image of {self.files[0].parent} can be read")

    def close(self) -> None:
        """Nothing to release."""
