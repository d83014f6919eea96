"""`archery keys init DIR`: the CA, one identity per role, the router's access control and
YARP's key of a `--secure` deployment (see `mesh.credentials`); warns where a git work tree
would commit its private keys. `archery keys yarp DIR`: YARP's key alone, for a deployment made
without one."""

from __future__ import annotations

import sys
from pathlib import Path

from archery.mesh.cliargs import ArgumentParser
from archery.mesh.credentials import (
    CA_CERT,
    DEFAULT_DAYS,
    DEFAULT_HOSTS,
    IDENTITIES,
    YARP_AUTH,
    init_deployment,
    unignored_keys,
    write_yarp_key,
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
    yarp = sub.add_parser(
        "yarp",
        help=f"write YARP's key DIR/{YARP_AUTH} into a deployment made without one; copied into "
        "a YARP client's configuration folder, it lets that client reach `archery yarp --secure`",
    )
    yarp.add_argument("dir", help="the deployment directory (`archery keys init DIR`)")
    yarp.add_argument("--force", action="store_true", help="replace the key (every client too)")
    args = parser.parse_args(argv)
    if args.action == "yarp":
        return _yarp(Path(args.dir), force=args.force)
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
        f"tls/127.0.0.1:7447` and every process with `--secure {path}`. "
        + _yarp_clients(Path(path) / YARP_AUTH)
    )
    exposed = unignored_keys(Path(path))
    if exposed:
        print(
            f"archery keys: warning: {path} is in a git work tree that does not ignore its "
            f"private keys ({', '.join(str(k.relative_to(path)) for k in exposed)}): add "
            f"`{Path(path).name}/` (or `*.key` and `{YARP_AUTH}`) to .gitignore",
            file=sys.stderr,
        )
    return 0


def _yarp_clients(key: Path) -> str:
    return (
        f"A YARP client of `archery yarp --secure` needs {key}: copy it into the client's YARP "
        "configuration folder (~/.config/yarp/)."
    )


def _yarp(folder: Path, *, force: bool) -> int:
    """`archery keys yarp DIR`: YARP's key written into the deployment `folder`."""
    path = folder / YARP_AUTH
    if not (folder / CA_CERT).is_file():
        print(
            f"archery keys: {folder} holds no deployment: `archery keys init {folder}`",
            file=sys.stderr,
        )
        return 2
    if path.exists() and not force:
        print(
            f"archery keys: {path} exists; --force replaces it (every YARP client then needs the "
            "new one)",
            file=sys.stderr,
        )
        return 2
    try:
        write_yarp_key(folder)
    except OSError as exc:
        print(f"archery keys: cannot write {path}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"{path}: YARP's key. {_yarp_clients(path)}")
    return 0
