"""The router's access control for one robot, generated from the port table.

Every identity (a certificate common name: the five services, `operator` for the CLI tools)
gets exactly the flows its role needs, and everything else is denied (`default_permission:
deny`). The router enforces the rules on its own links: `ingress` is what an identity sends to
the router, `egress` what the router forwards to it. A denied message is dropped silently at
the router: the sender's `put` or `declare_*` still succeeds, the receiver never sees it.

A role is described by the keys it publishes, subscribes to, serves (`rpc:i` queryables) and
calls; `_grants` turns each into the Zenoh messages and directions it takes:

* publish K: `put` in, `declare_subscriber` out (the publisher learns who listens);
* subscribe K: `declare_subscriber` in, `put` out;
* serve K: `declare_queryable` in, `query` out, `reply` in;
* call K: `query` in, `reply` out, `declare_queryable` out;
* every identity holds liveliness tokens only under its own name (`ROBOT/alive/NAME`,
  `ROBOT/alive/NAME/*`), serves its own `ROBOT/describe/NAME`, may query its own describe (the
  one-instance check) and watch every token of the robot (`wait_alive`, the replier check).

Every grant is a flow of the running services (a session of `archery learn` uses them all):

* robot: publishes joint states, the scene (`world/state:o`) and world events; takes joint
  commands; serves the joint RPCs and `archery/rpc:i` (nock, release, reset, setWind, status);
* camera: subscribes to the scene (a change wakes the renderer), calls `archery/rpc:i`
  (`status`: which scene to render), serves `cam/rpc:i` (grab, calibration marks) and
  publishes the frames (read by `archery view`, the operator);
* detector: calls `cam/rpc:i` (grabs the frame of a shot, the calibration marks), serves
  `detector/rpc:i` (measure, calibrate), publishes `detector/hit:o`; it does not subscribe
  to the frame stream;
* controller: subscribes to the joint states, publishes joint commands, calls the joint RPCs
  (`getLimits`, `setRefSpeeds`), serves the three cartesian controllers;
* learner: calls `cartesianController/archery/rpc:i` (status, posture), `archery/rpc:i`
  (reset, nock, release) and `detector/rpc:i` (measure, frame), subscribes to the world
  events (the shot's outcome), serves `learner/rpc:i` and publishes `learner/rollout:o`;
* operator (the CLI tools: `learn`, `ports`, `read`, `rpc`, `view`, `write`, and `up`
  waiting for its children): calls every RPC (the learner's `start`/`status`/`stop` for
  `archery learn`) and `describe/*`, reads every stream (`learner/rollout:o` for `archery
  learn`), commands the joints, watches the liveliness tokens; it holds no token and serves
  nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from protocol.keys import CARTESIAN_ARMS, Keys
from protocol.parts import PARTS

__all__ = ["OPERATOR", "Role", "roles", "rules", "server_of"]

OPERATOR = "operator"


@dataclass(frozen=True)
class Role:
    """The keys one identity publishes, subscribes to, serves and calls."""

    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    serve: tuple[str, ...] = ()
    call: tuple[str, ...] = ()


def roles(robot: str) -> dict[str, Role]:
    """The role of every identity of a deployment for robot prefix `robot`."""
    k = Keys(robot)
    states = tuple(k.state(p) for p in PARTS)
    commands = tuple(k.command(p) for p in PARTS)
    part_rpcs = tuple(k.part_rpc(p) for p in PARTS)
    cartesian = tuple(k.cartesian_rpc(a) for a in CARTESIAN_ARMS)
    every_rpc = (
        *part_rpcs,
        k.archery_rpc(),
        k.cam_rpc(),
        k.detector_rpc(),
        *cartesian,
        k.learner_rpc(),
        f"{robot}/describe/*",
    )
    return {
        "robot": Role(
            publish=(*states, k.world_state(), k.world_events()),
            subscribe=commands,
            serve=(*part_rpcs, k.archery_rpc()),
        ),
        "camera": Role(
            publish=(k.cam_frames(),),
            subscribe=(k.world_state(),),
            serve=(k.cam_rpc(),),
            call=(k.archery_rpc(),),
        ),
        "detector": Role(
            publish=(k.detector_hits(),),
            serve=(k.detector_rpc(),),
            call=(k.cam_rpc(),),  # it grabs frames by RPC; the frame stream is the operator's
        ),
        "controller": Role(
            publish=commands,
            subscribe=states,
            serve=cartesian,
            call=part_rpcs,
        ),
        "learner": Role(
            publish=(k.learner_rollouts(),),
            subscribe=(k.world_events(),),
            serve=(k.learner_rpc(),),
            call=(k.cartesian_rpc("archery"), k.archery_rpc(), k.detector_rpc()),
        ),
        # The CLI tools (ports, read, rpc, view, learn, up): read every stream, call every
        # verb, and command the joints (`archery write ROBOT/PART/command:i`), nothing else.
        OPERATOR: Role(publish=commands, subscribe=(f"{robot}/**",), call=every_rpc),
    }


def _rule(rule_id: str, messages: list[str], flow: str, key_exprs: tuple[str, ...]) -> dict:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": list(key_exprs),
    }


def _grants(name: str, role: Role, robot: str) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    if role.publish:
        out.append(_rule(f"{name}-publish", ["put"], "ingress", role.publish))
        out.append(_rule(f"{name}-publish-match", ["declare_subscriber"], "egress", role.publish))
    if role.subscribe:
        out.append(_rule(f"{name}-subscribe", ["declare_subscriber"], "ingress", role.subscribe))
        out.append(_rule(f"{name}-subscribe-data", ["put"], "egress", role.subscribe))
    own_describe = f"{robot}/describe/{name}"
    serve = (*role.serve, own_describe) if name != OPERATOR else role.serve
    if serve:
        out.append(_rule(f"{name}-serve", ["declare_queryable", "reply"], "ingress", serve))
        out.append(_rule(f"{name}-serve-queries", ["query"], "egress", serve))
    call = (*role.call, own_describe) if name != OPERATOR else role.call
    out.append(_rule(f"{name}-call", ["query"], "ingress", call))
    out.append(_rule(f"{name}-call-replies", ["reply", "declare_queryable"], "egress", call))
    alive = f"{robot}/alive/**"
    if name != OPERATOR:
        own = (f"{robot}/alive/{name}", f"{robot}/alive/{name}/*")
        out.append(_rule(f"{name}-token", ["liveliness_token"], "ingress", own))
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
    granting that identity its role's flows."""
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
    return next((name for name, role in roles(robot).items() if key in role.serve), None)
