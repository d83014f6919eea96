"""A YARP frame's capture time is its envelope stamp (`YarpSource.stamp`), as its sender
stamped it: a frame relayed over YARP arrives late, and `grab`'s "captured after" must not take
its arrival for when it was seen. YARP's own `BufferedPortImageRgb` on a loopback `yarpserver`."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from archery.services.camera.capture import _sender_stamp
from archery.services.camera.sources import YARP_STAMP_SKEW, YarpSource
from tests.ros2_sdk import until
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")


@pytest.fixture(scope="module")
def yarp_net(tmp_path_factory: pytest.TempPathFactory) -> Iterator[YarpSetup]:
    setup = YarpSetup(yarp, tmp_path_factory.mktemp("yarp"))
    try:
        yield setup
    finally:
        setup.close()


def test_the_envelope_stamp_is_the_frames_capture_time(yarp_net: YarpSetup) -> None:
    out = yarp.BufferedPortImageRgb()
    assert out.open("/test/stamped:o")
    source = YarpSource("/test/stamped:o", 5.0)
    try:
        until(lambda: out.getOutputCount() == 1, "the camera's connection", 60)

        def write(stamp: float | None) -> None:
            image = out.prepare()
            image.resize(8, 6)
            if stamp is not None:
                out.setEnvelope(yarp.Stamp(1, stamp))
            out.write()

        seen = time.time() - 2.0  # seen 2 s ago, relayed since
        write(seen)
        source.read()
        assert source.stamp == pytest.approx(seen, abs=1e-3)
        assert _sender_stamp(source, time.time()) == pytest.approx(seen, abs=1e-3)
        write(time.time() - 10 * YARP_STAMP_SKEW)  # another clock: the arrival stands
        source.read()
        assert source.stamp is None
        now = time.time()
        assert _sender_stamp(source, now) == now
    finally:
        source.close()
        out.close()
