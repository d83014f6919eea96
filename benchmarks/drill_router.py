"""Drill: kill the router of a supervised mesh mid-session and restart it after 2 s and 15 s.

The drills are `archery drill`'s (`apps.drills.router`); this runs only those two:
`MUJOCO_GL=egl python -m benchmarks.drill_router [--json OUT] [--seed N]`, the same as
`archery drill --only router-2s --only router-15s` (every other flag is `archery drill`'s). Each
row gives the router's outage, the seconds from the new router listening to all five services
alive again (the notes) and to the session's next done rollout (recover), and whether any
service was restarted (a failure).

`--smoke` runs the 2 s drill alone (its outage the shortest of the two; tens of seconds, the
mesh's start-up included), its logs and journals in a temporary directory, removed after.
"""

from __future__ import annotations

import argparse
import sys
import tempfile

from archery.apps.drills.runner import main as drill_main


def main(argv: list[str] | None = None) -> int:
    """Run the two router drills (or, with `--smoke`, the 2 s one) with `archery drill`'s
    other flags."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.drill_router", description=__doc__)
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="the 2 s drill alone, in a temporary directory (no figures kept)",
    )
    known, args = parser.parse_known_args(list(sys.argv[1:] if argv is None else argv))
    if known.smoke:
        with tempfile.TemporaryDirectory(prefix="drill-router-") as tmp:
            return drill_main(["--only", "router-2s", *args, "--workdir", tmp])
    return drill_main(["--only", "router-2s", "--only", "router-15s", *args])


if __name__ == "__main__":
    sys.exit(main())
