"""Bad input never shows a traceback: every verb prints one line naming the bad value and exits
2 (bad input) or 1 (a runtime failure, e.g. no router); a closed stdout ends a verb quietly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from archery.apps.cli import VERBS
from archery.apps.topics.selfcheck import ECHO_SERVICE, run_echo
from archery.mesh.cliargs import clean_zenoh_error, loads_finite
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import ConfigError, RpcError
from archery.protocol.messages import JointCommand
from archery.protocol.verbs.robot import PART_VERBS
from tests.conftest import archery, serving
from tests.rpc import rpc_call, some_verbs

# (argv, exit status, text the one stderr line must contain). In argv, {net} stands for the
# flags of a live router and a robot of the test's own, {dead} for an endpoint where nothing
# listens, {busy} for a TCP port in use (the router's), {robot} for the robot name and {tmp}
# for a fresh folder.
CASES: list[tuple[str, int, str]] = [
    # read
    ("read {robot}/torso/state:o --count 1 --timeout -1 {net}", 2, "'-1'"),
    ("read {robot}/torso/state:o --count 1 --timeout nan {net}", 2, "'nan'"),
    ("read {robot}/torso/state:o --count 1 --timeout 1e308 {net}", 2, "beyond 10000000 s"),
    ("read {robot}/torso/state:o --count -1 {net}", 2, "'-1'"),
    ("read {robot}/torso/state:o --count two {net}", 2, "'two'"),
    ("read {robot}/torso/rpc:i {net}", 2, "not a stream"),
    ("read {robot}/legs/state:o {net}", 2, "'{robot}/legs/state:o'"),
    ("read {robot}/torso/state:o --count 1 --timeout 0.2 {net}", 1, "within 0.2 s"),
    ("read {robot}/torso/state:o --connect {dead}", 1, "{dead}"),
    # rpc
    (
        'rpc {robot}/cartesianController/archery/rpc:i posture {{"theta":[NaN,0.03,-0.03]}}',
        2,
        "NaN",
    ),
    (
        'rpc {robot}/cartesianController/archery/rpc:i posture {{"theta":[Infinity,0,0]}}',
        2,
        "Infinity",
    ),
    (
        'rpc {robot}/cartesianController/archery/rpc:i posture {{"theta":[-Infinity,0,0]}}',
        2,
        "-Infinity",
    ),
    ('rpc {robot}/torso/rpc:i positionMove {{"position":[NaN,0,0,0,0,0,0]}}', 2, "NaN"),
    ("rpc {robot}/torso/rpc:i echo {{nope", 2, "{{nope"),
    ("rpc {robot}/torso/rpc:i echo [1]", 2, "[1]"),
    ("rpc {robot}/torso/state:o echo", 2, "not an rpc:i port"),
    ("rpc {robot}/torso/rpc:i echo --timeout -1", 2, "'-1'"),
    ("rpc {robot}/torso/rpc:i echo --timeout nan", 2, "'nan'"),
    ("rpc {robot}/learner/rpc:i status --timeout 0.5 {net}", 1, "{robot}/learner/rpc:i"),
    # write
    ('write {robot}/torso/command:i {{"part":"torso","position":[true,0,0]}} {net}', 2, "bool"),
    ('write {robot}/torso/command:i {{"part":"torso","position":[NaN,0,0]}} {net}', 2, "NaN"),
    ('write {robot}/torso/command:i {{"part":"torso","position":"up"}} {net}', 2, "position"),
    ("write {robot}/torso/command:i {{not-json {net}", 2, "{{not-json"),
    (
        'write {robot}/torso/command:i {{"part":"torso","position":[0,0,0]}} {net} --timeout 0.3',
        1,
        "nobody subscribes to {robot}/torso/command:i",
    ),
    # view
    ("view {robot}/cam/target:o --out {tmp}/frame.txt {net}", 2, "'.txt'"),
    ("interface {robot}/nosuch:o --offline", 2, "nosuch:o"),
    ("keys", 2, "action"),
    ("keys bogus {tmp}/k", 2, "'bogus'"),
    ("keys init", 2, "dir"),
    ("keys init /proc/x", 2, "'/proc/x'"),
    ("keys init {tmp}/k --days nan", 2, "nan"),
    ("keys init {tmp}/k --days 0", 2, "--days"),
    ("interface {robot}/torso/rpc:i --timeout nan --offline", 2, "'nan'"),
    ("interface {robot}/torso/rpc:i --connect 127.0.0.1:7447", 2, "'127.0.0.1:7447'"),
    ("view {robot}/cam/target:o --out {tmp}/no/dir/frame.png {net}", 2, "{tmp}/no/dir"),
    ("view {robot}/torso/state:o --out {tmp}/frame.png {net}", 2, "does not carry images"),
    # ports
    ("alive --timeout nan", 2, "'nan'"),
    ("alive --connect {dead}", 1, "{dead}"),
    ("alive robot camera {net} --timeout 0.5", 1, "not alive on robot '{robot}': camera, robot"),
    ("ports --timeout -1", 2, "'-1'"),
    ("ports --timeout nan", 2, "'nan'"),
    ("ports --wait -3", 2, "'-3'"),
    ("ports --connect 127.0.0.1:7447", 2, "'127.0.0.1:7447'"),
    ("ports {net} --robot 9lives", 2, "'9lives'"),
    ("ports --connect {dead}", 1, "{dead}"),
    ("ports --connect tcp/127.0.0.1:99999", 2, "port 99999 is not a port number"),
    ("ports {net} --timeout 0.5", 0, "no service alive on robot '{robot}'"),
    # selfcheck
    ("selfcheck --timeout -1", 2, "'-1'"),
    ("selfcheck --timeout nan", 2, "'nan'"),
    ("selfcheck --connect {dead}", 1, "{dead}"),
    # learn
    ("learn --theta0 nan,0,0 --connect {dead}", 2, "'nan,0,0'"),
    ("learn --theta0 1,2 --connect {dead}", 2, "'1,2'"),
    ("learn --hit-radius nan --connect {dead}", 2, "'nan'"),
    ("learn --hit-radius 3 --connect {dead}", 2, "'3'"),
    ("learn --option nosuch=1 --connect {dead}", 2, "trust_radius"),
    ("learn --algo cma --option nosuch=1 --connect {dead}", 2, "sigma0, popsize"),
    ("learn --option explore_std=NaN --connect {dead}", 2, "NaN"),
    ("learn --option explore_std --connect {dead}", 2, "'explore_std'"),
    ("learn --algo nosuch --connect {dead}", 2, "'nosuch'"),
    ("learn --from /no/such --connect {dead}", 2, "'/no/such'"),
    ("learn --algo power --from s1 --connect {dead}", 2, "archer-prior"),
    ("learn --rollouts 0 --connect {dead}", 2, "got 0"),
    ("learn --seed -1 --connect {dead}", 2, "got -1"),
    ("learn --wait -1", 2, "'-1'"),
    ("learn --wait nan", 2, "'nan'"),
    ("learn --mode client --connect {dead} --wait 0.5", 1, "{dead}"),
    ("learn --wait 0.3 {net}", 1, "not alive after 0.3 s"),
    ("learn --resume {tmp}/j.jsonl --rollouts 8 --seed 0", 2, "cannot honour --rollouts, --seed"),
    ("learn --attach s1 --algo power", 2, "--attach follows the session as it runs"),
    # up
    ("up --timeout -1", 2, "'-1'"),
    ("up --timeout nan", 2, "'nan'"),
    ("up --rtf nan", 2, "'nan'"),
    ("up --logs /proc/nope/logs", 2, "'/proc/nope/logs'"),
    # drill
    ("drill --only kill-nobody", 2, "no drill 'kill-nobody'"),
    ("drill --seed x", 2, "'x'"),
    ("drill --workdir /proc/nope", 2, "'/proc/nope'"),
    ("drill --json /proc/nope/out.json", 2, "'/proc/nope'"),
    ("up --record {tmp}/run.txt", 2, "--record '{tmp}/run.txt': give a file name ending in .mcap"),
    # report
    ("report {tmp}/missing", 2, "{tmp}/missing: no such file or folder"),
    ("report {tmp}", 2, "no journal.jsonl in it"),
    # film, info
    ("film {tmp}/journals/nohit", 2, "session old-format-from has no hit in its 0 rollouts"),
    ("film {tmp}/journals/session --rollout 99", 2, "--rollout 99 is not among them"),
    ("film {tmp}/journals/v9session", 2, "has journal version 9"),
    ("film {tmp}/missing", 2, "cannot read journal {tmp}/missing"),
    ("film {tmp}/journals/session --width 99", 2, "the frame size must be even"),
    ("demonstrate", 2, "one of the arguments --out --check is required"),
    ("imitate {tmp}/missing.json", 2, "cannot read it"),
    ("imitate {tmp}/file", 2, "not JSON"),
    ("imitate {tmp}/file --theta 0.4,0,0", 2, "outside the θ box"),
    ("imitate {tmp}/file --theta 0.2,0", 2, "--theta"),
    ("demonstrate --check {tmp}/file", 2, "not JSON"),
    ("demonstrate --check {tmp}/missing.json", 2, "cannot read it"),
    ("demonstrate --out {tmp}/missing/demo.json", 2, "no folder"),
    ("info {tmp}/file", 2, "is not an MCAP file"),
    ("info {tmp}/cut.mcap", 2, "cut short"),
    ("info {tmp}/missing.mcap", 2, "No such file or directory"),
    # experiment
    ("experiment --out {tmp}/file", 2, "'{tmp}/file'"),
    ("experiment --out /proc/x", 2, "'/proc/x'"),
    ("experiment --sessions 0", 2, "got 0"),
    ("experiment --power-scale -1", 2, "got -1.0"),
    ("experiment --fig6 mode", 2, "'mode'"),
    ("experiment --drag 0.05 --wind-change 20", 2, "'20'"),
    ("experiment --drag 0.05 --wind-change x:0,1,0", 2, "'x:0,1,0'"),
    ("experiment --drag 0.05 --wind-change 20:0,1", 2, "'0,1'"),
    ("experiment --drag 0.05 --wind-change 20:0,nan,0", 2, "'0,nan,0'"),
    ("experiment --drag 0.05 --wind-change 1:0,1,0", 2, "rollout 1"),
    ("experiment --drag 0.05 --wind-change 61:0,1,0", 2, "rollout 61"),
    ("experiment --wind-change 20:0,1,0", 2, "drag"),
    ("experiment --from /no/such", 2, "'/no/such'"),
    ("experiment --from {tmp} --algo power", 2, "learners.json"),
    ("compare --out {tmp}/file", 2, "'{tmp}/file'"),
    ("compare --methods archer,bogus --out {tmp}/c", 2, "'archer,bogus'"),
    ("compare --sessions 0 --out {tmp}/c", 2, "got '0'"),
    ("compare --drag 0.05 --wind-change 1:0,1,0 --out {tmp}/c", 2, "shot 1"),
    ("compare --noise nan --out {tmp}/c", 2, "'nan'"),
    ("compare --world mesh --connect {dead} --wait 0.5 --out {tmp}/c", 1, "{dead}"),
    # services: refused at start
    ("learner --runs /proc/nope {net}", 2, "'/proc/nope'"),
    ("learner --rpc-timeout nan {net}", 2, "nan"),
    ("detector --model /no/such/dir/m.json {net}", 2, "'/no/such/dir'"),
    ("detector --model {tmp} {net}", 2, "'{tmp}'"),
    ("robot --rtf nan {net}", 2, "nan"),
    ("camera --source bogus {net}", 2, "'bogus'"),
    ("controller --traj-time nan {net}", 2, "nan"),
    ("calibrate {tmp}/missing.png --pixels {tmp}/p.json --out {tmp}/m.json", 2, "missing.png"),
    ("router --listen localhost:1", 2, "'localhost:1'"),
    ("router --listen tcp/0.0.0.0:{busy}", 2, "plain mode trusts every peer"),
    ("up --listen tcp/0.0.0.0:7447 --runs {tmp}/up-runs2", 2, "--insecure-network"),
    ("detect {tmp}/missing.jpg --model {tmp}/m.json", 2, "'{tmp}/missing.jpg'"),
    # record, replay, hz
    ("record --out {tmp}/r.txt {net}", 2, "'{tmp}/r.txt': give a file name ending in .mcap"),
    ("record {robot}/nosuch/** --out {tmp}/r.mcap {net}", 2, "matches no stream port"),
    ("record {robot}//x --out {tmp}/r.mcap {net}", 2, "is not a key expression"),
    ("record --out {tmp}/no/dir/r.mcap {net}", 2, "'{tmp}/no/dir'"),
    ("record --out {tmp}/r.mcap --duration nan {net}", 2, "'nan'"),
    ("record --out {tmp}/r.mcap --connect {dead}", 1, "{dead}"),
    ("replay {tmp}/file {net}", 2, "'{tmp}/file' is not an MCAP file"),
    ("replay {tmp}/missing.mcap {net}", 2, "'{tmp}/missing.mcap': No such file"),
    ("replay {tmp}/cut.mcap {net}", 2, "is cut short"),
    ("replay {tmp}/v9.mcap {net}", 2, "schema version 9"),
    ("replay {tmp}/ok.mcap --keys {robot}/nosuch:o {net}", 2, "'{robot}/nosuch:o'"),
    ("replay {tmp}/ok.mcap --rate 0 {net}", 2, "'0'"),
    ("hz {robot}/cam/nosuch {net}", 2, "'{robot}/cam/nosuch' matches no stream port"),
    ("hz {robot}/** --duration -1 {net}", 2, "'-1'"),
    ("hz {robot}/torso/state:o --duration 0.3 {net}", 1, "no message on {robot}/torso/state:o"),
    ("read {robot}/torso/state:o --field nosuch {net}", 2, "JointState has no field 'nosuch'"),
    ("read {robot}/nosuch/** {net}", 2, "matches no stream port"),
    # ros2, export
    ("ros2 --domain 233 {net}", 2, "--domain 233: give a ROS 2 domain id from 0 to 232"),
    ("ros2 --wait 1 --connect {dead}", 1, "{dead}"),
    ("yarp --yarp-server nowhere {net}", 2, "--yarp-server 'nowhere': give HOST:PORT"),
    ("yarp --yarp-ip loopback {net}", 2, "--yarp-ip 'loopback': give an address"),
    ("yarp --wait 1 --connect {dead}", 1, "{dead}"),
    ("export {tmp}/none.mcap --ros2 {tmp}/bag", 2, "No such file or directory"),
    ("export README.md --ros2 {tmp}/bag2", 2, "is not an MCAP file"),
    # foxglove
    ("foxglove --port {busy} {net}", 2, "--port {busy}: already in use on 127.0.0.1"),
    ("foxglove --host 192.0.2.1 --port 0 --insecure-network {net}", 2, "not an address of this"),
    ("foxglove --host 0.0.0.0 --port 0 {net}", 2, "--host 0.0.0.0: this server authenticates"),
    ("foxglove --host :: --port 0 {net}", 2, "or give --insecure-network"),
    ("foxglove --port 70000 {net}", 2, "--port 70000: give a port number from 0 to 65535"),
    ("foxglove --port 0 --wait 1 --connect {dead}", 1, "{dead}"),
    ("foxglove --layout {tmp}/layout.txt", 2, "ending in .json"),
    # dashboard
    ("dashboard --port {busy} {net}", 2, "--port {busy}: address 127.0.0.1:{busy} is in use"),
    ("dashboard --host nohost --port 0 {net}", 2, "--host 'nohost' is not an IP address"),
    ("dashboard --host 192.0.2.1 --port 0 --insecure-network {net}", 2, "cannot listen"),
    ("dashboard --host 0.0.0.0 --port 0 {net}", 2, "--host 0.0.0.0: this server authenticates"),
    ("dashboard --port 70000 {net}", 2, "'70000'"),
    ("dashboard --port 0 --connect {dead}", 1, "{dead}"),
    # the dispatcher and demo
    ("", 2, "give a verb"),
    ("--version extra", 2, "--version takes no arguments, got 'extra'"),
    ("--help extra", 2, "--help takes no arguments"),
    ("ports --secure {tmp}/no-deployment", 2, "no ca.pem"),
    ("up --robots 1000 --runs {tmp}/up-runs", 2, "--robots 1000: this machine holds at most"),
    ("experiment --distance 1e308", 2, "--distance 1e308: distance must be <= 100"),
    ("experiment --sessions 20000", 2, "--sessions 20000: at most 10000"),
    ("fly", 2, "'fly'"),
    ("help fly", 2, "'fly'"),
    ("demo --rollouts 0", 2, "'0'"),
    ("demo --listen tcp/192.0.2.1:7447", 2, "the demo's mesh is for this machine only"),
    ("demo --algo nosuch", 2, "'nosuch'"),
    ("demo --listen 127.0.0.1:1", 2, "'127.0.0.1:1'"),
    ("demo --runs /proc/nope", 2, "'/proc/nope'"),
]


def _argv(template: str, values: dict[str, str]) -> list[str]:
    # Split first, so JSON arguments stay one argument each.
    return [part.format(**values) for part in template.split(" ") if part]


def _recordings(tmp: Path) -> None:
    """ok.mcap (one event), cut.mcap (it, cut short), v9.mcap (of schema version 9)."""
    from archery.apps.topics.recording import Recorder
    from archery.protocol.codec import encode
    from archery.protocol.messages import WorldEvent

    recorder = Recorder(tmp / "ok.mcap", "icubSim", ["icubSim/**"])
    recorder.put("icubSim/world/events:o", encode(WorldEvent(kind="reset")))
    recorder.close()
    data = (tmp / "ok.mcap").read_bytes()
    (tmp / "cut.mcap").write_bytes(data[: len(data) // 2])
    version = b"schema_version\x01\x00\x00\x00"
    (tmp / "v9.mcap").write_bytes(data.replace(version + b"1", version + b"9"))


def _journals(tmp: Path) -> None:
    """Session folders under journals/ (not under `tmp` itself, where `report` must find no
    journal): nohit (no done rollout), session (6 rollouts), v9session (of journal version 9)."""
    journals = Path(__file__).parent / "journals"
    for name, source in (("nohit", "old_format_from.jsonl"), ("session", "old_format.jsonl")):
        (tmp / "journals" / name).mkdir(parents=True)
        (tmp / "journals" / name / "journal.jsonl").write_bytes((journals / source).read_bytes())
    (tmp / "journals" / "v9session").mkdir()
    text = (journals / "old_format.jsonl").read_text()
    v9 = tmp / "journals" / "v9session" / "journal.jsonl"
    v9.write_text(text.replace('"version":1', '"version":9', 1))


@pytest.fixture(scope="module")
def table(router_endpoint: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """Every case run once, in parallel: {template: (values, CompletedProcess)}."""
    tmp = tmp_path_factory.mktemp("cli")
    (tmp / "file").write_text("not a folder\n")
    _recordings(tmp)
    _journals(tmp)
    dead = free_tcp_endpoint()
    runs: dict[str, object] = {}

    def run(case: tuple[int, tuple[str, int, str]]) -> None:
        i, (template, _, _) = case
        robot = f"cli{os.getpid()}n{i}"
        values = {
            "net": f"--connect {router_endpoint} --robot {robot}",
            "dead": dead,
            "busy": router_endpoint.rsplit(":", 1)[1],
            "robot": robot,
            "tmp": str(tmp),
        }
        argv = []
        for part in _argv(template, values):
            argv += part.split(" ") if part.startswith("--connect ") else [part]
        runs[template] = (values, archery(*argv, timeout=120))

    with ThreadPoolExecutor(max_workers=4) as pool:
        list(pool.map(run, enumerate(CASES)))
    return runs


@pytest.mark.parametrize(("template", "status", "text"), CASES, ids=[c[0][:60] for c in CASES])
def test_bad_input_is_one_line(
    table: dict[str, object], template: str, status: int, text: str
) -> None:
    values, out = table[template]  # type: ignore[misc]  # the fixture's (values, result) pairs
    assert "Traceback" not in out.stdout + out.stderr, out.stderr
    # one line, besides the line that says a wait began (`apps.waits`), before it
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    if len(lines) == 2 and lines[0].endswith("(Ctrl-C to stop)"):
        lines = lines[1:]
    assert out.returncode == status, out.stderr
    assert len(lines) == 1, out.stderr
    assert text.format(**values) in lines[0], lines[0]
    assert ".rs:" not in lines[0]


def test_every_verb_is_in_the_table() -> None:
    tried = {template.split(" ")[0] for template, _, _ in CASES}
    untried = set(VERBS) - tried
    assert not untried, untried


def test_version_and_help_verb() -> None:
    version = archery("--version")
    assert version.returncode == 0 and version.stdout.startswith("archery ")
    assert version.stdout.split()[1][0].isdigit()
    helped = archery("help", "read")
    assert helped.returncode == 0 and helped.stdout.startswith("usage: archery read")
    assert "--count" in helped.stdout
    usage = archery("help")
    assert usage.returncode == 0 and "  demo " in usage.stdout


def test_json_arguments_refuse_non_finite_constants() -> None:
    assert loads_finite('{"a": [1.5, -2]}', "x") == {"a": [1.5, -2]}
    for constant in ("NaN", "Infinity", "-Infinity"):
        with pytest.raises(ConfigError, match=constant):
            loads_finite(f'{{"theta": [{constant}, 0]}}', "the arguments")


def test_zenoh_errors_lose_their_rust_locations() -> None:
    raw = (
        "Unable to connect to any of [Single(tcp/127.0.0.1:1)]!  at /root/.cargo/git/checkouts/"
        "zenoh-9c599d5ef3e0480e/cc83980/zenoh/src/net/runtime/orchestrator.rs:447."
    )
    assert clean_zenoh_error(raw) == "Unable to connect to any of [Single(tcp/127.0.0.1:1)]"


@pytest.fixture
def echo(net: NetConfig) -> Iterator[NetConfig]:
    """The sample service (torso state at 50 Hz, rpc:i echo) on a thread."""
    with serving(run_echo, net), Node(None, net) as node:
        node.wait_alive([ECHO_SERVICE], 30)
        yield net


def _popen(*args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", *args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def test_a_closed_stdout_ends_quietly(echo: NetConfig) -> None:
    flags = ["--connect", echo.connect[0], "--robot", echo.robot]
    # `archery read KEY | head -1`: the reader goes away after one line.
    reader = _popen("read", f"{echo.robot}/torso/state:o", *flags)
    assert reader.stdout is not None and reader.stderr is not None
    first = json.loads(reader.stdout.readline())
    assert first["type"] == "JointState"
    reader.stdout.close()
    assert reader.wait(30) in (0, 1)
    assert reader.stderr.read() == b""
    # `archery rpc ... | head -c 0`: the reader is gone before the reply is printed.
    caller = _popen("rpc", f"{echo.robot}/torso/rpc:i", "getJointNames", *flags)
    assert caller.stdout is not None and caller.stderr is not None
    caller.stdout.close()
    assert caller.wait(30) in (0, 1)
    assert caller.stderr.read() == b""


def test_write_without_counters_says_the_verdict_is_unknown(net: NetConfig) -> None:
    """A torso that takes commands but whose controlboard does not serve `counters`."""
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    command = json.dumps({"part": "torso", "position": [0.1, 0.0, -0.1]})
    with Node("torso", net) as torso:
        torso.subscribe(torso.keys.command("torso"), JointCommand, mode="fifo")
        torso.serve(torso.keys.part_rpc("torso"), some_verbs(PART_VERBS, {}))
        torso.ready()
        out = archery("write", f"{net.robot}/torso/command:i", command, *flags)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["type"] == "JointCommand"
    assert out.stderr.strip().splitlines() == [
        f"archery write: delivered; whether it was accepted is unknown: {net.robot}/torso/rpc:i "
        "has no command counters (unknown_verb)"
    ]


def test_ports_waits_for_a_service_by_liveliness(net: NetConfig) -> None:
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    waiting = _popen("ports", *flags, "--wait", "60")
    with serving(run_echo, net):
        stdout, stderr = waiting.communicate(timeout=90)
    assert waiting.returncode == 0, stderr
    assert b"echo  (pid" in stdout and b"Traceback" not in stderr, stderr


def test_a_refused_joint_command_fails_with_the_robots_reason(
    net: NetConfig, tmp_path: Path
) -> None:
    from archery.protocol.robotspec import ROBOT
    from archery.services.robot.config import RobotConfig
    from archery.services.robot.service import run
    from archery.sim.scene_config import SceneConfig
    from archery.sim.world import WorldConfig

    config = RobotConfig(net=net, world=WorldConfig(scene=SceneConfig(meshes=False)))
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    key = f"{net.robot}/torso/command:i"
    with serving(run, config), Node(None, net) as node:
        node.wait_alive([ROBOT], 60)
        good = archery("write", key, '{"part": "torso", "position": [0.1, 0, 0]}', *flags)
        assert good.returncode == 0 and good.stderr == "", good.stderr
        for command, reason in (
            ('{"part": "torso", "position": [9, 0, 0]}', "torso_yaw = 9 rad is outside"),
            ('{"part": "left_arm", "position": [0, 0, 0]}', "part 'left_arm'"),
            ('{"part": "torso", "position": [0, 0]}', "got 2"),
        ):
            out = archery("write", key, command, *flags)
            lines = out.stderr.strip().splitlines()
            assert out.returncode == 1, out.stderr
            assert len(lines) == 1 and reason in lines[0], out.stderr
            assert lines[0].startswith(f"archery write: refused by {net.robot}/torso/rpc:i: ")
        # positionMove: true is not a joint angle (numpy would read it as 1 rad): the CLI
        # refuses it before sending, and so does the robot when another client sends it.
        moved = archery(
            "rpc", f"{net.robot}/torso/rpc:i", "positionMove", '{"position": [true, 0, 0]}', *flags
        )
        assert moved.returncode == 2, moved.stderr
        assert "`$.position[0]`: Expected `float`, got `bool`" in moved.stderr
        with pytest.raises(RpcError, match=r"Expected `float`, got `bool`") as refused:
            rpc_call(node, f"{net.robot}/torso/rpc:i", "positionMove", {"position": [True, 0, 0]})
        assert refused.value.code == "bad_request"
        counters = rpc_call(node, f"{net.robot}/torso/rpc:i", "counters")
    assert counters["accepted"] == 1 and counters["rejected"] == 3
