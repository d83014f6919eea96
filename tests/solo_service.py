"""A minimal service for the one-instance tests: `python -m tests.solo_service NAME [flags]`
runs `service_main` with a node named NAME that holds its tokens until SIGTERM."""

from __future__ import annotations

import sys
import threading
from types import SimpleNamespace

from archery.mesh.node import Node
from archery.mesh.service import service_main


def main(argv: list[str]) -> int:
    name, rest = argv[0], argv[1:]

    def run(config: SimpleNamespace, stop: threading.Event) -> None:
        with Node(name, config.net) as node:
            node.ready()
            stop.wait()

    return service_main(
        rest,
        prog=name,
        description="a service that only holds its name",
        add_arguments=lambda parser: None,
        make_config=lambda args, net: SimpleNamespace(net=net),
        run=run,
    )


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
