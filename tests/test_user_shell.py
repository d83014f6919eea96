"""docs/learning.md's path as a user runs it: `archery up` in one shell, `archery learn` in
another, both with only PATH, HOME and LANG in their environment, from a folder outside the
checkout; the session hits, its JSON result line comes out and the hit is filmed."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from archery.mesh.router import free_tcp_endpoint

pytestmark = pytest.mark.slow

CHECKOUT = Path(__file__).resolve().parents[1]


def bare_env(home: Path) -> dict[str, str]:
    """What a plain login shell with the package's environment on PATH holds."""
    home.mkdir(parents=True, exist_ok=True)
    return {
        "PATH": f"{Path(sys.executable).parent}:/usr/local/bin:/usr/bin:/bin",
        "HOME": str(home),
        "LANG": "C.UTF-8",
    }


def test_up_then_learn_in_a_plain_shell_hits_and_films(tmp_path: Path) -> None:
    folder = tmp_path / "work"
    folder.mkdir()
    assert not folder.is_relative_to(CHECKOUT)
    env = bare_env(tmp_path / "home")
    endpoint = free_tcp_endpoint()
    up = subprocess.Popen(
        ["archery", "up", "--listen", endpoint],
        cwd=folder,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        learn = subprocess.run(
            ["archery", "learn", "--connect", endpoint, "--algo", "archer", "--wait", "180"],
            cwd=folder,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,  # one stream: what comes before what
            text=True,
            timeout=600,
        )
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up_out, up_err = up.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            up.kill()
            up_out, up_err = up.communicate()
    output = learn.stdout
    assert learn.returncode == 0, output[-4000:]
    assert "Traceback" not in output and "warning" not in output, output[-4000:]
    lines = output.splitlines()
    (at,) = [i for i, line in enumerate(lines) if line.startswith("{")]
    result = json.loads(lines[at])
    assert result["hit_at"] is not None, result
    video = folder / result["video"]  # relative paths are the shell's: its folder
    assert video == (folder / result["journal"]).parent / "shot.mp4"
    assert video.is_file() and video.stat().st_size > 10_000, output[-2000:]
    assert video.is_relative_to(folder)  # the learner's runs folder: where `up` was started
    (filmed,) = [i for i, line in enumerate(lines) if "the hit filmed into" in line]
    assert at < filmed  # the result line first: filming cannot lose it
    assert up.returncode == 0, up_err[-4000:]
    assert "archery up: waiting up to 90 s for the services: robot, " in up_err, up_err[-4000:]
    assert "all stopped cleanly" in up_out, up_out[-2000:]
