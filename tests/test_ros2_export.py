"""`archery export --ros2` of a recording with every kind of rollout record: the bag, read back
by rosbags, holds one `learner/rollout` message per done rollout, its values the record's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader

from archery.apps.ros2 import typestore
from archery.apps.topics.recording import Recorder
from archery.protocol.codec import encode
from archery.protocol.journal_records import AbortedRecord, DoneRecord, ProposedRecord
from archery.protocol.messages import Rollout
from tests.conftest import archery

ROBOT = "icubSim"
START = 1_800_000_000_000_000_000  # ns


def _recording(path: Path) -> None:
    """Per attempt, a proposed record, then a done one (attempts 1 and 3) or an aborted one."""
    recorder = Recorder(path, ROBOT, [f"{ROBOT}/**"])
    seq = 0
    rollout = 0
    for index in (1, 2, 3):
        theta = [0.1 * index, 0.2]
        records: list[ProposedRecord | DoneRecord | AbortedRecord] = [
            ProposedRecord(index=index, theta=theta)
        ]
        if index == 2:
            records.append(
                AbortedRecord(
                    index=index,
                    theta=theta,
                    code="no_arrow",
                    cause="none seen",
                    retry_theta=theta,
                )
            )
        else:
            rollout += 1
            records.append(
                DoneRecord(
                    index=index,
                    rollout=rollout,
                    theta=theta,
                    r_m=[0.01 * index, -0.02],
                    distance_m=0.03,
                    hit=index == 1,
                )
            )
        for record in records:
            seq += 1
            message = Rollout(record=record, seq=seq)
            recorder.put(f"{ROBOT}/learner/rollout:o", encode(message), START + seq * 10**8)
    recorder.close()


def test_the_bag_holds_one_rollout_per_done_rollout(tmp_path: Path) -> None:
    recording = tmp_path / "run.mcap"
    _recording(recording)
    out = tmp_path / "bag"
    done = archery("export", str(recording), "--ros2", str(out), timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    store = typestore.messages()
    rollouts = []
    with Reader(out) as reader:
        for connection, _, data in reader.messages():
            if connection.topic == f"/{ROBOT}/learner/rollout":
                rollouts.append(store.deserialize_cdr(data, connection.msgtype))
    assert len(rollouts) == 2
    np.testing.assert_allclose(rollouts[0].data, [1.0, 1.0, 0.03, 0.1, 0.2, 0.01, -0.02])
    np.testing.assert_allclose(rollouts[1].data, [2.0, 0.0, 0.03, 0.3, 0.2, 0.03, -0.02])
    assert f"/{ROBOT}/learner/rollout: 2" in done.stdout
