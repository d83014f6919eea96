"""A flooder as a process of its own (so that its publishing does not hold up the test's own
threads): `python -m tests.flooder ENDPOINT ROBOT PART COUNT` connects, prints `ready`, then for
each line on stdin publishes COUNT valid `JointCommand`s on `ROBOT/PART/command:i` that hold the
part where it is (its latest measured position, without a lease), as fast as the network takes
them (congestion control BLOCK: every one reaches the router), and prints the seconds it took.
"""

from __future__ import annotations

import sys
import time

import zenoh

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.codec import encode
from archery.protocol.messages import JointCommand, JointState


def main(argv: list[str]) -> int:
    endpoint, robot, part, count = argv[0], argv[1], argv[2], int(argv[3])
    with Node(None, NetConfig(connect=(endpoint,), robot=robot)) as node:
        keys = node.keys
        state = node.subscribe(keys.state(part), JointState)
        publisher = node.session.declare_publisher(
            keys.command(part), congestion_control=zenoh.CongestionControl.BLOCK
        )
        state.wait_newer(60, after_seq=-1)
        print("ready", flush=True)
        for _ in sys.stdin:
            latest = state.latest()
            assert latest is not None
            payload = encode(JointCommand(part=part, position=list(latest.position)))
            start = time.monotonic()
            for _ in range(count):
                publisher.put(payload)
            print(time.monotonic() - start, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
