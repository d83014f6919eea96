"""Every output path a verb writes is checked before any work: a folder where a file is meant, a
missing folder, an unknown extension, an existing file without --force and an unwritable place
are each refused with one line naming the flag and the value, exit status 2, at once (no router
listens at the --connect given: the refusal comes before the mesh is contacted) and with the
existing file unchanged."""

from __future__ import annotations

import os
import stat
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from subprocess import CompletedProcess

import pytest

from archery.mesh.router import free_tcp_endpoint
from tests.conftest import archery

# verb: (argv with {out} for the output path, {tmp} for the test's folder and {dead} for an
# endpoint where nothing listens; the flag; a good file name; a name of an unknown extension).
FILE_OUTPUTS: dict[str, tuple[str, str, str, str]] = {
    "film": ("film {tmp}/no-session --out {out}", "--out", "shot.mp4", "shot.gif"),
    "demonstrate": (
        "demonstrate --out {out} --connect {dead} --wait 0.5",
        "--out",
        "demo.json",
        "demo.txt",
    ),
    "drill": ("drill --quick --json {out}", "--json", "drills.json", "drills.txt"),
    "record": ("record --out {out} --connect {dead}", "--out", "run.mcap", "run.txt"),
    "view": ("view icubSim/cam/target:o --out {out} --connect {dead}", "--out", "f.png", "f.txt"),
    "calibrate": (
        "calibrate {tmp}/no-image.png --pixels {tmp}/p.json --out {out}",
        "--out",
        "model.json",
        "model.yaml",
    ),
    "detect": (
        "detect {tmp}/no-image.jpg --model {tmp}/m.json --overlay {out}",
        "--overlay",
        "overlay.png",
        "overlay.jpg",
    ),
    "foxglove": ("foxglove --layout {out}", "--layout", "layout.json", "layout.txt"),
    "up": (
        "up --no-router --connect {dead} --runs {tmp}/up-runs --logs {tmp}/up-logs --record {out}",
        "--record",
        "run.mcap",
        "run.txt",
    ),
}

# (case, the path given, in the one stderr line after the flag and the value). {tmp}: the test's
# folder; NAME, BAD: the verb's good and unknown-extension names.
FILE_CASES: list[tuple[str, str, str]] = [
    ("folder", "{tmp}/a-folder", "is a folder"),
    ("missing folder", "{tmp}/no/such/NAME", "no folder '{tmp}/no/such'"),
    ("unknown extension", "{tmp}/BAD", "give a file name ending in"),
    ("existing file", "{tmp}/existing/NAME", "exists; give --force to replace it"),
    ("file as folder", "{tmp}/a-file/NAME", "'{tmp}/a-file' is not a folder"),
    ("unwritable", "/proc/NAME", "'/proc'"),
]

# Folder outputs: (argv, the flag, the path, in the stderr line).
FOLDER_CASES: list[tuple[str, str, str, str]] = [
    ("export {tmp}/none.mcap --ros2 {out}", "--ros2", "{tmp}/a-file", "is an existing file"),
    ("export {tmp}/none.mcap --ros2 {out}", "--ros2", "{tmp}/a-folder", "give a new folder"),
    ("export {tmp}/none.mcap --ros2 {out}", "--ros2", "{tmp}/no/such/bag", "no folder"),
    ("export {tmp}/none.mcap --ros2 {out}", "--ros2", "/proc/bag", "'/proc'"),
    ("experiment --out {out} --connect {dead}", "--out", "{tmp}/a-file", "is an existing file"),
    ("compare --out {out} --connect {dead}", "--out", "{tmp}/a-file", "is an existing file"),
    ("experiment --out {out}", "--out", "{tmp}/results", "holds the results of an earlier run"),
    ("compare --out {out}", "--out", "{tmp}/results", "give --force to replace them"),
    ("demo --runs {out}", "--runs", "{tmp}/a-file", "cannot be created"),
    ("drill --quick --workdir {out}", "--workdir", "{tmp}/a-file", "cannot be created"),
]

