"""Frame sources of the camera: the rendered scene, a real device (OpenCV), an image folder or
a YARP image port (a real iCub's camera, `/icub/cam/left`).

Every source is used from one thread only (the camera's capture thread: GL contexts and
capture devices belong to the thread that opened them) and gives RGB uint8 frames. YARP's
library (the `yarp` module) is imported only when a `yarp:` source is opened.
"""

from __future__ import annotations

import itertools
import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.text import shown

__all__ = [
    "DeviceSource",
    "FolderSource",
    "SourceError",
    "SourceSpec",
    "YarpSource",
    "parse_source",
]

log = logging.getLogger("archery.camera")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
YARP_PORT = re.compile(r"/[^\s@]{1,200}")  # a YARP port name: `/` then no blank, no `@`
YARP_POLL = 0.002  # s between two looks at a YARP port's input while a frame is awaited
#: s: a YARP frame's envelope stamp further than this from its arrival is not this clock's
YARP_STAMP_SKEW = 10.0
_local_ports = itertools.count()


class SourceError(ArcheryError):
    """A source that delivers no frame (device unplugged, unreadable files)."""

    code = "no_frame"


@dataclass(frozen=True)
class SourceSpec:
    """A parsed `--source`: kind "mujoco", "device" (index), "folder" (path) or "yarp" (port,
    the YARP port name)."""

    kind: str
    index: int = 0
    path: str = ""
    port: str = ""


def parse_source(text: str) -> SourceSpec:
    """Parse `mujoco`, `device:N`, `folder:PATH` or `yarp:/PORT`.

    Raises:
        ConfigError: anything else, a folder that does not exist, or not a YARP port name.
    """
    if text == "mujoco":
        return SourceSpec("mujoco")
    if text.startswith("yarp:"):
        port = text[len("yarp:") :]
        if not YARP_PORT.fullmatch(port):
            raise ConfigError(
                f"--source {shown(text)}: give a YARP image port's name, e.g. yarp:/icub/cam/left"
            )
        return SourceSpec("yarp", port=port)
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
        f"--source {text!r} is not one of mujoco, device:N (N = 0, 1, …), folder:PATH, yarp:/PORT"
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


