"""Secure mode against a real `archery router --secure` on a free loopback port: who may connect
(mutual TLS with the deployment's CA), and what each identity may do (the router's access
control). A denied flow is dropped at the router while the sender's call still succeeds, so
every "never receives" check asserts on the receiver, after a positive control sent later on
the same path has arrived."""

from __future__ import annotations

import datetime as dt
import json
import shutil
import signal
import stat
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from archery.mesh.acl import OPERATOR, REPLAY, VIEWER, roles, rules, server_of
from archery.mesh.credentials import (
    CA_CERT,
    CA_KEY,
    IDENTITIES,
    Authority,
    identity_folder,
    init_deployment,
    issue,
    write_identity,
)
from archery.mesh.netflags import NetConfig, open_session
from archery.mesh.node import Node, open_node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.codec import encode
from archery.protocol.errors import ConfigError, RpcError, Unreachable, WrongReplier
from archery.protocol.keys import Keys, verb_key, verbs_key
from archery.protocol.messages import Image, RpcReply
from archery.protocol.verbs import TABLES, names_caller, table_for_key
from archery.protocol.verbs import camera as cam_verbs
from archery.protocol.verbs.camera import CAMERA_VERBS, GRAB, GrabArgs
from archery.protocol.verbs.detector import CALIBRATE, DETECTOR_VERBS, STATUS, MeasureReply
from archery.protocol.verbs.robot import CLAIM, GET_CLAIM, ClaimArgs
from archery.services.learner.errors import RigError
from archery.services.learner.rig import MeshRig
from archery.services.learner.rig_protocol import Shot
from archery.services.robot.config import RobotConfig
from archery.services.robot.service import run as run_robot
from archery.sim.scene_config import SceneConfig
from archery.sim.world import WorldConfig
from tests.conftest import archery, serving
from tests.inbox import Inbox
from tests.rpc import rpc_call, some_verbs
from tests.spawn import spawn
from tests.test_replay_bounds import command, craft, event, frame

ROBOT = "secbot"
K = Keys(ROBOT)


def _no_target(_: object) -> MeasureReply:
    """A detector's measure reply that saw no target."""
    return MeasureReply(
        type="Detection",
        schema=1,
        seq=0,
        stamp=time.time(),
        sim_time=None,
        frame_stamp=0.0,
        status="no_target",
        target_px=None,
        arrow_px=None,
        target_confidence=0.0,
        arrow_confidence=0.0,
        r_m=None,
        frame=0,
        timing={},
    )


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return init_deployment(tmp_path_factory.mktemp("secure") / "deploy", robot=ROBOT)


@pytest.fixture(scope="module")
def other_deployment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return init_deployment(tmp_path_factory.mktemp("other") / "deploy", robot=ROBOT)


@pytest.fixture(scope="module")
def endpoint(deployment: Path) -> Iterator[str]:
    """A secure router process (mutual TLS + access control) on a free loopback port."""
    tls = free_tcp_endpoint().replace("tcp/", "tls/")
    proc = spawn_router(tls, secure=str(deployment))
    yield tls
    proc.terminate()
    assert proc.wait(10) == 0


def net_as(endpoint: str, identity: str, secure: Path) -> NetConfig:
    return NetConfig(connect=(endpoint,), robot=ROBOT, secure=str(secure), identity=identity)


@pytest.fixture
def session_as(endpoint: str, deployment: Path) -> Iterator[Callable[[str], zenoh.Session]]:
    """Open plain Zenoh sessions as an identity of the deployment; all closed at the end."""
    opened: list[zenoh.Session] = []

    def open_as(identity: str) -> zenoh.Session:
        opened.append(open_session(net_as(endpoint, identity, deployment)))
        return opened[-1]

    yield open_as
    for session in opened:
        session.close()


def put_until_received(pub: zenoh.Session, key: str, inbox: Inbox, payload: bytes) -> None:
    """Publish `payload` until `inbox` has it (a subscription propagates asynchronously)."""
    deadline = time.monotonic() + 10
    while not inbox.wait_for(payload, 0.1):
        assert time.monotonic() < deadline, f"{payload!r} on {key} never arrived"
        pub.put(key, payload)


def raw_config(endpoint: str, **tls: Any) -> zenoh.Config:
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    for name, value in tls.items():
        config.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
    return config


