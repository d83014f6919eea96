"""The router's access control for one robot, generated from the port and verb tables.

Default deny: every identity (a certificate common name: the five services, and `operator`,
`viewer` and `replay` for the CLI tools) gets exactly the flows its job needs, per verb (a call
of VERB goes to the key `PORT/VERB`, `protocol.keys.verb_key`, and a server answers `PORT/*`),
so a rule can grant one verb and not its neighbours. `roles` says what each identity
publishes, subscribes to, serves and calls, `_grants` turns a role into the router's rules and
`rules` is the whole policy; docs/secure.md tells the roles in prose.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import zenoh

from archery.protocol.keys import CARTESIAN_ARMS, Keys, tap_keys, verb_key, verbs_key
from archery.protocol.parts import PARTS
from archery.protocol.verbs import TABLES, names_caller

__all__ = [
    "OPERATOR",
    "REPLAY",
    "ROS2",
    "ROS2_OPERATOR",
    "TOOLS",
    "VIEWER",
    "Role",
    "granted",
    "roles",
    "rules",
    "server_of",
]

#: The command topics of `archery ros2 --operator` under each part (`apps.ros2.graph.COMMANDS`).
ROS2_COMMANDS = ("command", "joint_trajectory")
#: The node's topics under its namespace and its services (`apps.ros2.graph.TOPICS`,
#: `SERVICES`): what the `ros2` identities publish and serve.
ROS2_TOPICS = (
    "joint_states",
    "robot_description",
    "camera/image_raw",
    "camera/camera_info",
    "learner/rollout",
    "world/landing",
)
ROS2_SERVICES = ("reset", "nock", "release")
OPERATOR = "operator"  # the tools that move the robot
VIEWER = "viewer"  # the tools that only look
REPLAY = "replay"  # `archery replay`: the robot's output streams, the camera's verbs
ROS2 = "ros2"  # `archery ros2`: its rmw_zenoh keys and the robot's output streams
ROS2_OPERATOR = "ros2_operator"  # `archery ros2 --operator`: those, and the parts' moves
#: identities of tools: no alive token, describe or replace
TOOLS = (OPERATOR, VIEWER, REPLAY, ROS2, ROS2_OPERATOR)


@dataclass(frozen=True)
class Role:
    """The keys one identity publishes, subscribes to, serves and calls."""

    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    serve: tuple[str, ...] = ()
    call: tuple[str, ...] = ()
    watch: bool = True  # may watch the robot's liveliness tokens (`wait_alive`)
    tokens: tuple[str, ...] = ()  # liveliness tokens it holds beyond a service's own


def _calls(key: str, *verbs: str) -> tuple[str, ...]:
    """The keys of calls of `verbs` on the `rpc:i` port `key` (one key per verb)."""
    return tuple(verb_key(key, verb) for verb in verbs)


def _reading_calls(robot: str) -> tuple[str, ...]:
    """Every verb of every table that only reads (`Verb.reads`), on each port that serves it."""
    return tuple(
        verb_key(f"{robot}/{port}", verb.name)
        for table in TABLES
        for port in table.ports
        for verb in table
        if verb.reads
    )


def roles(robot: str) -> dict[str, Role]:
    """The role of every identity of a deployment for robot prefix `robot`: per verb, exactly
    the calls its job makes (the keys `protocol.keys.verb_key` gives).

    The calls of each service are those its code makes:

    * robot: publishes joint states, the world's state and events; takes joint commands;
      serves the joint RPCs and `archery/rpc:i`; calls nothing;
    * camera: follows the world's state; calls `archery/rpc:i status` (which scene to
      render); serves `cam/rpc:i`;
    * detector: calls `cam/rpc:i grab, calibration`; serves `detector/rpc:i`; it does not
      subscribe to the frame stream;
    * controller: calls each part's `getLimits, setRefSpeeds` and its lease verbs `claim,
      renewClaim, dropClaim` (one owner per arm), publishes joint commands, reads the joint
      states; serves the three cartesian controllers; `claim` and `setRefSpeeds` name their
      caller (`PORT/VERB~IDENTITY`, `Verb.names_caller`) and each identity is granted only its
      own name there (`_naming_calls`), so a lease's owner is the identity the router
      authenticated; calls `archery/rpc:i status, followTrajectory` (the robot's shot, and the
      whole shot's movement with its grasp and nock as one trajectory);
    * learner: calls the archery controller's `status, posture`, the robot's `reset, nock,
      release, status` (its world, journaled for replaying a shot) and the detector's
      `measure, frame, baseline`; follows the world's events; serves `learner/rpc:i`;
    * operator (the tools that move the robot or run sessions: `rpc`, `write`, `learn`, `up`):
      every verb, the joint commands, every stream, every `describe` and `replace`;
    * viewer (the tools that only look: `ports`, `alive`, `read`, `hz`, `record`, `view`,
      `interface`, `dashboard`): every stream and the verbs that change nothing
      (`Verb.reads`), among them the camera's `scene` (the dashboard's view of the whole
      robot); the detector, which grabs frames, is not granted it;
    * replay (`archery replay`, which publishes a recording again, a file anyone may have
      crafted): publishes the robot's output streams (`protocol.keys.OUTPUT_PORTS`: joint
      states, the world's state and events, the camera's frames, detections, rollouts) and,
      for `--serve-grab`, serves the camera's verbs (and publishes their taps); nothing else:
      no joint command, no call, no subscription, no watch of the liveliness tokens;
    * ros2 (`archery ros2`, read-only, and a ROS 2 client of the lab that only looks): the
      rmw_zenoh keys of the node's topics under its namespace (`/ROBOT`) and of `/tf` and
      `/tf_static` on any domain (published, subscribed), its Trigger services and the
      transient local topics' caches (served), the graph's tokens under `@ros2_lv/` (held
      and seen), the robot's output streams and the robot's `status`; no command key, no
      move;
    * ros2_operator (`archery ros2 --operator`, and a ROS 2 client of the lab that moves the
      robot): what ros2 has, the command topics of the namespace, the Trigger services'
      calls, each part's `positionMove` and `followTrajectory` (the robot applies them only
      where no other client's lease runs) and the robot's `reset, nock, release`.

    Every server also publishes its `rpc:i` ports' request and reply taps (`mesh.rpc_tap`).
    """
    k = Keys(robot)
    states = tuple(k.state(p) for p in PARTS)
    commands = tuple(k.command(p) for p in PARTS)
    part_rpcs = tuple(k.part_rpc(p) for p in PARTS)
    cartesian = tuple(k.cartesian_rpc(a) for a in CARTESIAN_ARMS)
    every_rpc = (*part_rpcs, k.archery_rpc(), k.cam_rpc(), k.detector_rpc(), *cartesian)
    every_verb = (*(verbs_key(key) for key in (*every_rpc, k.learner_rpc())),)
    describe_all = f"{robot}/describe/*"

    def taps(*rpc_keys: str) -> tuple[str, ...]:
        return tuple(key for rpc in rpc_keys for key in tap_keys(rpc) or ())

    every = {
        "robot": Role(
            publish=(
                *states,
                k.world_state(),
                k.world_events(),
                *taps(*part_rpcs, k.archery_rpc()),
            ),
            subscribe=commands,
            serve=tuple(verbs_key(key) for key in (*part_rpcs, k.archery_rpc())),
        ),
        "camera": Role(
            publish=(k.cam_frames(), *taps(k.cam_rpc())),
            subscribe=(k.world_state(),),
            serve=(verbs_key(k.cam_rpc()),),
            call=_calls(k.archery_rpc(), "status"),  # which scene to render
        ),
        "detector": Role(
            publish=(k.detector_hits(), *taps(k.detector_rpc())),
            serve=(verbs_key(k.detector_rpc()),),
            # it grabs frames by RPC; the frame stream is for people
            call=_calls(k.cam_rpc(), "grab", "calibration"),
        ),
        "controller": Role(
            publish=(*commands, *taps(*cartesian)),
            subscribe=states,
            serve=tuple(verbs_key(key) for key in cartesian),
            call=tuple(
                c
                for key in part_rpcs
                for c in _calls(
                    key, "getLimits", "setRefSpeeds", "claim", "renewClaim", "dropClaim"
                )
            )
            # the whole shot: its robot's shot, and the movement as one trajectory with its
            # grasp and nock
            + _calls(k.archery_rpc(), "status", "followTrajectory"),
        ),
        "learner": Role(
            publish=(k.learner_rollouts(), *taps(k.learner_rpc())),
            subscribe=(k.world_events(),),
            serve=(verbs_key(k.learner_rpc()),),
            call=(
                *_calls(k.cartesian_rpc("archery"), "status", "posture"),
                *_calls(k.archery_rpc(), "reset", "nock", "release", "status"),
                *_calls(k.detector_rpc(), "measure", "frame", "baseline"),
            ),
        ),
        # The tools that move the robot or run sessions (rpc, write, learn, up): every verb,
        # the joint commands, every stream.
        OPERATOR: Role(
            publish=commands,
            subscribe=(f"{robot}/**",),
            call=(*every_verb, describe_all, f"{robot}/replace/*"),
        ),
        # The tools that only look (ports, read, hz, record, view, dashboard, alive,
        # interface): every stream and the verbs that change nothing.
        VIEWER: Role(subscribe=(f"{robot}/**",), call=(*_reading_calls(robot), describe_all)),
        # A replay (its file may be crafted): the robot's output streams, and for --serve-grab
        # the camera's verbs (after the camera, which `server_of` names as their server).
        REPLAY: Role(
            publish=(*k.output_streams(), *taps(k.cam_rpc())),
            serve=(verbs_key(k.cam_rpc()),),
            watch=False,
        ),
    }
    every[ROS2] = _ros2(robot, operator=False)
    every[ROS2_OPERATOR] = _ros2(robot, operator=True)
    return {name: _naming_calls(name, role) for name, role in every.items()}


def _ros2(robot: str, *, operator: bool) -> Role:
    """The role of `archery ros2` and of a ROS 2 client of the lab holding the same identity
    (`operator`: `--operator`): rmw_zenoh's data keys `DOMAIN/NAME/TYPE/HASH` of the node's
    topics and services under its namespace `/ROBOT` and of `/tf`, `/tf_static`, on any
    domain; the graph's tokens (`@ros2_lv/`)."""
    k = Keys(robot)
    topics = (
        *(f"*/{robot}/{name}/**" for name in ROS2_TOPICS),
        "*/tf/**",
        "*/tf_static/**",
    )
    services = tuple(f"*/{robot}/{name}/**" for name in ROS2_SERVICES)
    commands = tuple(f"*/{robot}/{p}/{leaf}/**" for p in PARTS for leaf in ROS2_COMMANDS)
    moves = tuple(
        c for p in PARTS for c in _calls(k.part_rpc(p), "positionMove", "followTrajectory")
    )
    return Role(
        publish=(*topics, *(commands if operator else ())),
        subscribe=(*k.output_streams(), *topics, *(commands if operator else ())),
        serve=(*topics, *services),  # the services, the transient local topics' caches
        call=(
            *_calls(k.archery_rpc(), "status"),
            *((*moves, *_calls(k.archery_rpc(), "reset", "nock", "release")) if operator else ()),
            *(services if operator else ()),
        ),
        tokens=("@ros2_lv/**", *topics),
    )


def _naming_calls(name: str, role: Role) -> Role:
    """`role` with each call of a verb that names its caller (`Verb.names_caller`) made on the
    key that names `name`, the only one the router lets it use."""

    def named(call: str) -> str:
        head, _, verb = call.rpartition("/")
        return verb_key(head, verb, name) if names_caller(head, verb) else call

    return dataclasses.replace(role, call=tuple(named(call) for call in role.call))


def _port_of_call(call: str) -> str:
    """`KEY/*` for a call's key `KEY/VERB` of an `rpc:i` port (other keys as they are)."""
    head, _, _ = call.rpartition("/")
    return verbs_key(head) if head.endswith("rpc:i") else call


def _rule(
    rule_id: str, messages: list[str], flow: str, key_exprs: tuple[str, ...]
) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": list(key_exprs),
    }


def _grants(name: str, role: Role, robot: str) -> list[dict[str, Any]]:
    """The router's rules for identity `name` with `role`: the Zenoh messages and directions
    (`ingress`: what the identity sends to the router, `egress`: what the router forwards to
    it) each of its keys takes.

    * publish K: `put` in, `declare_subscriber` out on K and on `ROBOT/**` (the publisher
      learns who listens, also a listener of the whole robot: a publisher that hears of no
      subscriber drops what it puts);
    * subscribe K: `declare_subscriber` in, `put` out;
    * serve K: `declare_queryable` in, `query` out, `reply` in;
    * call K: `query` in; `reply` and `declare_queryable` out on the port (`PORT/*`);
    * every service holds liveliness tokens only under its own name (`ROBOT/alive/NAME`,
      `ROBOT/alive/NAME/*`), serves and may call its own `ROBOT/describe/NAME` and
      `ROBOT/replace/NAME` (its next instance presents the same identity); every identity but
      `replay` may watch the robot's tokens (`wait_alive`, the replier check).
    """
    out: list[dict[str, Any]] = []
    if role.publish:
        out.append(_rule(f"{name}-publish", ["put"], "ingress", role.publish))
        # a publisher learns of the subscribers that match it, also those declared on a wider
        # key expression (`ROBOT/**`: a recorder's, a replay's listener): without that
        # declaration it takes its key for unwatched and drops what it puts
        matching = (*role.publish, f"{robot}/**")
        out.append(_rule(f"{name}-publish-match", ["declare_subscriber"], "egress", matching))
    if role.subscribe:
        out.append(_rule(f"{name}-subscribe", ["declare_subscriber"], "ingress", role.subscribe))
        out.append(_rule(f"{name}-subscribe-data", ["put"], "egress", role.subscribe))
    # its own describe and replace keys: served, and called by its next instance (a
    # replacement presents the same identity; it holds no other)
    own = (f"{robot}/describe/{name}", f"{robot}/replace/{name}")
    serve = (*role.serve, *own) if name not in TOOLS else role.serve
    if serve:
        out.append(_rule(f"{name}-serve", ["declare_queryable", "reply"], "ingress", serve))
        out.append(_rule(f"{name}-serve-queries", ["query"], "egress", serve))
    call = (*role.call, *own) if name not in TOOLS else role.call
    if call:
        out.append(_rule(f"{name}-call", ["query"], "ingress", call))
        # the replies come on the verb's key; the server's queryable is declared on every verb
        # of its port (`verbs_key`), which the caller learns of whole
        ports = tuple(dict.fromkeys(_port_of_call(c) for c in call))
        out.append(_rule(f"{name}-call-replies", ["reply", "declare_queryable"], "egress", ports))
    alive = f"{robot}/alive/**"
    tokens = role.tokens
    if name not in TOOLS:
        tokens = (f"{robot}/alive/{name}", f"{robot}/alive/{name}/*", *tokens)
    if tokens:
        out.append(_rule(f"{name}-token", ["liveliness_token"], "ingress", tokens))
    if role.tokens:  # and sees the others' (the ROS 2 graph)
        watched = ["declare_liveliness_subscriber", "liveliness_query"]
        out.append(_rule(f"{name}-graph", watched, "ingress", role.tokens))
        seen = ["liveliness_token", "reply"]
        out.append(_rule(f"{name}-graph-tokens", seen, "egress", role.tokens))
    if not role.watch:
        return out
    out.append(
        _rule(
            f"{name}-watch",
            ["declare_liveliness_subscriber", "liveliness_query"],
            "ingress",
            (alive,),
        )
    )
    out.append(_rule(f"{name}-watch-tokens", ["liveliness_token", "reply"], "egress", (alive,)))
    return out


def rules(robot: str) -> dict[str, Any]:
    """The `access_control` section of the router's Zenoh config for robot prefix `robot`:
    default deny, one subject per identity (matched by certificate common name), one policy
    granting that identity its role's flows.

    The router enforces the rules on its own links. A denied message is dropped silently
    there: the sender's `put` or `declare_*` still succeeds, the receiver never sees it (a
    caller whose rules do not grant its call is told "denied by access control" by
    `mesh.rpc_client`, which asks `granted`)."""
    all_rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for name, role in roles(robot).items():
        granted = _grants(name, role, robot)
        all_rules += granted
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": name, "rules": [r["id"] for r in granted], "subjects": [name]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": all_rules,
        "subjects": subjects,
        "policies": policies,
    }


def server_of(robot: str, key: str) -> str | None:
    """The identity that serves the `rpc:i` key `key` of robot `robot`, or None."""
    served = verbs_key(key)
    return next((name for name, role in roles(robot).items() if served in role.serve), None)


def granted(robot: str, identity: str, call: str) -> bool:
    """Whether the rules let `identity` make the call on key `call` (`PORT/VERB`) of robot
    `robot`: an identity the rules do not name is granted nothing."""
    role = roles(robot).get(identity)
    if role is None:
        return False
    own = () if identity in TOOLS else (f"{robot}/replace/{identity}",)
    target = zenoh.KeyExpr(call)
    return any(zenoh.KeyExpr(expr).includes(target) for expr in (*role.call, *own))
