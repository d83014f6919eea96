"""The README and the pages of docs/ are executable: every block marked ```sh test or ```python
test runs here against a real mesh on a free port, and each `#=> TEXT` of the block must appear
in its output. A block's id names its page and its number on that page (`secure-block0`).

A shell block runs in bash in a fresh folder, with `archery` a function that adds the endpoint:
`--listen` for `router` and `up`, `--connect` for the verbs that talk to the mesh (unless the
line gives its own), the mutual-TLS endpoint when the line says `--secure`. The README's
`tcp/127.0.0.1:7447` and `tls/127.0.0.1:7447` become the free ports; `.venv/bin/archery` is
`archery`. Background jobs (`&`) are stopped when the block ends. A Python block runs once a
router and a robot are alive, with the same endpoint substitution.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from archery.mesh.router import free_tcp_endpoint

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```(sh|python) test\n(.*?)^```", re.M | re.S)
EXPECT = re.compile(r"# ?=> (.+)$", re.M)  # `#=> TEXT`; `# => TEXT` in Python
MESH_VERBS = [
    "ports",
    "alive",
    "read",
    "write",
    "rpc",
    "interface",
    "hz",
    "view",
    "record",
    "replay",
    "learn",
    "robot",
    "camera",
    "detector",
    "controller",
    "learner",
    "dashboard",
]

WRAPPER = r"""
set -euo pipefail
stop_jobs() {  # SIGTERM the background jobs; SIGKILL what still runs after 15 s
  local pids; pids=$(jobs -p)
  [[ -z "$pids" ]] && return 0
  kill $pids 2>/dev/null || true
  for _ in $(seq 150); do kill -0 $pids 2>/dev/null || break; sleep 0.1; done
  kill -9 $pids 2>/dev/null || true
  wait || true
}
trap stop_jobs EXIT
archery() {
  local verb="$1"; shift
  local ep="$TCP"
  case " $* " in *" --secure "*) ep="$TLS";; esac
  case "$verb" in
    router|up)
      case " $* " in *" --listen "*) ;; *) set -- "$@" --listen "$ep";; esac ;;
    *)
      if [[ " $MESH_VERBS " == *" $verb "* ]]; then
        case " $* " in *" --connect "*) ;; *) set -- "$@" --connect "$ep";; esac
      fi ;;
  esac
  if [[ $BASHPID != $$ ]]; then  # a background job: python replaces the subshell
    exec "$PYTHON" -m archery.apps.cli "$verb" "$@"
  fi
  "$PYTHON" -m archery.apps.cli "$verb" "$@"
}
"""


def _blocks() -> list[tuple[str, str, str]]:
    """(id, language, text) of every block the README and the pages of docs/ mark to run."""
    return [
        (f"{page.stem}-block{i}", m.group(1), m.group(2))
        for page in PAGES
        for i, m in enumerate(BLOCK.finditer(page.read_text()))
    ]


def _substituted(text: str, tcp: str, tls: str) -> str:
    text = text.replace("tcp/127.0.0.1:7447", tcp).replace("tls/127.0.0.1:7447", tls)
    return text.replace(".venv/bin/archery", "archery")


def test_the_pages_mark_their_runnable_blocks() -> None:
    kinds = [language for _, language, _ in _blocks()]
    assert kinds.count("sh") >= 4 and kinds.count("python") >= 1
    assert any(block_id.startswith("README-") for block_id, _, _ in _blocks())
    assert all(EXPECT.search(text) for _, _, text in _blocks())


@pytest.mark.slow
@pytest.mark.parametrize(
    ("language", "text"),
    [(language, text) for _, language, text in _blocks()],
    ids=[block_id for block_id, _, _ in _blocks()],
)
def test_a_readme_block_runs_and_prints_what_it_says(
    language: str, text: str, tmp_path: Path
) -> None:
    tcp = free_tcp_endpoint()
    tls = free_tcp_endpoint().replace("tcp/", "tls/")
    body = _substituted(text, tcp, tls)
    if language == "python":
        (tmp_path / "example.py").write_text(body)
        body = (
            "archery router &\narchery robot &\narchery alive robot --wait 60\n"
            f"{sys.executable} example.py\n"
        )
    env = os.environ | {
        "TCP": tcp,
        "TLS": tls,
        "PYTHON": sys.executable,
        "MESH_VERBS": " ".join(MESH_VERBS),
    }
    proc = subprocess.Popen(
        ["bash", "-c", WRAPPER + body],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its own process group: nothing outlives the test
    )
    try:
        output, _ = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        raise AssertionError(f"the block did not end within 240 s:\n{output[-6000:]}") from None
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, output[-3000:]
    for expected in EXPECT.findall(text):
        assert expected.strip() in output, f"{expected!r} not in:\n{output[-3000:]}"