# -- the credentials -----------------------------------------------------------------------------
def test_keys_init_writes_a_deployment(tmp_path: Path) -> None:
    out = archery("keys", "init", str(tmp_path / "d"), "--robot", ROBOT, "--days", "30")
    assert out.returncode == 0, out.stderr
    d = tmp_path / "d"
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    ca = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    for name in IDENTITIES:
        assert stat.S_IMODE((d / f"{name}.key").stat().st_mode) == 0o600, name
        cert = x509.load_pem_x509_certificate((d / f"{name}.pem").read_bytes())
        cn = cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)[0].value
        assert cn == name and cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
        days = (cert.not_valid_after_utc - cert.not_valid_before_utc).total_seconds() / 86400
        assert 29.9 < days < 30.1
    router = x509.load_pem_x509_certificate((d / "router.pem").read_bytes())
    san = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "localhost" in san.get_values_for_type(x509.DNSName)
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert json.loads((d / "acl.json5").read_text()) == rules(ROBOT)
    before = (d / "ca.pem").read_bytes()
    again = archery("keys", "init", str(d))
    assert again.returncode == 2 and "--force" in again.stderr
    assert (d / "ca.pem").read_bytes() == before
    forced = archery("keys", "init", str(d), "--force")
    assert forced.returncode == 0 and (d / "ca.pem").read_bytes() != before


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_keys_init_warns_of_keys_a_git_work_tree_would_commit(tmp_path: Path) -> None:
    """Inside a work tree that does not ignore them, private keys are one `git add -A` from a
    commit: `keys init` says so (and still writes them); ignored, it says nothing."""
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    out = archery("keys", "init", str(tmp_path / "secrets"))
    assert out.returncode == 0, out.stderr
    assert "warning" in out.stderr and "ca.key" in out.stderr and ".gitignore" in out.stderr
    (tmp_path / ".gitignore").write_text("secrets/\n")
    quiet = archery("keys", "init", str(tmp_path / "secrets"), "--force")
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr


def test_the_acl_loads_into_a_zenoh_config() -> None:
    """insert_json5 refuses unknown keys: every key the generated policy uses is Zenoh's."""
    policy = rules(ROBOT)
    config = zenoh.Config()
    config.insert_json5("access_control", json.dumps(policy))
    loaded = json.loads(config.get_json("access_control"))
    assert loaded["default_permission"] == "deny" and loaded["enabled"] is True
    assert len(loaded["rules"]) == len(policy["rules"])
    with pytest.raises(zenoh.ZError):
        config.insert_json5("access_control", json.dumps(policy | {"no_such_key": 1}))


def test_secure_mode_refuses_plain_endpoints(deployment: Path) -> None:
    with pytest.raises(ConfigError, match="only mutual-TLS endpoints"):
        NetConfig(connect=("tcp/127.0.0.1:7447",), secure=str(deployment))
    with pytest.raises(ConfigError, match=r"no nobody\.key \(identity .nobody.\)"):
        open_session(net_as("tls/127.0.0.1:7447", "nobody", deployment))


# -- who may connect -------------------------------------------------------------------------
def test_no_credentials_cannot_connect(endpoint: str, deployment: Path) -> None:
    with pytest.raises(zenoh.ZError):  # trusts the router, presents no certificate
        zenoh.open(raw_config(endpoint, root_ca_certificate=str(deployment / "ca.pem")))
    with pytest.raises(zenoh.ZError):  # nothing at all
        zenoh.open(raw_config(endpoint))


def test_another_deployments_credentials_cannot_connect(
    endpoint: str, deployment: Path, other_deployment: Path
) -> None:
    with pytest.raises(ConfigError, match="cannot open a secure"):
        open_session(net_as(endpoint, "operator", other_deployment))
    # Trusting the right router, but with a certificate of another CA: the router refuses it.
    foreign = raw_config(
        endpoint,
        root_ca_certificate=str(deployment / "ca.pem"),
        enable_mtls=True,
        connect_private_key=str(other_deployment / "operator.key"),
        connect_certificate=str(other_deployment / "operator.pem"),
    )
    with pytest.raises(zenoh.ZError):
        zenoh.open(foreign)
    # The control: the same config with this deployment's certificate connects.
    own = raw_config(
        endpoint,
        root_ca_certificate=str(deployment / "ca.pem"),
        enable_mtls=True,
        connect_private_key=str(deployment / "operator.key"),
        connect_certificate=str(deployment / "operator.pem"),
    )
    zenoh.open(own).close()


