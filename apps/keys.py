"""`archery keys init DIR`: the CA, one identity per role and the router's access control of a
`--secure` deployment (see `mesh.credentials`); warns where a git work tree would commit its
private keys."""

from __future__ import annotations

import sys
from pathlib import Path

from archery.mesh.cliargs import ArgumentParser
from archery.mesh.credentials import (
    DEFAULT_DAYS,
    DEFAULT_HOSTS,
    IDENTITIES,
    init_deployment,
    unignored_keys,
)
from archery.protocol.errors import ConfigError
from archery.protocol.keys import DEFAULT_ROBOT

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """`archery keys init DIR [--robot R] [--days N] [--host H ...] [--force]`."""
    parser = ArgumentParser(
        prog="archery keys",
        description="the CA, identities and access control of a --secure deployment",
    )
    sub = parser.add_subparsers(dest="action", required=True, parser_class=ArgumentParser)
    init = sub.add_parser("init", help="create the CA, identities and ACL of one deployment")
    init.add_argument("dir", help="the deployment directory (created, mode 0700)")
    init.add_argument(
        "--robot", default=DEFAULT_ROBOT, help=f"robot prefix the ACL covers ({DEFAULT_ROBOT})"
    )
    init.add_argument(
        "--days", type=float, default=DEFAULT_DAYS, help=f"validity (default {DEFAULT_DAYS})"
    )
    init.add_argument(
        "--host",
        action="append",
        metavar="NAME",
        help=f"a name or IP the router is reached at, repeatable (default {list(DEFAULT_HOSTS)})",
    )
    init.add_argument("--force", action="store_true", help="replace an existing deployment")
    args = parser.parse_args(argv)
    try:
        hosts = tuple(args.host) if args.host else DEFAULT_HOSTS
        path = init_deployment(
            args.dir, robot=args.robot, days=args.days, hosts=hosts, force=args.force
        )
    except (ConfigError, ValueError) as exc:
        print(f"archery keys: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"archery keys: cannot write {args.dir!r}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(
        f"{path}: CA and identities {', '.join(IDENTITIES)} for robot {args.robot!r}, valid "
        f"{args.days:g} days. Start the router with `archery router --secure {path} --listen "
        f"tls/127.0.0.1:7447` and every process with `--secure {path}`."
    )
    exposed = unignored_keys(Path(path))
    if exposed:
        print(
            f"archery keys: warning: {path} is in a git work tree that does not ignore its "
            f"private keys ({', '.join(k.name for k in exposed)}): add `{Path(path).name}/` or "
            "`*.key` to .gitignore",
            file=sys.stderr,
        )
    return 0
