"""One `--log-level` flag: RUST_LOG-style specs; every log line on stderr, data alone on stdout."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from archery.mesh.logs import _zenoh_spec, parse_spec
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import ConfigError

ANSI = re.compile(r"\x1b\[")


@pytest.mark.parametrize(
    ("spec", "default", "targets", "zenoh"),
    [
        ("info", "info", {}, "error"),
        ("debug", "debug", {}, "debug"),
        ("WARNING", "warn", {}, "error"),
        ("off", "off", {}, "off"),
        ("info,zenoh=debug", "info", {"zenoh": "debug"}, "debug"),
        ("error,archery.robot=debug", "error", {"archery.robot": "debug"}, "error"),
        ("info,zenoh::net=trace", "info", {"zenoh::net": "trace"}, "error,zenoh::net=trace"),
        ("", "info", {}, "error"),
    ],
)
def test_specs(spec: str, default: str, targets: dict[str, str], zenoh: str) -> None:
    assert parse_spec(spec) == (default, targets)
    assert _zenoh_spec(*parse_spec(spec)) == zenoh


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("loud", "'loud' is not a level; levels: trace, debug, info, warn, error, off"),
        ("info,=debug", "names no target"),
        ("zenoh=verbose", "'verbose' is not a level"),
    ],
)
def test_bad_specs_name_the_bad_part(spec: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        parse_spec(spec)


def test_zenoh_logs_go_to_stderr_without_colour_and_stdout_keeps_the_data() -> None:
    """A child that logs Zenoh's debug lines and prints one data line."""
    code = (
        "import zenoh; from mesh.logs import configure; configure('info,zenoh=debug'); "
        "from mesh.netflags import NetConfig, open_session\n"
        f"print('data line', flush=True)\n"
        "try:\n"
        f"    open_session(NetConfig(connect=({free_tcp_endpoint()!r},)))\n"
        "except Exception as exc:\n"
        "    print('refused', flush=True)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert done.stdout.splitlines() == ["data line", "refused"]
    assert "zenoh" in done.stderr and "DEBUG" in done.stderr
    assert not ANSI.search(done.stderr)
