"""A whole learning session in secure mode, through the commands docs/secure.md gives: `archery keys
init DIR`, `archery up --secure DIR --listen tls/...` (router and five services, each with its
own identity, the router enforcing DIR/acl.json5) and `archery learn --secure DIR --connect
tls/...` (the `operator` identity). The controls in the same run: the same `learn` presenting
another service's identity is refused by the access control (no session starts), and one with
the credentials of another deployment cannot connect at all."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.services.learner.journal import read_records
from tests.conftest import archery

ROLLOUTS = 3


def _wait_for_line(proc: subprocess.Popen[str], text: str, timeout: float) -> str:
    """Read `proc`'s stdout until a line containing `text` (the lines read so far on failure)."""
    assert proc.stdout is not None
    seen = ""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break  # it exited
        seen += line
        if text in line:
            return seen
    proc.kill()
    out, err = proc.communicate(timeout=10)
    raise AssertionError(f"no {text!r} from archery up:\n{seen}{out}\n{err}")


@pytest.mark.slow
@pytest.mark.parametrize("shot", ["posture", "whole"])
def test_a_learning_session_runs_end_to_end_in_secure_mode(tmp_path: Path, shot: str) -> None:
    """Also the whole shot: the controller plays the movement under its own grants (the
    robot's trajectory verb, the parts' leases), the learner only asks for postures."""
    deploy, other = tmp_path / "secrets", tmp_path / "other"
    for directory in (deploy, other):
        made = archery("keys", "init", str(directory))
        assert made.returncode == 0, made.stderr
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    runs = tmp_path / "runs"
    logs = tmp_path / "logs"
    up_args = ["up", "--secure", str(deploy), "--listen", endpoint, "--shot", shot]
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "archery.apps.cli",
            *up_args,
            "--logs",
            str(logs),
            "--runs",
            str(runs),
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        alive = _wait_for_line(up, "all alive", timeout=60)
        secure = ["--secure", str(deploy), "--connect", endpoint]
        assert f"`archery learn {' '.join(secure)}`" in alive  # the hint is the secure command
        learn = archery("learn", *secure, "--rollouts", str(ROLLOUTS), "--no-until-hit", timeout=60)
        assert learn.returncode == 0, learn.stderr
        result = json.loads(learn.stdout.strip().splitlines()[-1])
        assert result["status"] == "finished", result
        assert result["rollouts"] == ROLLOUTS and result["aborted"] == 0, result
        # Each rollout was streamed to the operator through the router (learner/rollout:o).
        for n in range(1, ROLLOUTS + 1):
            assert f"attempt {n}: θ" in learn.stderr, learn.stderr
        # Every flow of a rollout passed the router: the controller's posture, the robot's
        # release, the camera's frame grabbed by the detector, the detector's measurement.
        records = read_records(Path(result["journal"]))[0]
        done = [r for r in records if isinstance(r, DoneRecord)]
        assert len(done) == ROLLOUTS
        for record in done:
            assert len(record.r_m) == 2 and all(abs(v) < 1.0 for v in record.r_m)
        assert Path(runs) in Path(result["journal"]).parents

        # Control: the camera's identity may not call the learner. The access control hides
        # its queryable from the camera, so the start request has no one to go to.
        as_camera = archery("learn", *secure, "--identity", "camera", "--rollouts", "1")
        assert as_camera.returncode == 1, as_camera.stdout + as_camera.stderr
        assert "learner/rpc:i" in as_camera.stderr and not as_camera.stdout.strip()
        # Control: the operator of another deployment cannot connect.
        foreign = archery("learn", "--secure", str(other), "--connect", endpoint)
        assert foreign.returncode == 1 and "cannot open a secure" in foreign.stderr
        sessions = [p for p in runs.iterdir() if p.is_dir()]
        assert len(sessions) == 1, sessions  # neither control started a session

        up.send_signal(signal.SIGINT)
        out, err = up.communicate(timeout=60)
        assert up.returncode == 0, err
        assert "all stopped cleanly" in out
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate(timeout=10)
