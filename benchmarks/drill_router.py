"""Drill: kill the router of a supervised mesh mid-session and restart it after 2 s and 15 s.

The drills are `archery drill`'s (`apps.drills.router`); this runs only those two:
`MUJOCO_GL=egl python -m benchmarks.drill_router [--json OUT] [--seed N]`, the same as
`archery drill --only router-2s --only router-15s`. Each row gives the router's outage, the
seconds from the new router listening to all five services alive again (the notes) and to the
session's next done rollout (recover), and whether any service was restarted (a failure).
"""

from __future__ import annotations

import sys

from apps.drills.runner import main as drill_main


def main(argv: list[str] | None = None) -> int:
    """Run the two router drills with `archery drill`'s other flags."""
    args = list(sys.argv[1:] if argv is None else argv)
    return drill_main(["--only", "router-2s", "--only", "router-15s", *args])


if __name__ == "__main__":
    sys.exit(main())