def _load_authority(directory: Path) -> Authority:
    """The CA of a deployment directory (its `ca.key` and `ca.pem`), to issue test identities."""
    key = serialization.load_pem_private_key((directory / CA_KEY).read_bytes(), password=None)
    assert isinstance(key, ec.EllipticCurvePrivateKey)
    return Authority(key, x509.load_pem_x509_certificate((directory / CA_CERT).read_bytes()))


def test_an_expired_certificate_cannot_connect(
    endpoint: str, deployment: Path, tmp_path: Path
) -> None:
    ca = _load_authority(deployment)
    now = dt.datetime.now(dt.UTC)
    key, cert = issue(
        ca, "camera", not_before=now - dt.timedelta(days=10), not_after=now - dt.timedelta(days=1)
    )
    expired = tmp_path / "expired"
    expired.mkdir()
    shutil.copy(deployment / "ca.pem", expired / "ca.pem")
    write_identity(expired, "camera", key, cert)
    with pytest.raises(ConfigError, match="expired"):
        open_session(net_as(endpoint, "camera", expired))
    key, cert = issue(ca, "camera", days=1)  # the control: a valid one from the same CA
    write_identity(expired, "camera", key, cert)
    open_session(net_as(endpoint, "camera", expired)).close()


def test_plain_tcp_to_a_secure_router_fails(endpoint: str) -> None:
    with pytest.raises(zenoh.ZError):
        zenoh.open(raw_config(endpoint.replace("tls/", "tcp/")))


# -- what each identity may do ---------------------------------------------------------------
def test_only_controller_and_operator_command_the_joints(session_as: Callable) -> None:
    robot, camera, controller, operator = map(
        session_as, ("robot", "camera", "controller", "operator")
    )
    key = K.command("left_arm")
    at_robot, everything = Inbox(), Inbox()
    robot.declare_subscriber(key, at_robot)
    operator.declare_subscriber(f"{ROBOT}/**", everything)
    put_until_received(controller, key, at_robot, b"controller-1")
    put_until_received(camera, K.cam_frames(), everything, b"frame-1")
    camera.put(key, b"camera-command")  # denied at the router: put() itself succeeds
    camera.put(K.cam_frames(), b"frame-2")  # the control, same sender, after it
    controller.put(key, b"controller-2")
    operator.put(key, b"operator-1")  # the operator may command too
    assert everything.wait_for(b"frame-2") and at_robot.wait_for(b"controller-2")
    assert at_robot.wait_for(b"operator-1")
    assert b"camera-command" not in at_robot.payloads()
    assert b"camera-command" not in everything.payloads()
    assert everything.wait_for(b"controller-2")  # the operator sees commands


def test_the_replay_identity_publishes_the_robots_output_streams_only(
    session_as: Callable,
) -> None:
    """What a crafted recording would make a replay send, sent by hand as `replay`: the router
    drops its joint command and its subscription, while its state and frames go through."""
    robot, camera, replay, operator = map(session_as, ("robot", "camera", REPLAY, OPERATOR))
    key = K.command("left_arm")
    at_robot, everything, at_replay = Inbox(), Inbox(), Inbox()
    robot.declare_subscriber(key, at_robot)
    operator.declare_subscriber(f"{ROBOT}/**", everything)
    replay.declare_subscriber(f"{ROBOT}/**", at_replay)  # denied: a replay reads nothing
    put_until_received(replay, K.state("torso"), everything, b"state-1")
    put_until_received(operator, key, at_robot, b"operator-1")  # the robot listens
    replay.put(key, b"replay-command")  # denied at the router: put() itself succeeds
    replay.put(K.part_rpc("left_arm"), b"replay-rpc")
    replay.put("other/left_arm/command:i", b"replay-other")
    replay.put(K.cam_frames(), b"frame-1")  # the controls, same sender, after them
    operator.put(key, b"operator-2")
    camera.put(K.cam_frames(), b"frame-2")
    assert everything.wait_for(b"frame-1") and at_robot.wait_for(b"operator-2")
    assert everything.wait_for(b"frame-2")
    assert b"replay-command" not in at_robot.payloads()
    for denied in (b"replay-command", b"replay-rpc", b"replay-other"):
        assert denied not in everything.payloads()
    # its own puts reach its own subscriber in the session; nobody else's reach it
    assert not {b"operator-1", b"operator-2", b"frame-2"} & set(at_replay.payloads())


