"""`archery up`'s logs: each child's output goes through a pipe into rotating files whose total
is bounded, whatever the child writes; the end of a log still tells why a child ended, and the
children still die with their parent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from archery.apps.up.child import spawn
from archery.apps.up.launcher import Launcher
from archery.apps.up.logfile import RotatingLog
from archery.mesh.router import free_tcp_endpoint

SPAM = """
import sys
line = "x" * 99 + "\\n"
for i in range(40_000):  # 4 MB of lines
    sys.stdout.write(line)
sys.stderr.write("a line longer than a whole file: " + "y" * 100_000 + "\\n")
print("the last words", flush=True)
"""


def _on_disk(folder: Path, name: str) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in folder.glob(f"{name}.log*")}


def test_a_spamming_child_leaves_at_most_the_bound(tmp_path: Path) -> None:
    output = RotatingLog(tmp_path / "spam.log", file_bytes=64 * 1024, files=3)
    child = spawn("spam", [sys.executable, "-c", SPAM], output, os.environ)
    assert child.proc is not None and child.proc.wait(60) == 0  # never blocked on its pipe
    assert child.tail(1) == "the last words"  # all of it reached the log
    sizes = _on_disk(tmp_path, "spam")
    assert set(sizes) == {"spam.log", "spam.log.1", "spam.log.2"}
    assert all(size <= 64 * 1024 for size in sizes.values())
    assert output.written > 4_000_000 and output.dropped == 0
    lines = (tmp_path / "spam.log.1").read_text().splitlines()
    assert lines and all(len(line) in (99, 64 * 1024) or "longer" in line for line in lines[1:])
    # A log written before the bound (or with a bigger one) keeps only its end.
    again = RotatingLog(tmp_path / "spam.log", file_bytes=1000, files=2)
    again.write(b"more\n")
    again.close()
    kept = (tmp_path / "spam.log.1").read_text()  # its end, then rotated: no room left
    assert len(kept) <= 1000 and kept.endswith("the last words\n")
    assert (tmp_path / "spam.log").read_text() == "more\n"


def test_up_bounds_a_childs_logs(tmp_path: Path) -> None:
    bound = 2 * 8 * 1024  # two files of 8 KiB
    logs = tmp_path / "logs"
    args = {"controller": ["--log-level", "trace"]}  # Zenoh's trace: lines, all the time
    with Launcher(
        free_tcp_endpoint(), "uplog", logs, args, log_bytes=8 * 1024, log_files=2
    ) as launcher:
        launcher.up(60, services=("controller",))
        output = launcher.output("controller")
        deadline = time.monotonic() + 90
        while output.written < 4 * bound:  # it wrote the bound four times over
            assert time.monotonic() < deadline, f"only {output.written} bytes of output"
            assert launcher.first_exit() is None
            time.sleep(0.1)
        assert sum(_on_disk(logs, "controller").values()) <= bound
        assert set(_on_disk(logs, "controller")) <= {"controller.log", "controller.log.1"}
        launcher.kill("controller")
        assert launcher.children["controller"].tail()  # the end of its log, for the message
    assert sum(_on_disk(logs, "controller").values()) <= bound


PARENT = """
import sys
from pathlib import Path
from archery.apps.up.launcher import Launcher
launcher = Launcher(sys.argv[1], "orphans", Path(sys.argv[2]))
launcher.start_router()
print(launcher.children["router"].proc.pid, flush=True)
sys.stdin.read()  # until killed
"""


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status  # a zombie has ended, it waits to be reaped


def test_children_die_with_up(tmp_path: Path) -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, free_tcp_endpoint(), str(tmp_path)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert parent.stdout is not None
    router = int(parent.stdout.readline())
    deadline = time.monotonic() + 30
    while "router listening" not in (tmp_path / "router.log").read_text():  # through the pipe
        assert time.monotonic() < deadline and _alive(router)
        time.sleep(0.05)
    parent.send_signal(signal.SIGKILL)  # no chance to stop its children itself
    parent.wait(10)
    deadline = time.monotonic() + 30
    while _alive(router):
        assert time.monotonic() < deadline, "the router outlived its parent"
        time.sleep(0.05)
