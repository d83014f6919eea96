"""Print the requirements of the project's core plus the named extras, one per line, read from
pyproject.toml (extras that name `archery[...]` are expanded): what an image installs before the
project's own code is copied in, so that a code change rebuilds no dependency layer.

    python3 docker/requirements.py pyproject.toml controller > requirements.txt
"""

from __future__ import annotations

import re
import sys
import tomllib

_SELF = re.compile(r"^archery\[(?P<extras>[^\]]+)\]$")


def requirements(project: dict, extras: list[str]) -> list[str]:
    """The core dependencies and those of `extras` (expanded, each listed once, in order).

    Raises:
        KeyError: an extra the project does not define.
    """
    optional = project["optional-dependencies"]
    out: list[str] = list(project["dependencies"])
    todo = list(extras)
    while todo:
        name = todo.pop(0)
        if name not in optional:
            raise KeyError(f"no extra {name!r}; extras: {', '.join(sorted(optional))}")
        for requirement in optional[name]:
            match = _SELF.match(requirement)
            if match:
                todo += [e.strip() for e in match["extras"].split(",")]
            elif requirement not in out:
                out.append(requirement)
    return out


def main(argv: list[str]) -> int:
    """`requirements.py PYPROJECT [EXTRA…]`: exit 2 on an unknown extra."""
    with open(argv[0], "rb") as file:
        project = tomllib.load(file)["project"]
    try:
        print("\n".join(requirements(project, argv[1:])))
    except KeyError as exc:
        print(f"requirements.py: {exc.args[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