def test_replay_presents_its_own_identity_and_serves_the_detector_its_grab(
    endpoint: str, deployment: Path, session_as: Callable, tmp_path: Path
) -> None:
    """`archery replay --secure` with a folder that holds the `replay` identity only: it runs as
    that identity by default, replays a crafted file's frames and events but not its joint
    command, and answers the detector's `grab` (`--serve-grab`)."""
    path = craft(
        tmp_path / "crafted.mcap",
        ROBOT,
        [
            (K.command("left_arm"), command()),
            (K.cam_frames(), frame(1)),
            (K.command("left_arm"), command()),
            (K.world_events(), event(99)),
        ],
    )
    own = identity_folder(deployment, REPLAY, tmp_path / "ids")
    assert sorted(p.name for p in own.iterdir()) == ["ca.pem", "replay.key", "replay.pem"]
    robot, operator = session_as("robot"), session_as(OPERATOR)
    everything = Inbox()
    operator.declare_subscriber(f"{ROBOT}/**", everything)
    put_until_received(robot, K.world_state(), everything, b"probe")
    replay = spawn(
        "replay",
        str(path),
        "--serve-grab",
        "--rate",
        "100",
        "--connect",
        endpoint,
        "--secure",
        str(own),
        ready="archery replay: serving grab on",
    )
    try:
        deadline = time.monotonic() + 10
        while K.world_events() not in [k for k, _ in everything.items]:  # the control, last
            assert time.monotonic() < deadline, everything.items
            time.sleep(0.05)
        assert K.command("left_arm") not in [k for k, _ in everything.items]
        with Node("detector", net_as(endpoint, "detector", deployment)) as detector:
            got = detector.call_typed(K.cam_rpc(), GRAB, GrabArgs(after_sim_time=0.0), timeout=10)
        assert got.frame == 1
    finally:
        replay.send_signal(signal.SIGINT)
        out, err = replay.communicate(timeout=30)
    assert replay.returncode == 0, err
    assert "published 2 messages on 2 keys (2 messages on 1 channels skipped" in out
    assert [line for line in err.splitlines() if "archery replay" in line] == [
        f"archery replay: skipped channel {K.command('left_arm')!r}: not an output stream of "
        f"robot {ROBOT!r} (a replay publishes only the robot's state:o, world, camera frame and "
        "event streams)"
    ]


def test_frames_reach_the_operator_only(session_as: Callable) -> None:
    """The frame stream is for `archery view`; the detector grabs its frames by RPC, so its
    subscription to the stream is denied while its call on `cam/rpc:i` goes through."""
    camera, detector, operator, learner, robot = map(
        session_as, ("camera", "detector", "operator", "learner", "robot")
    )
    at_detector, at_operator, learner_all, learner_events = Inbox(), Inbox(), Inbox(), Inbox()
    detector.declare_subscriber(K.cam_frames(), at_detector)  # denied
    operator.declare_subscriber(f"{ROBOT}/**", at_operator)
    learner.declare_subscriber(f"{ROBOT}/**", learner_all)  # not the operator: denied
    learner.declare_subscriber(K.world_events(), learner_events)  # allowed: the control
    camera.declare_queryable(verbs_key(K.cam_rpc()), lambda q: q.reply(q.key_expr, b"grabbed"))
    put_until_received(camera, K.cam_frames(), at_operator, b"frame-1")
    put_until_received(robot, K.world_events(), learner_events, b"event-1")
    deadline = time.monotonic() + 10  # the detector's declarations reached the router in order
    grab = verb_key(K.cam_rpc(), "grab", "detector")
    while [r.ok.payload.to_bytes() for r in detector.get(grab) if r.ok] != [b"grabbed"]:
        assert time.monotonic() < deadline, "the detector cannot grab a frame by RPC"
        time.sleep(0.05)
    for n in range(2, 6):
        camera.put(K.cam_frames(), f"frame-{n}".encode())
    robot.put(K.world_events(), b"event-2")
    assert at_operator.wait_for(b"frame-5") and learner_events.wait_for(b"event-2")
    assert at_detector.items == []
    assert not [k for k, _ in learner_all.items if k == K.cam_frames()]


