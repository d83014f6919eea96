"""The `archery` console script: one verb per service or tool, dispatched lazily."""

from __future__ import annotations

import importlib
import sys

__all__ = ["VERBS", "main"]

# verb -> ("module:function", one-line help). Each function takes argv (list[str]) and returns
# the process exit status. Modules are imported only when their verb runs, so a tool never pays
# for MuJoCo or Pinocchio it does not use.
VERBS: dict[str, tuple[str, str]] = {
    "router": ("protocol.router:main", "run a Zenoh router (the mesh's embedded default)"),
    "ports": ("protocol.tools:ports_main", "list live services and their ports (yarp name list)"),
    "read": ("protocol.tools:read_main", "print decoded messages from a key as JSON lines"),
    "write": ("protocol.tools:write_main", "publish one message, given as JSON, on a key"),
    "rpc": ("protocol.tools:rpc_main", "call an rpc:i verb and print the reply"),
    "view": ("protocol.tools:view_main", "save the next image on an image port as PNG"),
    "selfcheck": ("protocol.selfcheck:main", "start a router and two nodes, check the mesh"),
    "robot": ("services.robot.service:main", "the simulated iCub: joint ports, bow, arrow, target"),
    "camera": (
        "services.camera.service:main",
        "camera frames of the target (rendered/device/folder)",
    ),
    "detector": ("services.detector.service:main", "GMM colour detector: target centre, arrow tip"),
    "calibrate": ("services.detector.offline:calibrate_main", "fit the colour model from pixels"),
    "detect": ("services.detector.offline:detect_main", "detect target and arrow in an image"),
    "controller": ("services.controller.service:main", "Pinocchio IK: archery posture for θ"),
    "learner": (
        "services.learner.service:main",
        "learning sessions over the mesh (ARCHER, PoWER, baselines), journaled",
    ),
    "learn": ("services.learner.learn:main", "run one learning session against running services"),
    "up": ("services.launcher:main", "start a router and all five services; stop them on Ctrl-C"),
    "experiment": (
        "services.learner.experiment:main",
        "run the paper's simulation experiment (learners on the ballistic world)",
    ),
    "keys": ("protocol.credentials:main", "keys init DIR: CA, identities and ACL for --secure"),
}


def _usage() -> str:
    width = max(len(v) for v in VERBS)
    lines = ["usage: archery VERB [options]   (archery VERB --help for a verb's options)", ""]
    lines += [f"  {verb.ljust(width)}  {help_}" for verb, (_, help_) in VERBS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run `archery VERB ...`; returns the verb's exit status."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    verb, rest = args[0], args[1:]
    if verb not in VERBS:
        print(f"archery: unknown verb {verb!r}; valid verbs: {', '.join(VERBS)}", file=sys.stderr)
        return 2
    module_name, func_name = VERBS[verb][0].split(":")
    func = getattr(importlib.import_module(module_name), func_name)
    return int(func(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
