"""A recorder with nothing to write waits for its next message without using the CPU."""

from __future__ import annotations

import time
from pathlib import Path

from archery.apps.topics.recording import Recorder
from archery.protocol.codec import encode
from archery.protocol.messages import JointState


def test_an_idle_recorder_waits_without_using_the_cpu(tmp_path: Path) -> None:
    """Once its last message is flushed, a recorder with nothing to write waits for the next
    one: its writer thread uses no CPU (it used a whole core before)."""
    recorder = Recorder(tmp_path / "idle.mcap", "icubSim", ["icubSim/**"], flush_interval=0.05)
    try:
        state = JointState(part="torso", names=["a"], position=[0.0], velocity=[0.0], seq=1)
        recorder.put("icubSim/torso/state:o", encode(state), 1_800_000_000_000_000_000)
        deadline = time.monotonic() + 10
        while recorder.stats.chunks == 0:  # the message flushed
            assert time.monotonic() < deadline
            time.sleep(0.01)
        cpu, wall = time.process_time(), time.monotonic()
        time.sleep(1.0)  # idle: the CPU a second of it costs
        used = (time.process_time() - cpu) / (time.monotonic() - wall)
    finally:
        recorder.close()
    assert used < 0.2, f"an idle recorder used {used:.0%} of a core"