def test_only_the_owner_serves_an_rpc_key(session_as: Callable) -> None:
    detector, controller, learner = map(session_as, ("detector", "controller", "learner"))
    key = verb_key(K.cartesian_rpc("archery"), "posture")
    stolen: list[str] = []

    def rogue(query: zenoh.Query) -> None:
        stolen.append(str(query.key_expr))
        query.reply(query.key_expr, b"from the detector")

    detector.declare_queryable(verbs_key(K.cartesian_rpc("archery")), rogue)  # denied
    measure = verb_key(K.detector_rpc(), "measure", "learner")
    detector.declare_queryable(
        verbs_key(K.detector_rpc()), lambda q: q.reply(q.key_expr, b"measured")
    )
    controller.declare_queryable(
        verbs_key(K.cartesian_rpc("archery")), lambda q: q.reply(q.key_expr, b"posture")
    )
    zids = {str(s.info.zid()): name for s, name in ((detector, "d"), (controller, "c"))}

    def ask(k: str) -> list[tuple[str, bytes]]:
        replies = learner.get(
            k, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE
        )
        return [(zids.get(str(r.replier_id.zid), "?"), r.ok.payload.to_bytes()) for r in replies]

    deadline = time.monotonic() + 10  # the detector's declarations, in order, reached the router
    while ask(measure) != [("d", b"measured")] or ask(key) != [("c", b"posture")]:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    for _ in range(5):
        assert ask(key) == [("c", b"posture")]
    assert stolen == []


def test_liveliness_tokens_only_under_ones_own_name(session_as: Callable) -> None:
    camera, operator = session_as("camera"), session_as("operator")
    denied = camera.liveliness().declare_token(K.alive("detector"))
    control = camera.liveliness().declare_token(K.alive("camera"))  # after it
    deadline = time.monotonic() + 10
    while True:
        seen = {str(r.ok.key_expr) for r in operator.liveliness().get(K.alive_all()) if r.ok}
        if K.alive("camera") in seen:
            break
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert K.alive("detector") not in seen
    denied.undeclare()
    control.undeclare()


def forged_reply(result: dict[str, Any]) -> Callable[[zenoh.Query], None]:
    def answer(query: zenoh.Query) -> None:
        query.reply(query.key_expr, encode(RpcReply(ok=True, result=result, seq=1, stamp=0.0)))

    return answer


def test_a_rogue_measure_never_reaches_the_learner(
    endpoint: str, deployment: Path, session_as: Callable
) -> None:
    camera = session_as("camera")
    asked: list[bytes] = []

    def rogue(query: zenoh.Query) -> None:
        asked.append(b"")
        forged_reply({"status": "ok", "r_m": [9.0, 9.0]})(query)

    camera.declare_queryable(verbs_key(K.detector_rpc()), rogue)  # denied: may not serve it
    with (
        Node("detector", net_as(endpoint, "detector", deployment)) as detector,
        Node("learner", net_as(endpoint, "learner", deployment)) as learner,
    ):
        detector.serve(K.detector_rpc(), some_verbs(DETECTOR_VERBS, {"measure": _no_target}))
        detector.ready()
        learner.wait_alive(["detector"], 10)
        for _ in range(5):
            result = rpc_call(
                learner, K.detector_rpc(), "measure", timeout=5, expect_service="detector"
            )
            assert result["status"] == "no_target"
    assert asked == []