# Numeric flags of these verbs, refused before any work: (argv, in the stderr line).
NUMERIC_CASES: list[tuple[str, str]] = [
    ("drill --seed -1", "'-1' is negative"),
    ("calibrate {tmp}/no-image.png --pixels {tmp}/p.json --out {tmp}/m2.json --seed -1", "'-1'"),
    (
        "calibrate {tmp}/no-image.png --pixels {tmp}/p.json --out {tmp}/m2.json --max-components 0",
        "'0'",
    ),
    ("record --out {tmp}/n.mcap --count -1 --connect {dead}", "'-1'"),
    ("record --out {tmp}/n.mcap --duration 0 --connect {dead}", "'0'"),
    ("record --out {tmp}/n.mcap --flush-interval nan --connect {dead}", "'nan'"),
    ("view icubSim/cam/target:o --out {tmp}/n.png --timeout -1 --connect {dead}", "'-1'"),
    ("demonstrate --out {tmp}/n.json --timeout 0 --connect {dead}", "'0'"),
    ("demonstrate --out {tmp}/n.json --wait nan --connect {dead}", "'nan'"),
    ("film {tmp}/no-session --fps 0", "--fps"),
    ("film {tmp}/no-session --rollout -1", "'-1'"),
    ("demo --seed -1", "'-1'"),
    ("demo --rollouts 0", "'0'"),
    ("experiment --seed -1 --out {tmp}/ex", "seed must be an integer >= 0"),
    ("compare --seed -1 --out {tmp}/cmp", "'-1'"),
    ("up --foxglove -1 --runs {tmp}/up-runs", "--foxglove -1"),
]

AT_ONCE_S = 30.0  # a refusal is a Python start and an argument check, on a busy machine


def _cases() -> list[tuple[str, str, str, str]]:
    """(id, argv template, the path given, in the stderr line) of every refusal."""
    cases = []
    for verb, (template, flag, name, bad) in FILE_OUTPUTS.items():
        for case, path, text in FILE_CASES:
            given = path.replace("NAME", name).replace("BAD", bad)
            cases.append((f"{verb} {flag}: {case}", template, given, text))
    for template, flag, path, text in FOLDER_CASES:
        cases.append((f"{template.split()[0]} {flag}: {path}", template, path, text))
    return cases


CASES = _cases()


def _tree(tmp: Path) -> None:
    """The paths the cases name: a folder, a file, existing outputs of every verb."""
    (tmp / "a-folder").mkdir()
    (tmp / "a-file").write_text("not a folder\n")
    (tmp / "existing").mkdir()
    for _, _, name, _ in FILE_OUTPUTS.values():
        (tmp / "existing" / name).write_text(f"an earlier {name}\n")
    (tmp / "results").mkdir()
    (tmp / "results" / "summary.json").write_text("{}\n")


@dataclass(frozen=True)
class Run:
    """One case's run: the values its template was filled with, its wall time and result."""

    values: dict[str, str]
    seconds: float
    done: CompletedProcess[str]


def _run(template: str, values: dict[str, str]) -> Run:
    argv = [part.format(**values) for part in template.split(" ") if part]
    start = time.monotonic()
    done = archery(*argv, timeout=120)
    return Run(values, time.monotonic() - start, done)


@dataclass(frozen=True)
class Refusals:
    """Every case run once, in parallel, in the folder `tmp`: {id or template: Run}."""

    tmp: Path
    runs: dict[str, Run]


@pytest.fixture(scope="module")
def refusals(tmp_path_factory: pytest.TempPathFactory) -> Refusals:
    """Every case of CASES and NUMERIC_CASES, run once in parallel."""
    tmp = tmp_path_factory.mktemp("outputs")
    _tree(tmp)
    dead = free_tcp_endpoint()
    runs: dict[str, Run] = {}

    def run(case: tuple[str, str, str, str]) -> None:
        ident, template, path, _ = case
        runs[ident] = _run(template, {"tmp": str(tmp), "dead": dead, "out": path.format(tmp=tmp)})

    def numeric(case: tuple[str, str]) -> None:
        runs[case[0]] = _run(case[0], {"tmp": str(tmp), "dead": dead})

    with ThreadPoolExecutor(max_workers=4) as pool:
        list(pool.map(run, CASES))
        list(pool.map(numeric, NUMERIC_CASES))
    return Refusals(tmp, runs)