class YarpSource:
    """The newest frame of a YARP image port (`PORT`, any size), through YARP's own library: a
    `BufferedPortImageRgb` of the camera's own (`/archery/camera/PID/N:i`) that YARP connects
    from `PORT` (tcp), keeping only the newest frame it receives.

    `stamp` is the last frame's capture time as its sender stamped it (the envelope's
    `yarp::os::Stamp`, wall s since the Unix epoch, as `archery yarp` and a real iCub's camera
    stamp theirs), or None when it has none or one more than `YARP_STAMP_SKEW` s from its
    arrival (another clock): a frame relayed over YARP arrives late, and its arrival is not
    when it was seen.

    YARP finds its name server as its users configure it (`yarp conf HOST PORT`, `YARP_IP`).
    Every failure is one `SourceError` that names the port: no name server configured, or none
    answering within `timeout`; no such port; no frame within `timeout`; a frame of another
    size than the first.

    Args:
        port: the YARP port that writes the images, e.g. `/icub/cam/left`.
        timeout: how long to wait for the name server, and for a frame (s).
    """

    def __init__(self, port: str, timeout: float) -> None:
        try:
            import yarp
        except ImportError:
            raise ConfigError(
                f"--source yarp:{port}: YARP's Python bindings are not installed (install YARP "
                f"3.5 into this environment: `make yarp` in the project's checkout)"
            ) from None
        self.remote = port
        self.timeout = timeout
        self.local = f"/archery/camera/{os.getpid()}/{next(_local_ports)}:i"
        self.size: tuple[int, int] | None = None  # (width, height) px of the first frame
        self.stamp: float | None = None  # wall s: the last frame's envelope stamp
        self._skewed = False  # a stamp from another clock, said once
        self._yarp: Any = yarp
        self._port: Any = None
        yarp.Network.init()
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    def _connect(self) -> None:
        yarp, port = self._yarp, self.remote
        contact = yarp.Network.getNameServerContact()
        if not contact.isValid():
            raise SourceError(
                f"yarp:{port}: no YARP name server is configured (`yarp conf HOST PORT` names "
                f"one; YARP_IP the address this machine's ports take)"
            )
        server = f"{contact.getHost()}:{contact.getPort()}"
        if not yarp.Network.checkNetwork(self.timeout):
            raise SourceError(f"yarp:{port}: the YARP name server at {server} does not answer")
        if not yarp.Network.exists(port, True):
            raise SourceError(f"yarp:{port}: no port {port} on the YARP name server at {server}")
        self._port = yarp.BufferedPortImageRgb()
        self._port.setStrict(False)  # the newest frame replaces one not read yet
        if not self._port.open(self.local):
            raise SourceError(f"yarp:{port}: the camera's port {self.local} does not open")
        if not yarp.Network.connect(port, self.local):
            raise SourceError(f"yarp:{port}: YARP does not connect {port} to {self.local}")

    def read(self, fresh: bool = False) -> np.ndarray:
        """The newest frame (RGB, H×W×3 uint8) received; none yet, the next one. With `fresh`,
        a frame received before the call is dropped: the one returned arrived after it started.
        Waits at most `timeout` s.

        Raises:
            SourceError: no frame within the timeout (the connection from the port is made
                again, if it went, for the next read), or a frame of another size than the
                first one.
        """
        deadline = time.monotonic() + self.timeout
        if fresh:
            self._port.read(False)  # not strict: at most one frame waits, the newest
        while (image := self._port.read(False)) is None:
            if time.monotonic() > deadline:
                self._reconnect()
                raise SourceError(f"yarp:{self.remote}: no frame within {self.timeout:g} s")
            time.sleep(YARP_POLL)
        self.stamp = self._envelope()
        width, height = image.width(), image.height()
        if width == 0 or height == 0:
            raise SourceError(f"yarp:{self.remote}: an empty frame ({width}x{height} px)")
        if self.size is None:
            self.size = (width, height)
            log.info("yarp:%s: %dx%d frames", self.remote, width, height)
        elif (width, height) != self.size:
            raise SourceError(
                f"yarp:{self.remote}: a {width}x{height} px frame after {self.size[0]}x"
                f"{self.size[1]} px ones (a port's frames keep one size: start the camera again)"
            )
        view = self._yarp.ImageRgb()
        view.resize(width, height)  # YARP copies into the external pixels of an allocated image
        rows = np.empty((height, view.getRowSize()), np.uint8)  # YARP pads a row to 8 bytes
        view.setExternal(rows, width, height)
        view.copy(image)
        return np.ascontiguousarray(rows[:, : 3 * width].reshape(height, width, 3))

    def _envelope(self) -> float | None:
        """The frame just read's envelope stamp (wall s), None if it has none or one from
        another clock (said once)."""
        envelope = self._yarp.Stamp()
        if not self._port.getEnvelope(envelope) or not envelope.isValid():
            return None
        stamp = float(envelope.getTime())
        if abs(stamp - time.time()) > YARP_STAMP_SKEW:
            if not self._skewed:
                self._skewed = True
                log.warning(
                    "yarp:%s: the frames' stamps are %.1f s from this clock: their arrival "
                    "stands for their capture time",
                    self.remote,
                    stamp - time.time(),
                )
            return None
        return stamp

    def _reconnect(self) -> None:
        """Connect the port to ours again if the connection went (the port's program ended and
        started again); quietly, for the next read."""
        network = self._yarp.Network
        if not network.isConnected(self.remote, self.local, True):
            network.connect(self.remote, self.local, "", True)

    def close(self) -> None:
        """Close the camera's port and YARP's network."""
        if self._port is not None:
            self._port.interrupt()
            self._port.close()
            self._port = None
        if self._yarp is not None:
            self._yarp.Network.fini()
            self._yarp = None