# -- a rogue responder on a plain mesh: the learner-side check ----------------------------------
def test_a_reply_from_a_non_instance_is_rejected(net: NetConfig, tmp_path: Path) -> None:
    """No access control here: a plain session answers the detector's key while the detector is
    alive; its reply is refused, as `wrong_replier`, never used as a measurement."""
    keys = Keys(net.robot)
    rogue = open_session(net)
    try:
        with Node("detector", net) as detector, Node("learner", net) as learner:
            detector.ready()  # alive, but it serves no measure: only the rogue answers
            rogue.declare_queryable(
                verbs_key(keys.detector_rpc()), forged_reply({"status": "ok", "r_m": [9.0, 9.0]})
            )
            deadline = time.monotonic() + 10
            while True:  # the rogue's queryable has reached the router: it answers
                try:
                    forged = rpc_call(learner, keys.detector_rpc(), "measure", timeout=2)
                    break
                except RpcError:
                    assert time.monotonic() < deadline
            assert forged["r_m"] == [9.0, 9.0]  # what the learner would take without the check
            with pytest.raises(WrongReplier) as caught:
                rpc_call(
                    learner,
                    keys.detector_rpc(),
                    "measure",
                    timeout=2,
                    expect_service="detector",
                )
            assert caught.value.code == "wrong_replier"
            assert str(rogue.info.zid()) in caught.value.message
            rig = MeshRig(learner, timeout=3.0)
            with pytest.raises(RigError) as rig_error:
                rig.measure(Shot(shot=1, sim_time=0.0, stamp=time.time(), outcome="landed"))
            assert rig_error.value.code == "wrong_replier"
            # The live instance's own reply passes the same check.
            tiny = Image.from_numpy(np.zeros((2, 2, 3), np.uint8), frame=1)
            detector.serve(keys.cam_rpc(), some_verbs(CAMERA_VERBS, {"grab": lambda _: tiny}))
            deadline = time.monotonic() + 10
            while True:
                try:
                    got = rpc_call(
                        learner, keys.cam_rpc(), "grab", timeout=2, expect_service="detector"
                    )
                    break
                except RpcError:
                    assert time.monotonic() < deadline
            assert got["frame"] == 1
    finally:
        rogue.close()


def test_the_session_journals_wrong_replier_as_an_abort(tmp_path: Path) -> None:
    from archery.protocol.journal_records import AbortedRecord, DoneRecord
    from archery.services.learner.config import SessionConfig
    from archery.services.learner.journal import read_records
    from archery.services.learner.session import Session
    from tests.test_learner_service_session import FakeRig

    class RogueRig(FakeRig):
        def __init__(self) -> None:
            super().__init__()
            self.rogue_once = True

        def measure(self, shot: Shot):
            if self.rogue_once:
                self.rogue_once = False
                raise RigError(
                    "detector/rpc:i: the reply came from session x", code="wrong_replier"
                )
            return super().measure(shot)

    session = Session.create(
        SessionConfig(algorithm="hill", rollouts=2, seed=0), RogueRig(), tmp_path, session_id="s"
    )
    session.run(threading.Event())
    records = read_records(session.journal.path)[0]
    aborted = [r for r in records if isinstance(r, AbortedRecord)]
    assert [a.code for a in aborted] == ["wrong_replier"]
    assert "session x" in aborted[0].cause
    assert not hasattr(aborted[0], "r_m") and aborted[0].retry_theta == aborted[0].theta
    done = [r for r in records if isinstance(r, DoneRecord)]
    assert len(done) == 2 and done[0].theta == aborted[0].theta  # the same θ, re-run


def test_a_call_the_access_control_denies_says_so(endpoint: str, deployment: Path) -> None:
    """The learner may not grab frames: with the camera alive, its call is named a denial by
    access control, not an absent service."""
    with Node("camera", net_as(endpoint, "camera", deployment)) as camera:
        camera.serve(K.cam_rpc(), some_verbs(CAMERA_VERBS, {}))
        camera.ready()
        with Node("learner", net_as(endpoint, "learner", deployment)) as learner:
            learner.wait_alive(["camera"], timeout=10)
            with pytest.raises(RpcError) as denied:
                learner.call_typed(K.cam_rpc(), cam_verbs.STATUS, timeout=3)
    assert denied.value.code == "denied"
    assert "denied by access control: the camera is alive" in str(denied.value)
    assert "identity 'learner'" in str(denied.value)


def test_a_stuck_call_the_rules_grant_is_a_timeout_and_a_denial_names_the_identity(
    endpoint: str, deployment: Path
) -> None:
    """A call the rules grant that gets no reply in time (the server is stuck) is a timeout,
    never "denied"; a call they deny names the identity the node presented (`--identity`)."""
    release = threading.Event()

    def stuck(_: Any) -> Any:
        release.wait(30)
        raise RpcError("released", code="rpc_error")

    try:
        with Node("detector", net_as(endpoint, "detector", deployment)) as detector:
            detector.serve(K.detector_rpc(), some_verbs(DETECTOR_VERBS, {"status": stuck}))
            detector.ready()
            viewer_net = net_as(endpoint, VIEWER, deployment)
            with Node(None, viewer_net) as viewer:
                viewer.wait_alive(["detector"], timeout=10)
                with pytest.raises(RpcError) as slow:
                    viewer.call_typed(K.detector_rpc(), STATUS, timeout=1)
                with pytest.raises(RpcError) as denied:
                    viewer.call_typed(K.detector_rpc(), CALIBRATE, timeout=1)
    finally:
        release.set()
    assert slow.value.code == "timeout" and "denied" not in str(slow.value), slow.value
    assert denied.value.code == "denied", denied.value
    assert "identity 'viewer'" in str(denied.value)


