"""`archery keys init DIR`: the credentials of one secure deployment (mutual TLS + access control).

A deployment directory holds a certificate authority, one identity per process role (the five
services, the `router`, and `operator`, `viewer` and `replay` for the CLI tools; `mesh.acl`
says what each may do), the router's access-control policy and `deployment.json`
and YARP's key (`yarp/auth.conf`, `write_yarp_key`; `init_deployment` lists the files, and why
certificates rather than passwords). The CA key signs every identity: keep it off the machines
that run the mesh (the compose profile mounts only the CA certificate and each container's own
identity). docs/secure.md.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import secrets
import subprocess
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from archery.mesh.acl import OPERATOR, REPLAY, ROS2, ROS2_OPERATOR, VIEWER
from archery.protocol.errors import ConfigError
from archery.protocol.keys import DEFAULT_ROBOT, validate_robot
from archery.protocol.robotspec import SERVICES

__all__ = [
    "IDENTITIES",
    "Authority",
    "identity_folder",
    "init_deployment",
    "issue",
    "new_authority",
    "unignored_keys",
    "write_identity",
    "write_yarp_key",
]

ROUTER = "router"
IDENTITIES = (*SERVICES, ROUTER, OPERATOR, VIEWER, REPLAY, ROS2, ROS2_OPERATOR)
DEFAULT_DAYS = 365
DEFAULT_HOSTS = ("localhost", "127.0.0.1", "router", "router-secure")  # + compose names
CA_CERT, CA_KEY, ACL_FILE, META_FILE = "ca.pem", "ca.key", "acl.json5", "deployment.json"
#: YARP's shared key, as YARP 3.5's AuthHMAC reads it from a file named auth.conf
YARP_AUTH = "yarp/auth.conf"
#: a key YARP's config parser reads as a word, never a number; its length a multiple of 16, for
#: YARP 3.5 copies the key with its terminating NUL into a buffer of the key's length, one byte
#: past it, which corrupts glibc's heap (the process aborts) when the length is 8 modulo 16
YARP_KEY_PREFIX = "archery-"


@dataclass(frozen=True)
class Authority:
    """A CA: its private key and self-signed certificate."""

    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "archery mesh"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def new_authority(days: float = DEFAULT_DAYS, name: str = "archery CA") -> Authority:
    """A new CA (ECDSA P-256) valid from a minute ago for `days` days."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(name))
        .issuer_name(_name(name))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=1))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return Authority(key, cert)