def _one_line(done: CompletedProcess[str]) -> str:
    assert "Traceback" not in done.stdout + done.stderr, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    return lines[0]


@pytest.mark.parametrize(("ident", "template", "path", "text"), CASES, ids=[c[0] for c in CASES])
def test_an_output_path_is_refused_before_any_work(
    refusals: Refusals, ident: str, template: str, path: str, text: str
) -> None:
    run = refusals.runs[ident]
    line = _one_line(run.done)
    assert run.done.returncode == 2, run.done.stderr
    flag = ident.split(":")[0].split(" ")[1]
    assert f"{flag} {run.values['out']!r}" in line, line
    assert text.format(tmp=run.values["tmp"]) in line, line
    assert run.seconds < AT_ONCE_S, f"{run.seconds:.1f} s: {line}"


def test_the_existing_outputs_are_unchanged(refusals: Refusals) -> None:
    tmp = refusals.tmp
    for _, _, name, _ in FILE_OUTPUTS.values():
        assert (tmp / "existing" / name).read_text() == f"an earlier {name}\n"
    assert (tmp / "a-file").read_text() == "not a folder\n"
    assert [p.name for p in (tmp / "results").iterdir()] == ["summary.json"]
    assert (tmp / "results" / "summary.json").read_text() == "{}\n"
    assert not (tmp / "no").exists()
    assert list((tmp / "a-folder").iterdir()) == []


@pytest.mark.parametrize(("template", "text"), NUMERIC_CASES, ids=[c[0] for c in NUMERIC_CASES])
def test_a_numeric_flag_is_refused_before_any_work(
    refusals: Refusals, template: str, text: str
) -> None:
    run = refusals.runs[template]
    line = _one_line(run.done)
    assert run.done.returncode == 2, run.done.stderr
    assert text in line, line
    assert run.seconds < AT_ONCE_S, f"{run.seconds:.1f} s: {line}"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes in a folder without write permission")
def test_a_folder_without_write_permission_is_refused(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        done = archery("record", "--out", str(locked / "r.mcap"), "--connect", free_tcp_endpoint())
    finally:
        locked.chmod(stat.S_IRWXU)
    assert done.returncode == 2, done.stderr
    assert f"the folder {str(locked)!r} is not writable" in _one_line(done)


def test_force_passes_the_check_and_the_work_begins(tmp_path: Path) -> None:
    """With --force an existing output passes: `record` goes on to the mesh (none listens:
    exit 1 naming the endpoint) and the file is untouched until it writes."""
    out = tmp_path / "run.mcap"
    out.write_text("an earlier recording\n")
    dead = free_tcp_endpoint()
    done = archery("record", "--out", str(out), "--force", "--connect", dead)
    assert done.returncode == 1, done.stderr
    assert dead in _one_line(done)
    assert out.read_text() == "an earlier recording\n"


def test_export_writes_a_new_bag_refuses_it_then_replaces_it_with_force(tmp_path: Path) -> None:
    from archery.apps.topics.recording import Recorder
    from archery.protocol.codec import encode
    from archery.protocol.messages import WorldEvent

    recording = tmp_path / "ok.mcap"
    recorder = Recorder(recording, "icubSim", ["icubSim/**"])
    recorder.put("icubSim/world/events:o", encode(WorldEvent(kind="reset")))
    recorder.close()
    bag = tmp_path / "bag"
    first = archery("export", str(recording), "--ros2", str(bag), timeout=300)
    assert first.returncode == 0, first.stderr
    made = {p.name: p.stat().st_mtime_ns for p in bag.iterdir()}
    again = archery("export", str(recording), "--ros2", str(bag), timeout=300)
    assert again.returncode == 2, again.stderr
    assert "or --force to replace the bag" in _one_line(again)
    assert {p.name: p.stat().st_mtime_ns for p in bag.iterdir()} == made
    forced = archery("export", str(recording), "--ros2", str(bag), "--force", timeout=300)
    assert forced.returncode == 0, forced.stderr
    assert (bag / "metadata.yaml").is_file()
    # a folder that is no bag is never replaced, --force or not
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep\n")
    kept = archery("export", str(recording), "--ros2", str(tmp_path / "mine"), "--force")
    assert kept.returncode == 2, kept.stderr
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep\n"