def test_a_plain_client_meeting_a_secure_router_is_told_so(endpoint: str) -> None:
    plain = NetConfig(connect=(endpoint.replace("tls/", "tcp/"),), robot=ROBOT)
    with pytest.raises(Unreachable, match="does not answer plain Zenoh: a secure router") as err:
        open_session(plain)
    assert f"--connect {endpoint}" in str(err.value)


def test_a_tool_waiting_for_a_router_is_told_at_once_when_one_listens_and_refuses(
    endpoint: str,
) -> None:
    """`--wait` waits while nothing listens; a router that listens and refuses the session
    (here a secure one, met in plain) is said after a second attempt, not after the wait."""
    plain = NetConfig(connect=(endpoint.replace("tls/", "tcp/"),), robot=ROBOT)
    began = time.monotonic()
    with pytest.raises(Unreachable, match="does not answer plain Zenoh: a secure router"):
        open_node(plain, 120)
    assert time.monotonic() - began < 60


def test_up_hands_each_child_only_the_ca_certificate_and_its_own_identity(
    deployment: Path, tmp_path: Path
) -> None:
    from archery.apps.up.launcher import Launcher

    launcher = Launcher(
        free_tcp_endpoint().replace("tcp/", "tls/"),
        ROBOT,
        tmp_path / "logs",
        secure=str(deployment),
    )
    flag, robot_dir = launcher._identity("robot")
    _, router_dir = launcher._identity("router")
    assert flag == "--secure"
    assert sorted(p.name for p in Path(robot_dir).iterdir()) == ["ca.pem", "robot.key", "robot.pem"]
    assert sorted(p.name for p in Path(router_dir).iterdir()) == [
        "acl.json5",
        "ca.pem",
        "router.key",
        "router.pem",
    ]
    assert stat.S_IMODE(Path(robot_dir).stat().st_mode) == 0o700
    assert stat.S_IMODE((Path(robot_dir) / "robot.key").stat().st_mode) == 0o600
    launcher.stop_all()
    assert not Path(robot_dir).exists() and not Path(router_dir).exists()


