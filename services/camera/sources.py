"""Frame sources of the camera: the rendered scene, a real device (OpenCV) or an image folder.

Every source is used from one thread only (the camera's capture thread: GL contexts and
capture devices belong to the thread that opened them) and gives RGB uint8 frames.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.errors import ConfigError

__all__ = ["DeviceSource", "FolderSource", "SourceSpec", "parse_source"]

log = logging.getLogger("archery.camera")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


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
        return SourceSpec("folder", path=path)
    raise ConfigError(f"--source {text!r} is not one of mujoco, device:N, folder:PATH")


class DeviceSource:
    """A real camera through OpenCV's VideoCapture, at the requested size."""

    def __init__(self, index: int, width: int, height: int) -> None:
        self._capture = cv2.VideoCapture(index)
        if not self._capture.isOpened():
            raise ConfigError(f"camera device {index} cannot be opened (is it connected?)")
        self._capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        self._capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)

    def read(self) -> np.ndarray:
        """The next frame (RGB)."""
        ok, bgr = self._capture.read()
        if not ok:
            raise ConfigError("the camera device returned no frame")
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

    def read(self) -> np.ndarray:
        """The next image (RGB); unreadable files are skipped with a warning."""
        for _ in range(len(self.files)):
            path = self.files[self._next]
            self._next = (self._next + 1) % len(self.files)
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is not None:
                return np.ascontiguousarray(bgr[:, :, ::-1])
            log.warning("skipping %s: not a readable image", path)
        raise ConfigError(f"no image of {self.files[0].parent} can be read")

    def close(self) -> None:
        """Nothing to release."""