def issue(
    ca: Authority,
    common_name: str,
    *,
    hosts: tuple[str, ...] = DEFAULT_HOSTS,
    not_before: dt.datetime | None = None,
    not_after: dt.datetime | None = None,
    days: float = DEFAULT_DAYS,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A key and a certificate for `common_name`, signed by `ca`, usable by a TLS client and
    server (subject alternative names `hosts`: DNS names or IP addresses)."""
    key = ec.generate_private_key(ec.SECP256R1())
    start = not_before or _now() - dt.timedelta(minutes=1)
    end = not_after or _now() + dt.timedelta(days=days)
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(ca.cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()), critical=False
        )
        .sign(ca.key, hashes.SHA256())
    )
    return key, cert


def _write(path: Path, data: bytes, mode: int) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.chmod(path, mode)  # O_CREAT's mode does not apply to a file that existed


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def write_identity(
    directory: Path, name: str, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate
) -> None:
    """Write `NAME.key` (0600) and `NAME.pem` (0644) into `directory`."""
    _write(directory / f"{name}.key", _key_pem(key), 0o600)
    _write(directory / f"{name}.pem", cert.public_bytes(serialization.Encoding.PEM), 0o644)


def write_yarp_key(deployment: Path) -> Path:
    """Write a new YARP key, `DEPLOYMENT/yarp/auth.conf` (folder 0700, file 0600): YARP 3.5's
    `[AUTH] key`, 224 random bits. Every YARP process holding it (the bridge, its name server,
    the lab's clients) authenticates each connection with HMAC-SHA256 before YARP reads a byte
    of it; a process without it is refused. The only file a YARP client needs."""
    path = deployment / YARP_AUTH
    path.parent.mkdir(mode=0o700, exist_ok=True)
    os.chmod(path.parent, 0o700)
    key = YARP_KEY_PREFIX + secrets.token_hex(28)  # 64 characters: see YARP_KEY_PREFIX
    text = (
        "# YARP's key of this deployment (archery keys init): copy this file into the YARP\n"
        "# configuration folder (~/.config/yarp/, `yarp conf` shows it) of each YARP client\n"
        f"[AUTH]\nkey {key}\n"
    )
    _write(path, text.encode(), 0o600)
    return path


def init_deployment(
    directory: str | Path,
    *,
    robot: str = DEFAULT_ROBOT,
    days: float = DEFAULT_DAYS,
    hosts: tuple[str, ...] = DEFAULT_HOSTS,
    force: bool = False,
) -> Path:
    """Create the CA, every identity of `IDENTITIES`, `acl.json5` and `deployment.json`.

    The directory (0700) holds the certificate authority (`ca.pem`, `ca.key`), one identity
    per process role (`NAME.pem` + `NAME.key`, signed by the CA, common name = NAME), the
    router's access-control policy `acl.json5` (generated by `mesh.acl.rules` for one robot
    prefix), `deployment.json` (robot, identities, hosts, validity) and YARP's shared key
    `yarp/auth.conf` (`write_yarp_key`). Private keys are written with mode 0600.

    Why mutual TLS and not Zenoh's user/password authentication: with mTLS every link is
    encrypted and both ends prove who they are with a key that never crosses the wire; the
    router learns the peer's identity from its certificate's common name, which is what its
    access control matches on (`subjects: [{cert_common_names: [...]}]`). User/password
    (`transport/auth/usrpwd`) only authenticates: the traffic stays plain TCP, readable and
    alterable by anyone on the path, the passwords sit in a dictionary file on the router in
    clear text, and a client's password is sent to whichever router it reaches. With
    certificates, a compromised service key is one file to reissue, and expiry is built in
    (`days`, `--days`; links are closed when a certificate expires).

    Raises:
        ConfigError: `directory` holds a deployment already (unless `force`), or a bad value.
    """
    from archery.mesh.acl import rules

    validate_robot(robot)
    if not 0 < days <= 3650:
        raise ConfigError(f"--days must be in (0, 3650], got {days!r}")
    path = Path(directory)
    existing = [n for n in (CA_CERT, CA_KEY, META_FILE) if (path / n).exists()]
    if existing and not force:
        raise ConfigError(
            f"{path} holds a deployment already ({', '.join(existing)}); use --force to replace "
            f"it (every process then needs the new credentials)"
        )
    path.mkdir(parents=True, exist_ok=True)
    os.chmod(path, 0o700)
    ca = new_authority(days)
    _write(path / CA_KEY, _key_pem(ca.key), 0o600)
    _write(path / CA_CERT, ca.cert.public_bytes(serialization.Encoding.PEM), 0o644)
    for name in IDENTITIES:
        key, cert = issue(ca, name, hosts=hosts, days=days)
        write_identity(path, name, key, cert)
    _write(path / ACL_FILE, (json.dumps(rules(robot), indent=2) + "\n").encode(), 0o644)
    meta = {
        "robot": robot,
        "identities": list(IDENTITIES),
        "hosts": list(hosts),
        "not_after": ca.cert.not_valid_after_utc.isoformat(),
    }
    _write(path / META_FILE, (json.dumps(meta, indent=2) + "\n").encode(), 0o644)
    write_yarp_key(path)
    return path


def unignored_keys(folder: Path) -> list[Path]:
    """The private keys (`*.key`, YARP's `yarp/auth.conf`) in `folder` that a git work tree
    holding it does not ignore: one `git add -A` from a commit. Empty outside a work tree, or
    where git is not installed."""
    keys = sorted(folder.glob("*.key")) + sorted(folder.glob(YARP_AUTH))
    try:
        inside = subprocess.run(
            ["git", "-C", str(folder), "rev-parse", "--is-inside-work-tree"],
            capture_output=True,
            text=True,
            timeout=30,
        )
        if not keys or inside.stdout.strip() != "true":
            return []
        ignored = subprocess.run(
            ["git", "-C", str(folder), "check-ignore", "--stdin"],
            input="\n".join(str(k.relative_to(folder)) for k in keys),
            capture_output=True,
            text=True,
            timeout=30,
        ).stdout.split()
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [k for k in keys if str(k.relative_to(folder)) not in ignored]


def identity_folder(deployment: Path, identity: str, into: Path) -> Path:
    """A folder `into`/`identity` (0700) holding what one process of `identity` needs of the
    deployment and nothing more: the CA's certificate (never its key), the identity's
    certificate and key, and for the router its access control. What `archery up --secure`
    hands each child, so no service can read another's key or sign a certificate.

    Raises:
        ConfigError: the deployment lacks one of those files.
    """
    folder = into / identity
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    names = [CA_CERT, f"{identity}.pem", f"{identity}.key"]
    if identity == ROUTER:
        names.append(ACL_FILE)
    for name in names:
        source = deployment / name
        try:
            data = source.read_bytes()
        except OSError as exc:
            raise ConfigError(
                f"--secure {deployment}: cannot read {name} ({exc.strerror}); create the "
                f"deployment with `archery keys init {deployment}`"
            ) from None
        _write(folder / name, data, 0o600 if name.endswith(".key") else 0o644)
    return folder