def test_each_identity_may_call_exactly_the_verbs_of_its_job(session_as: Callable) -> None:
    """Every identity × every verb of every `rpc:i` port, checked on the receiver's side: a fake
    server (as the port's owner) records each call that reaches it."""
    role_of = roles(ROBOT)
    ports = [f"{ROBOT}/{port}" for table in TABLES for port in table.ports]
    verbs = {key: [v.name for v in table_for_key(key)] for key in ports}
    reached: set[tuple[str, str]] = set()  # (caller's tag, verb key)
    lock = threading.Lock()

    def record(query: zenoh.Query) -> None:
        tag = query.payload.to_bytes().decode() if query.payload is not None else "?"
        with lock:
            reached.add((tag, str(query.key_expr)))
        query.reply(query.key_expr, b"ok")

    for key in ports:
        owner = server_of(ROBOT, key)
        assert owner is not None, key
        session_as(owner).declare_queryable(verbs_key(key), record)
    callers = ("robot", "camera", "detector", "controller", "learner", OPERATOR, VIEWER, REPLAY)
    sessions = {name: session_as(name) for name in callers}
    deadline = time.monotonic() + 10  # every queryable has reached the router
    while any(
        not list(sessions[OPERATOR].get(verb_key(key, "status"), payload=b"probe", timeout=2))
        for key in ports
        if "status" in verbs[key]
    ):
        assert time.monotonic() < deadline
    calls = [
        (name, verb_key(key, v, name if names_caller(key, v) else None))
        for name in callers
        for key in ports
        for v in verbs[key]
    ]
    # a verb that names its caller, naming another: only the operator may
    left_claim = verb_key(K.part_rpc("left_arm"), "claim", OPERATOR)
    impostors = [
        ("controller", left_claim),
        ("learner", left_claim),
        (VIEWER, left_claim),
        ("controller", verb_key(K.part_rpc("left_arm"), "claim")),  # naming no caller
    ]
    calls += impostors

    def call(item: tuple[str, str]) -> None:
        name, target = item
        list(sessions[name].get(target, payload=name.encode(), timeout=2))

    with ThreadPoolExecutor(max_workers=16) as pool:
        list(pool.map(call, calls))
    granted = {(n, t) for n, t in calls if _grants_call(role_of[n].call, t)}
    assert len(granted) > 100 and len(calls) - len(granted) > 100  # both kinds are tried
    assert {(n, t) for n, t in reached if n in callers} == granted
    # what the issue names, spelled out
    arch, cam, det = K.archery_rpc(), K.cam_rpc(), K.detector_rpc()
    for name, target in (
        ("camera", verb_key(arch, "nock")),
        ("camera", verb_key(arch, "release")),
        ("camera", verb_key(arch, "setWind")),
        ("camera", verb_key(arch, "reset")),
        ("controller", verb_key(K.part_rpc("left_arm"), "positionMove")),
        ("learner", verb_key(det, "calibrate")),
        ("learner", verb_key(K.cartesian_rpc("archery"), "setTrajTime")),
        (VIEWER, verb_key(K.cartesian_rpc("archery"), "posture")),
        (VIEWER, verb_key(K.learner_rpc(), "start")),
        ("detector", verb_key(cam, "scene")),  # the scene view is for people
        *impostors,
    ):
        assert (name, target) not in reached, (name, target)
    for name, target in (
        ("learner", verb_key(arch, "release")),
        ("detector", verb_key(cam, "grab", "detector")),
        ("controller", verb_key(K.part_rpc("left_arm"), "setRefSpeeds", "controller")),
        ("controller", verb_key(K.part_rpc("left_arm"), "claim", "controller")),
        (OPERATOR, left_claim),
        (VIEWER, verb_key(det, "status")),
        (VIEWER, verb_key(cam, "scene")),  # the dashboard's scene view
        (OPERATOR, verb_key(K.cartesian_rpc("archery"), "posture")),
    ):
        assert (name, target) in reached, (name, target)


def _grants_call(allowed: tuple[str, ...], target: str) -> bool:
    """Whether one of the role's call keys (a verb key, or `KEY/*`) covers `target`."""
    return any(a == target or (a.endswith("/*") and target.startswith(a[:-1])) for a in allowed)


def test_a_lease_belongs_to_the_identity_that_claims_it_only_the_operator_takes_over(
    endpoint: str, deployment: Path
) -> None:
    """Secure mode: a claim's `owner` text is not who owns the lease, the identity the router
    authenticated is; the controller cannot take the operator's part (naming itself
    "operator" or asking for a takeover), the operator can."""
    claim, get_claim = CLAIM, GET_CLAIM
    robot_net = net_as(endpoint, "robot", deployment)
    world = WorldConfig(scene=SceneConfig(meshes=False))
    with (
        serving(run_robot, RobotConfig(net=robot_net, world=world)),
        Node(None, net_as(endpoint, OPERATOR, deployment)) as operator,
        Node(None, net_as(endpoint, "controller", deployment)) as controller,
    ):
        operator.wait_alive(["robot"], timeout=60)
        key = K.part_rpc("left_arm")
        held = operator.call_typed(key, claim, ClaimArgs(owner="someone", ttl=30.0))
        assert held.owner == OPERATOR  # not the text it wrote
        for args in (ClaimArgs(owner=OPERATOR, ttl=30.0), ClaimArgs(owner="x", takeover=True)):
            with pytest.raises(RpcError) as refused:
                controller.call_typed(key, claim, args)
            assert refused.value.code == "not_owner", refused.value
        assert "only the operator takes a part over" in refused.value.message
        assert operator.call_typed(key, get_claim).owner == OPERATOR
        # the controller's own claim once the part is free, and the operator's takeover
        free = K.part_rpc("right_arm")
        assert controller.call_typed(free, claim, ClaimArgs(owner=OPERATOR)).owner == "controller"
        took = operator.call_typed(free, claim, ClaimArgs(owner=OPERATOR, takeover=True))
        assert took.owner == OPERATOR and took.took_over == "controller"
